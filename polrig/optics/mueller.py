"""Mueller calculus: one small pure function per optical element, vectorised.

Frame convention: ``docs/conventions.md`` (Stokes bases as in Mitsuba 3; an element rotated
by ``angle`` has its axis turned from the basis ``x`` towards ``y``). Every function returns
arrays with the matrix axes last, ``(..., 4, 4)``; :func:`linear_block` takes the 3x3 linear
part ``(..., 3, 3)`` used throughout polrig. Angles are radians unless the name says ``_deg``.

References: E. Collett, *Field Guide to Polarization* (SPIE 2005) for the element matrices;
Mitsuba 3 ``include/mitsuba/render/mueller.h`` for the Fresnel matrices and sign conventions
(reflection ``[[a,b,0,0],[b,a,0,0],[0,0,c cos d, -c sin d],[0,0,c sin d, c cos d]]`` with
``a = (Rs+Rp)/2``, ``b = (Rs-Rp)/2``, ``c = sqrt(Rs Rp)``, ``d`` the s-p phase difference).
"""

from __future__ import annotations

import numpy as np

ArrayLike = np.ndarray | float


def _stack(rows: list[list], shape: tuple[int, ...]) -> np.ndarray:
    """Build a ``(..., n, n)`` array from nested lists of scalars/arrays broadcast to ``shape``."""
    n = len(rows)
    out = np.empty(shape + (n, n), dtype=np.result_type(*[np.asarray(v) for r in rows for v in r], np.float64))
    for i, r in enumerate(rows):
        for j, v in enumerate(r):
            out[..., i, j] = v
    return out


def _shape(*xs) -> tuple[int, ...]:
    return np.broadcast_shapes(*[np.shape(x) for x in xs])


def identity(shape: tuple[int, ...] = ()) -> np.ndarray:
    return np.broadcast_to(np.eye(4), shape + (4, 4)).copy()


def depolarizer(value: ArrayLike = 1.0) -> np.ndarray:
    """Ideal depolarizer of transmittance ``value``: ``diag(value, 0, 0, 0)``."""
    v = np.asarray(value, dtype=np.float64)
    out = np.zeros(v.shape + (4, 4))
    out[..., 0, 0] = v
    return out


def linear_polarizer(value: ArrayLike = 1.0) -> np.ndarray:
    """Ideal linear polarizer with its transmission axis along the basis ``x`` axis."""
    v = 0.5 * np.asarray(value, dtype=np.float64)
    out = np.zeros(v.shape + (4, 4))
    out[..., :2, :2] = v[..., None, None]
    return out


def diattenuator(tx: ArrayLike, ty: ArrayLike) -> np.ndarray:
    """Linear diattenuator with intensity transmittances ``tx`` (along ``x``) and ``ty``.

    A polarizer of finite extinction ratio ``ER = tx / ty`` is ``diattenuator(1, 1/ER)``.
    """
    tx, ty = np.asarray(tx, float), np.asarray(ty, float)
    a, b, c = 0.5 * (tx + ty), 0.5 * (tx - ty), np.sqrt(tx * ty)
    z = np.zeros(_shape(tx, ty))
    return _stack([[a, b, z, z], [b, a, z, z], [z, z, c, z], [z, z, z, c]], z.shape)


def linear_retarder(phase_rad: ArrayLike) -> np.ndarray:
    """Linear retarder with its fast axis along ``x`` and retardance ``phase_rad``:
    ``[[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, cos d, sin d], [0, 0, -sin d, cos d]]``
    (D. H. Goldstein, *Polarized Light*, 3rd ed., eq. 6.43; Mitsuba 3
    ``mueller::linear_retarder``). This is the sign of :func:`specular_reflection`'s
    retardance block (``docs/conventions.md``: ``S3`` as in Mitsuba 3), so films and metals
    compose consistently; ``jones_to_mueller(diag(1, exp(i d)))`` is this matrix."""
    s, c = np.sin(phase_rad), np.cos(phase_rad)
    one, z = np.ones(np.shape(s)), np.zeros(np.shape(s))
    return _stack([[one, z, z, z], [z, one, z, z], [z, z, c, s], [z, z, -s, c]], np.shape(s))


