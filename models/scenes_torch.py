"""Training scenes made on the training device (issue 32, item 1): a batched PyTorch generator
of the simulator's training distribution (:func:`polrig.sim.dataset.make_sample`).

:class:`SceneGenerator` draws ``n`` random scenes at once and renders them on the tensors' device
(CPU or CUDA): no disk, no worker pool, no numpy in the per-batch path. :meth:`SceneGenerator.batch`
returns the arrays :func:`polrig.models.data.load_dataset` gives training for ``n`` samples (same
keys, shapes, dtypes and normalisation: ``analyzer`` black-subtracted DN / ``scale``, ``mueller``
DN per unit incident S0 / ``scale``, ``mask`` float32, vectors in the camera frame);
:func:`training_tensors` turns them into the tensors :func:`polrig.models.train._tensors` makes from a
loaded set.

What is sampled, as ``polrig sim dataset`` does (``sim/dataset.py``, ``sim/scene.py``,
``sim/materials.py``):

* **Shape families**: every training family: ``sphere``, ``box``, ``cylinder`` and ``multi`` (a
  sphere and a box) intersected in closed form per pixel (sphere quadratic, slab test, quadric
  plus caps), ``blob`` and ``torus`` marched and bisected inside their bounding spheres as
  :func:`polrig.sim.shapes.march_to_surface` (64 samples, 24 bisections; a blob's 4-10 bumps
  padded to :data:`MAX_BUMPS` with zero amplitudes), with the same size, pose and centre draws
  as :func:`polrig.sim.scene.random_scene` and the turntable angle uniform in [0, 360). Not
  covered: the held-out ``heightfield`` and ``plane`` (never trained on); asking for them is a
  :class:`ConfigError`. The default families are the six training ones (``polrig sim
  dataset``'s default training side).
* **Materials**: the ``baek`` mix (kd per colour uniform in [0.02, 0.9], alpha log-uniform in
  [0.01, 0.8], eta uniform in [1.3, 1.8], ks 0 for one in ten) rendered with the differentiable
  pBRDF :mod:`polrig.models.pbrdf_torch` (GGX, the simulator's default distribution); the ``train``
  mix (baek 0.4, conductor, dispersive, anisotropic 0.2 each) and each of those kinds alone,
  drawn on the Baek material as :func:`polrig.sim.materials.random_surface_material` draws them
  and rendered per colour as :mod:`polrig.sim.surface_bsdf` (:func:`surface_blocks`: anisotropic GGX
  or Beckmann with the projected-roughness Smith term, the complex-index Fresnel matrix of each
  colour, the Baek diffuse term with each colour's index), with the ground-truth ``alpha``,
  ``eta`` and ``kd`` of :data:`polrig.sim.dataset.GROUND_TRUTH_PARAMETERS` and ``material_kind``. Not
  covered: the ``heldout`` kinds (films, depolarizing layers with textures) and interreflections
  (``indirect_samples``); asking for another mix is a :class:`ConfigError`.
* **Light and stage geometry**: light azimuth +-70 deg, elevation 5-60 deg, 0.3-0.6 m, colour
  uniform in [0.6, 1] per channel over its maximum; the default camera (``fx = fy = 2.5 min(W,
  H)``); the stage zero axis as ``stage_zero_axes="random"`` (rig axis 0.5, camera up 0.2, else
  a uniform angle about the illumination axis) or ``"camera-up"``; stage angle uniform in
  [0, 180) deg, extinction ratio log-uniform in [200, 3000], no stage offset.
* **Sensor**: the ideal-analyzer intensities (0/45/90/135 deg) per colour at ``H x W``, exposure
  scaled so the 99.5th percentile of the clean values inside the mask is 25-85 % of the clip
  level, Poisson photo- and dark electrons (clipped at the full well), Gaussian read noise,
  the gain, black level, rounding to the nearest code and clipping to the ADC range
  (:meth:`polrig.sensor.noise.SensorModel.sample_raw` with :data:`polrig.sim.options.SENSOR_MODEL_DEFAULTS`),
  black level and mean dark signal removed, divided by ``scale`` (the 99.5th percentile of the
  noisy values inside the mask, at least 1 DN; numpy's linear-interpolation percentile).
* **Ground truth**: ``mask``, ``lit`` (hit, facing the light, no occluder on the shadow ray),
  ``normal``, ``wi``, ``wo``, ``kd`` images (0 outside the mask), ``alpha``, ``eta``, ``s_in``,
  the ``mueller`` blocks ``(ks Ms + kd_c Md) / r^2 x light colour x colour QE x k / scale``.

**Same distribution, not the same scenes.** The simulator draws every sample from its own numpy
``Generator`` seeded by ``(seed, holdout, index)`` (PCG64 streams, Poisson and normal variates
from numpy's own algorithms, in a fixed order of draws within a sample). Reproducing them in
torch would mean re-implementing numpy's bit generator, its seed-sequence hashing and its
Poisson sampler, and drawing sample by sample: exactly the per-sample serial work a batched
device generator exists to avoid, and torch's CUDA generator (Philox) cannot produce those
streams. So :class:`SceneGenerator` samples the same distributions from a seeded
``torch.Generator`` (reproducible for a given seed, device and batch size), and
``tests/test_models_scenes_torch.py`` shows it is the simulator's distribution with two-sample
Kolmogorov-Smirnov and chi-square tests on the parameter marginals and on summary statistics of
the rendered images against :func:`polrig.sim.dataset.generate_dataset`, plus a per-scene check
that the renderer agrees with :func:`polrig.sim.render.render` on the same scene (the
deterministic part, where equality is practical), and a power check (a generator with a shifted
roughness range is rejected).
"""

from __future__ import annotations

import math
from typing import Sequence

import numpy as np
import torch

from polrig.errors import ConfigError
from polrig.models.pbrdf_torch import (
    _Vec,
    image_blocks,
    rotation_2phi,
    transmission_ab,
)
from polrig.sim.dataset import (
    CAMERA_UP_FRACTION,
    DATASET_EXPOSURE_US,
    RIG_AXIS_FRACTION,
    SCALE_PERCENTILE,
    SIZE_MULTIPLE,
    STAGE_ZERO_AXES,
    dataset_sensor_model,
)
from polrig.sim.materials import _LINES_NM, MATERIAL_KINDS, MATERIAL_MIXES
from polrig.sim.optical_data import CONDUCTORS, WAVELENGTHS_NM
from polrig.sim.options import HIDDEN_DEFAULTS
from polrig.sim.scene import FAMILIES, OBJECT_Z_M, RANDOM_FOCAL_PER_PX, default_camera

