"""The simulated DoFP sensor: radiometric response, per-pixel analyzers and noise.

Chain for one sensor pixel ``p`` of colour ``c`` (``docs/conventions.md``, "Radiometric
units"):

1. radiance ``L`` (the renderer's unit) -> signal electrons
   ``e = L * photons_per_radiance_us * exposure_us * QE * colour_qe[c]`` (before the analyzer);
2. -> black-subtracted DN ``e / gain_e_per_dn * 10**(gain_db / 20)`` (:meth:`DoFPSensor.response_dn`);
   the image-plane Mueller matrix (the simulator's ``truth_mueller``) is the radiance Mueller
   matrix times the light's radiant intensity times this response, so that the noise-free,
   black-subtracted Stokes image the sensor sees is ``S_out_DN = M @ S_in``;
3. each pixel's analyzer (:class:`polrig.sensor.analyzer.AnalyzerModel`: orientation error,
   diattenuation, gain; Powell and Gruev, Opt. Express 21(18):21039, 2013) turns its colour's
   Stokes vector into an intensity (:meth:`polrig.sensor.analyzer.AnalyzerModel.mosaic`);
4. noise, dark current, black level, quantization and saturation
   (:class:`polrig.sensor.noise.SensorModel`), or, with noise off, the exact float mean.

A mono sensor (IMX250MZR) integrates the three colour radiances with ``mono_weights``.
Defaults follow the IMX250MZR/MYR class (~10.5 ke- full well, ~2.3 e- read noise, 12-bit
ADC; the published figures are cited in :mod:`polrig.sensor.noise`).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.layouts import get_layout
from polrig.sensor.noise import SensorModel

#: Default relative quantum efficiency of the R, G, B pixels of the colour sensor.
COLOUR_QE = (0.75, 1.0, 0.85)
#: How a mono sensor weighs the renderer's R, G, B radiance (a flat spectrum sums to 1).
MONO_WEIGHTS = (1 / 3, 1 / 3, 1 / 3)


def gain_factor(gain_db: float) -> float:
    """Amplitude gain of an analogue gain in dB (``10**(gain_db / 20)``)."""
    return float(10.0 ** (float(gain_db) / 20.0))


def random_analyzer(layout: str, shape: tuple[int, int], rng: np.random.Generator, *,
                    angle_sigma_deg: float = 0.4, angle_bias_deg: float = 0.3,
                    diattenuation_mean: float = 0.985, diattenuation_sigma: float = 0.004,
                    gain_sigma: float = 0.01) -> AnalyzerModel:
    """A non-ideal analyzer model: per-pixel orientation error (a per-angle bias drawn once
    with standard deviation ``angle_bias_deg`` plus per-pixel ``angle_sigma_deg``), per-pixel
    diattenuation (clipped to [0.5, 1]) and gain around 1, offset 0."""
    ideal = AnalyzerModel.ideal(layout, shape)
    lay = get_layout(layout)
    angles = ideal.angle_deg
    bias = {a: rng.normal(0.0, angle_bias_deg) for a in (0, 45, 90, 135)}
    err = np.zeros(shape)
    for a, b in bias.items():
        err[angles == a] = b
    err += rng.normal(0.0, angle_sigma_deg, shape)
    dia = np.clip(rng.normal(diattenuation_mean, diattenuation_sigma, shape), 0.5, 1.0)
    gain = np.clip(rng.normal(1.0, gain_sigma, shape), 0.5, 1.5)
    return AnalyzerModel(lay.name, gain, angles + err, dia, np.zeros(shape))


@dataclasses.dataclass(frozen=True)
class DoFPSensor:
    """Full simulated sensor (``analyzer.shape`` pixels; a ROI is cut from it).

    ``photons_per_radiance_us``: photo-electrons before QE per pixel per microsecond per unit
    radiance of the renderer (the lens and pixel area folded into one constant).
    """

    analyzer: AnalyzerModel
    model: SensorModel
    colour_qe: tuple[float, ...] = COLOUR_QE
    mono_weights: tuple[float, float, float] = MONO_WEIGHTS
    photons_per_radiance_us: float = 2.0
    _roi_cache: dict = dataclasses.field(default_factory=dict, init=False, repr=False,
                                         compare=False)

    def __post_init__(self) -> None:
        n = self.analyzer.n_colours
        qe = tuple(float(v) for v in self.colour_qe)
        if n == 1 and len(qe) != 1:
            qe = (1.0,)
        if len(qe) != n:
            raise ValueError(f"colour_qe needs {n} values for layout {self.analyzer.layout}")
        object.__setattr__(self, "colour_qe", qe)

    @property
    def layout(self) -> str:
        return self.analyzer.layout

    @property
    def n_colours(self) -> int:
        return self.analyzer.n_colours

    @property
    def shape(self) -> tuple[int, int]:
        return self.analyzer.shape

    def gained_model(self, gain_db: float) -> SensorModel:
        """The sensor model at an analogue gain: fewer electrons per DN, same e- noise."""
        return dataclasses.replace(self.model,
                                   gain_e_per_dn=self.model.gain_e_per_dn / gain_factor(gain_db))

    def response_dn(self, exposure_us: float, gain_db: float) -> np.ndarray:
        """Black-subtracted DN per unit radiance per colour channel ``(C,)``."""
        e = (self.photons_per_radiance_us * float(exposure_us) * self.model.quantum_efficiency
             * np.asarray(self.colour_qe))
        return e / self.gained_model(gain_db).gain_e_per_dn

    def signal_mosaic(self, stokes_dn: np.ndarray, roi: tuple[int, int, int, int]) -> np.ndarray:
        """Noise-free black-subtracted DN mosaic ``(h, w)`` of the Stokes images
        ``(C, 3, h, w)`` of a ROI ``(width, height, offset_x, offset_y)``."""
        return self.roi_analyzer(roi).mosaic(stokes_dn)

    def roi_analyzer(self, roi: tuple[int, int, int, int]) -> AnalyzerModel:
        """The analyzer model of a ROI (its layout phase follows the offset), cached."""
        roi = tuple(int(v) for v in roi)
        cache = self._roi_cache
        if roi not in cache:
            w, h, ox, oy = roi
            if len(cache) > 8:
                cache.clear()
            cache[roi] = self.analyzer.crop(ox, oy, w, h)
        return cache[roi]

    def expose(self, signal_dn: np.ndarray, *, exposure_us: float, gain_db: float,
               rng: np.random.Generator | None, noise: bool = True) -> np.ndarray:
        """Raw frame from a noise-free signal mosaic (black-subtracted DN at ``gain_db``).

        ``noise=True``: ``uint16`` DN sampled by :meth:`polrig.sensor.noise.SensorModel.sample_raw`
        (shot, read and dark noise, black level, quantization, saturation), reproducible for
        a seeded ``rng``. ``noise=False``: the exact float64 mean (black level + signal + dark
        signal, saturating at full well and at the ADC range, not quantized).
        """
        model = self.gained_model(gain_db)
        e = np.clip(np.asarray(signal_dn, np.float64), 0.0, None) * model.gain_e_per_dn
        if noise:
            if rng is None:
                raise ValueError("a noisy exposure needs a numpy Generator 'rng'")
            return model.sample_raw(e, rng, exposure_us)
        e_total = np.minimum(e + model.dark_electrons(exposure_us), model.full_well_e)
        mean = model.black_level_dn + e_total / model.gain_e_per_dn
        return np.clip(mean, 0.0, model.max_code_dn)

    def to_json(self) -> dict:
        m = self.model
        a = self.analyzer
        t_nominal = AnalyzerModel.ideal(a.layout, a.shape).angle_deg
        err = a.angle_deg - t_nominal
        return {
            "layout": a.layout, "shape": list(a.shape),
            "sensor_model": {k: (v if isinstance(v, (int, float, str, bool, type(None)))
                                 else np.asarray(v).tolist())
                             for k, v in dataclasses.asdict(m).items()},
            "colour_qe": list(self.colour_qe), "mono_weights": list(self.mono_weights),
            "photons_per_radiance_us": self.photons_per_radiance_us,
            "analyzer_summary": {
                "angle_error_deg_mean_by_angle": {
                    str(t): float(err[t_nominal == t].mean()) for t in (0, 45, 90, 135)},
                "angle_error_deg_std": float(err.std()),
                "diattenuation_mean": float(a.diattenuation.mean()),
                "diattenuation_std": float(a.diattenuation.std()),
                "gain_mean": float(a.gain.mean()), "gain_std": float(a.gain.std()),
            },
        }