def retarder_at(fast_axis_rad: ArrayLike, retardance_rad: ArrayLike) -> np.ndarray:
    """Linear retarder with its fast axis at ``fast_axis_rad`` (from ``x`` towards ``y``) and
    retardance ``retardance_rad`` (the phase the slow axis gains over the fast one; Jones
    ``diag(1, exp(i d))`` in the axes of the plate, as :func:`linear_retarder`):
    ``R(-a) LR(d) R(a)``.

    Identities (tested): ``d = 0`` is the identity; ``d = pi`` (half-wave plate) mirrors the
    linear polarization angle about the fast axis; ``retarder_at(a, d) @ retarder_at(a, e) =
    retarder_at(a, d + e)``; the matrix is orthogonal with ``m00 = 1`` (non-depolarizing,
    no diattenuation). Mitsuba 3 ``mueller::rotated_element(a, mueller::linear_retarder(d))``.
    """
    return rotated_element(fast_axis_rad, linear_retarder(retardance_rad))


def partial_depolarizer(polarized_fraction: ArrayLike) -> np.ndarray:
    """Isotropic partial depolarizer ``diag(1, p, p, p)`` keeping a fraction ``p`` in
    ``[0, 1]`` of the polarized part (``p = 1``: identity, ``p = 0``: ideal depolarizer).
    A convex sum ``p I + (1 - p) depolarizer(1)`` of realizable matrices, so realizable."""
    p = np.asarray(polarized_fraction, dtype=np.float64)
    out = np.zeros(p.shape + (4, 4))
    out[..., 0, 0] = 1.0
    for i in (1, 2, 3):
        out[..., i, i] = p
    return out


def rotator(angle_rad: ArrayLike) -> np.ndarray:
    """Rotation of the Stokes basis ``x`` axis by ``angle_rad`` towards ``y``.

    ``rotator(a) @ S`` expresses ``S`` in the basis turned by ``a``.
    """
    s, c = np.sin(2 * np.asarray(angle_rad, float)), np.cos(2 * np.asarray(angle_rad, float))
    one, z = np.ones(np.shape(s)), np.zeros(np.shape(s))
    return _stack([[one, z, z, z], [z, c, s, z], [z, -s, c, z], [z, z, z, one]], np.shape(s))


def rotated_element(angle_rad: ArrayLike, m: np.ndarray) -> np.ndarray:
    """Element ``m`` turned by ``angle_rad`` (from ``x`` towards ``y``): ``R(-a) M R(a)``."""
    return rotator(-np.asarray(angle_rad)) @ m @ rotator(angle_rad)


def polarizer_at(angle_rad: ArrayLike, extinction_ratio: ArrayLike = np.inf) -> np.ndarray:
    """Linear polarizer (unit major transmittance) with axis at ``angle_rad``.

    ``extinction_ratio`` = major / minor intensity transmittance, ``>= 1`` (``1`` transmits
    both axes alike; ``inf`` is ideal). Raises ``ValueError`` otherwise (NaN included).
    """
    er = np.asarray(extinction_ratio, float)
    if not np.all(er >= 1.0):
        raise ValueError(f"extinction_ratio must be >= 1 (inf for an ideal polarizer), got {extinction_ratio!r}")
    ty = np.where(np.isinf(er), 0.0, 1.0 / np.where(np.isinf(er), 1.0, er))
    return rotated_element(angle_rad, diattenuator(np.ones_like(ty), ty))


def _fresnel_amplitudes(cos_theta_i: ArrayLike, eta: ArrayLike | complex):
    """Complex Fresnel amplitudes ``(r_s, r_p)`` for light arriving
    from the side with index 1 onto a medium of relative index ``eta`` (may be complex).

    ``r_p`` uses Mitsuba 3's sign (``(eta cos_i - cos_t) / (eta cos_i + cos_t)``), which makes
    normal-incidence reflection ``diag(R, R, -R, -R)``: reflection flips the handedness of
    the basis. Energy transmittances are ``1 - |r|^2`` (valid for lossless dielectrics).

    Evaluated with ``eta cos_t = sqrt(eta^2 - 1 + cos_i^2)`` (Snell's law; the principal root
    is the decaying transmitted wave for ``Re eta > 0, Im eta >= 0``), which has no
    cancellation near grazing when ``eta`` is close to 1; ``r_p`` is multiplied through by
    ``eta``. An index-matched interface (``eta = 1``) reflects nothing, also at exactly
    grazing incidence, where the quotients are ``0 / 0``.
    """
    ci = np.clip(np.abs(np.asarray(cos_theta_i, dtype=np.float64)), 0.0, 1.0)
    eta_c = np.asarray(eta).astype(np.complex128)
    ect = np.sqrt(eta_c**2 - 1.0 + ci**2)  # eta cos_t
    e2ci = eta_c**2 * ci
    den_s, den_p = ci + ect, e2ci + ect
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = np.where(den_s == 0, 0.0, (ci - ect) / den_s)
        rp = np.where(den_p == 0, 0.0, (e2ci - ect) / den_p)
    return rs, rp


