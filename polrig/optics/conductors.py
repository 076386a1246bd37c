"""Tabulated complex refractive indices of metals at the rig's three colour channels.

The simulated rig renders, and the calibration models, three colour channels (R, G, B) at the
representative wavelengths :data:`WAVELENGTHS_NM` (630, 532 and 465 nm: the peaks of a typical
Bayer colour filter set under white LED light).

:data:`CONDUCTORS`: complex index of refraction ``eta = n + i k`` per channel (the
``exp(-i omega t)`` convention of :func:`polrig.optics.mueller.specular_reflection`), linearly
interpolated in wavelength from the tables that Mitsuba 3 distributes in
``data/ior/<metal>.{eta,k}.spd`` (headers: "data from www.luxpop.com database", the luxpop
compilation of handbook data, largely E. D. Palik, *Handbook of Optical Constants of Solids*,
Academic Press 1985/1991; for gold the values agree with P. B. Johnson and R. W. Christy,
Phys. Rev. B 6, 4370 (1972), n = 0.18, k = 3.07 near 633 nm). Interpolating the same tables
the same way is what Mitsuba's ``conductor`` plugin does for ``material = "Au"`` etc., which
``tests/test_materials_mitsuba.py`` uses as the oracle of this table. Chrome is ``Cr``.

The table lives in the core because both the simulator (:mod:`polrig.sim.optical_data`, its metal
materials and calibration targets) and the calibration (the metal mirror of the DoFP step,
:mod:`polrig.calibration.mirror`) need it.
"""

from __future__ import annotations

#: Representative wavelengths of the colour channels R, G, B (nm).
WAVELENGTHS_NM = (630.0, 532.0, 465.0)

#: Complex refractive index ``n + i k`` per channel (R, G, B) of the tabulated metals.
CONDUCTORS: dict[str, tuple[complex, complex, complex]] = {
    "gold": (0.18370 + 3.06634j, 0.45726 + 2.40840j, 1.37237 + 1.82500j),
    "silver": (0.13425 + 3.96283j, 0.12965 + 3.19420j, 0.13952 + 2.61355j),
    "copper": (0.24588 + 3.37835j, 1.07229 + 2.59073j, 1.15686 + 2.45722j),
    "aluminium": (1.35707 + 7.58780j, 0.88429 + 6.46996j, 0.66048 + 5.65363j),
    "chrome": (3.55729 + 4.36215j, 2.97880 + 4.45005j, 2.12553 + 4.30249j),
}

#: Mitsuba 3 ``material`` names of :data:`CONDUCTORS` (the data files they were read from).
MITSUBA_NAMES = {"gold": "Au", "silver": "Ag", "copper": "Cu", "aluminium": "Al", "chrome": "Cr"}


def conductor_rgb(name: str) -> tuple[complex, complex, complex]:
    """Complex index per channel (R, G, B) of the conductor ``name`` (:data:`CONDUCTORS`);
    ``ValueError`` naming the known ones otherwise."""
    try:
        return CONDUCTORS[name]
    except KeyError:
        raise ValueError(f"unknown conductor {name!r}; known: {', '.join(CONDUCTORS)}") from None
