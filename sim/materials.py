"""Materials of the simulator: parameters of the Baek et al. 2018 pBRDF (:mod:`polrig.pbrdf`).

A material is ``kd`` (diffuse albedo per colour R, G, B, in [0, 1]), ``alpha`` (microfacet
roughness, GGX/Beckmann parameter), ``eta`` (real refractive index of the dielectric) and
``ks`` (specular weight; 0 makes a purely diffuse material whose specular term is never
evaluated). :meth:`Material.components` names the pBRDF terms the renderer must evaluate.
"""

from __future__ import annotations

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class Material:
    name: str
    kd: tuple[float, float, float]
    alpha: float
    eta: float = 1.5
    ks: float = 1.0

    def __post_init__(self) -> None:
        kd = tuple(float(v) for v in np.asarray(self.kd, float).reshape(3))
        if not all(0.0 <= v <= 1.0 for v in kd):
            raise ValueError(f"material {self.name}: kd must be in [0, 1], got {kd}")
        if not (self.alpha > 0.0 and np.isfinite(self.alpha)):
            raise ValueError(f"material {self.name}: alpha must be > 0, got {self.alpha}")
        if not (self.eta > 1.0 and np.isfinite(self.eta)):
            raise ValueError(f"material {self.name}: eta must be > 1, got {self.eta}")
        if not (self.ks >= 0.0):
            raise ValueError(f"material {self.name}: ks must be >= 0, got {self.ks}")
        object.__setattr__(self, "kd", kd)

    @property
    def components(self) -> tuple[str, ...]:
        """pBRDF terms with a non-zero weight (``"specular"``, ``"diffuse"``)."""
        out = []
        if self.ks > 0.0:
            out.append("specular")
        if max(self.kd) > 0.0:
            out.append("diffuse")
        return tuple(out)

    def to_json(self) -> dict:
        return dataclasses.asdict(self) | {"kd": list(self.kd)}


#: Named presets (``mirror``: alpha 0.01; ``rough``: alpha 0.8; ``diffuse``: ks = 0).
PRESETS: dict[str, Material] = {m.name: m for m in (
    Material("plastic_red", (0.55, 0.08, 0.06), 0.15, 1.5),
    Material("plastic_green", (0.08, 0.45, 0.12), 0.25, 1.49),
    Material("plastic_blue", (0.06, 0.12, 0.55), 0.2, 1.52),
    Material("plastic_white", (0.8, 0.8, 0.78), 0.3, 1.5),
    Material("ceramic", (0.7, 0.65, 0.55), 0.08, 1.6),
    Material("mirror", (0.02, 0.02, 0.02), 0.01, 1.7),
    Material("rough", (0.35, 0.3, 0.25), 0.8, 1.45),
    Material("diffuse", (0.6, 0.6, 0.6), 0.5, 1.5, ks=0.0),
    Material("diffuse_grey", (0.3, 0.3, 0.3), 0.5, 1.5, ks=0.0),
)}


def get_material(name: str) -> Material:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown material {name!r}; presets: {', '.join(PRESETS)}") from None


def random_material(rng: np.random.Generator, *, name: str = "random") -> Material:
    """A random dielectric: kd uniform per colour in [0.02, 0.9], log-uniform alpha in
    [0.01, 0.8], eta in [1.3, 1.8], ks 1 (or 0 for one material in ten)."""
    kd = rng.uniform(0.02, 0.9, size=3)
    alpha = float(np.exp(rng.uniform(np.log(0.01), np.log(0.8))))
    eta = float(rng.uniform(1.3, 1.8))
    ks = 0.0 if rng.random() < 0.1 else 1.0
    return Material(name, tuple(kd), alpha, eta, ks)
