"""Physical realizability of Mueller matrices: Givens-Kostinski test, coherency (Cloude) test,
Cloude filtering, and the completion of a measured 3x3 linear block to 4x4.

Conventions: ``docs/conventions.md`` (Stokes order ``S0..S3``, matrix axes last). Every function
takes ``(..., 4, 4)`` (or ``(..., 3, 3)`` for the ``*_linear`` helpers), is vectorised over the
leading axes and never raises for NaN/inf entries: such matrices test ``False`` and filter to the
zero matrix (finite output; the caller's mask says why).

Two notions of "physical":

* **Stokes-Stokes** (Givens & Kostinski): ``M`` maps every physical Stokes vector
  (``s0 >= |(s1, s2, s3)|``) to a physical one. Test: with ``G = diag(1, -1, -1, -1)``, the
  spectrum of ``G M^T G M`` is real and an eigenvector of its largest eigenvalue is a physical
  Stokes vector (C. R. Givens and A. B. Kostinski, "A simple necessary and sufficient condition on
  physically realizable Mueller matrices", J. Mod. Opt. 40(3), 471-481, 1993).
* **Cloude / coherency**: ``M`` is a convex sum of non-depolarizing (Jones-derived) matrices,
  which holds iff its coherency matrix ``H = 1/4 sum_ij m_ij (sigma_i (x) sigma_j^*)`` is
  positive semidefinite (S. R. Cloude, "Group theory and polarisation algebra", Optik 75(1),
  26-36, 1986; B. N. Simon et al., JOSA A 27(2), 188-199, 2010). This is the stricter test: every
  Cloude-physical matrix is Stokes-Stokes, not conversely (``diag(1, 1, 1, -1)`` is
  Stokes-Stokes but not a convex sum of Jones matrices).

Pauli basis (same order as the Stokes components, so that ``m_ij = 1/2 tr(sigma_i J sigma_j
J^H)`` for a Jones matrix ``J``): ``sigma_0 = I``, ``sigma_1 = diag(1, -1)``,
``sigma_2 = [[0, 1], [1, 0]]``, ``sigma_3 = [[0, -i], [i, 0]]``. This ``sigma_3`` is the
opposite of :func:`polrig.optics.mueller.jones_to_mueller`'s (which follows Mitsuba 3's ``S3``): with
it ``M`` of ``J`` is ``M`` of ``conj(J)`` there, and every test here is independent of the sign
(``H`` changes to its complex conjugate, with the same eigenvalues). ``trace(H) = m00``. The construction was checked against the
Hermitian matrix of usnistgov pySCATMECH ``mueller.py`` (``MuellerToHermitian``, a different
basis whose eigenvalues are exactly twice those of ``H``); the test suite repeats that check.

**Cloude filtering** (Cloude 1986; the eigen-decomposition of ``H`` is the Cloude
decomposition of ``M`` into at most four non-depolarizing terms): eigen-decompose ``H``, clip
its negative eigenvalues to zero, and rebuild ``M`` from ``m_ij = tr(H (sigma_i (x)
sigma_j^*))``. A realizable matrix is returned unchanged up to rounding.

**3x3 linear blocks.** A DoFP rig measures only the upper-left 3x3 block. Realizability is a
property of a 4x4 matrix, so a block must be completed first, and the answer depends on the
completion (J. J. Gil et al., "Interpretation of measured 3x3 partial depolarizing Mueller
matrices", arXiv:2510.06305, 2025). Two completions are offered, both with the circular
couplings ``m03, m13, m23, m30, m31, m32`` set to zero:

* ``"zero"``: :func:`polrig.optics.mueller.pad_linear`, ``m33 = 0``. Simple, but it fails even for
  some non-depolarizing elements: the identity block gives ``diag(1, 1, 1, 0)``, whose
  coherency matrix has the eigenvalue ``-1/4``.
* ``"max_min_eigenvalue"`` (default for the ``*_linear`` helpers): ``m33`` is chosen to
  maximise the smallest coherency eigenvalue, i.e. the completion that is "most realizable".
  With zero circular couplings the coherency matrix is real in a suitable basis and ``m33``
  enters only its diagonal (as ``+-m33/2``), so the smallest eigenvalue is a concave function of
  ``m33``; it is maximised by a vectorised golden-section search over ``[-s, s]``,
  ``s = max |m_ij|``. Gil et al. instead pick, among the admissible completions, the one of
  maximal polarimetric purity (and they also let the circular elements vary); ours is the
  completion furthest inside the realizable set along ``m33`` alone, which is what a
  pass/fail test and a filter need. A block passes under this completion iff some ``m33``
  (with zero circular couplings) makes it Cloude-realizable.
"""

