"""Lower-order models of the 3x3 linear Mueller block in the rig's frames, and their weighted
nonlinear least-squares fit, vectorised over pixels.

**Frames.** The block maps the incident Stokes vector (incident frame: the polarizer stage's
zero axis) to the emergent one (camera axes), ``docs/conventions.md``. Those frames differ per
pixel, so an element whose own frame has its axis at ``theta`` is seen through two different
rotations. Write ``R(psi) = diag(1, Q(psi))`` with ``Q(psi) = [[cos psi, sin psi],
[-sin psi, cos psi]]`` (``psi`` a doubled angle, ``2 theta``: the rotator of
:func:`polrig.optics.bases.rotate_rows`). A non-depolarizing element with a diattenuation axis
and a retardance axis in common (Fresnel reflection by a dielectric or a metal; a linear
diattenuator; a linear retarder) is, in the rig's frames,

    M = R(psi_o) F R(psi_i)^T,   F = [[a, b, 0], [b, a, 0], [0, 0, c]]

(:func:`polrig.optics.pbrdf._specular_elements` writes the specular term this way):
``a = (r_s^2 + r_p^2) / 2``, ``b = (r_s^2 - r_p^2) / 2``, ``c = |r_s r_p| cos delta`` (the
4x4 element's ``s = |r_s r_p| sin delta`` lies outside the linear block, which therefore sees
only ``cos delta``: the sign of the retardance is not observable). ``psi_i``, ``psi_o`` are
the axis as seen in the incident and emergent frames.

**The models** (``k`` parameters; each a subset of the 9-parameter block, so the
likelihood-ratio test against the full block has ``9 - k`` degrees of freedom):

====================  ==  ==========================================================================
name                  k   block
====================  ==  ==========================================================================
``unpolarizing``      1   ``diag(m00, 0, 0)``: an ideal depolarizer (Lambertian-like)
``depolarizer``       3   ``[[m00, 0, 0], [0, L]]``, ``L = p O`` with ``O`` a rotation or a reflection
                          (an isotropic partial depolarizer ``diag(m00, p, +-p)`` in its own frames;
                          reflection flips the handedness: ``L`` of either kind is fitted, the better
                          kept)
``diattenuator``      4   ``F`` with ``a = (u^2 + v^2) / 2``, ``b = (u^2 - v^2) / 2``, ``c = u v``:
                          non-depolarizing, no retardance (0 or pi: ``u v`` may be negative);
                          amplitude transmittances ``|u|``, ``|v|``; ``D = 1`` (``v = 0``) is regular
``retarder``          4   ``F`` with ``b = 0``: ``a = m00``, ``c = m00 cos delta``
``fresnel``           5   ``F`` with ``a, b, c`` free: diattenuator and retarder with a common axis
``rank_one``          5   ``x y^T`` with ``y = (1, y1, y2)``: a depolarizing layer between two
                          diattenuators (Baek et al. 2018's diffuse term; ``x``, ``y`` the
                          polarizance and diattenuation vectors up to scale)
====================  ==  ==========================================================================

**The fit.** With the samples' weighted least squares normal matrix ``N = D^T W D`` and the
full block's estimate ``m_hat`` (both per pixel, :mod:`polrig.solve.model_selection`), every
block ``m`` has ``chi^2(m) = chi^2(m_hat) + (m - m_hat)^T N (m - m_hat)`` exactly (the
samples are linear in ``m``), so a model is fitted by minimising the 9-dimensional quadratic
form ``q(theta) = (m(theta) - m_hat)^T N (m(theta) - m_hat)``: the same weighted least squares
as the reference solve, without revisiting the ``4 N`` samples. Linear models (the first two)
have the closed form ``theta = (B^T N B)^-1 B^T N m_hat``; the others run Levenberg-Marquardt
(Marquardt's diagonal scaling, at most ``iterations`` steps) from closed-form starts read off
``m_hat`` (its singular value decomposition), compiled per pixel
(:mod:`polrig.solve._reduced_kernel`; the previous numpy version,
:mod:`polrig.solve._reduced_numpy`, is the tests' oracle and the benchmark's baseline). A pixel
stops once a step lowers ``q`` by less than ``1e-6 (q + 1)`` (the test compares ``q`` with
critical values of order 10) or its damping reaches ``1e9`` (on a 64x64 full-model scene the
decisions at 8, 12 and 30 iterations differ in at most 0.02 % of the pixels). Covariance by the delta method: ``cov(m) = J (J^T N J)^+
J^T`` at the optimum (``J = dm / dtheta``; invariant to the parametrisation, and finite where a
parametrisation is singular, e.g. ``u = v = 0``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from polrig.optics.mueller import jones_to_mueller
from polrig.solve.chunks import in_chunks

__all__ = ["ReducedModel", "MODELS", "MODEL_CODES", "fit_model", "block_covariance", "random_blocks"]


@dataclass(frozen=True)
class ReducedModel:
    """A lower-order model of the 3x3 block.

    ``code``: its integer in the model map (0 is the full block). ``n_params``: ``k``.
    ``matrix(theta)``: ``(P, k)`` -> ``(P, 9)`` row-major block. ``jacobian(theta)``:
    ``(P, 9, k)``, or None for a linear model, whose ``basis`` list holds one or more
    ``(9, k)`` bases (several: a union of subspaces, the best fit kept). ``starts(m_hat)``:
    ``(P, 9)`` -> list of ``(P, k)`` start points."""

    name: str
    code: int
    n_params: int
    matrix: Callable[[np.ndarray], np.ndarray] | None = None
    jacobian: Callable[[np.ndarray], np.ndarray] | None = None
    starts: Callable[[np.ndarray], list[np.ndarray]] | None = None
    basis: tuple[np.ndarray, ...] = ()

    @property
    def linear(self) -> bool:
        return bool(self.basis)


# --------------------------------------------------------------------------- axis form
def _axis_form(a, b, c, pi, po, with_jacobian: bool = True):
    """``M = R(po) F(a, b, c) R(pi)^T`` ``(P, 9)`` and its derivatives ``(P, 9, 5)`` with
    respect to ``(a, b, c, pi, po)`` (module docstring)."""
    ci, si, co, so = np.cos(pi), np.sin(pi), np.cos(po), np.sin(po)
    z = np.zeros_like(a)

    def block(a, b, c, ci, si, co, so):
        return np.stack([a, b * ci, -b * si,
                         b * co, co * ci * a + so * si * c, -co * si * a + so * ci * c,
                         -b * so, -so * ci * a + co * si * c, so * si * a + co * ci * c], -1)

    m = block(a, b, c, ci, si, co, so)
    if not with_jacobian:
        return m, None
    one = np.ones_like(a)
    jac = np.stack([
        block(one, z, z, ci, si, co, so),
        block(z, one, z, ci, si, co, so),
        block(z, z, one, ci, si, co, so),
        block(a, b, c, -si, ci, co, so),  # d/dpi: (ci, si) -> (-si, ci)
        block(a, b, c, ci, si, -so, co),  # d/dpo
    ], -1)
    # that substitution differentiates the elements linear in (ci, si) resp. (co, so); the
    # ones that do not depend on the angle (m00; the first column for pi, the first row for
    # po) are zeroed
    jac[:, 0, 3:] = 0.0
    jac[:, [3, 6], 3] = 0.0
    jac[:, [1, 2], 4] = 0.0
    return m, jac


def _axis_starts(m_hat: np.ndarray) -> list[np.ndarray]:
    """Two start points ``(a, b, c, pi, po)`` ``(P, 5)`` from the SVD of the lower 2x2 block
    of ``m_hat`` (``L = Q(po) diag(a, c) Q(pi)^T`` with the two assignments of its singular
    values), ``b`` projected from the first row and column."""
    m = m_hat.reshape(-1, 3, 3)
    lower = m[:, 1:, 1:]
    u, s, vt = np.linalg.svd(lower)
    v = np.swapaxes(vt, -1, -2).copy()
    u = u.copy()
    s = s.copy()
    for q in (u, v):  # make both rotations (det +1), the second singular value signed
        neg = np.linalg.det(q) < 0
        q[neg, :, 1] *= -1.0
        s[neg, 1] *= -1.0
    out = []
    for swap in (False, True):
        qo, qi = u, v
        a, c = s[:, 0], s[:, 1]
        if swap:  # Q(psi + pi/2) = Q(psi) [[0, 1], [-1, 0]]: a and c exchange
            rot = np.array([[0.0, 1.0], [-1.0, 0.0]])
            qo, qi, a, c = qo @ rot, qi @ rot, s[:, 1], s[:, 0]
        po = np.arctan2(qo[:, 0, 1], qo[:, 0, 0])
        pi = np.arctan2(qi[:, 0, 1], qi[:, 0, 0])
        b = 0.5 * (np.einsum("pi,pi->p", m[:, 0, 1:], qi[:, :, 0])
                   + np.einsum("pi,pi->p", m[:, 1:, 0], qo[:, :, 0]))
        a = 0.5 * (a + m[:, 0, 0])
        out.append(np.stack([a, b, c, pi, po], -1))
    return out


# --------------------------------------------------------------------------- models
def _fresnel_matrix(t):
    return _axis_form(*t.T, with_jacobian=False)[0]


def _fresnel_jacobian(t):
    return _axis_form(*t.T)[1]


def _retarder_full(t):
    a, c, pi, po = t.T
    return np.stack([a, np.zeros_like(a), c, pi, po], -1)


def _retarder_matrix(t):
    return _fresnel_matrix(_retarder_full(t))


def _retarder_jacobian(t):
    return _fresnel_jacobian(_retarder_full(t))[:, :, [0, 2, 3, 4]]


def _retarder_starts(m_hat):
    return [t[:, [0, 2, 3, 4]] for t in _axis_starts(m_hat)]


def _diattenuator_full(t):
    u, v, pi, po = t.T
    return np.stack([(u * u + v * v) / 2, (u * u - v * v) / 2, u * v, pi, po], -1)


def _diattenuator_matrix(t):
    return _fresnel_matrix(_diattenuator_full(t))


def _diattenuator_jacobian(t):
    u, v = t[:, 0], t[:, 1]
    j5 = _fresnel_jacobian(_diattenuator_full(t))
    ja, jb, jc = j5[:, :, 0], j5[:, :, 1], j5[:, :, 2]
    du = ja * u[:, None] + jb * u[:, None] + jc * v[:, None]
    dv = ja * v[:, None] - jb * v[:, None] + jc * u[:, None]
    return np.stack([du, dv, j5[:, :, 3], j5[:, :, 4]], -1)


def _diattenuator_starts(m_hat):
    out = []
    for a, b, c, pi, po in (t.T for t in _axis_starts(m_hat)):
        u = np.sqrt(np.clip(a + b, 0.0, None))
        v = np.sqrt(np.clip(a - b, 0.0, None)) * np.where(c < 0, -1.0, 1.0)
        out.append(np.stack([u, v, pi, po], -1))
    return out


def _rank_one_matrix(t):
    x, y = t[:, :3], np.concatenate([np.ones_like(t[:, :1]), t[:, 3:]], -1)
    return (x[:, :, None] * y[:, None, :]).reshape(-1, 9)


def _rank_one_jacobian(t):
    p = len(t)
    x, y = t[:, :3], np.concatenate([np.ones((p, 1)), t[:, 3:]], -1)
    jac = np.zeros((p, 3, 3, 5))
    for r in range(3):
        jac[:, r, :, r] = y  # d M[r, :] / d x_r
    jac[:, :, 1, 3] = x  # d M[:, 1] / d y1
    jac[:, :, 2, 4] = x
    return jac.reshape(p, 9, 5)


def _rank_one_starts(m_hat):
    m = m_hat.reshape(-1, 3, 3)
    u, s, vt = np.linalg.svd(m)
    starts = []
    y0 = vt[:, 0, :]
    ok = np.abs(y0[:, 0]) > 1e-12 * np.abs(y0).max(axis=1).clip(1e-300)
    y = np.where(ok[:, None], y0 / np.where(ok, y0[:, 0], 1.0)[:, None], [1.0, 0.0, 0.0])
    x = s[:, 0, None] * u[:, :, 0] * np.where(ok, y0[:, 0], 0.0)[:, None]
    starts.append(np.concatenate([x, y[:, 1:]], -1))
    m00 = m[:, 0, 0]
    ok = np.abs(m00) > 0
    y = np.where(ok[:, None], m[:, 0, 1:] / np.where(ok, m00, 1.0)[:, None], 0.0)
    starts.append(np.concatenate([m[:, :, 0], y], -1))
    return starts


def _basis(*mats) -> np.ndarray:
    return np.stack([np.asarray(m, float).reshape(9) for m in mats], -1)


_E00 = [[1, 0, 0], [0, 0, 0], [0, 0, 0]]

#: The candidate models, by code (``0`` is the full block and not listed).
MODELS: tuple[ReducedModel, ...] = (
    ReducedModel("unpolarizing", 1, 1, basis=(_basis(_E00),)),
    ReducedModel("depolarizer", 2, 3, basis=(
        _basis(_E00, [[0, 0, 0], [0, 1, 0], [0, 0, -1]], [[0, 0, 0], [0, 0, 1], [0, 1, 0]]),
        _basis(_E00, [[0, 0, 0], [0, 1, 0], [0, 0, 1]], [[0, 0, 0], [0, 0, 1], [0, -1, 0]]))),
    ReducedModel("diattenuator", 3, 4, _diattenuator_matrix, _diattenuator_jacobian,
                 _diattenuator_starts),
    ReducedModel("retarder", 4, 4, _retarder_matrix, _retarder_jacobian, _retarder_starts),
    ReducedModel("fresnel", 5, 5, _fresnel_matrix, _fresnel_jacobian, _axis_starts),
    ReducedModel("rank_one", 6, 5, _rank_one_matrix, _rank_one_jacobian, _rank_one_starts),
)

#: ``{code: name}`` of the model map, ``0`` the full 9-parameter block.
MODEL_CODES: dict[int, str] = {0: "full", **{m.code: m.name for m in MODELS}}


# --------------------------------------------------------------------------- fitting
def _quad(r: np.ndarray, normal: np.ndarray) -> np.ndarray:
    return np.einsum("pi,pi->p", r, (normal @ r[..., None])[..., 0])


def _fit_linear(model: ReducedModel, m_hat, normal):
    best_q = best_m = best_j = None
    for basis in model.basis:
        nb = normal @ basis  # (P, 9, k)
        a = basis.T @ nb
        g = (np.swapaxes(nb, 1, 2) @ m_hat[..., None])[..., 0]
        theta = np.linalg.solve(_ridge(a), g[..., None])[..., 0]
        m = theta @ basis.T
        q = _quad(m - m_hat, normal)
        jac = np.broadcast_to(basis, (len(m_hat),) + basis.shape)
        if best_q is None:
            best_q, best_m, best_j = q, m, jac.copy()
        else:
            better = q < best_q
            best_q = np.where(better, q, best_q)
            best_m = np.where(better[:, None], m, best_m)
            best_j = np.where(better[:, None, None], jac, best_j)
    return best_m, best_q, best_j


def _ridge(a: np.ndarray) -> np.ndarray:
    """``a + eps I`` with ``eps`` a tiny fraction of the trace: a solve that never raises on
    a singular batch member (its step is then rejected or its covariance masked)."""
    k = a.shape[-1]
    tr = np.einsum("pii->p", a)
    eps = 1e-13 * np.abs(tr) / k + 1e-300
    return a + eps[:, None, None] * np.eye(k)


#: pixels a chunk of the compiled fits has at least (a thread per few hundred microseconds of
#: work at least; the threads: :data:`polrig.solve.chunks.THREADS`)
_CHUNK_PIXELS = 256


def fit_model(model: ReducedModel, m_hat: np.ndarray, normal: np.ndarray, *,
              iterations: int = 12) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Weighted least-squares fit of ``model`` to ``P`` pixels.

    ``m_hat``: ``(P, 9)`` float64, the full block's estimate (row-major); ``normal``:
    ``(P, 9, 9)`` its normal matrix ``D^T W D``. Returns the fitted block ``(P, 9)``, the
    statistic ``q = (m - m_hat)^T N (m - m_hat)`` ``(P,)`` (``chi^2`` of the model minus that of
    the full block; non-finite where the fit failed) and the Jacobian ``(P, 9, k)`` at the
    optimum (for :func:`block_covariance`). Nonlinear models: the compiled kernel
    (:func:`polrig.solve._reduced_kernel.fit_nonlinear`, chunks of pixels on up to
    the CPUs' threads, :func:`polrig.solve.chunks.in_chunks`, every start in turn, the lowest ``q`` kept; ``q`` and the block NaN
    where ``N`` is not positive definite)."""
    if model.linear:
        return _fit_linear(model, m_hat, normal)
    from polrig.solve import _reduced_kernel as kern  # numba: imported on first use

    starts = np.ascontiguousarray(  # C-contiguous: one compiled version of the fits
        np.stack([np.where(np.isfinite(t), t, 0.0) for t in model.starts(m_hat)], 1))
    m_hat = np.ascontiguousarray(m_hat, np.float64)
    normal = np.ascontiguousarray(normal, np.float64)
    p = len(m_hat)
    theta, m, q = np.empty((p, model.n_params)), np.empty((p, 9)), np.empty(p)

    def fit(sl: slice) -> None:
        kern.fit_nonlinear(model.code, m_hat[sl], normal[sl], starts[sl], int(iterations),
                           theta[sl], m[sl], q[sl])

    in_chunks(p, fit, min_pixels=_CHUNK_PIXELS, name="reduced-fit")
    return m, q, model.jacobian(theta)


