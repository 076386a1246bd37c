"""How close three states can come to four without a prior: a closed-form bound (issue 33's
"three states within 1 dB of four").

For the samples ``I = kron(a_j, s_k) . vec(M) + noise`` of equal variance, the least-squares
covariance is ``(D^T D)^-1 = (A^T A)^-1 (x) (S^T S)^-1`` (``A`` the four analyzer rows, ``S``
the ``N`` incident states), so the summed variance of the nine elements is
``tr (A^T A)^-1 * tr (S^T S)^-1``. For fully polarized states ``s = c (1, cos 2t, sin 2t)``,
``S^T S = c^2 [[N, sum cos, sum sin], [., sum cos^2, sum cos sin], [., ., sum sin^2]]`` has
trace ``2 N c^2``, and ``tr X^-1`` over positive definite ``X`` with ``X_00 = N c^2`` and
``X_11 + X_22 = N c^2`` is smallest for ``diag(N, N/2, N/2) c^2`` (Cauchy-Schwarz / the
A-optimality of equiangular designs): ``5 / (N c^2)``. So with one frame per state and no
prior the best three states have at least 4/3 of the four-state 0/45/90/135 variance, a matrix
PSNR ``10 log10(4/3) = 1.25 dB`` lower, whatever the angles; only a prior, a lower-order model
or more frames per state can bring three states within 1 dB of four (``benchmarks/results/continuum.md``).
"""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.optics.mueller import polarizer_stokes
from polrig.solve.reference import design_matrix


def summed_variance(angles_deg) -> float:
    d = design_matrix(polarizer_stokes(np.deg2rad(np.asarray(angles_deg, np.float64))))
    return float(np.trace(np.linalg.inv(d.T @ d)))


def test_equiangular_three_states_have_four_thirds_the_variance_of_four():
    ratio = summed_variance([0, 60, 120]) / summed_variance([0, 45, 90, 135])
    assert abs(ratio - 4 / 3) < 1e-12
    assert abs(10 * np.log10(ratio) - 1.2494) < 1e-4
    # the bound holds at any rotation of either set
    assert abs(summed_variance([17, 77, 137]) / summed_variance([5, 50, 95, 140]) - 4 / 3) < 1e-12


@settings(max_examples=200, deadline=None)
@given(a=st.floats(0, 180), b=st.floats(0, 180), c=st.floats(0, 180))
def test_no_three_states_come_closer_to_four_than_four_thirds(a, b, c):
    d = design_matrix(polarizer_stokes(np.deg2rad([a, b, c])))
    n = d.T @ d
    if np.linalg.cond(n) > 1e10:  # two states (nearly) alike: the block is not determined
        return
    assert np.trace(np.linalg.inv(n)) >= (4 / 3) * summed_variance([0, 45, 90, 135]) * (1 - 1e-9)
