"""Tabulated optical constants of the simulator's materials at its three colour channels.

The simulated rig renders three colour channels (R, G, B) at the representative wavelengths
:data:`WAVELENGTHS_NM` (630, 532 and 465 nm: the peaks of a typical Bayer colour filter set
under white LED light). Every material whose optics depend on wavelength is evaluated at
exactly these wavelengths.

**Conductors** (:data:`CONDUCTORS`): complex index of refraction ``eta = n + i k`` per
channel, linearly interpolated in wavelength from the tables that Mitsuba 3 distributes in
``data/ior/<metal>.{eta,k}.spd`` (headers: "data from www.luxpop.com database", the luxpop
compilation of handbook data, largely E. D. Palik, *Handbook of Optical Constants of Solids*,
Academic Press 1985/1991; for gold the values agree with P. B. Johnson and R. W. Christy,
Phys. Rev. B 6, 4370 (1972), n = 0.18, k = 3.07 near 633 nm). Interpolating the same tables
the same way is what Mitsuba's ``conductor`` plugin does for ``material = "Au"`` etc., which
``tests/test_materials_mitsuba.py`` uses as the oracle of this table. Chrome is ``Cr``.

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

#: Representative wavelengths of the colour channels R, G, B (nm).
WAVELENGTHS_NM = (630.0, 532.0, 465.0)

#: Complex refractive index ``n + i k`` per channel (R, G, B) of the simulated conductors.
CONDUCTORS: dict[str, tuple[complex, complex, complex]] = {
    "gold": (0.18370 + 3.06634j, 0.45726 + 2.40840j, 1.37237 + 1.82500j),
    "silver": (0.13425 + 3.96283j, 0.12965 + 3.19420j, 0.13952 + 2.61355j),
    "copper": (0.24588 + 3.37835j, 1.07229 + 2.59073j, 1.15686 + 2.45722j),
    "aluminium": (1.35707 + 7.58780j, 0.88429 + 6.46996j, 0.66048 + 5.65363j),
    "chrome": (3.55729 + 4.36215j, 2.97880 + 4.45005j, 2.12553 + 4.30249j),
}

#: Mitsuba 3 ``material`` names of :data:`CONDUCTORS` (the data files they were read from).
MITSUBA_NAMES = {"gold": "Au", "silver": "Ag", "copper": "Cu", "aluminium": "Al", "chrome": "Cr"}

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


def conductor_rgb(name: str) -> tuple[complex, complex, complex]:
    """Complex index per channel (R, G, B) of the conductor ``name``."""
    try:
        return CONDUCTORS[name]
    except KeyError:
        raise ValueError(f"unknown conductor {name!r}; known: {', '.join(CONDUCTORS)}") from None