#: Shape families the torch generator renders (indices into :data:`polrig.sim.scene.FAMILIES`).
COVERED_FAMILIES = ("sphere", "box", "cylinder", "multi", "blob", "torus")
#: Material mixes it draws from: the Baek family and the training mix's kinds.
COVERED_MIXES = ("baek", "train", "conductor", "dispersive", "anisotropic")
#: Smallest roughness of the microfacet distributions (:data:`polrig.optics.pbrdf.ALPHA_MIN`).
ALPHA_MIN = 1e-4
#: Shadow-ray origin offset along the geometric normal (m), as :data:`polrig.sim.raycast.SHADOW_EPS_M`.
SHADOW_EPS_M = 1e-5
T_MIN = 1e-6

_SPHERE, _BOX, _CYLINDER, _BLOB, _TORUS = 0, 1, 2, 3, 4
#: Most bumps of a random blob (``polrig.sim.scene.random_scene``: 4 to 10).
MAX_BUMPS = 10
#: Marching samples and bisections of the implicit solids (``polrig.sim.shapes.Blob``, ``Torus``).
MARCH_STEPS, BISECTIONS = 64, 24


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _unit(v: torch.Tensor) -> torch.Tensor:
    n = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
    return v / n.clamp_min(1e-30)


def _rot_x(deg: torch.Tensor) -> torch.Tensor:
    a = torch.deg2rad(deg)
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([torch.stack([o, z, z], -1), torch.stack([z, c, -s], -1),
                        torch.stack([z, s, c], -1)], -2)


def _rot_z(deg: torch.Tensor) -> torch.Tensor:
    a = torch.deg2rad(deg)
    c, s = torch.cos(a), torch.sin(a)
    o, z = torch.ones_like(a), torch.zeros_like(a)
    return torch.stack([torch.stack([c, -s, z], -1), torch.stack([s, c, z], -1),
                        torch.stack([z, z, o], -1)], -2)


def _tilt(deg_x: torch.Tensor, deg_z: torch.Tensor) -> torch.Tensor:
    """:func:`polrig.sim.scene._tilt`: ``Rz(deg_z) @ Rx(deg_x)``, batched."""
    return _rot_z(deg_z) @ _rot_x(deg_x)


# ------------------------------------------------------------------------------- intersections
# Rays o + t d (B, P, 3) in a shape's local frame; parameters (B, 1[, 3]). Each returns
# (t (B, P) with inf for a miss, outward normal (B, P, 3)), as polrig.sim.shapes.


def sphere_hit(o, d, radius, t_min=T_MIN):
    b = _dot(o, d)
    c = _dot(o, o) - radius * radius
    disc = b * b - c
    sq = torch.sqrt(disc.clamp_min(0.0))
    t1, t2 = -b - sq, -b + sq
    inf = torch.full_like(t1, math.inf)
    t = torch.where(t1 > t_min, t1, torch.where(t2 > t_min, t2, inf))
    t = torch.where(disc >= 0, t, inf)
    p = o + torch.where(torch.isfinite(t), t, 0.0)[..., None] * d
    return t, p / radius[..., None]


def box_hit(o, d, half, t_min=T_MIN):
    """``half`` (B, 1, 3)."""
    inv = 1.0 / d
    t1, t2 = (-half - o) * inv, (half - o) * inv
    t1 = torch.nan_to_num(t1, nan=-math.inf)
    t2 = torch.nan_to_num(t2, nan=math.inf)
    lo, hi = torch.minimum(t1, t2), torch.maximum(t1, t2)
    t_near, ax_near = lo.max(-1)
    t_far, ax_far = hi.min(-1)
    hit = (t_near <= t_far) & (t_far > t_min)
    entering = t_near > t_min
    t = torch.where(hit, torch.where(entering, t_near, t_far), torch.full_like(t_near, math.inf))
    ax = torch.where(entering, ax_near, ax_far)
    p = o + torch.where(torch.isfinite(t), t, 0.0)[..., None] * d
    onehot = torch.nn.functional.one_hot(ax, 3).to(o.dtype)
    return t, onehot * torch.sign(p)


def cylinder_hit(o, d, radius, half_height, t_min=T_MIN):
    r, hh = radius, half_height
    inf = math.inf
    a = d[..., 0] ** 2 + d[..., 1] ** 2
    b = o[..., 0] * d[..., 0] + o[..., 1] * d[..., 1]
    c = o[..., 0] ** 2 + o[..., 1] ** 2 - r * r
    disc = b * b - a * c
    sq = torch.sqrt(disc.clamp_min(0.0))
    t_best = torch.full_like(a, inf)
    n_best = torch.zeros_like(o)
    for sgn in (-1.0, 1.0):
        ts = (-b + sgn * sq) / a
        z = o[..., 2] + ts * d[..., 2]
        ok = (disc >= 0) & (ts > t_min) & (z.abs() <= hh) & torch.isfinite(ts)
        ts = torch.where(ok, ts, inf)
        p = o + torch.where(ok, ts, 0.0)[..., None] * d
        ns = torch.stack([p[..., 0] / r, p[..., 1] / r, torch.zeros_like(ts)], -1)
        closer = ts < t_best
        t_best = torch.where(closer, ts, t_best)
        n_best = torch.where(closer[..., None], ns, n_best)
    for zc in (-1.0, 1.0):
        tc = (zc * hh - o[..., 2]) / d[..., 2]
        x, y = o[..., 0] + tc * d[..., 0], o[..., 1] + tc * d[..., 1]
        ok = (tc > t_min) & (x * x + y * y <= r * r) & torch.isfinite(tc)
        tc = torch.where(ok, tc, inf)
        nc = torch.zeros_like(o)
        nc[..., 2] = zc
        closer = tc < t_best
        t_best = torch.where(closer, tc, t_best)
        n_best = torch.where(closer[..., None], nc, n_best)
    return t_best, n_best

def _march(f, grad, o, d, bound, t_min=T_MIN):
    """Nearest entry into the solid ``f(p) <= 0`` inside the sphere of radius ``bound`` (B, 1)
    about the local origin, as :func:`polrig.sim.shapes.march_to_surface` and
    ``_MarchedSolid.intersect``: :data:`MARCH_STEPS` uniform samples, then :data:`BISECTIONS`
    halvings of the bracket; a ray whose first sample is inside misses. Returns ``(t, normal)``."""
    b = _dot(o, d)
    disc = b * b - (_dot(o, o) - bound * bound)
    sq = torch.sqrt(disc.clamp_min(0.0))
    t0, t1 = torch.clamp_min(-b - sq, t_min), -b + sq
    ok = (disc > 0) & (t0 < t1)
    found = torch.zeros_like(ok)
    starts_inside = torch.zeros_like(ok)
    lo = torch.zeros_like(t0)
    hi = torch.zeros_like(t0)
    prev = t0
    for k in range(MARCH_STEPS + 1):
        tk = t0 + (t1 - t0) * (k / MARCH_STEPS)
        inside = f(o + tk[..., None] * d) <= 0.0
        new = inside & ~found
        if k == 0:
            starts_inside = inside
        lo = torch.where(new, prev, lo)
        hi = torch.where(new, tk, hi)
        found = found | inside
        prev = tk
    for _ in range(BISECTIONS):
        mid = 0.5 * (lo + hi)
        go_hi = f(o + mid[..., None] * d) <= 0.0
        hi = torch.where(go_hi, mid, hi)
        lo = torch.where(go_hi, lo, mid)
    hit = ok & found & ~starts_inside
    t = torch.where(hit, hi, torch.full_like(hi, math.inf))
    n = _unit(grad(o + torch.where(hit, hi, 0.0)[..., None] * d))
    return t, torch.where(hit[..., None], n, 0.0)


