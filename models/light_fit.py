"""Global light direction by analysis-by-synthesis: which direction makes the pBRDF explain the
one measured Stokes image best? (PyTorch; used by :mod:`polrig.models.diagnose`, not by the shipped
graph: with PIPNet's normals on unseen shapes it does no better than PIPNet's own light, with
the true normals it finds the light to about 9 deg, ``models/MODEL_CARD.md``.)

The rig has one point light, so over an object a few centimetres across at 0.3-0.6 m the
direction to it varies by a few degrees: one direction per image. For each of ``K`` candidate
directions ``w`` the analytic pBRDF (:func:`polrig.models.pbrdf_torch.image_blocks`, eta = 1.5) on
the given normals renders the unit specular and diffuse Stokes images under the known incident
state, ``a = Ms(w) s_in`` and ``b = Md(w) s_in`` (``(B, 3, H, W)`` each), and the global gains
of the model ``S_c = g_s a + g_c b`` (one specular gain, one diffuse gain per colour ``c``: one
material per image, colour only in the diffuse part) are solved in closed form by variable
projection:

* ``g_c = (b.S_c - g_s a.b) / b.b``; substituting, ``g_s = sum_c q.S_c / (C q.q)`` with
  ``q = a - (a.b / b.b) b`` (``a`` with ``b`` projected out);
* both clamped at zero (``g_c`` recomputed from the clamped ``g_s``), and the residual
  ``sum_c |S_c - g_s a - g_c b|^2`` evaluated from the same dot products.

Dot products run over the masked pixels of an average-pooled copy of the images (``pool``:
cheap, and the fall-off of the light across the object matters little at that scale). The
candidate with the smallest residual is refined once on a finer local set around it.

Unlike PIPNet's learned light head this is local physics: shading (``cos theta_i`` through the
diffuse block), the highlight position and the polarization of both components all vote, on
any shape; it needs normals that are roughly right (PIPNet's, with its shape-from-polarization
prior). All ops are element-wise, reductions, ``ArgMin`` and ``Gather``, so it could run inside
an exported graph once the normals are good enough to make it worth it.

:func:`shading_pick` chooses between two candidate normals per pixel by Lambertian shading
under a given light (used by :mod:`polrig.models.diagnose` on the shape-from-polarization candidates).
"""

from __future__ import annotations

import math

import torch
from torch.nn import functional as F

from polrig.models.pbrdf_torch import cross, image_blocks

_EPS = 1e-12


def fibonacci_directions(count: int, max_z: float = 1.0) -> torch.Tensor:
    """About ``count`` near-uniform unit vectors on the sphere (Fibonacci lattice), those with
    ``z <= max_z`` kept -> ``(K, 3)``. In the camera frame (``+Z`` forward) a light in front of
    the object has ``z < 0`` as seen from it."""
    k = torch.arange(count, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * k / count
    r = torch.sqrt((1.0 - z * z).clamp_min(0.0))
    phi = math.pi * (1.0 + math.sqrt(5.0)) * k
    d = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], 1)
    return d[d[:, 2] <= max_z].to(torch.float32)


def local_offsets(spread_deg: float, rings: int = 2, per_ring: int = 8) -> torch.Tensor:
    """Offsets ``(K, 2)`` (radians, tangent plane) of a polar grid with ``rings`` rings of
    ``per_ring`` points out to ``spread_deg``, plus the centre."""
    pts = [(0.0, 0.0)]
    for i in range(1, rings + 1):
        rad = math.radians(spread_deg) * i / rings
        pts += [(rad * math.cos(2 * math.pi * j / per_ring + i), rad * math.sin(2 * math.pi * j / per_ring + i))
                for j in range(per_ring)]
    return torch.tensor(pts, dtype=torch.float32)


def _masked_pool(x: torch.Tensor, mask: torch.Tensor, pool: int) -> torch.Tensor:
    return F.avg_pool2d(x * mask, pool, pool) / F.avg_pool2d(mask, pool, pool).clamp_min(1e-6)


