"""Differentiable microfacet pBRDF (Baek et al. 2018) in PyTorch, linear 3x3 blocks in rig frames.

The same math as :mod:`polrig.optics.pbrdf` (the core numpy implementation; ``tests/test_models_pbrdf.py``
checks the two agree to 1e-5 on random inputs), written with torch ops only so that it runs
inside the training graph and exports to ONNX (no ``atan2``, no complex numbers: basis
rotations use ``cos 2phi = c^2 - s^2``, ``sin 2phi = 2 c s`` from dot and cross products).
The rotated specular matrix is written out in closed form element by element and the rank-one
diffuse matrix as one broadcast outer product ``u w^T`` (no batched 3x3 matmuls): the vector
axis is a parameter, so the same code serves matrix-last arrays ``(..., 3)`` and plane-first
images ``(B, 3, H, W)``, and the exported graph is a chain of element-wise ops. Written for
onnxruntime's CPU kernels (measured, ``models/MODEL_CARD.md``): sums over the 3 vector
components as Split + Add (its ReduceSum over 3 channels of an image is about 5 times slower),
choices as {0, 1} blends (its Where and And are slow on images), the mask applied to the
per-pixel scale factors rather than to the 9 elements.

Conventions (``docs/conventions.md``): vectors are camera-frame unit vectors with the vector
axis last, ``normal`` points out of the surface, ``wi`` from the surface towards the light,
``wo`` from the surface towards the camera. Incident Stokes frame ``k = -wi``, ``x`` = stage
zero axis made perpendicular to ``k``; emergent frame ``k = wo``, ``x`` = camera ``X`` made
perpendicular to ``k``; ``y = k x x``. Returned blocks are the dimensionless pBRDF Mueller
matrix times ``cos(theta_i)`` (1/sr), matrix axes last ``(..., 3, 3)``.

Model (Baek, Jeon, Kim, Jung, Kim, "Simultaneous acquisition of polarimetric SVBRDF and
normals", ACM TOG 37(6) 2018; Mitsuba 3 ``src/bsdfs/pplastic.cpp`` for the basis choice):

* specular ``Ms = ks D(h) G(wi, wo) / (4 cos_o) * F_R(theta_d)`` with the Fresnel reflection
  matrix in the s/p bases of the plane (wi, wo), ``s = normalize(wi x h)``;
* diffuse ``Md = cos_i / pi * T_o * diag(1, 0, 0) * T_i`` (unit albedo) with Fresnel
  transmission matrices in the s/p bases of the planes (n, wi) and (n, wo).

GGX ``D = a^2 / (pi (cos_h^2 (a^2 - 1) + 1)^2)`` and the separable Smith shadowing
``G1(w) = 2 cos_w / (cos_w + sqrt(a^2 + (1 - a^2) cos_w^2))`` (Walter et al., EGSR 2007).
"""

from __future__ import annotations

import math

import torch

from polrig.models.layers import sum_over

_EPS = 1e-12
_DEGENERATE_SQ = 1e-14


def cross(a: torch.Tensor, b: torch.Tensor, dim: int = 1) -> torch.Tensor:
    """``a x b`` along axis ``dim`` written out with element-wise ops (ONNX has no Cross op)."""
    a0, a1, a2 = torch.split(a, 1, dim)
    b0, b1, b2 = torch.split(b, 1, dim)
    return torch.cat([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], dim)


