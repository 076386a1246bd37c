"""Tabulated optical constants of the simulator's materials at its three colour channels.

The simulated rig renders three colour channels (R, G, B) at the representative wavelengths
:data:`WAVELENGTHS_NM` (630, 532 and 465 nm: the peaks of a typical Bayer colour filter set
under white LED light). Every material whose optics depend on wavelength is evaluated at
exactly these wavelengths.

**Conductors**: :data:`CONDUCTORS` (complex ``n + i k`` per channel of gold, silver,
copper, aluminium and chrome, with their source) live in :mod:`polrig.optics.conductors`, because
the calibration models a metal mirror with them too; they are re-exported here.

**Dispersive dielectrics** (:data:`DIELECTRICS`): Sellmeier equations
``n^2 - 1 = sum_j B_j l^2 / (l^2 - C_j)`` (``l`` in micrometres):

* ``bk7``: Schott N-BK7 catalogue coefficients (SCHOTT optical glass data sheet;
  n_d = 1.5168, Abbe number 64.17);
* ``pmma``: poly(methyl methacrylate), M. Szczurowski's fit as published on
  refractiveindex.info (n_d = 1.4905);
* ``polycarbonate``: N. Sultanova, S. Kasarova, I. Nikolov, Acta Phys. Pol. A 116, 585 (2009)
  (n_d = 1.585, a strongly dispersive plastic: Abbe number near 30).
"""

from __future__ import annotations

import numpy as np

from polrig.optics.conductors import (  # noqa: F401
    CONDUCTORS,
    MITSUBA_NAMES,
    WAVELENGTHS_NM,
    conductor_rgb,
)

#: Sellmeier coefficients ``((B1, B2, B3), (C1, C2, C3))`` (``C`` in square micrometres).
SELLMEIER: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "bk7": ((1.03961212, 0.231792344, 1.01046945), (0.00600069867, 0.0200179144, 103.560653)),
    "pmma": ((0.99654, 0.18964, 0.00411), (0.00787, 0.02191, 3.85727)),
    "polycarbonate": ((1.4182,), (0.021304,)),
}


def sellmeier(wavelength_nm, b: tuple[float, ...], c: tuple[float, ...]) -> np.ndarray:
    """Refractive index from the Sellmeier equation at ``wavelength_nm`` (array or scalar)."""
    l2 = np.square(np.asarray(wavelength_nm, dtype=np.float64) * 1e-3)
    n2 = 1.0 + sum(bj * l2 / (l2 - cj) for bj, cj in zip(b, c))
    return np.sqrt(n2)


def dielectric_rgb(name: str) -> tuple[float, float, float]:
    """Real index per channel (R, G, B) of the dispersive dielectric ``name``."""
    try:
        b, c = SELLMEIER[name]
    except KeyError:
        raise ValueError(f"unknown dielectric {name!r}; known: {', '.join(SELLMEIER)}") from None
    return tuple(float(v) for v in sellmeier(np.array(WAVELENGTHS_NM), b, c))  # type: ignore[return-value]