def blob_hit(o, d, radius, centres, widths, amplitudes):
    """:class:`polrig.sim.shapes.Blob` per sample: ``radius`` (B, 1), unit ``centres``
    (B, K, 3), ``widths`` and ``amplitudes`` (B, K) (amplitude 0 pads the unused bumps)."""
    w2 = (widths * widths)[:, None]  # (B, 1, K)

    def radius_and_grad(u):
        e = amplitudes[:, None] * torch.exp((u @ centres.transpose(1, 2) - 1.0) / w2)  # (B, P, K)
        r = radius * torch.exp(e.sum(-1))
        return r, r[..., None] * ((e / w2) @ centres)

    def f(p):
        rho = torch.linalg.vector_norm(p, dim=-1)
        r, _ = radius_and_grad(p / rho.clamp_min(1e-30)[..., None])
        return rho - r

    def grad(p):
        rho = torch.linalg.vector_norm(p, dim=-1).clamp_min(1e-30)
        u = p / rho[..., None]
        _, g = radius_and_grad(u)
        g_tan = g - _dot(g, u)[..., None] * u
        return u - g_tan / rho[..., None]

    bound = radius * torch.exp(amplitudes.clamp_min(0.0).sum(1, keepdim=True)) * 1.001
    return _march(f, grad, o, d, bound)


def torus_hit(o, d, major, minor):
    """:class:`polrig.sim.shapes.Torus` per sample: radii (B, 1)."""
    def f(p):
        rho = torch.hypot(p[..., 0], p[..., 1])
        return (rho - major) ** 2 + p[..., 2] ** 2 - minor ** 2

    def grad(p):
        rho = torch.hypot(p[..., 0], p[..., 1]).clamp_min(1e-30)
        k = (rho - major) / rho
        return torch.stack([k * p[..., 0], k * p[..., 1], p[..., 2]], -1)

    return _march(f, grad, o, d, (major + minor) * 1.001)


def _g1(v_l, h_dot_v, au, av, beckmann):
    """Smith masking of :func:`polrig.sim.surface_bsdf.smith_g1` (projected roughness, Heitz 2014):
    ``v_l`` the local (t, b, n) components (tuple of three tensors)."""
    xy = (au * v_l[0]) ** 2 + (av * v_l[1]) ** 2
    a2t2 = xy / (v_l[2] * v_l[2]).clamp_min(1e-30)
    g_ggx = 2.0 / (1.0 + torch.sqrt(1.0 + a2t2))
    b = 1.0 / torch.sqrt(a2t2.clamp_min(1e-30))
    g_beck = torch.where(b >= 1.6, torch.ones_like(b), (3.535 * b + 2.181 * b * b) / (1.0 + 2.276 * b + 2.577 * b * b))
    g = torch.where(beckmann, g_beck, g_ggx)
    g = torch.where(xy == 0, torch.ones_like(g), g)
    return torch.where(h_dot_v * v_l[2] <= 0, torch.zeros_like(g), g)


def surface_blocks(normal, wi, wo, tangent, *, au, av, beckmann, eta_re, eta_im, stage_zero_axis, mask):
    """Unit specular (``ks = 1``) and diffuse (``kd = 1``) linear blocks per colour
    ``(B, 3, 3, 3, H, W)`` (colour, row, col) in the rig frames of
    :func:`polrig.sim.surface_bsdf.evaluate` without film or depolarization: the anisotropic GGX
    or Beckmann microfacet term with the complex-index Fresnel matrix of each colour, and the
    Baek diffuse term with each colour's real index. Images ``(B, 3, H, W)`` (``tangent``: the
    tangent reference, projected here); per sample ``au``, ``av``, ``beckmann`` ``(B,)`` and
    ``eta_re``, ``eta_im`` ``(B, 3)``; ``mask`` ``(B, 1, H, W)``."""
    v = _Vec(1)
    n, wi, wo = v.normalize(normal), v.normalize(wi), v.normalize(wo)
    cos_i, cos_o = v.dot(n, wi), v.dot(n, wo)
    visible = (cos_i > 0).to(n.dtype) * (cos_o > 0).to(n.dtype) * mask
    k_in, k_out = -wi, wo
    cam = torch.zeros_like(n[:1, :, :1, :1])
    cam[:, 0] = 1.0
    x_in = v.perpendicular(stage_zero_axis[:, :, None, None], k_in)
    x_out = v.perpendicular(cam, k_out)
    y_in, y_out = v.cross(k_in, x_in), v.cross(k_out, x_out)
    # the tangent reference projected on the surface; where it is parallel to the normal any
    # perpendicular axis (the roughness is then isotropic or the case has probability zero)
    fallback = v.axis_or(v.cross(n, torch.ones_like(n) * torch.tensor([1.0, 0.0, 0.0], dtype=n.dtype,
                                                                        device=n.device)[:, None, None]),
                         v.normalize(v.cross(n, torch.ones_like(n) * torch.tensor(
                             [0.0, 1.0, 0.0], dtype=n.dtype, device=n.device)[:, None, None])))
    t = v.axis_or(tangent - v.dot(tangent, n) * n, fallback)
    b = v.cross(n, t)
    h = v.normalize(wi + wo)
    loc = lambda u: (v.dot(u, t), v.dot(u, b), v.dot(u, n))  # noqa: E731
    h_l, i_l, o_l = loc(h), loc(wi), loc(wo)
    au4, av4 = au.clamp_min(ALPHA_MIN)[:, None, None, None], av.clamp_min(ALPHA_MIN)[:, None, None, None]
    beck = beckmann[:, None, None, None]
    x2 = (h_l[0] / au4) ** 2 + (h_l[1] / av4) ** 2
    z = h_l[2]
    z2 = (z * z).clamp_min(1e-30)
    d_ggx = 1.0 / (math.pi * au4 * av4 * (x2 + z * z) ** 2)
    d_beck = torch.exp(-x2 / z2) / (math.pi * au4 * av4 * z2 * z2)
    d = torch.where(beck, d_beck, d_ggx)
    d = torch.where((z > 0) & torch.isfinite(d) & (d * z > 1e-20), d, torch.zeros_like(d))
    scalar = d * _g1(i_l, v.dot(wi, h), au4, av4, beck) * _g1(o_l, v.dot(wo, h), au4, av4, beck) \
        / (4.0 * cos_o.clamp_min(1e-6)) * visible
    s_axis = v.axis_or(v.cross(wi, h), x_in)
    ci, si = rotation_2phi(v.dot(x_in, s_axis), v.dot(y_in, s_axis))
    co, so = rotation_2phi(v.dot(s_axis, x_out), -v.dot(y_out, s_axis))
    # complex Fresnel per colour (B, 3, H, W), polrig.optics.mueller._fresnel_amplitudes
    cih = v.dot(wi, h).abs().clamp(0.0, 1.0)
    eta = torch.complex(eta_re, eta_im)[:, :, None, None]
    cc = torch.complex(cih, torch.zeros_like(cih))
    ect = torch.sqrt(eta * eta - 1.0 + cc * cc)
    e2ci = eta * eta * cc
    rs, rp = (cc - ect) / (cc + ect), (e2ci - ect) / (e2ci + ect)
    rs2, rp2 = rs.abs() ** 2, rp.abs() ** 2
    a, bb, c = 0.5 * (rs2 + rp2) * scalar, 0.5 * (rs2 - rp2) * scalar, (rs * rp.conj()).real * scalar
    a_ci, a_si, c_si, c_ci = a * ci, a * si, c * si, c * ci
    spec = torch.stack([a, bb * ci, bb * si,
                        co * bb, co * a_ci - so * c_si, co * a_si + so * c_ci,
                        -so * bb, -so * a_ci - co * c_si, -so * a_si + co * c_ci], 2).unflatten(2, (3, 3))
    # diffuse, per colour's real index
    s_in = v.axis_or(v.cross(n, k_in), x_in)
    s_out = v.axis_or(v.cross(n, k_out), x_out)
    ci_d, si_d = rotation_2phi(v.dot(x_in, s_in), v.dot(y_in, s_in))
    co_d, so_d = rotation_2phi(v.dot(s_out, x_out), -v.dot(y_out, s_out))
    # a conductor has no diffuse term (kd = 0); a dielectric index keeps its blocks finite
    eta_d = torch.where(eta_im > 0, 1.5, eta_re)[:, :, None, None]

    a_i, b_i = transmission_ab(cos_i, eta_d)
    a_o, b_o = transmission_ab(cos_o, eta_d)
    scale = cos_i.clamp_min(0.0) / math.pi * visible
    u = torch.stack([a_o, co_d * b_o, -so_d * b_o], 2)
    w = torch.stack([scale * a_i, scale * ci_d * b_i, scale * si_d * b_i], 2)
    return spec, u[:, :, :, None] * w[:, :, None, :]