class _Vec:
    """Vector helpers along axis ``dim`` (kept with length 1 by reductions).

    Sums over the vector axis are a split and two additions rather than a reduction
    (:func:`polrig.models.layers.sum_over`: on ``(B, 3, H, W)`` images onnxruntime's ReduceSum over
    the 3 channels takes about 6 times as long as Split + 2 Add, ``models/MODEL_CARD.md``)."""

    def __init__(self, dim: int):
        self.dim = dim

    def dot(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return sum_over(a * b, self.dim)

    def cross(self, a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
        return cross(a, b, self.dim)

    def normalize(self, v: torch.Tensor, squared_norm: torch.Tensor | None = None) -> torch.Tensor:
        """``v / sqrt(|v|^2 + eps)``; ``squared_norm``: ``|v|^2`` where the caller has it."""
        return v / torch.sqrt((self.dot(v, v) if squared_norm is None else squared_norm) + _EPS)

    def perpendicular(self, axis: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
        """``axis`` made perpendicular to the unit vector ``k``, normalised."""
        return self.normalize(axis - self.dot(axis, k) * k)

    def axis_or(self, raw: torch.Tensor, fallback: torch.Tensor) -> torch.Tensor:
        """``normalize(raw)``, or ``fallback`` where ``raw`` is (nearly) zero. Written as the
        blend ``f fallback + (1 - f) normalize(raw)`` with ``f`` in {0, 1}, which picks one of
        the two finite values exactly (onnxruntime's Where is slow on images)."""
        r2 = self.dot(raw, raw)
        f = (r2 < _DEGENERATE_SQ).to(raw.dtype)
        return f * fallback + (1.0 - f) * self.normalize(raw, r2)


def rotation_2phi(c: torch.Tensor, s: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(cos 2phi, sin 2phi)`` of the angle ``phi`` with ``(cos phi, sin phi)`` proportional
    to ``(c, s)``. For a rotation about the unit vector ``k`` from the unit axis ``x_from`` to
    ``x_to`` (towards ``y = k x x_from``) ``c = x_from . x_to`` and ``s = k . (x_from x x_to)
    = y . x_to``; ``R(phi) = [[1,0,0],[0,C,S],[0,-S,C]]`` maps Stokes in the ``x_from`` basis
    to the ``x_to`` basis."""
    n2 = c * c + s * s + _EPS
    return (c * c - s * s) / n2, 2.0 * c * s / n2


def _fresnel_r(cos_i: torch.Tensor, eta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Real Fresnel amplitudes ``(r_s, r_p)`` from outside onto a dielectric ``eta > 1``
    (Mitsuba 3 sign of ``r_p``, as :func:`polrig.optics.mueller.specular_reflection`)."""
    ci = cos_i.clamp(0.0, 1.0)
    sin2_t = (1.0 - ci * ci) / (eta * eta)
    ct = torch.sqrt((1.0 - sin2_t).clamp_min(0.0))
    rs = (ci - eta * ct) / (ci + eta * ct)
    rp = (eta * ci - ct) / (eta * ci + ct)
    return rs, rp


def transmission_ab(cos_t: torch.Tensor, eta) -> tuple[torch.Tensor, torch.Tensor]:
    """The diffuse term's Fresnel transmission as ``(a, b)``: half the sum and half the difference
    of the s and p intensity transmittances ``1 - r_s^2`` and ``1 - r_p^2`` (clamped to [0, 1])
    at incidence cosine ``cos_t`` and index ``eta`` (a float or a tensor broadcasting with it);
    a diattenuator ``[[a, b], [b, a]]`` in the plane of incidence (Baek et al. 2018)."""
    ts_r, tp_r = _fresnel_r(cos_t, eta)
    ts, tp = (1.0 - ts_r * ts_r).clamp(0.0, 1.0), (1.0 - tp_r * tp_r).clamp(0.0, 1.0)
    return 0.5 * (ts + tp), 0.5 * (ts - tp)


def ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution (1/sr) at ``cos_h = n . h`` (zero for ``cos_h <= 0``)."""
    a2 = alpha * alpha
    t = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * t * t + _EPS) * (cos_h > 0).to(cos_h.dtype)


def smith_g1(cos_w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Separable Smith GGX masking ``2 cos / (cos + sqrt(a^2 + (1 - a^2) cos^2))``."""
    a2 = alpha * alpha
    c = cos_w.clamp_min(0.0)
    return 2.0 * c / (c + torch.sqrt(a2 + (1.0 - a2) * c * c) + _EPS)


def _blocks(n, wi, wo, alpha, stage_zero_axis, camera_x_axis, eta: float, dim: int,
            weight: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Specular and diffuse blocks with the matrix axes at ``dim`` and ``dim + 1`` (``dim = 1``:
    ``(B, 3, 3, H, W)``; ``dim = -1``: ``(..., 3, 3)``), times ``weight`` (e.g. a mask)
    where given. Vector inputs have the vector axis at ``dim``.

    Rotation angles come from dot products with the frames' ``y`` axes, computed once per
    frame: ``k . (x x t) = t . (k x x) = t . y`` and ``k . (t x x) = -t . y``."""
    v = _Vec(dim)
    n, wi, wo = v.normalize(n), v.normalize(wi), v.normalize(wo)
    cos_i, cos_o = v.dot(n, wi), v.dot(n, wo)
    visible = (cos_i > 0).to(n.dtype) * (cos_o > 0).to(n.dtype)  # not &: onnxruntime's And is slow on images
    if weight is not None:
        visible = visible * weight
    k_in, k_out = -wi, wo
    x_in = v.perpendicular(stage_zero_axis, k_in)
    x_out = v.perpendicular(camera_x_axis, k_out)
    y_in, y_out = v.cross(k_in, x_in), v.cross(k_out, x_out)

    # Specular: Fresnel reflection at the half vector in the plane (wi, wo), s = wi x h.
    h = v.normalize(wi + wo)
    s_axis = v.axis_or(v.cross(wi, h), x_in)
    ci, si = rotation_2phi(v.dot(x_in, s_axis), v.dot(y_in, s_axis))
    co, so = rotation_2phi(v.dot(s_axis, x_out), -v.dot(y_out, s_axis))
    rs, rp = _fresnel_r(v.dot(wi, h), eta)
    scalar = (ggx_d(v.dot(n, h), alpha) * smith_g1(cos_i, alpha) * smith_g1(cos_o, alpha)
              / (4.0 * cos_o.clamp_min(1e-6))) * visible
    a = 0.5 * (rs * rs + rp * rp) * scalar
    b = 0.5 * (rs * rs - rp * rp) * scalar
    c = rs * rp * scalar
    # R(co, so) F R(ci, si) with the Fresnel block F = [[a, b, 0], [b, a, 0], [0, 0, c]]
    a_ci, a_si, c_si, c_ci = a * ci, a * si, c * si, c * ci
    spec = [a, b * ci, b * si,
            co * b, co * a_ci - so * c_si, co * a_si + so * c_ci,
            -so * b, -so * a_ci - co * c_si, -so * a_si + co * c_ci]

    # Diffuse: rank one, (R_out T_out e0) (e0^T T_in R_in) cos_i / pi = u w^T.
    s_in = v.axis_or(v.cross(n, k_in), x_in)
    s_out = v.axis_or(v.cross(n, k_out), x_out)
    ci_d, si_d = rotation_2phi(v.dot(x_in, s_in), v.dot(y_in, s_in))
    co_d, so_d = rotation_2phi(v.dot(s_out, x_out), -v.dot(y_out, s_out))

    a_i, b_i = transmission_ab(cos_i, eta)
    a_o, b_o = transmission_ab(cos_o, eta)
    scale = cos_i.clamp_min(0.0) / math.pi * visible
    u = torch.cat([a_o, co_d * b_o, -so_d * b_o], dim)
    w = torch.cat([scale * a_i, scale * ci_d * b_i, scale * si_d * b_i], dim)
    shape = torch.broadcast_shapes(*[t.shape for t in spec])
    rows = dim if dim >= 0 else dim - 1  # the row axis of the block
    spec_block = torch.cat([p if p.shape == shape else p.expand(shape) for p in spec], dim).unflatten(dim, (3, 3))
    return spec_block, u.unsqueeze(rows + 1) * w.unsqueeze(rows)


def specular_diffuse_blocks(normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, *,
                            alpha: torch.Tensor, stage_zero_axis: torch.Tensor,
                            camera_x_axis: torch.Tensor, eta: float = 1.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Unit specular (``ks = 1``) and diffuse (``kd = 1``) blocks ``(..., 3, 3)`` in the rig
    frames, as :func:`polrig.optics.pbrdf.specular_diffuse_blocks`.

    ``normal``, ``wi``, ``wo``: ``(..., 3)`` (normalised here); ``alpha``: GGX roughness
    broadcastable to ``(...)``; ``stage_zero_axis``, ``camera_x_axis``: ``(..., 3)`` or ``(3,)``.
    Pixels facing away from the light or the camera (``cos <= 0``) get zero blocks.
    """
    alpha = torch.as_tensor(alpha, dtype=normal.dtype, device=normal.device)[..., None]
    return _blocks(normal, wi, wo, alpha, stage_zero_axis, camera_x_axis, eta, -1)


def image_blocks(normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor,
                 stage_zero_axis: torch.Tensor, camera_x_axis: torch.Tensor | None = None,
                 eta: float = 1.5, mask: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Plane-first version for networks: ``normal``/``wi``/``wo`` ``(B, 3, H, W)``, ``alpha``
    ``(B,)``, ``stage_zero_axis`` ``(B, 3)`` -> blocks ``(B, 3, 3, H, W)`` (ks = kd = 1), each
    times ``mask`` ``(B, 1, H, W)`` where given (applied to the per-pixel scale factors, before
    the 9 elements are formed)."""
    if camera_x_axis is None:  # the camera X axis, built from the input so tracing keeps no constant tensor
        cam = torch.cat([torch.ones_like(normal[:1, :1, :1, :1]), torch.zeros_like(normal[:1, :2, :1, :1])], 1)
    else:
        cam = camera_x_axis.reshape(-1, 3, 1, 1)
    return _blocks(normal, wi, wo, alpha[:, None, None, None], stage_zero_axis[:, :, None, None],
                   cam, eta, 1, mask)