def _residuals(cands: torch.Tensor, stokes: torch.Tensor, normal: torch.Tensor, wo: torch.Tensor,
               alpha: torch.Tensor, s_in: torch.Tensor, axis: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Residual of the best global-gain fit for every candidate: ``cands`` (B, K, 3) -> (B, K)."""
    b, k, _ = cands.shape
    c, h, w = stokes.shape[1], stokes.shape[-2], stokes.shape[-1]
    rep = lambda t: t[:, None].expand(b, k, *t.shape[1:]).reshape(b * k, *t.shape[1:])  # noqa: E731
    wi = cands.reshape(b * k, 3, 1, 1).expand(b * k, 3, h, w)
    ms, md = image_blocks(rep(normal), wi, rep(wo), rep(alpha[:, None])[:, 0], rep(axis))
    sv = rep(s_in)[:, None, :, None, None]
    m = rep(mask)  # (BK, 1, H, W)
    av = (ms * sv).sum(2) * m  # (BK, 3, H, W)
    bv = (md * sv).sum(2) * m
    st = rep(stokes) * m[:, None]  # (BK, C, 3, H, W)
    dot = lambda x, y: (x * y).sum((-3, -2, -1))  # noqa: E731
    aa, ab, bb = dot(av, av), dot(av, bv), dot(bv, bv) + _EPS
    a_s = (av[:, None] * st).sum((-3, -2, -1))  # (BK, C)
    b_s = (bv[:, None] * st).sum((-3, -2, -1))
    ss = (st * st).sum((-3, -2, -1))
    qq = (aa - ab * ab / bb).clamp_min(_EPS)
    g_s = ((a_s - (ab / bb)[:, None] * b_s).sum(1) / (c * qq)).clamp_min(0.0)
    g_c = ((b_s - g_s[:, None] * ab[:, None]) / bb[:, None]).clamp_min(0.0)
    res = (ss - 2 * g_s[:, None] * a_s - 2 * g_c * b_s + (g_s * g_s * aa)[:, None]
           + 2 * g_s[:, None] * g_c * ab[:, None] + g_c * g_c * bb[:, None]).sum(1)
    return res.reshape(b, k)


def _pick(cands: torch.Tensor, res: torch.Tensor) -> torch.Tensor:
    best = torch.argmin(res, 1)  # (B,)
    return torch.gather(cands, 1, best[:, None, None].expand(-1, 1, 3))[:, 0]


def fit_light_direction(stokes: torch.Tensor, normal: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor,
                        s_in: torch.Tensor, stage_zero_axis: torch.Tensor, mask: torch.Tensor, *,
                        candidates: torch.Tensor, offsets: torch.Tensor, pool: int = 4) -> torch.Tensor:
    """Unit light direction ``(B, 3)`` (camera frame, from the object towards the light).

    ``stokes`` (B, C, 3, H, W) measured; ``normal``, ``wo`` (B, 3, H, W) unit; ``alpha`` (B,);
    ``s_in`` (B, 3); ``stage_zero_axis`` (B, 3); ``mask`` (B, 1, H, W); ``candidates`` (K, 3)
    unit (coarse search, e.g. :func:`fibonacci_directions`); ``offsets`` (L, 2) radians in the
    tangent plane of the coarse winner (fine search, :func:`local_offsets`). ``H`` and ``W``
    must be multiples of ``pool``."""
    b, c = stokes.shape[:2]
    h, w = stokes.shape[-2:]
    st = _masked_pool(stokes.reshape(b, c * 3, h, w), mask, pool).reshape(b, c, 3, h // pool, w // pool)
    n = F.normalize(_masked_pool(normal, mask, pool), dim=1, eps=1e-6)
    v = F.normalize(_masked_pool(wo, mask, pool), dim=1, eps=1e-6)
    m = (F.avg_pool2d(mask, pool, pool) > 0.5).to(stokes.dtype)
    coarse = candidates.to(stokes.dtype)[None].expand(b, -1, -1)
    best = _pick(coarse, _residuals(coarse, st, n, v, alpha, s_in, stage_zero_axis, m))
    # tangent basis at the coarse winner
    helper = torch.where(best[:, 2:3].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0], dtype=best.dtype).expand_as(best),
                         torch.tensor([1.0, 0.0, 0.0], dtype=best.dtype).expand_as(best))
    t1 = F.normalize(helper - (helper * best).sum(1, keepdim=True) * best, dim=1)
    t2 = cross(best, t1)
    off = offsets.to(stokes.dtype)
    fine = F.normalize(best[:, None] + off[None, :, 0:1] * t1[:, None] + off[None, :, 1:2] * t2[:, None], dim=2)
    return _pick(fine, _residuals(fine, st, n, v, alpha, s_in, stage_zero_axis, m))


def shading_pick(plus: torch.Tensor, minus: torch.Tensor, wi: torch.Tensor, intensity: torch.Tensor,
                 mask: torch.Tensor, iterations: int = 5) -> torch.Tensor:
    """Per pixel, the one of two candidate normals ``(B, 3, H, W)`` whose Lambertian shading
    ``k max(n . wi, 0)`` explains ``intensity`` ``(B, H, W)`` better, with one albedo ``k`` per
    image (least squares over ``mask`` ``(B, H, W)`` bool, alternated with the choice); ``wi``
    broadcasts against ``plus`` -> ``(B, 3, H, W)``."""
    sp, sm = (plus * wi).sum(1).clamp_min(0.0), (minus * wi).sum(1).clamp_min(0.0)
    m = mask.to(intensity.dtype)
    k = torch.ones(plus.shape[0], 1, 1, dtype=intensity.dtype)
    for _ in range(iterations):
        take_plus = (intensity - k * sp).abs() < (intensity - k * sm).abs()
        s = torch.where(take_plus, sp, sm) * m
        k = ((intensity * s).sum((1, 2)) / (s * s).sum((1, 2)).clamp_min(_EPS))[:, None, None]
    return torch.where(take_plus[:, None], plus, minus)