def masked_percentile(values: torch.Tensor, valid: torch.Tensor, q: float) -> tuple[torch.Tensor, torch.Tensor]:
    """numpy's ``percentile(values[valid], q)`` (linear interpolation) per row of ``values``
    ``(B, K)``; returns ``(percentile (B,), any valid (B,))`` (0 where a row has none). Only the
    top ``(1 - q / 100)`` of a row is ordered (:func:`torch.topk`), not the whole row."""
    n = valid.sum(1)
    pos = (q / 100.0) * (n - 1).clamp_min(0).to(torch.float64)  # float64 as numpy
    lo, hi = pos.floor().long(), pos.ceil().long()
    k = min(values.shape[1], int(math.ceil((1.0 - q / 100.0) * max(int(n.max()) - 1, 0))) + 2)
    top, _ = torch.topk(torch.where(valid, values, -math.inf), k, dim=1)  # descending
    rank = lambda r: (n - 1 - r).clamp(0, k - 1)[:, None]  # noqa: E731 - ascending rank r, from the top
    v_lo, v_hi = top.gather(1, rank(lo))[:, 0], top.gather(1, rank(hi))[:, 0]
    out = v_lo + (v_hi - v_lo) * (pos - lo).to(values.dtype)
    has = n > 0
    return torch.where(has, out, torch.zeros_like(out)), has