from __future__ import annotations

import numpy as np

from polrig.optics.mueller import pad_linear

__all__ = [
    "PAULI",
    "coherency_matrix",
    "mueller_from_coherency",
    "coherency_eigenvalues",
    "is_physical_coherency",
    "is_physical_gk",
    "cloude_filter",
    "optimal_m33",
    "complete_linear",
    "is_physical_linear",
    "filter_linear",
    "pass_rate",
]

#: Pauli matrices ``sigma_0..sigma_3`` in the Stokes order (see the module docstring).
PAULI = np.array([
    [[1, 0], [0, 1]],
    [[1, 0], [0, -1]],
    [[0, 1], [1, 0]],
    [[0, -1j], [1j, 0]],
], dtype=np.complex128)

# B[i, j] = sigma_i (x) sigma_j^*  (4x4 each); H = 1/4 sum m_ij B_ij and m_ij = tr(B_ij H).
_BASIS = np.einsum("iab,jcd->ijacbd", PAULI, PAULI.conj()).reshape(4, 4, 4, 4)

_G = np.diag([1.0, -1.0, -1.0, -1.0])

COMPLETIONS = ("zero", "max_min_eigenvalue")


def _as_matrices(m: np.ndarray, n: int) -> np.ndarray:
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (n, n):
        raise ValueError(f"expected matrices of shape (..., {n}, {n}), got {m.shape}")
    return m


