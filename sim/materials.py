"""Materials of the simulator: parameters of the Baek et al. 2018 pBRDF (:mod:`polrig.optics.pbrdf`).

A material is ``kd`` (diffuse albedo per colour R, G, B, in [0, 1]), ``alpha`` (microfacet
roughness, GGX/Beckmann parameter), ``eta`` (real refractive index of the dielectric) and
``ks`` (specular weight; 0 makes a purely diffuse material whose specular term is never
evaluated). :meth:`Material.components` names the pBRDF terms the renderer must evaluate.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.choices import MATERIAL_KINDS, MATERIAL_MIXES
from polrig.sim.optical_data import CONDUCTORS, WAVELENGTHS_NM


def pbrdf_components(ks: float, kd) -> tuple[str, ...]:
    """The pBRDF terms a material with specular weight ``ks`` and diffuse albedo ``kd`` (RGB)
    actually has: ``"specular"`` where ``ks > 0``, ``"diffuse"`` where some ``kd > 0``."""
    out = []
    if ks > 0.0:
        out.append("specular")
    if max(kd) > 0.0:
        out.append("diffuse")
    return tuple(out)


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
        return pbrdf_components(self.ks, self.kd)

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


# ---------------------------------------------------------------------------------------------
# Materials beyond the initialization's family (issue 23): evaluated by polrig.sim.surface_bsdf

#: Refractive index of the thin retarding film (enters only its internal propagation angle).
FILM_INDEX = 1.5


@dataclasses.dataclass(frozen=True)
class Texture:
    """A smooth scalar pattern over an object's local frame (metres), values in
    ``[low, high]``: ``low + (high - low) (1 + sin(2 pi u / period_m + phase)) / 2`` with
    ``u = p . axis`` (``kind = "stripes"``) or ``u = |p - (p . axis) axis|`` (``"rings"``,
    distance from the axis through the local origin)."""

    low: float
    high: float
    period_m: float = 0.02
    axis: tuple[float, float, float] = (1.0, 0.0, 0.0)
    phase: float = 0.0
    kind: str = "stripes"

    def __post_init__(self) -> None:
        if self.kind not in ("stripes", "rings"):
            raise ValueError(f"texture kind must be 'stripes' or 'rings', got {self.kind!r}")
        if not (self.period_m > 0 and np.isfinite(self.period_m)):
            raise ValueError(f"texture period_m must be > 0, got {self.period_m}")
        if not (np.isfinite(self.low) and np.isfinite(self.high)):
            raise ValueError("texture low and high must be finite")
        a = np.asarray(self.axis, float).reshape(3)
        if not np.linalg.norm(a) > 0:
            raise ValueError("texture axis must be non-zero")
        object.__setattr__(self, "axis", tuple(float(v) for v in a / np.linalg.norm(a)))

    def __call__(self, p_local: np.ndarray) -> np.ndarray:
        """Values ``(N,)`` at local points ``(N, 3)``."""
        a = np.asarray(self.axis)
        u = p_local @ a
        if self.kind == "rings":
            u = np.linalg.norm(p_local - u[:, None] * a, axis=1)
        w = 0.5 * (1.0 + np.sin(2.0 * np.pi * u / self.period_m + self.phase))
        return self.low + (self.high - self.low) * w


@dataclasses.dataclass(frozen=True)
class SurfaceMaterial:
    """A microfacet surface outside the Baek 2018 dielectric family of :class:`Material`.

    * ``eta_rgb``: relative index per colour (R, G, B at :data:`polrig.sim.optical_data.WAVELENGTHS_NM`),
      complex ``n + i k`` for a conductor (``k > 0``, no diffuse term), real and varying for a
      dispersive dielectric (:mod:`polrig.sim.optical_data`).
    * ``alpha`` / ``alpha_v``: roughness along the surface tangent / across it (``alpha_v``
      ``None``: isotropic); ``distribution`` ``"ggx"`` or ``"beckmann"`` (anisotropic forms of
      Walter et al. 2007 and Heitz, JCGT 3(2) 2014, as Mitsuba 3's ``MicrofacetDistribution``).
    * ``kd``, ``ks``: diffuse albedo per colour and specular weight as in :class:`Material`.
    * ``polarized_fraction``: fraction ``p0`` of the polarized part that survives the way in
      and out of a depolarizing layer at normal incidence and exitance; each pass keeps
      ``p0 ** (1 / (2 cos theta))`` (path length through the layer), so the degree of
      polarization falls below the Fresnel prediction and more so towards grazing
      (:mod:`polrig.sim.surface_bsdf`). ``1``: no depolarization.
    * ``retardance_rad``: normal-incidence retardance of a thin birefringent film over the
      surface at 532 nm (``0``: no film); ``fast_axis_deg``: its fast axis from the surface
      tangent towards the bitangent.
    * ``tangent_axis``: local direction whose projection on the tangent plane is the tangent.
    * Textures (:class:`Texture`, functions of the object's local point): ``kd_texture`` and
      ``alpha_texture`` multiply ``kd`` and both roughnesses, ``eta_texture`` is added to the
      real part of ``eta_rgb``, ``retardance_texture`` multiplies the retardance and
      ``fast_axis_texture`` adds degrees to the fast axis.
    """

    name: str
    eta_rgb: tuple[complex, complex, complex]
    alpha: float
    alpha_v: float | None = None
    kd: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ks: float = 1.0
    distribution: str = "ggx"
    polarized_fraction: float = 1.0
    retardance_rad: float = 0.0
    fast_axis_deg: float = 0.0
    tangent_axis: tuple[float, float, float] = (0.0, 0.0, 1.0)
    kd_texture: Texture | None = None
    alpha_texture: Texture | None = None
    eta_texture: Texture | None = None
    retardance_texture: Texture | None = None
    fast_axis_texture: Texture | None = None

    def __post_init__(self) -> None:
        eta = tuple(complex(v) for v in np.asarray(self.eta_rgb, complex).reshape(3))
        if not all(np.isfinite(e) and e.real > 0 and e.imag >= 0 for e in eta):
            raise ValueError(f"material {self.name}: eta_rgb must have real part > 0 and "
                             f"imaginary part >= 0, got {eta}")
        conductor = any(e.imag > 0 for e in eta)
        if not conductor and not all(e.real > 1.0 for e in eta):
            raise ValueError(f"material {self.name}: a dielectric's eta must be > 1, got {eta}")
        kd = tuple(float(v) for v in np.asarray(self.kd, float).reshape(3))
        if not all(0.0 <= v <= 1.0 for v in kd):
            raise ValueError(f"material {self.name}: kd must be in [0, 1], got {kd}")
        if conductor and max(kd) > 0:
            raise ValueError(f"material {self.name}: a conductor has no diffuse term (kd must be 0)")
        for label, a in (("alpha", self.alpha), ("alpha_v", self.alpha_v)):
            if a is not None and not (a > 0.0 and np.isfinite(a)):
                raise ValueError(f"material {self.name}: {label} must be > 0, got {a}")
        if self.distribution not in ("ggx", "beckmann"):
            raise ValueError(f"material {self.name}: distribution must be 'ggx' or 'beckmann', "
                             f"got {self.distribution!r}")
        if not (0.0 <= self.polarized_fraction <= 1.0):
            raise ValueError(f"material {self.name}: polarized_fraction must be in [0, 1], "
                             f"got {self.polarized_fraction}")
        if not (self.ks >= 0.0 and np.isfinite(self.retardance_rad) and np.isfinite(self.fast_axis_deg)):
            raise ValueError(f"material {self.name}: ks must be >= 0, retardance and fast axis finite")
        tex_lo = {k: (getattr(self, k).low, getattr(self, k).high) for k in
                  ("kd_texture", "alpha_texture", "eta_texture") if getattr(self, k) is not None}
        lo_hi = lambda k, d: (min(tex_lo.get(k, d)), max(tex_lo.get(k, d)))  # noqa: E731
        if lo_hi("alpha_texture", (1, 1))[0] <= 0 or max(kd) * lo_hi("kd_texture", (1, 1))[1] > 1 \
                or lo_hi("kd_texture", (1, 1))[0] < 0:
            raise ValueError(f"material {self.name}: textures must keep alpha > 0 and kd in [0, 1]")
        if min(e.real for e in eta) + lo_hi("eta_texture", (0, 0))[0] <= (0.0 if conductor else 1.0):
            raise ValueError(f"material {self.name}: the eta texture must keep eta > "
                             f"{'0' if conductor else '1'}")
        t = np.asarray(self.tangent_axis, float).reshape(3)
        if not np.linalg.norm(t) > 0:
            raise ValueError(f"material {self.name}: tangent_axis must be non-zero")
        object.__setattr__(self, "eta_rgb", eta)
        object.__setattr__(self, "kd", kd)
        object.__setattr__(self, "tangent_axis", tuple(float(v) for v in t / np.linalg.norm(t)))

    @property
    def conductor(self) -> bool:
        return any(e.imag > 0 for e in self.eta_rgb)

    @property
    def eta(self) -> float:
        """Nominal real index (green channel's real part), for per-pixel truth images."""
        return self.eta_rgb[1].real

    @property
    def components(self) -> tuple[str, ...]:
        """pBRDF terms with a non-zero weight (``"specular"``, ``"diffuse"``)."""
        return pbrdf_components(self.ks, self.kd)

    def parameters(self, p_local: np.ndarray) -> dict[str, np.ndarray]:
        """Per-point parameters at local points ``(N, 3)``: ``eta`` ``(N, 3)`` complex,
        ``kd`` ``(N, 3)``, ``alpha_u``, ``alpha_v``, ``ks``, ``polarized_fraction``,
        ``retardance_rad`` (green, normal incidence), ``fast_axis_rad`` ``(N,)``."""
        n = len(p_local)

        def tex(t: Texture | None, neutral: float) -> np.ndarray:
            return np.full(n, neutral) if t is None else np.asarray(t(p_local), float)

        a_scale = tex(self.alpha_texture, 1.0)
        eta = np.broadcast_to(np.asarray(self.eta_rgb, complex), (n, 3)) + tex(self.eta_texture, 0.0)[:, None]
        alpha_v = self.alpha if self.alpha_v is None else self.alpha_v
        return {
            "eta": eta, "kd": np.asarray(self.kd)[None, :] * tex(self.kd_texture, 1.0)[:, None],
            "alpha_u": self.alpha * a_scale, "alpha_v": alpha_v * a_scale,
            "ks": np.full(n, float(self.ks)), "polarized_fraction": np.full(n, float(self.polarized_fraction)),
            "retardance_rad": self.retardance_rad * tex(self.retardance_texture, 1.0),
            "fast_axis_rad": np.deg2rad(self.fast_axis_deg + tex(self.fast_axis_texture, 0.0)),
        }

    def to_json(self) -> dict:
        d = {"name": self.name, "model": "surface",
             "eta_rgb": [[e.real, e.imag] for e in self.eta_rgb], "alpha": self.alpha,
             "alpha_v": self.alpha_v, "kd": list(self.kd), "ks": self.ks,
             "distribution": self.distribution, "polarized_fraction": self.polarized_fraction,
             "retardance_rad": self.retardance_rad, "fast_axis_deg": self.fast_axis_deg,
             "tangent_axis": list(self.tangent_axis)}
        for k in ("kd_texture", "alpha_texture", "eta_texture", "retardance_texture", "fast_axis_texture"):
            t = getattr(self, k)
            d[k] = None if t is None else dataclasses.asdict(t)
        return d


# ---------------------------------------------------------------------------------------------
# Random materials of the dataset mixes (issue 23, item 4)

#: Fraunhofer d, F and C lines (nm) of the Abbe number.
_LINES_NM = (587.5618, 486.1327, 656.2725)


def cauchy_rgb(n_d: float, abbe: float) -> tuple[float, float, float]:
    """Real index per channel of a two-term Cauchy dielectric ``n = A + B / lambda^2`` with
    refractive index ``n_d`` and Abbe number ``V_d = (n_d - 1) / (n_F - n_C)`` (the catalogue
    parametrisation of optical glasses and plastics)."""
    ld, lf, lc = _LINES_NM
    b = (n_d - 1.0) / abbe / (1.0 / lf ** 2 - 1.0 / lc ** 2)
    a = n_d - b / ld ** 2
    return tuple(float(a + b / lam ** 2) for lam in WAVELENGTHS_NM)  # type: ignore[return-value]


def _random_texture(rng: np.random.Generator, low: float, high: float) -> Texture:
    axis = rng.normal(size=3)
    return Texture(low, high, float(rng.uniform(0.01, 0.05)), tuple(axis / np.linalg.norm(axis)),
                   float(rng.uniform(0, 2 * np.pi)), str(rng.choice(["stripes", "rings"])))


def random_surface_material(rng: np.random.Generator, kind: str, base: Material,
                            *, name: str = "random") -> SurfaceMaterial:
    """A random material of ``kind`` (:data:`MATERIAL_KINDS` other than ``baek``) built on the
    dielectric ``base`` (its kd, alpha, eta):

    * ``conductor``: a metal of :data:`polrig.sim.optical_data.CONDUCTORS`, log-uniform alpha in
      [0.02, 0.6], GGX or Beckmann;
    * ``dispersive``: the base with a Cauchy dispersion of Abbe number uniform in [20, 65]
      (:func:`cauchy_rgb`; ``n_d`` = the base eta);
    * ``anisotropic``: the base with ``alpha_u, alpha_v = alpha exp(+-u)``, ``u`` uniform in
      [0.3, 1.2], Beckmann or GGX, random tangent;
    * ``film``: the base under a retarding film of retardance uniform in [0.3, 3] rad with a
      random fast axis, both varying over the object (textures);
    * ``depolarizing``: the base with polarized fraction uniform in [0.3, 0.9] and kd, alpha
      and eta textures.
    """
    eta3 = (base.eta,) * 3
    tangent = tuple(rng.normal(size=3))
    if kind == "conductor":
        metal = str(rng.choice(list(CONDUCTORS)))
        alpha = float(np.exp(rng.uniform(np.log(0.02), np.log(0.6))))
        return SurfaceMaterial(f"{name}_{metal}", CONDUCTORS[metal], alpha,
                               distribution=str(rng.choice(["ggx", "beckmann"])))
    if kind == "dispersive":
        return SurfaceMaterial(name, cauchy_rgb(base.eta, float(rng.uniform(20, 65))), base.alpha,
                               kd=base.kd, ks=base.ks)
    if kind == "anisotropic":
        u = float(rng.uniform(0.3, 1.2))
        return SurfaceMaterial(name, eta3, base.alpha * np.exp(u), base.alpha * np.exp(-u), kd=base.kd,
                               ks=base.ks, distribution=str(rng.choice(["ggx", "beckmann"])),
                               tangent_axis=tangent)
    if kind == "film":
        return SurfaceMaterial(name, eta3, base.alpha, kd=base.kd, ks=base.ks,
                               retardance_rad=float(rng.uniform(0.3, 3.0)),
                               fast_axis_deg=float(rng.uniform(0, 180)), tangent_axis=tangent,
                               retardance_texture=_random_texture(rng, 0.3, 1.0),
                               fast_axis_texture=_random_texture(rng, -30.0, 30.0))
    if kind == "depolarizing":
        kd_hi = 1.0 / max(max(base.kd), 1e-6)
        return SurfaceMaterial(name, eta3, base.alpha, kd=base.kd, ks=base.ks,
                               polarized_fraction=float(rng.uniform(0.3, 0.9)), tangent_axis=tangent,
                               kd_texture=_random_texture(rng, 0.4, min(1.0, kd_hi)),
                               alpha_texture=_random_texture(rng, 0.5, 2.0),
                               eta_texture=_random_texture(rng, -0.2, 0.2))
    raise ValueError(f"unknown material kind {kind!r}; known: {', '.join(MATERIAL_KINDS[1:])}")


def random_mix_material(rng: np.random.Generator, mix: str, base: Material) -> Material | SurfaceMaterial:
    """A material drawn from the named ``mix`` (:data:`MATERIAL_MIXES`); ``baek`` returns
    ``base`` itself and draws nothing from ``rng``."""
    try:
        probs = MATERIAL_MIXES[mix]
    except KeyError:
        raise ValueError(f"unknown material mix {mix!r}; known: {', '.join(MATERIAL_MIXES)}") from None
    kinds = list(probs)
    if kinds == ["baek"]:
        return base
    kind = kinds[int(rng.choice(len(kinds), p=np.array([probs[k] for k in kinds])))]
    return base if kind == "baek" else random_surface_material(rng, kind, base, name=base.name)
