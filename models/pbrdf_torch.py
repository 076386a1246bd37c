"""Differentiable microfacet pBRDF (Baek et al. 2018) in PyTorch, linear 3x3 blocks in rig frames.

The same math as :mod:`polrig.pbrdf` (the core numpy implementation; ``tests/test_models_pbrdf.py``
checks the two agree to 1e-5 on random inputs), written with torch ops only so that it runs
inside the training graph and exports to ONNX (no ``atan2``, no complex numbers: basis
rotations use ``cos 2phi = c^2 - s^2``, ``sin 2phi = 2 c s`` from dot and cross products).

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

_EPS = 1e-12


def _dot(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return (a * b).sum(-1)


def _normalize(v: torch.Tensor) -> torch.Tensor:
    return v / torch.sqrt((v * v).sum(-1, keepdim=True) + _EPS)


def _perpendicular_axis(axis: torch.Tensor, k: torch.Tensor) -> torch.Tensor:
    """``axis`` made perpendicular to the unit vector ``k`` and normalised."""
    return _normalize(axis - _dot(axis, k)[..., None] * k)


def _basis_rotation(k: torch.Tensor, x_from: torch.Tensor, x_to: torch.Tensor) -> torch.Tensor:
    """Stokes rotator ``R(phi)`` (``(..., 3, 3)``) with ``phi`` the angle from ``x_from`` to
    ``x_to`` about ``k`` (towards ``y = k x x_from``): ``S_to = R(phi) S_from``."""
    c = _dot(x_from, x_to)
    s = _dot(k, torch.cross(x_from, x_to, dim=-1))
    n2 = c * c + s * s + _EPS
    c2 = (c * c - s * s) / n2
    s2 = 2.0 * c * s / n2
    one, zero = torch.ones_like(c2), torch.zeros_like(c2)
    return torch.stack([
        torch.stack([one, zero, zero], -1),
        torch.stack([zero, c2, s2], -1),
        torch.stack([zero, -s2, c2], -1),
    ], -2)


def _fresnel_r(cos_i: torch.Tensor, eta: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Real Fresnel amplitudes ``(r_s, r_p)`` from outside onto a dielectric ``eta > 1``
    (Mitsuba 3 sign of ``r_p``, as :func:`polrig.mueller.specular_reflection`)."""
    ci = cos_i.clamp(0.0, 1.0)
    sin2_t = (1.0 - ci * ci) / (eta * eta)
    ct = torch.sqrt((1.0 - sin2_t).clamp_min(0.0))
    rs = (ci - eta * ct) / (ci + eta * ct)
    rp = (eta * ci - ct) / (eta * ci + ct)
    return rs, rp


def _sp_block(a: torch.Tensor, b: torch.Tensor, c: torch.Tensor) -> torch.Tensor:
    zero = torch.zeros_like(a)
    return torch.stack([
        torch.stack([a, b, zero], -1),
        torch.stack([b, a, zero], -1),
        torch.stack([zero, zero, c], -1),
    ], -2)


def fresnel_reflection_block(cos_i: torch.Tensor, eta: float) -> torch.Tensor:
    """3x3 Fresnel reflection block in s/p bases (``polrig.mueller.specular_reflection``)."""
    rs, rp = _fresnel_r(cos_i, eta)
    Rs, Rp = rs * rs, rp * rp
    return _sp_block(0.5 * (Rs + Rp), 0.5 * (Rs - Rp), rs * rp)


def fresnel_transmission_block(cos_i: torch.Tensor, eta: float) -> torch.Tensor:
    """3x3 Fresnel transmission block in s/p bases (``polrig.mueller.specular_transmission``)."""
    rs, rp = _fresnel_r(cos_i, eta)
    Ts, Tp = (1.0 - rs * rs).clamp(0.0, 1.0), (1.0 - rp * rp).clamp(0.0, 1.0)
    return _sp_block(0.5 * (Ts + Tp), 0.5 * (Ts - Tp), torch.sqrt(Ts * Tp + _EPS) * (Ts * Tp > 0))