def _finite_or_zero(m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(m with non-finite matrices replaced by zeros, finite mask (...))``."""
    finite = np.isfinite(m).all(axis=(-2, -1))
    return np.where(finite[..., None, None], m, 0.0), finite


def coherency_matrix(m: np.ndarray) -> np.ndarray:
    """Cloude coherency matrix ``H = 1/4 sum_ij m_ij sigma_i (x) sigma_j^*``, ``(..., 4, 4)``
    complex Hermitian, ``trace(H) = m00``. Non-finite entries propagate (use the ``is_*`` tests
    for masks)."""
    m = _as_matrices(m, 4)
    return 0.25 * np.einsum("...ij,ijab->...ab", m, _BASIS)


def mueller_from_coherency(h: np.ndarray) -> np.ndarray:
    """Inverse of :func:`coherency_matrix`: ``m_ij = Re tr(H (sigma_i (x) sigma_j^*))``."""
    h = np.asarray(h)
    return np.einsum("ijab,...ba->...ij", _BASIS, h).real


def coherency_eigenvalues(m: np.ndarray) -> np.ndarray:
    """Eigenvalues of the coherency matrix, ascending, ``(..., 4)``; they sum to ``m00``.

    A diagnostic: matrices with non-finite entries give NaN eigenvalues (the tests return
    ``False`` for them).
    """
    m = _as_matrices(m, 4)
    mz, finite = _finite_or_zero(m)
    ev = np.linalg.eigvalsh(coherency_matrix(mz))
    return np.where(finite[..., None], ev, np.nan)


def is_physical_coherency(m: np.ndarray, *, rtol: float = 1e-9, atol: float = 0.0) -> np.ndarray:
    """Cloude test: ``H >= 0``, i.e. smallest eigenvalue ``>= -(rtol * max|eigenvalue| + atol)``.

    Returns a boolean array of the leading shape; non-finite matrices are ``False``; the zero
    matrix (a perfect absorber) is ``True``.
    """
    m = _as_matrices(m, 4)
    mz, finite = _finite_or_zero(m)
    norm = np.abs(mz).max(axis=(-2, -1))
    norm = np.where(norm > 0, norm, 1.0)
    ev = np.linalg.eigvalsh(coherency_matrix(mz / norm[..., None, None])) * norm[..., None]
    scale = np.abs(ev).max(axis=-1)
    return finite & (ev[..., 0] >= -(rtol * scale + atol))


def is_physical_gk(m: np.ndarray, *, rtol: float = 1e-6) -> np.ndarray:
    """Givens-Kostinski test (Stokes-Stokes mapping), vectorised.

    ``M`` is normalised by its largest absolute entry; then ``m00 > 0`` (so that it maps the
    forward light cone into itself, not onto its negative), the eigenvalues of
    ``N = G M^T G M`` must be real (``|Im| <= rtol``), and the eigenspace of the largest
    eigenvalue must contain a physical Stokes vector. Eigenvalues within ``rtol`` of the
    largest are treated as degenerate with it: a non-depolarizing matrix has
    ``N = |det J|^2 I`` (fourfold degenerate), and ``numpy.linalg.eig`` returns an arbitrary
    basis of such an eigenspace with nearly parallel vectors when rounding perturbs ``N``. The
    test therefore takes the eigenspace as the right singular vectors of ``N - lambda_max I``
    with singular values ``<= rtol`` (an orthonormal ``U``) and asks whether it contains ``x``
    with ``x^T G x >= -rtol |x|^2``, i.e. whether the largest eigenvalue of ``U^T G U`` is
    ``>= -rtol``.

    Non-finite matrices are ``False``; the zero matrix is ``True`` (perfect absorber).
    """
    m = _as_matrices(m, 4)
    mz, finite = _finite_or_zero(m)
    scale = np.abs(mz).max(axis=(-2, -1))
    zero = scale == 0
    mn = mz / np.where(zero, 1.0, scale)[..., None, None]
    n_mat = _G @ np.swapaxes(mn, -1, -2) @ _G @ mn
    w = np.linalg.eigvals(n_mat)
    real = np.all(np.abs(w.imag) <= rtol * np.maximum(1.0, np.abs(w).max(axis=-1, keepdims=True)), axis=-1)
    top = w.real.max(axis=-1)
    # (pseudo-)eigenspace of the largest eigenvalue: right singular vectors of N - top I whose
    # singular values are below the tolerance (always at least the smallest one)
    _, s, vh = np.linalg.svd(n_mat - top[..., None, None] * np.eye(4))
    rank = s <= rtol * np.maximum(1.0, np.abs(top))[..., None]
    rank[..., -1] = True
    u = np.swapaxes(vh, -1, -2)  # columns are the right singular vectors
    b = np.swapaxes(u, -1, -2) @ _G @ u
    keep = rank[..., :, None] & rank[..., None, :]
    b = np.where(keep, b, 0.0) - 1e3 * np.eye(4) * (~rank)[..., None, :]
    timelike = np.linalg.eigvalsh(b)[..., -1] >= -rtol
    return finite & (zero | ((mn[..., 0, 0] > rtol) & real & timelike))


def cloude_filter(m: np.ndarray) -> np.ndarray:
    """Nearest Cloude-realizable matrix: negative coherency eigenvalues clipped to zero.

    Returns float64 ``(..., 4, 4)``. Realizable input comes back unchanged (to rounding,
    ~1e-15 relative); matrices with non-finite entries come back as the zero matrix.
    """
    m = _as_matrices(m, 4)
    mz, finite = _finite_or_zero(m)
    norm = np.abs(mz).max(axis=(-2, -1))[..., None, None]
    norm = np.where(norm > 0, norm, 1.0)
    ev, vec = np.linalg.eigh(coherency_matrix(mz / norm))
    neg = (ev < 0).any(axis=-1)
    h = np.einsum("...ik,...k,...jk->...ij", vec, np.clip(ev, 0.0, None), vec.conj())
    out = np.where(neg[..., None, None], mueller_from_coherency(h) * norm, mz)
    return np.where(finite[..., None, None], out, 0.0)


def _real_coherency_linear(m3: np.ndarray, m33: np.ndarray) -> np.ndarray:
    """Real symmetric matrix with twice the coherency eigenvalues of ``pad_linear(m3)`` with
    ``M[3, 3] = m33`` (circular couplings zero).

    Derivation: for such matrices the pySCATMECH Hermitian matrix is real; in the orthonormal
    basis ``(e0 + e3, e0 - e3, e1 + e2, e1 - e2) / sqrt(2)`` of it ``m33`` appears only on the
    diagonal, with signs ``(+, -, -, +) / 2``.
    """
    g = lambda i, j: m3[..., i, j]  # noqa: E731
    d0 = 0.5 * (g(0, 0) + g(1, 1))
    d1 = 0.5 * (g(0, 0) - g(1, 1))
    r = np.empty(m3.shape[:-2] + (4, 4))
    r[..., 0, 0] = d0 + 0.5 * (g(2, 2) + m33)
    r[..., 1, 1] = d0 - 0.5 * (g(2, 2) + m33)
    r[..., 2, 2] = d1 + 0.5 * (g(2, 2) - m33)
    r[..., 3, 3] = d1 - 0.5 * (g(2, 2) - m33)
    r[..., 0, 1] = r[..., 1, 0] = 0.5 * (g(0, 1) + g(1, 0))
    r[..., 2, 3] = r[..., 3, 2] = 0.5 * (g(1, 0) - g(0, 1))
    r[..., 0, 2] = r[..., 2, 0] = 0.5 * (g(0, 2) + g(2, 0))
    r[..., 0, 3] = r[..., 3, 0] = 0.5 * (g(1, 2) - g(2, 1))
    r[..., 1, 2] = r[..., 2, 1] = 0.5 * (g(1, 2) + g(2, 1))
    r[..., 1, 3] = r[..., 3, 1] = 0.5 * (g(0, 2) - g(2, 0))
    return r


def _m33_search(mz: np.ndarray, n_iter: int, stop_at: np.ndarray | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
    """Golden-section search of ``m33`` for finite blocks ``(P, 3, 3)``.

    Returns ``(m33, best)``: the bracket midpoints and the largest smallest eigenvalue of the
    real form seen (twice the coherency eigenvalue). With ``stop_at`` ``(P,)``, a block leaves
    the search as soon as ``best >= stop_at`` (enough for a pass/fail test).
    """
    p = mz.shape[0]
    r0 = _real_coherency_linear(mz, np.zeros(p))
    diag0 = np.diagonal(r0, axis1=-2, axis2=-1).copy()
    k = 0.5 * np.array([1.0, -1.0, -1.0, 1.0])
    idx = np.arange(4)
    s = np.abs(mz).max(axis=(-2, -1)) if p else np.zeros(0)
    lo, hi = -s, s.copy()
    invphi = (np.sqrt(5.0) - 1.0) / 2.0

    def f(act, t):
        r = r0[act]
        r[:, idx, idx] = diag0[act] + t[:, None] * k
        return np.linalg.eigvalsh(r)[:, 0] if len(t) else np.zeros(0)

    act = np.arange(p)
    c = hi - invphi * (hi - lo)
    d = lo + invphi * (hi - lo)
    fc, fd = f(act, c), f(act, d)
    best = np.maximum(fc, fd)
    for _ in range(n_iter):
        if stop_at is not None:
            keep = best[act] < stop_at[act]
            act = act[keep]
            c, d, fc, fd = c[keep], d[keep], fc[keep], fd[keep]
            if not len(act):
                break
        left = fc >= fd  # maximum in [lo, d]
        lo_a, hi_a = lo[act], hi[act]
        hi_a = np.where(left, d, hi_a)
        lo_a = np.where(left, lo_a, c)
        lo[act], hi[act] = lo_a, hi_a
        new_c = hi_a - invphi * (hi_a - lo_a)
        new_d = lo_a + invphi * (hi_a - lo_a)
        # reuse one interior evaluation per step
        c_next = np.where(left, new_c, d)
        d_next = np.where(left, c, new_d)
        ft = f(act, np.where(left, c_next, d_next))
        fc, fd = np.where(left, ft, fd), np.where(left, fc, ft)
        c, d = c_next, d_next
        best[act] = np.maximum(best[act], ft)
    return 0.5 * (lo + hi), best


def optimal_m33(m3: np.ndarray, *, n_iter: int = 48) -> np.ndarray:
    """``m33`` that maximises the smallest coherency eigenvalue of the completed block.

    Golden-section search on the concave function ``m33 -> lambda_min`` over ``[-s, s]``,
    ``s = max |m_ij|``; after ``n_iter`` steps the bracket is ``2 s 0.618^n_iter`` wide
    (``4e-10 s`` for the default). Cost: about ``n_iter`` batched 4x4 ``eigvalsh`` calls
    (roughly 50 us per block; see ``benchmarks/bench_reference.py``). Non-finite blocks give 0.
    """
    m3 = _as_matrices(m3, 3)
    mz, finite = _finite_or_zero(m3)
    t, _ = _m33_search(mz.reshape(-1, 3, 3), n_iter)
    return np.where(finite, t.reshape(m3.shape[:-2]), 0.0)


def complete_linear(m3: np.ndarray, completion: str = "max_min_eigenvalue", **kwargs) -> np.ndarray:
    """Complete 3x3 linear blocks to 4x4 (circular couplings zero); ``completion`` is
    ``"zero"`` (:func:`polrig.optics.mueller.pad_linear`) or ``"max_min_eigenvalue"``
    (:func:`optimal_m33`, keyword ``n_iter``). See the module docstring for which to use."""
    m3 = _as_matrices(m3, 3)
    if completion not in COMPLETIONS:
        raise ValueError(f"unknown completion {completion!r}; expected one of {COMPLETIONS}")
    m4 = pad_linear(m3)
    if completion == "max_min_eigenvalue":
        m4[..., 3, 3] = optimal_m33(m3, **kwargs)
    return m4


def is_physical_linear(m3: np.ndarray, *, test: str = "coherency",
                       completion: str = "max_min_eigenvalue", rtol: float | None = None,
                       n_iter: int = 48) -> np.ndarray:
    """Realizability of 3x3 blocks: ``test`` ``"coherency"`` or ``"gk"`` applied to the
    ``completion`` (see :func:`complete_linear`). ``rtol`` defaults to the test's own.

    The coherency test under the max-min-eigenvalue completion asks whether *some* ``m33``
    makes the smallest coherency eigenvalue ``>= -rtol * max|m_ij|``; it is evaluated without
    a full search where possible: blocks that pass with ``m33 = 0`` pass, and the search stops
    for a block as soon as a passing ``m33`` is found. Non-finite blocks are ``False``.
    """
    tests = {"coherency": (is_physical_coherency, 1e-9), "gk": (is_physical_gk, 1e-6)}
    if test not in tests:
        raise ValueError(f"unknown test {test!r}; expected one of {tuple(tests)}")
    if completion not in COMPLETIONS:
        raise ValueError(f"unknown completion {completion!r}; expected one of {COMPLETIONS}")
    fn, default_rtol = tests[test]
    rtol = default_rtol if rtol is None else rtol
    m3 = _as_matrices(m3, 3)
    mz, finite = _finite_or_zero(m3)
    if test == "gk" or completion == "zero":
        return finite & fn(complete_linear(mz, completion, **({"n_iter": n_iter} if completion != "zero" else {})),
                           rtol=rtol)
    flat = mz.reshape(-1, 3, 3)
    ok = is_physical_coherency(pad_linear(flat), rtol=rtol)
    rest = np.flatnonzero(~ok)
    scale = np.abs(flat[rest]).max(axis=(-2, -1))
    # the real form has twice the coherency eigenvalues
    _, best = _m33_search(flat[rest], n_iter, stop_at=-2.0 * rtol * scale)
    ok[rest] = best >= -2.0 * rtol * scale
    return finite & ok.reshape(m3.shape[:-2])


def filter_linear(m3: np.ndarray, completion: str = "max_min_eigenvalue") -> np.ndarray:
    """Realizable 3x3 block: complete, Cloude-filter, take the upper-left block.

    Blocks that already pass :func:`is_physical_linear` (same completion) are returned as they
    are (the filter would not change them) without a search, which makes the filter cheap on
    mostly-physical images. The filter maps matrices with zero circular couplings to matrices
    with zero circular couplings (the clipping commutes with the symmetry ``M -> D M D``,
    ``D = diag(1, 1, 1, -1)``), so the result is realizable under the same kind of completion.
    Non-finite blocks give the zero block. Returns float64.

    Only the ``"max_min_eigenvalue"`` completion is accepted: the filtered 4x4 matrix has its
    own ``m33``, which the ``"zero"`` completion would drop again (the result failed its own
    test, and repeated filtering kept changing physical blocks such as the identity).
    """
    if completion != "max_min_eigenvalue":
        raise ValueError(f"filter_linear needs the 'max_min_eigenvalue' completion, got {completion!r}: "
                         f"under the zero completion (m33 = 0) a filtered block is not realizable again")
    m3 = _as_matrices(m3, 3)
    mz, finite = _finite_or_zero(m3)
    out = mz.reshape(-1, 3, 3).copy()
    bad = np.flatnonzero(~is_physical_linear(mz, completion=completion).reshape(-1))
    if len(bad):
        out[bad] = cloude_filter(complete_linear(out[bad], completion))[..., :3, :3]
    return np.where(finite[..., None, None], out.reshape(m3.shape), 0.0)


def pass_rate(mask: np.ndarray, valid: np.ndarray | None = None) -> float:
    """Fraction of ``True`` in ``mask`` among the entries where ``valid`` is true (all when
    ``None``); NaN when there is nothing to count."""
    mask = np.asarray(mask, dtype=bool)
    if valid is None:
        valid = np.ones_like(mask)
    valid = np.broadcast_to(np.asarray(valid, dtype=bool), mask.shape)
    n = int(valid.sum())
    return float(np.count_nonzero(mask & valid) / n) if n else float("nan")