def fresnel_reflectance(cos_theta_i: ArrayLike, eta: ArrayLike | complex) -> tuple[np.ndarray, np.ndarray]:
    """Intensity reflectances ``(Rs, Rp)``."""
    rs, rp = _fresnel_amplitudes(cos_theta_i, eta)
    return np.abs(rs) ** 2, np.abs(rp) ** 2


def specular_reflection(cos_theta_i: ArrayLike, eta: ArrayLike | complex) -> np.ndarray:
    """Fresnel reflection Mueller matrix in the s/p bases of the plane of incidence.

    Bases: ``x`` = s direction (perpendicular to the plane of incidence) for both the incident
    and the reflected beam (Mitsuba 3 ``mueller::specular_reflection``).
    """
    rs, rp = _fresnel_amplitudes(cos_theta_i, eta)
    Rs, Rp = np.abs(rs) ** 2, np.abs(rp) ** 2
    a, b = 0.5 * (Rs + Rp), 0.5 * (Rs - Rp)
    prod = rs * np.conj(rp)  # c * exp(i delta)
    ccos, csin = prod.real, prod.imag
    z = np.zeros(a.shape)
    return _stack([[a, b, z, z], [b, a, z, z], [z, z, ccos, -csin], [z, z, csin, ccos]], a.shape)


def specular_transmission(cos_theta_i: ArrayLike, eta: ArrayLike) -> np.ndarray:
    """Fresnel transmission Mueller matrix (energy, lossless dielectric ``eta``), s/p bases.

    ``a = (Ts+Tp)/2``, ``b = (Ts-Tp)/2``, ``c = sqrt(Ts Tp)`` with ``T = 1 - R``; zero beyond
    total internal reflection.
    """
    Rs, Rp = fresnel_reflectance(cos_theta_i, eta)
    Ts, Tp = np.clip(1.0 - Rs, 0.0, 1.0), np.clip(1.0 - Rp, 0.0, 1.0)
    a, b, c = 0.5 * (Ts + Tp), 0.5 * (Ts - Tp), np.sqrt(Ts * Tp)
    z = np.zeros(a.shape)
    return _stack([[a, b, z, z], [b, a, z, z], [z, z, c, z], [z, z, z, c]], a.shape)


def linear_block(m: np.ndarray) -> np.ndarray:
    """The 3x3 linear block ``M[..., :3, :3]`` (exact for incident states with ``S3 = 0``)."""
    return np.asarray(m)[..., :3, :3]


def pad_linear(m3: np.ndarray) -> np.ndarray:
    """Complete a 3x3 linear block to 4x4 by zero padding (``m33 = 0``, no circular coupling).

    This is the completion used by the realizability tests unless stated otherwise; a zero
    padded block can fail a test that some other completion would pass (Gil et al.,
    arXiv:2510.06305), see :mod:`polrig.optics.realizability`.
    """
    m3 = np.asarray(m3)
    out = np.zeros(m3.shape[:-2] + (4, 4), dtype=m3.dtype)
    out[..., :3, :3] = m3
    return out