def ggx_d(cos_h: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """GGX normal distribution (1/sr) for ``cos_h = n . h``."""
    a2 = alpha * alpha
    t = cos_h * cos_h * (a2 - 1.0) + 1.0
    return a2 / (math.pi * t * t + _EPS) * (cos_h > 0)


def smith_g1(cos_w: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """Separable Smith GGX masking for a direction at ``cos_w = n . w``."""
    a2 = alpha * alpha
    c = cos_w.clamp_min(0.0)
    return 2.0 * c / (c + torch.sqrt(a2 + (1.0 - a2) * c * c) + _EPS)


def specular_diffuse_blocks(normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, *,
                            alpha: torch.Tensor, stage_zero_axis: torch.Tensor,
                            camera_x_axis: torch.Tensor, eta: float = 1.5,
                            ks: float | torch.Tensor = 1.0) -> tuple[torch.Tensor, torch.Tensor]:
    """Specular and (unit-albedo) diffuse 3x3 blocks ``(..., 3, 3)`` in the rig frames.

    ``normal``, ``wi``, ``wo``: ``(..., 3)`` (normalised here); ``alpha``: GGX roughness
    broadcastable to ``(...)``; ``stage_zero_axis``, ``camera_x_axis``: ``(..., 3)`` or ``(3,)``.
    Pixels facing away from the light or the camera (``cos <= 0``) get zero blocks.
    """
    n, wi, wo = _normalize(normal), _normalize(wi), _normalize(wo)
    alpha = torch.as_tensor(alpha, dtype=n.dtype)
    cos_i, cos_o = _dot(n, wi), _dot(n, wo)
    visible = ((cos_i > 0) & (cos_o > 0)).to(n.dtype)
    k_in, k_out = -wi, wo
    x_in = _perpendicular_axis(torch.broadcast_to(stage_zero_axis, k_in.shape), k_in)
    x_out = _perpendicular_axis(torch.broadcast_to(camera_x_axis, k_out.shape), k_out)

    # Specular: Fresnel reflection at the half vector, s axis perpendicular to the plane (wi, wo).
    h = _normalize(wi + wo)
    cos_d = _dot(wi, h)
    s_raw = torch.cross(wi, h, dim=-1)
    degenerate = (_dot(s_raw, s_raw) < 1e-14)[..., None]
    s_axis = torch.where(degenerate, x_out, _normalize(s_raw))
    f_local = fresnel_reflection_block(cos_d, eta)
    spec = (_basis_rotation(k_out, s_axis, x_out) @ f_local
            @ _basis_rotation(k_in, x_in, _perpendicular_axis(s_axis, k_in)))
    scalar = (ggx_d(_dot(n, h), alpha) * smith_g1(cos_i, alpha) * smith_g1(cos_o, alpha)
              / (4.0 * cos_o.clamp_min(1e-6)))
    spec = spec * (ks * scalar * visible)[..., None, None]

    # Diffuse: transmission in at theta_i, depolarize, transmission out at theta_o.
    s_in_raw = torch.cross(n, k_in, dim=-1)
    s_out_raw = torch.cross(n, k_out, dim=-1)
    s_in = torch.where((_dot(s_in_raw, s_in_raw) < 1e-14)[..., None], x_in, _normalize(s_in_raw))
    s_out = torch.where((_dot(s_out_raw, s_out_raw) < 1e-14)[..., None], x_out, _normalize(s_out_raw))
    t_in = fresnel_transmission_block(cos_i, eta) @ _basis_rotation(k_in, x_in, s_in)
    t_out = _basis_rotation(k_out, s_out, x_out) @ fresnel_transmission_block(cos_o, eta)
    diff = t_out[..., :, 0:1] * t_in[..., 0:1, :]
    diff = diff * (cos_i.clamp_min(0.0) / math.pi * visible)[..., None, None]
    return spec, diff


def image_blocks(normal: torch.Tensor, wi: torch.Tensor, wo: torch.Tensor, alpha: torch.Tensor,
                 stage_zero_axis: torch.Tensor, camera_x_axis: torch.Tensor | None = None,
                 eta: float = 1.5) -> tuple[torch.Tensor, torch.Tensor]:
    """Plane-first wrapper for networks: ``normal``/``wi``/``wo`` ``(B, 3, H, W)``, ``alpha``
    ``(B,)``, ``stage_zero_axis`` ``(B, 3)`` -> blocks ``(B, 3, 3, H, W)`` (ks = 1)."""
    perm = lambda t: t.permute(0, 2, 3, 1)  # noqa: E731
    if camera_x_axis is None:
        camera_x_axis = torch.tensor([1.0, 0.0, 0.0], dtype=normal.dtype)
    spec, diff = specular_diffuse_blocks(
        perm(normal), perm(wi), perm(wo), alpha=alpha[:, None, None],
        stage_zero_axis=stage_zero_axis[:, None, None, :], camera_x_axis=camera_x_axis, eta=eta)
    return spec.permute(0, 3, 4, 1, 2), diff.permute(0, 3, 4, 1, 2)
