"""The polished metal mirror of the DoFP calibration: its Mueller matrix in the rig frames.

The DoFP step (:func:`polrig.calibration.procedures.run_dofp`) sees the generator's light after one
reflection off a rough metal plate. Per pixel the microfacet that reflects towards the camera
has the half vector ``h = normalize(wi + wo)``, so the light path's Mueller matrix is the
complex-index Fresnel reflection at ``cos theta = wi . h``
(:func:`polrig.optics.mueller.specular_reflection`, s/p bases with ``x = s = wi x h``) times the
scalar microfacet weight ``D(h) G1(wi) G1(wo) / (4 cos theta_o)``, turned into the rig frames
(incident: ``k = -wi``, ``x`` = stage zero axis; emergent: ``k = wo``, ``x`` = camera ``x``;
``docs/conventions.md``). Baek et al. 2018 (ACM TOG 37(6)) and Mitsuba 3 ``roughconductor``
use the same specular term; the simulator renders the plate with it
(:func:`polrig.sim.surface_bsdf.evaluate`, tested equal).

A real metal is no ideal mirror: with ``r_s``, ``r_p`` the complex amplitudes the s/p block is
``[[a, b, 0], [b, a, 0], [0, 0, c cos d]]`` (``a, b = (Rs +- Rp) / 2``, ``c = sqrt(Rs Rp)``,
``d`` the s-p phase difference). ``b / a`` is the mirror's diattenuation and
``1 - |c cos d| / a`` the part of ``S2`` (in the s/p basis) that the retardance turns into
``S3``, which a linear DoFP analyzer cannot see. An ideal mirror (``Rs = Rp = 1``, ``d = pi``,
the handedness flip) is ``diag(1, 1, -1)``. For aluminium at the simulated rig's 11.6 deg the
departure is 0.0016 (diattenuation) and 1e-4 (``m22``); at 45 deg 0.03 and 0.02.

The metal is a calibration input (:class:`MirrorMetal`; default :data:`DEFAULT_MIRROR_METAL`
from :data:`polrig.optics.conductors.CONDUCTORS`). A colour sensor's pixel uses its channel's index;
a mono sensor the mean of the three channels' Mueller matrices (a flat light spectrum and
equal channel weights, the simulated mono sensor's :data:`polrig.sim.sensor.MONO_WEIGHTS`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.optics import bases as fr
from polrig.optics import mueller as mu
from polrig.optics.conductors import CONDUCTORS, conductor_rgb
from polrig.optics.pbrdf import microfacet_d, smith_g1

#: The front-surface mirror metal the DoFP step assumes unless told otherwise: aluminium, the
#: usual bare first-surface mirror coating (broadband over the visible, stable in air under
#: its few-nanometre native oxide, which this model neglects; silver tarnishes unless
#: over-coated, and a dielectric over-coat adds its own retardance).
DEFAULT_MIRROR_METAL = "aluminium"
#: The metal of the light calibration's mirror ball (:func:`polrig.calibration.procedures.run_light`):
#: chrome, what polished steel balls sold as "chrome" spheres are plated with.
DEFAULT_SPHERE_METAL = "chrome"
#: Name of the ideal mirror (``Rs = Rp = 1``, no retardance): the old assumption, kept for
#: comparison (``polrig calibrate dofp --mirror-metal ideal``) and closed-form tests.
IDEAL = "ideal"


@dataclasses.dataclass(frozen=True)
class MirrorMetal:
    """The metal of a calibration mirror (the DoFP plate, the light calibration's ball):
    ``name`` and complex index ``n + i k`` per colour channel (R, G, B at
    :data:`polrig.optics.conductors.WAVELENGTHS_NM`), or the ideal mirror (``name == "ideal"``,
    ``eta_rgb`` ``None``)."""

    name: str
    eta_rgb: tuple[complex, complex, complex] | None

    def __post_init__(self) -> None:
        if self.eta_rgb is None:
            if self.name != IDEAL:
                raise ValueError(f"mirror {self.name!r} needs its complex index per colour "
                                 f"(eta_rgb); only {IDEAL!r} has none")
            return
        eta = tuple(complex(v) for v in np.asarray(self.eta_rgb, complex).reshape(-1))
        if len(eta) != 3 or not all(np.isfinite(e) and e.real > 0 and e.imag >= 0 for e in eta):
            raise ValueError(f"mirror {self.name!r}: eta_rgb must be 3 complex indices n + i k "
                             f"(R, G, B) with n > 0 and k >= 0, got {self.eta_rgb!r}")
        object.__setattr__(self, "eta_rgb", eta)

    @classmethod
    def named(cls, name: str) -> "MirrorMetal":
        """A metal of :data:`polrig.optics.conductors.CONDUCTORS` or ``"ideal"``; ``ValueError``
        naming the known ones otherwise."""
        if name == IDEAL:
            return cls(IDEAL, None)
        if name not in CONDUCTORS:
            raise ValueError(f"unknown mirror metal {name!r}; known: "
                             f"{', '.join((*CONDUCTORS, IDEAL))}")
        return cls(name, conductor_rgb(name))

    @property
    def ideal(self) -> bool:
        return self.eta_rgb is None

    def reflectance_rgb(self, cos_theta: float = 1.0) -> np.ndarray:
        """Unpolarized reflectance ``(Rs + Rp) / 2`` per colour channel ``(3,)`` at
        ``cos_theta`` (default normal incidence: ``((n - 1)^2 + k^2) / ((n + 1)^2 + k^2)``);
        ones for the ideal mirror."""
        if self.ideal:
            return np.ones(3)
        rs, rp = mu.fresnel_reflectance(np.full(3, float(cos_theta)),
                                        np.asarray(self.eta_rgb, complex))
        return 0.5 * (rs + rp)

    def to_json(self) -> dict:
        return {"name": self.name, "eta_rgb": None if self.eta_rgb is None else
                [[e.real, e.imag] for e in self.eta_rgb]}

    @classmethod
    def from_json(cls, d: dict) -> "MirrorMetal":
        eta = d.get("eta_rgb")
        return cls(str(d["name"]), None if eta is None else
                   tuple(complex(float(re), float(im)) for re, im in eta))


def fresnel_sp(cos_theta: np.ndarray, metal: MirrorMetal,
               channel: np.ndarray | None = None) -> np.ndarray:
    """Fresnel reflection Mueller matrices ``(P, 4, 4)`` in the s/p bases at ``cos_theta``
    ``(P,)``: of colour ``channel`` ``(P,)`` (0, 1, 2 = R, G, B), or the mean over the three
    channels where ``channel`` is ``None`` (mono sensor); ``diag(1, 1, -1, -1)`` for the ideal
    mirror."""
    ct = np.asarray(cos_theta, dtype=np.float64).reshape(-1)
    if metal.ideal:
        return np.broadcast_to(np.diag([1.0, 1.0, -1.0, -1.0]), (ct.size, 4, 4)).copy()
    eta = np.asarray(metal.eta_rgb, complex)
    if channel is None:
        return np.mean([mu.specular_reflection(ct, e) for e in eta], axis=0)
    return mu.specular_reflection(ct, eta[np.asarray(channel, np.int64).reshape(-1)])


def mirror_mueller(normal, wi, wo, metal: MirrorMetal, *, alpha: float,
                   stage_zero_axis, camera_x_axis,
                   channel: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Linear block of the rough mirror's Mueller matrix in the rig frames, normalised by its
    ``m00``, ``(P, 3, 3)``, and ``m00`` itself ``(P,)`` (1/sr: Fresnel ``(Rs + Rp) / 2``
    times the GGX microfacet weight of roughness ``alpha``; module docstring).

    ``normal``, ``wi`` (towards the light), ``wo`` (towards the camera): ``(P, 3)`` or
    ``(3,)``; ``stage_zero_axis``, ``camera_x_axis``: ``(3,)`` or ``(P, 3)``; ``channel``:
    each point's colour channel ``(P,)`` or ``None`` (mono). Points where ``wi`` or ``wo`` is
    at or below the plate's horizon get NaN blocks and ``m00 = 0``.
    """
    shape = np.broadcast_shapes(*(np.shape(np.atleast_2d(v)) for v in (normal, wi, wo)))
    n, wi, wo = (fr.normalize(np.broadcast_to(np.atleast_2d(np.asarray(v, float)), shape))
                 for v in (normal, wi, wo))
    h = fr.normalize(wi + wo)
    cos_i, cos_o, cos_h, cos_ih = fr.dot(n, wi), fr.dot(n, wo), fr.dot(n, h), fr.dot(wi, h)
    ok = (cos_i > 0) & (cos_o > 0)
    f = fresnel_sp(cos_ih, metal, channel)
    k_in = -wi
    x_in = fr.basis_from_reference_unit(k_in, stage_zero_axis)
    x_out = fr.basis_from_reference_unit(wo, camera_x_axis)
    s = fr.cross(wi, h)  # perpendicular to the microfacet's plane of incidence
    s = np.where((fr.dot(s, s) > 1e-24)[:, None], s, x_in)  # retro-reflection: any axis
    ci, si = fr.rotation_cos_sin_2theta_to_frame(s, x_in, fr.cross(k_in, x_in))
    co, so = fr.rotation_cos_sin_2theta_to_frame(s, x_out, fr.cross(wo, x_out))
    m = fr.rotate_rows(fr.rotate_cols(f, ci, si), co, so)[:, :3, :3]
    weight = np.where(ok, microfacet_d(cos_h, alpha) * smith_g1(cos_i, cos_ih, alpha)
                      * smith_g1(cos_o, fr.dot(wo, h), alpha) / (4.0 * np.where(ok, cos_o, 1.0)),
                      0.0)
    m00 = m[:, 0, 0] * weight
    good = ok & (m00 > 0)
    block = np.where(good[:, None, None], m / np.where(good, m[:, 0, 0], 1.0)[:, None, None],
                     np.nan)
    return block, m00