class SceneGenerator:
    """Fresh random scenes of ``polrig sim dataset``'s training distribution, rendered in batches
    on ``device`` (module docstring). ``seed`` seeds a :class:`torch.Generator` on that device:
    the same seed, device and sequence of batch sizes give the same batches.

    ``roughness_range`` (the log-uniform alpha range) and ``exposure_range`` (the exposure's
    target as a fraction of the clip level) are there for the tests' power checks only: a
    generator with a shifted range must be told apart from the simulator."""

    def __init__(self, width: int = 256, height: int | None = None, *, seed: int = 0,
                 device: str | torch.device = "cpu", families: Sequence[str] | None = None,
                 material_mix: str = "baek", stage_zero_axes: str = "random",
                 dtype: torch.dtype = torch.float32,
                 roughness_range: tuple[float, float] = (0.01, 0.8),
                 exposure_range: tuple[float, float] = (0.25, 0.85)) -> None:
        height = width if height is None else int(height)
        if width % SIZE_MULTIPLE or height % SIZE_MULTIPLE or not (8 <= width <= 4096 and 8 <= height <= 4096):
            raise ConfigError(f"generator size {width}x{height}: the sides must be multiples of {SIZE_MULTIPLE} "
                              f"in 8..4096")
        names = tuple(COVERED_FAMILIES if families is None else families)
        bad = [f for f in names if f not in COVERED_FAMILIES]
        if bad or not names:
            raise ConfigError(f"the torch scene generator renders the families {', '.join(COVERED_FAMILIES)}; "
                              f"got {', '.join(names) or 'none'} (heightfield and plane, the held-out families, "
                              f"are not ported)")
        if material_mix not in COVERED_MIXES:
            raise ConfigError(f"the torch scene generator draws the material mixes {', '.join(COVERED_MIXES)}; got "
                              f"{material_mix!r} (films and depolarizing layers, the held-out kinds, are not "
                              f"ported)")
        if stage_zero_axes not in STAGE_ZERO_AXES:
            raise ConfigError(f"stage_zero_axes must be one of {STAGE_ZERO_AXES}, got {stage_zero_axes!r}")
        self.width, self.height = int(width), height
        self.device = torch.device(device)
        self.dtype = dtype
        self.families = names
        self.family_ids = torch.tensor([FAMILIES.index(f) for f in names], device=self.device)
        self.material_mix = material_mix
        self.stage_zero_axes = stage_zero_axes
        self.log_alpha = (math.log(roughness_range[0]), math.log(roughness_range[1]))
        self.exposure_range = tuple(float(v) for v in exposure_range)
        self.generator = torch.Generator(device=self.device)
        self.generator.manual_seed(int(seed))
        model = dataset_sensor_model()
        self.gain = float(model.gain_e_per_dn)
        self.full_well = float(model.full_well_e)
        self.read_noise = float(model.read_noise_e)
        self.black = float(model.black_level_dn)
        self.max_code = float(model.max_code_dn)
        self.clip_dn = float(model.clip_dn)
        self.dark_e = float(model.dark_electrons(DATASET_EXPOSURE_US))
        cam = default_camera(self.width, self.height, focal_per_px=RANDOM_FOCAL_PER_PX)
        t = dict(device=self.device, dtype=dtype)
        self.cam_r = torch.tensor(cam.R, **t)  # world -> camera
        self.cam_t = torch.tensor(cam.t, **t)
        u = (torch.arange(self.width, device=self.device, dtype=torch.float64) - cam.cx) / cam.fx
        v = (torch.arange(self.height, device=self.device, dtype=torch.float64) - cam.cy) / cam.fy
        d = torch.stack([u[None, :].expand(self.height, -1), v[:, None].expand(-1, self.width),
                         torch.ones(self.height, self.width, dtype=torch.float64, device=self.device)], -1)
        self.rays = _unit(d).reshape(1, -1, 3).to(dtype)  # camera frame, pixel centres, row-major
        self.colour_qe = torch.tensor(HIDDEN_DEFAULTS["colour_qe"], **t)
        probs = MATERIAL_MIXES[material_mix]
        self.mix_kinds = torch.tensor([MATERIAL_KINDS.index(k) for k in probs], device=self.device)
        self.mix_probs = torch.tensor([probs[k] for k in probs], device=self.device, dtype=torch.float64)
        metals = list(CONDUCTORS)
        eta_m = np.array([CONDUCTORS[m] for m in metals], complex)  # (5, 3)
        self.metal_re = torch.tensor(eta_m.real, **t)
        self.metal_im = torch.tensor(eta_m.imag, **t)
        r = np.abs((eta_m[:, 1] - 1.0) / (eta_m[:, 1] + 1.0))
        self.metal_eta_fit = torch.tensor((1.0 + r) / (1.0 - r), **t)  # polrig.sim.dataset.effective_eta
        self.inv_l2 = torch.tensor([1.0 / lam ** 2 for lam in WAVELENGTHS_NM], **t)
        self.target_w = torch.tensor([0.0, 0.0, OBJECT_Z_M], **t)

    # -- random draws ----------------------------------------------------------------------
    def _u(self, *shape, lo=0.0, hi=1.0) -> torch.Tensor:
        r = torch.rand(*shape, generator=self.generator, device=self.device, dtype=self.dtype)
        return lo + (hi - lo) * r

    def _draw(self, n: int) -> dict[str, torch.Tensor]:
        """Per-sample scene parameters, as :func:`polrig.sim.scene.random_scene` and
        :func:`polrig.sim.dataset.make_sample` draw them."""
        fam = self.family_ids[torch.randint(len(self.family_ids), (n,), generator=self.generator,
                                            device=self.device)]
        kd = self._u(n, 3, lo=0.02, hi=0.9)
        alpha = torch.exp(self._u(n, lo=self.log_alpha[0], hi=self.log_alpha[1]))
        eta = self._u(n, lo=1.3, hi=1.8)
        ks = (self._u(n) >= 0.1).to(self.dtype)
        rot = _tilt(self._u(n, lo=-40.0, hi=40.0), self._u(n, lo=0.0, hi=360.0))
        c = self.target_w + self._u(n, 3, lo=-0.01, hi=0.01)
        is_multi = fam == FAMILIES.index("multi")
        kind = torch.full((n,), _SPHERE, device=self.device)
        kind = torch.where(fam == FAMILIES.index("box"), _BOX, kind)
        kind = torch.where(fam == FAMILIES.index("cylinder"), _CYLINDER, kind)
        kind = torch.where(fam == FAMILIES.index("blob"), _BLOB, kind)
        kind = torch.where(fam == FAMILIES.index("torus"), _TORUS, kind)
        r_sphere = torch.where(is_multi, self._u(n, lo=0.02, hi=0.035), self._u(n, lo=0.035, hi=0.06))
        half_box = self._u(n, 3, lo=0.02, hi=0.045)
        r_cyl, hh_cyl = self._u(n, lo=0.02, hi=0.04), self._u(n, lo=0.025, hi=0.05)
        # blob: 4-10 bumps (unit centres, widths, amplitudes; the unused ones amplitude 0)
        r_blob = self._u(n, lo=0.035, hi=0.05)
        n_bumps = torch.randint(4, MAX_BUMPS + 1, (n,), generator=self.generator, device=self.device)
        used = torch.arange(MAX_BUMPS, device=self.device)[None] < n_bumps[:, None]
        centres = _unit(torch.randn(n, MAX_BUMPS, 3, generator=self.generator, device=self.device,
                                    dtype=self.dtype))
        widths = self._u(n, MAX_BUMPS, lo=0.25, hi=0.7)
        amplitudes = self._u(n, MAX_BUMPS, lo=-0.35, hi=0.45) * used
        # torus: radii and its own tilt
        r_major, r_minor = self._u(n, lo=0.03, hi=0.045), self._u(n, lo=0.01, hi=0.02)
        rot_torus = _tilt(self._u(n, lo=-70.0, hi=70.0), self._u(n, lo=0.0, hi=360.0))
        radius = torch.where(kind == _CYLINDER, r_cyl, r_sphere)
        radius = torch.where(kind == _BLOB, r_blob, torch.where(kind == _TORUS, r_major, radius))
        hh_cyl = torch.where(kind == _TORUS, r_minor, hh_cyl)
        eye = torch.eye(3, device=self.device, dtype=self.dtype).expand(n, 3, 3)
        rot_a = torch.where((kind == _SPHERE)[:, None, None], eye,
                            torch.where((kind == _TORUS)[:, None, None], rot_torus, rot))
        off_a = torch.tensor([-0.03, -0.02, -0.02], device=self.device, dtype=self.dtype)
        c_a = c + is_multi[:, None].to(self.dtype) * off_a
        half_b = self._u(n, 3, lo=0.015, hi=0.03)
        c_b = c + torch.tensor([0.03, 0.02, -0.01], device=self.device, dtype=self.dtype)
        az = torch.deg2rad(self._u(n, lo=-70.0, hi=70.0))
        el = torch.deg2rad(self._u(n, lo=5.0, hi=60.0))
        dist = self._u(n, lo=0.3, hi=0.6)
        light = self.target_w + dist[:, None] * torch.stack(
            [torch.sin(az) * torch.cos(el), -torch.cos(az) * torch.cos(el), torch.sin(el)], -1)
        colour = self._u(n, 3, lo=0.6, hi=1.0)
        colour = colour / colour.max(1, keepdim=True).values
        turn = _rot_z(self._u(n, lo=0.0, hi=360.0))
        # stage zero axis (world), as sample_stage_zero_axis and Scene.__post_init__
        k = _unit(self.target_w - light)
        up = torch.tensor([0.0, 0.0, 1.0], device=self.device, dtype=self.dtype).expand(n, 3)
        rig_axis = _unit(torch.linalg.cross(self.target_w - light, up))
        cam_up = -self.cam_r[1].expand(n, 3)
        cam_up = _unit(cam_up - _dot(cam_up, k)[:, None] * k)
        if self.stage_zero_axes == "camera-up":
            axis = cam_up
        else:
            pick = self._u(n)
            ang = self._u(n, lo=0.0, hi=math.pi)
            y = torch.linalg.cross(k, cam_up)
            turned = torch.cos(ang)[:, None] * cam_up + torch.sin(ang)[:, None] * y
            axis = torch.where((pick < RIG_AXIS_FRACTION)[:, None], rig_axis,
                               torch.where((pick < RIG_AXIS_FRACTION + CAMERA_UP_FRACTION)[:, None], cam_up,
                                           turned))
            axis = _unit(axis - _dot(axis, k)[:, None] * k)
        stage_deg = self._u(n, lo=0.0, hi=180.0)
        er = torch.exp(self._u(n, lo=math.log(200.0), hi=math.log(3000.0)))
        exposure = self._u(n, lo=self.exposure_range[0], hi=self.exposure_range[1])
        mat = self._draw_material(n, kd, alpha, eta, ks)
        # to the camera frame: p_cam = R_cam (R_turn p) + t_cam
        rc = self.cam_r @ turn
        return {**mat, "family": fam, "kind": kind, "is_multi": is_multi,
                "rot_a": rc @ rot_a, "t_a": (rc @ c_a[..., None])[..., 0] + self.cam_t,
                "radius": radius, "half_a": half_box, "hh": hh_cyl, "centres": centres, "widths": widths,
                "amplitudes": amplitudes,
                "rot_b": rc @ rot, "t_b": (rc @ c_b[..., None])[..., 0] + self.cam_t, "half_b": half_b,
                "light": (self.cam_r @ light[..., None])[..., 0] + self.cam_t, "colour": colour,
                "axis": (self.cam_r @ axis[..., None])[..., 0], "stage_deg": stage_deg, "er": er,
                "exposure": exposure}

    def _draw_material(self, n, kd, alpha, eta, ks) -> dict[str, torch.Tensor]:
        """The sample's material drawn from the mix on the Baek material ``(kd, alpha, eta, ks)``
        as :func:`polrig.sim.materials.random_mix_material`, with its ground-truth parameters
        (:data:`polrig.sim.dataset.GROUND_TRUTH_PARAMETERS`)."""
        kinds = self.mix_kinds[torch.multinomial(self.mix_probs, n, replacement=True, generator=self.generator)]
        is_k = {k: kinds == MATERIAL_KINDS.index(k) for k in ("conductor", "dispersive", "anisotropic")}
        tangent = torch.randn(n, 3, generator=self.generator, device=self.device, dtype=self.dtype)
        metal = torch.randint(len(self.metal_re), (n,), generator=self.generator, device=self.device)
        alpha_c = torch.exp(self._u(n, lo=math.log(0.02), hi=math.log(0.6)))
        beckmann = self._u(n) < 0.5
        abbe = self._u(n, lo=20.0, hi=65.0)
        u = self._u(n, lo=0.3, hi=1.2)
        # polrig.sim.materials.cauchy_rgb
        ld, lf, lc = _LINES_NM
        bc = (eta - 1.0) / abbe / (1.0 / lf ** 2 - 1.0 / lc ** 2)
        cauchy = (eta - bc / ld ** 2)[:, None] + bc[:, None] * self.inv_l2
        cond, disp, aniso = is_k["conductor"][:, None], is_k["dispersive"][:, None], is_k["anisotropic"]
        eta3 = eta[:, None].expand(n, 3)
        eta_re = torch.where(cond, self.metal_re[metal], torch.where(disp, cauchy, eta3))
        eta_im = torch.where(cond, self.metal_im[metal], torch.zeros_like(eta3))
        au = torch.where(is_k["conductor"], alpha_c, torch.where(aniso, alpha * torch.exp(u), alpha))
        av = torch.where(is_k["conductor"], alpha_c, torch.where(aniso, alpha * torch.exp(-u), alpha))
        alpha_fit = torch.where(is_k["conductor"], alpha_c, alpha)
        eta_fit = torch.where(is_k["conductor"], self.metal_eta_fit[metal], torch.where(is_k["dispersive"],
                                                                                      cauchy[:, 1], eta))
        return {"material_kind": kinds, "kd": torch.where(cond, 0.0, kd), "ks": torch.where(is_k["conductor"], 1.0, ks),
                "alpha": alpha_fit, "alpha_empty": au, "eta": eta_fit, "au": au, "av": av,
                "beckmann": beckmann & (is_k["conductor"] | aniso), "eta_re": eta_re, "eta_im": eta_im,
                "tangent": tangent}

    # -- ray casting -----------------------------------------------------------------------
    @staticmethod
    def _local(o, d, rot, t):
        """Rays (B, P, 3) into an object's local frame (``p_cam = rot p_local + t``: row vectors
        ``p_local = (p_cam - t) rot``)."""
        return (o - t[:, None]) @ rot, d @ rot

    def _hit_a(self, s, o, d):
        """Nearest hit of the rays (B, P, 3) on each sample's first object (only the samples
        of each shape kind are intersected with that kind)."""
        ol, dl = self._local(o, d, s["rot_a"], s["t_a"])
        t = torch.full(ol.shape[:2], math.inf, dtype=ol.dtype, device=ol.device)
        n = torch.zeros_like(ol)
        for kind, hit in ((_SPHERE, lambda q: sphere_hit(ol[q], dl[q], s["radius"][q, None])),
                          (_BOX, lambda q: box_hit(ol[q], dl[q], s["half_a"][q, None])),
                          (_CYLINDER, lambda q: cylinder_hit(ol[q], dl[q], s["radius"][q, None], s["hh"][q, None])),
                          (_BLOB, lambda q: blob_hit(ol[q], dl[q], s["radius"][q, None], s["centres"][q],
                                                     s["widths"][q], s["amplitudes"][q])),
                          (_TORUS, lambda q: torus_hit(ol[q], dl[q], s["radius"][q, None], s["hh"][q, None]))):
            q = torch.nonzero(s["kind"] == kind)[:, 0]
            if len(q):
                t[q], n[q] = hit(q)
        return t, n @ s["rot_a"].transpose(1, 2)

    def _hit_b(self, s, o, d):
        """Nearest hit on the second object (the box of ``multi``; a miss for other samples)."""
        t = torch.full(o.shape[:2], math.inf, dtype=o.dtype, device=o.device)
        n = torch.zeros_like(o)
        q = torch.nonzero(s["is_multi"])[:, 0]
        if len(q):
            ol, dl = self._local(o[q], d[q], s["rot_b"][q], s["t_b"][q])
            tq, nq = box_hit(ol, dl, s["half_b"][q, None])
            t[q], n[q] = tq, nq @ s["rot_b"][q].transpose(1, 2)
        return t, n

    def _render(self, s):
        n = len(s["kd"])
        h, w = self.height, self.width
        d = self.rays.expand(n, -1, -1)
        o = torch.zeros_like(d)
        ta, na = self._hit_a(s, o, d)
        tb, nb = self._hit_b(s, o, d)
        closer_b = tb < ta
        t = torch.where(closer_b, tb, ta)
        ng = _unit(torch.where(closer_b[..., None], nb, na))
        mask = torch.isfinite(t)
        p = torch.where(mask[..., None], t[..., None] * d, 0.0)
        flip = _dot(ng, d) > 0  # two-sided surfaces face the camera
        ng = torch.where(flip[..., None], -ng, ng)
        to_light = s["light"][:, None] - p
        dist = torch.linalg.vector_norm(to_light, dim=-1)
        wi = to_light / dist[..., None]
        facing = mask & (_dot(ng, wi) > 0)
        so = p + SHADOW_EPS_M * ng
        t_max = dist - SHADOW_EPS_M
        sa, _ = self._hit_a(s, so, wi)
        sb, _ = self._hit_b(s, so, wi)
        shadowed = (torch.minimum(sa, sb) < t_max)
        lit = facing & ~shadowed
        wo = -d
        zero = torch.zeros((), dtype=self.dtype, device=self.device)
        img = lambda v: v.reshape(n, h, w, 3).permute(0, 3, 1, 2)  # noqa: E731
        m3 = mask[..., None]
        normal = img(torch.where(m3, ng, zero))
        wi_img = img(torch.where(m3, wi, zero))
        wo_img = img(torch.where(m3, wo, zero))
        mask_img = mask.reshape(n, 1, h, w)
        lit_img = lit.reshape(n, 1, h, w)
        inv_r2 = torch.where(lit, 1.0 / (dist * dist), zero).reshape(n, 1, h, w)
        self._on_b = closer_b.reshape(n, 1, h, w)  # which object a pixel sees (the tangent's frame)
        return mask_img, lit_img, normal, wi_img, wo_img, inv_r2

    # -- a batch ---------------------------------------------------------------------------
    @torch.no_grad()
    def batch(self, n: int) -> dict[str, torch.Tensor]:
        """``n`` fresh samples: the arrays of :func:`polrig.models.data.load_dataset` (``mask``
        float32 ``(n, H, W)``, shard dtypes for ``lit``, ``family``, ``material_kind``) plus
        ``stage_deg``."""
        return self.render(self._draw(int(n)))

    def clean(self, s: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """The noiseless part of a sample from its parameters ``s`` (:meth:`_draw`, or
        :func:`scene_parameters`): geometry images and ``m_rad`` ``(n, 3, 3, 3, H, W)``, the
        emergent radiance Mueller per unit light intensity times the light colour and colour QE
        (what :func:`polrig.sim.dataset.make_sample` calls ``m_rad``)."""
        mask, lit, normal, wi, wo, inv_r2 = self._render(s)
        if self.material_mix == "baek":  # one real index, isotropic GGX: the networks' pBRDF
            spec, diff = image_blocks(normal, wi, wo, s["alpha"], s["axis"], eta=s["eta"][:, None, None, None],
                                      mask=lit.to(self.dtype))
            spec, diff = spec[:, None], diff[:, None]
        else:  # per colour, polrig.sim.surface_bsdf
            tan = lambda r: (r @ _unit(s["tangent"])[..., None])[..., 0][:, :, None, None]  # noqa: E731
            tangent = torch.where(self._on_b, tan(s["rot_b"]), tan(s["rot_a"]))
            spec, diff = surface_blocks(normal, wi, wo, tangent, au=s["au"], av=s["av"], beckmann=s["beckmann"],
                                        eta_re=s["eta_re"], eta_im=s["eta_im"], stage_zero_axis=s["axis"],
                                        mask=lit.to(self.dtype))
        light = s["colour"] * self.colour_qe  # (n, 3)
        # (n, colour, 3, 3, H, W): (ks Ms + kd_c Md) / r^2 x light colour
        m_rad = (s["ks"][:, None, None, None, None, None] * spec
                 + s["kd"][:, :, None, None, None, None] * diff) * inv_r2[:, None, None] \
            * light[:, :, None, None, None, None]
        ang = torch.deg2rad(s["stage_deg"])
        t1, t2 = torch.ones_like(s["er"]), 1.0 / s["er"]
        s_in = torch.stack([(t1 + t2) / 2, (t1 - t2) / 2 * torch.cos(2 * ang), (t1 - t2) / 2 * torch.sin(2 * ang)], -1)
        return {"mask": mask, "lit": lit, "normal": normal, "wi": wi, "wo": wo, "m_rad": m_rad, "s_in": s_in}

    def sample_codes(self, mean_electrons: torch.Tensor) -> torch.Tensor:
        """Raw codes (as floats) for mean photo-electrons, as
        :meth:`polrig.sensor.noise.SensorModel.sample_raw` of the dataset's sensor model: Poisson
        photo- and dark electrons clipped at the full well, Gaussian read noise, the gain, the
        black level, rounding to the nearest code, clipping to ``0 .. max code``."""
        lam = mean_electrons + self.dark_e
        electrons = torch.poisson(lam, generator=self.generator).clamp_max(self.full_well)
        electrons = electrons + self.read_noise * torch.randn(lam.shape, generator=self.generator,
                                                              device=self.device, dtype=self.dtype)
        return torch.floor(electrons / self.gain + self.black + 0.5).clamp(0.0, self.max_code)

    @torch.no_grad()
    def render(self, s: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """A batch (:meth:`batch`) from scene parameters ``s``: render, expose, add the sensor's
        noise, normalise."""
        n = len(s["kd"])
        c = self.clean(s)
        mask, lit, normal, wi, wo, m_rad, s_in = (c[k] for k in ("mask", "lit", "normal", "wi", "wo", "m_rad",
                                                                 "s_in"))
        maskf = mask.to(self.dtype)
        stokes = (m_rad * s_in[:, None, None, :, None, None]).sum(3)  # (n, c, 3, H, W)
        s0, s1, s2 = stokes[:, :, 0], stokes[:, :, 1], stokes[:, :, 2]
        an = 0.5 * torch.stack([s0 + s1, s0 + s2, s0 - s1, s0 - s2], 2)  # (n, c, 4, H, W)
        inside = mask[:, None].expand(-1, 3, 4, -1, -1).reshape(n, -1)
        ref, has = masked_percentile(an.reshape(n, -1), inside, SCALE_PERCENTILE)
        target = s["exposure"] * self.clip_dn
        k = torch.where(has & (ref > 0), target / torch.where(ref > 0, ref, 1.0), torch.ones_like(ref))
        codes = self.sample_codes((an * k[:, None, None, None, None]).clamp_min(0.0) * self.gain)
        analyzer = codes - self.black - self.dark_e / self.gain
        sc, has = masked_percentile(analyzer.reshape(n, -1), inside, SCALE_PERCENTILE)
        scale = torch.where(has, sc.clamp_min(1.0), torch.ones_like(sc))
        kd_img = s["kd"][:, :, None, None] * maskf
        f32 = torch.float32
        return {
            "analyzer": (analyzer / scale[:, None, None, None, None]).to(f32),
            "scale": scale.to(f32), "mask": maskf[:, 0].to(f32),
            "normal": normal.to(f32), "kd": kd_img.to(f32), "wi": wi.to(f32), "wo": wo.to(f32),
            "alpha": torch.where(maskf.flatten(1).any(1), s["alpha"], s["alpha_empty"]).to(f32),
            "eta": s["eta"].to(f32), "s_in": s_in.to(f32),
            "mueller": (m_rad * (k / scale)[:, None, None, None, None, None]).to(f32),
            "family": s["family"].to(torch.int16), "stage_deg": s["stage_deg"].to(f32),
            "lit": lit[:, 0].to(torch.uint8), "stage_zero_axis": s["axis"].to(f32),
            "material_kind": s["material_kind"].to(torch.int16),
        }


def training_tensors(batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """The tensors :func:`polrig.models.train._tensors` makes of a loaded dataset, from a
    :meth:`SceneGenerator.batch` (``mask`` gets its channel axis)."""
    t = {k: batch[k] for k in ("analyzer", "normal", "kd", "wi", "wo", "alpha", "s_in", "mueller",
                               "stage_zero_axis")}
    t["mask"] = batch["mask"][:, None]
    return t


def scene_parameters(gen: SceneGenerator, scene, turntable_deg: float, *, stage_deg: float = 0.0,
                     extinction_ratio: float = 800.0, exposure: float = 0.5) -> dict[str, torch.Tensor]:
    """The parameters :meth:`SceneGenerator.render` takes (one sample) of a
    :class:`polrig.sim.scene.Scene` of a covered family (a random scene of
    :func:`polrig.sim.scene.random_scene` with a Baek material), so that the torch renderer can be
    compared with :func:`polrig.sim.render.render` on the same scene (tests; not the hot path)."""
    from polrig.sim.shapes import Blob, Box, Cylinder, Sphere, Torus

    t = dict(device=gen.device, dtype=gen.dtype)
    cam_r, cam_t = scene.camera.R, scene.camera.t
    objs = scene.objects
    mat = objs[0].materials[0]

    def pose(ob):
        r, tr = ob.world_pose(scene.turntable, turntable_deg)
        return cam_r @ r, cam_r @ tr + cam_t

    a = objs[0].shape
    rot_a, t_a = pose(objs[0])
    kind = {Sphere: _SPHERE, Box: _BOX, Cylinder: _CYLINDER, Blob: _BLOB, Torus: _TORUS}[type(a)]
    centres, widths, amps = np.zeros((MAX_BUMPS, 3)), np.ones(MAX_BUMPS), np.zeros(MAX_BUMPS)
    if kind == _BLOB:
        k = len(a.amplitudes)
        c = np.asarray(a.centres, float)
        centres[:k] = c / np.linalg.norm(c, axis=1, keepdims=True)
        widths[:k], amps[:k] = a.widths, a.amplitudes
    multi = len(objs) > 1
    rot_b, t_b = pose(objs[1]) if multi else (np.eye(3), np.zeros(3))
    one = lambda v: torch.tensor(np.asarray(v, float), **t)[None]  # noqa: E731
    return {
        "family": torch.tensor([FAMILIES.index(scene.name)], device=gen.device),
        "kind": torch.tensor([kind], device=gen.device), "is_multi": torch.tensor([multi], device=gen.device),
        **_material_parameters(mat, one, gen.device),
        "rot_a": one(rot_a), "t_a": one(t_a),
        "radius": one(getattr(a, "radius_m", getattr(a, "major_radius_m", 0.03))),
        "hh": one(getattr(a, "half_height_m", getattr(a, "minor_radius_m", 0.03))),
        "centres": one(centres), "widths": one(widths), "amplitudes": one(amps),
        "half_a": one(getattr(a, "half_m", (0.03,) * 3)),
        "rot_b": one(rot_b), "t_b": one(t_b),
        "half_b": one(objs[1].shape.half_m if multi else (0.03,) * 3),
        "light": one(cam_r @ scene.light.position_m + cam_t), "colour": one(scene.light.intensity_rgb),
        "axis": one(cam_r @ scene.stage_zero_axis), "stage_deg": one(stage_deg),
        "er": one(extinction_ratio), "exposure": one(exposure),
    }


def _material_parameters(mat, one, device) -> dict[str, torch.Tensor]:
    """The material entries of :func:`scene_parameters` for a :class:`polrig.sim.materials.Material`
    or a :class:`polrig.sim.materials.SurfaceMaterial` without film or depolarization."""
    from polrig.sim.dataset import effective_eta, material_kind

    kind = material_kind(mat)
    if kind in ("film", "depolarizing"):
        raise ValueError(f"scene_parameters: {kind} materials are not rendered by the torch generator")
    if kind == "baek":
        eta = np.full(3, complex(mat.eta))
        au = av = mat.alpha
        beck, tangent, alpha_fit, eta_fit = False, (0.0, 0.0, 1.0), mat.alpha, mat.eta
    else:
        eta = np.asarray(mat.eta_rgb, complex)
        au = mat.alpha
        av = mat.alpha if mat.alpha_v is None else mat.alpha_v
        beck, tangent = mat.distribution == "beckmann", mat.tangent_axis
        alpha_fit = float(np.sqrt(au * av))
        eta_fit = effective_eta(mat.eta_rgb[1]) if mat.conductor else mat.eta_rgb[1].real
    return {"material_kind": torch.tensor([MATERIAL_KINDS.index(kind)], device=device),
            "kd": one(mat.kd), "ks": one(mat.ks), "alpha": one(alpha_fit), "alpha_empty": one(au), "eta": one(eta_fit),
            "au": one(au), "av": one(av), "beckmann": torch.tensor([beck], device=device),
            "eta_re": one(eta.real), "eta_im": one(eta.imag), "tangent": one(tangent)}