def block_covariance(jac: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Delta-method covariance ``(P, 9, 9)`` of a fitted block, ``J (J^T N J)^+ J^T``
    (pseudo-inverse by a symmetric eigendecomposition: directions the samples do not
    determine, eigenvalues below ``1e-10`` of the largest, are dropped)."""
    a = np.swapaxes(jac, 1, 2) @ (normal @ jac)
    w, v = np.linalg.eigh(a)
    keep = w > 1e-10 * np.abs(w).max(axis=1, keepdims=True)
    inv_w = np.where(keep, 1.0 / np.where(keep, w, 1.0), 0.0)
    jv = jac @ v
    return (jv * inv_w[:, None, :]) @ np.swapaxes(jv, 1, 2)


_BY_NAME = {m.name: m for m in MODELS}


def random_blocks(rng: np.random.Generator, name: str, p: int, scale: float = 1.0) -> np.ndarray:
    """``p`` random blocks ``(P, 9)`` of model ``name`` (a :data:`MODELS` name, or ``full``:
    convex sums of three random Jones matrices), in physical ranges (``m00`` in [0.5, 1],
    uniform axes, diattenuation and retardance), times ``scale``: the tests' and
    ``python -m benchmarks model_selection``'s synthetic truths."""
    u = lambda lo, hi, *shape: rng.uniform(lo, hi, (p,) + shape)  # noqa: E731
    ang = lambda: u(0.0, 2 * np.pi)  # noqa: E731
    if name == "unpolarizing":
        m = (_BY_NAME[name].basis[0] @ u(0.5, 1.0, 1).T).T
    elif name == "depolarizer":
        a = u(0.5, 1.0)
        q = a * u(0.0, 1.0)
        b = ang()
        m = (_BY_NAME[name].basis[int(rng.integers(2))] @ np.stack([a, q * np.cos(b), q * np.sin(b)])).T
    elif name == "diattenuator":
        m = _BY_NAME[name].matrix(np.stack([u(0.5, 1.0), u(-1.0, 1.0), ang(), ang()], -1))
    elif name == "retarder":
        a = u(0.5, 1.0)
        m = _BY_NAME[name].matrix(np.stack([a, a * np.cos(u(0, np.pi)), ang(), ang()], -1))
    elif name == "fresnel":
        a = u(0.5, 1.0)
        b = a * u(-1.0, 1.0)
        c = np.sqrt(a * a - b * b) * np.cos(u(0, np.pi))
        m = _BY_NAME[name].matrix(np.stack([a, b, c, ang(), ang()], -1))
    elif name == "rank_one":
        x = np.stack([u(0.5, 1.0), u(-0.4, 0.4), u(-0.4, 0.4)], -1)
        m = _BY_NAME[name].matrix(np.concatenate([x, u(-0.5, 0.5, 2)], -1))
    else:  # full: convex sums of 3 random Jones matrices, m00 in [0.5, 1]
        j = rng.normal(size=(3, p, 2, 2)) + 1j * rng.normal(size=(3, p, 2, 2))
        m = np.einsum("k,k...->...", rng.random(3), jones_to_mueller(j))[..., :3, :3]
        m = (m / m[..., :1, :1] * u(0.5, 1.0)[:, None, None]).reshape(p, 9)
    return m * scale