def apply(m: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Forward model ``S_out = M @ S_in``, broadcast over leading axes (works for 3 or 4)."""
    return np.einsum("...ij,...j->...i", m, s)


def polarizer_stokes(angle_rad: ArrayLike, extinction_ratio: ArrayLike = np.inf,
                     intensity: ArrayLike = 1.0) -> np.ndarray:
    """Linear Stokes ``(..., 3)`` of unpolarized light of ``intensity`` after a polarizer."""
    s_unpol = np.zeros(np.shape(intensity) + (4,))
    s_unpol[..., 0] = intensity
    return apply(polarizer_at(angle_rad, extinction_ratio), s_unpol)[..., :3]


def estimate_linear(s_in: np.ndarray, s_out: np.ndarray,
                    weights: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """Least-squares 3x3 Mueller block from ``N`` pairs ``S_out_k = M S_in_k``.

    ``s_in``: ``(N, 3)`` incident states (one set for all pixels); ``s_out``: ``(..., N, 3)``.
    Optional ``weights`` ``(..., N)`` (finite, ``>= 0``) give a weighted solve per pixel.
    Returns ``(M (..., 3, 3), condition number of s_in)``; the condition number (2-norm, of the
    unweighted states) is how much relative noise in ``S_out`` can grow in ``M``. Raises
    ``ValueError`` for ``N < 3``, a rank-deficient state set, or weights that leave fewer than
    three independent states at some pixel (zero weights on all but two states, say).
    """
    s_in = np.asarray(s_in, dtype=np.float64)
    if s_in.ndim != 2 or s_in.shape[1] != 3 or s_in.shape[0] < 3:
        raise ValueError(f"need at least 3 incident linear Stokes states as (N, 3), got {s_in.shape}")
    sv = np.linalg.svd(s_in, compute_uv=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 1e-12 * sv[0] else float("inf")
    if not np.isfinite(cond):
        raise ValueError("incident states are linearly dependent (collinear); the Mueller block is not determined")
    s_out = np.asarray(s_out, dtype=np.float64)
    if weights is None:
        pinv = np.linalg.pinv(s_in)  # (3, N)
        mt = np.einsum("ik,...kj->...ij", pinv, s_out)  # M^T (..., 3, 3)
    else:
        w = np.asarray(weights, dtype=np.float64)
        if not (np.isfinite(w).all() and (w >= 0).all()):
            raise ValueError("weights must be finite and >= 0")
        a = np.einsum("...k,ki,kj->...ij", w, s_in, s_in)
        ev = np.linalg.eigvalsh(a)  # ascending
        short = ~(ev[..., 0] > 1e-12 * ev[..., -1])
        if short.any():
            raise ValueError(f"the weights leave fewer than 3 independent incident states at "
                             f"{int(short.sum())} of {short.size} pixel(s); the Mueller block is not determined there")
        rhs = np.einsum("...k,ki,...kj->...ij", w, s_in, s_out)
        mt = np.linalg.solve(a, rhs)
    return np.swapaxes(mt, -1, -2), cond


def jones_to_mueller(jones: np.ndarray) -> np.ndarray:
    """Non-depolarizing Mueller matrix ``(..., 4, 4)`` of Jones matrices ``(..., 2, 2)``.

    ``m_ij = 1/2 tr(sigma_i J sigma_j J^H)`` with the Pauli matrices in Stokes order and
    ``sigma_3 = [[0, i], [-i, 0]]``, the sign that makes the Stokes vector of a field ``E``
    ``(E^H sigma_i E)`` follow Mitsuba 3's ``S3`` (``docs/conventions.md``): then
    ``jones_to_mueller(diag(1, exp(i d)))`` is :func:`linear_retarder` ``(d)`` and
    ``jones_to_mueller(diag(r_s, r_p))`` is :func:`specular_reflection` (tested), for the
    ``exp(-i omega t)`` time dependence in which a conductor's index is ``n + i k``.
    (:data:`polrig.optics.realizability.PAULI` has the opposite ``sigma_3``; realizability does not
    depend on that sign: it maps ``M`` of ``J`` to ``M`` of ``conj(J)``.) Reference: R. A.
    Chipman, W. S. T. Lam, G. Young, *Polarized Light and Optical Systems* (CRC 2018), ch. 6.
    """
    j = np.asarray(jones, dtype=np.complex128)
    pauli = np.array([[[1, 0], [0, 1]], [[1, 0], [0, -1]], [[0, 1], [1, 0]], [[0, 1j], [-1j, 0]]])
    return 0.5 * np.einsum("iab,...bc,jcd,...ad->...ij", pauli, j, pauli, j.conj()).real


def diattenuation(m: np.ndarray) -> np.ndarray:
    """Diattenuation ``|(m01, m02[, m03])| / m00`` of ``(..., 3, 3)`` or ``(..., 4, 4)`` matrices
    (linear diattenuation for a 3x3 block); Lu and Chipman, JOSA A 13(5), 1106 (1996).
    ``0`` where ``m00 <= 0`` or non-finite."""
    m = np.asarray(m, dtype=np.float64)
    m00 = m[..., 0, 0]
    ok = np.isfinite(m).all(axis=(-2, -1)) & (m00 > 0)
    num = np.sqrt(np.sum(np.where(ok[..., None], m[..., 0, 1:], 0.0) ** 2, axis=-1))
    return np.where(ok, num / np.where(ok, m00, 1.0), 0.0)


def polarizance(m: np.ndarray) -> np.ndarray:
    """Polarizance ``|(m10, m20[, m30])| / m00`` (DoP of the output for unpolarized input);
    Lu and Chipman 1996. ``0`` where ``m00 <= 0`` or non-finite."""
    return diattenuation(np.swapaxes(np.asarray(m, dtype=np.float64), -1, -2))
