"""Sensor noise model of a DoFP camera (photon transfer), for uncertainty and simulation.

The model is the linear camera model of the EMVA Standard 1288 (European Machine Vision
Association, "Standard for Characterization of Image Sensors and Cameras", Release 3.1, 2016,
section 2; Release 4.0, 2021, keeps it): a pixel collects ``mu_e`` photo-electrons (Poisson) plus
``mu_d = dark_current * t`` dark electrons (Poisson), the readout adds Gaussian noise of
``sigma_read`` electrons, the ADC converts with the overall system gain ``K = 1 / gain_e_per_dn``
DN per electron, adds the black level (offset) and rounds (uniform quantisation noise of variance
``1/12`` DN^2). Mean and variance of the black-subtracted output ``y``:

    mu_y  = K (mu_e + mu_d)
    var_y = K^2 (mu_e + mu_d + sigma_read^2) + 1/12

The pixel well holds at most ``full_well_e`` electrons and the ADC codes ``0 .. 2**bit_depth - 1``;
both clip. Default values describe the Sony IMX250MZR/MYR class (about 10.5 ke- full well,
2.3 e- read noise, 12-bit ADC); set them from your camera's EMVA 1288 datasheet. Published
figures for cameras with the IMX250: full well 10.7 ke- (Teledyne DALSA Genie Nano M2450
specification, 12-bit design); SNRmax 40.3 dB (= sqrt of about 10.7 ke-) and dynamic range
71.2 dB (read noise about 2.9 e-) measured per EMVA 1288 on the MATRIX VISION
mvBlueFOX3-2051; 12-bit ADC in both. Units: electrons ``*_e``, digital numbers ``*_dn``,
exposure in microseconds (``docs/conventions.md``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from polrig.errors import ConfigError

__all__ = ["SensorModel"]


@dataclass(frozen=True)
class SensorModel:
    """Photon-transfer model of one sensor at one gain setting (EMVA 1288, see module doc).

    ``gain_e_per_dn`` defaults to ``full_well_e / (2**bit_depth - 1)``, i.e. the full well
    exactly fills the ADC range. ``black_level_dn`` defaults to 0: the 12-bit Mono12/Mono12p
    output of the IMX250 cameras is commonly delivered black-subtracted; with a zero offset the
    negative half of the read noise of a dark pixel is clipped at code 0 (so dark pixels are
    biased high by about ``0.4 sigma_read``). Set the camera's real offset when it has one.
    ``quantum_efficiency`` converts photons to electrons in :meth:`electrons_from_photons`
    only; everything else takes electrons (default 1: inputs already in electrons).
    """

    full_well_e: float = 10500.0
    read_noise_e: float = 2.3
    bit_depth: int = 12
    gain_e_per_dn: float | None = field(default=None)
    dark_current_e_per_s: float = 5.0
    black_level_dn: float = 0.0
    quantum_efficiency: float = 1.0

    def __post_init__(self) -> None:
        if not (isinstance(self.bit_depth, (int, np.integer)) and 1 <= self.bit_depth <= 16):
            raise ConfigError(f"bit_depth must be an integer in 1..16, got {self.bit_depth!r}")
        for name in ("full_well_e",):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ConfigError(f"{name} must be positive and finite, got {getattr(self, name)!r}")
        for name in ("read_noise_e", "dark_current_e_per_s", "black_level_dn"):
            if not (np.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ConfigError(f"{name} must be >= 0 and finite, got {getattr(self, name)!r}")
        if not (0 < self.quantum_efficiency <= 1):
            raise ConfigError(f"quantum_efficiency must be in (0, 1], got {self.quantum_efficiency!r}")
        if self.black_level_dn >= self.max_code_dn:
            raise ConfigError(f"black_level_dn {self.black_level_dn} is not below the largest code {self.max_code_dn}")
        if self.gain_e_per_dn is None:
            object.__setattr__(self, "gain_e_per_dn", float(self.full_well_e) / self.max_code_dn)
        elif not (np.isfinite(self.gain_e_per_dn) and self.gain_e_per_dn > 0):
            raise ConfigError(f"gain_e_per_dn must be positive and finite, got {self.gain_e_per_dn!r}")
        if not self.saturation_dn > 0:
            raise ConfigError(f"no unsaturated range: the saturation threshold is {self.saturation_dn:.4g} DN "
                              f"(clip level {self.clip_dn:.4g} DN minus 5 read-noise sigmas and one code); "
                              f"check full_well_e, read_noise_e, bit_depth and gain_e_per_dn")

    # ------------------------------------------------------------------ derived constants
    @property
    def max_code_dn(self) -> int:
        """Largest ADC code, ``2**bit_depth - 1``."""
        return (1 << int(self.bit_depth)) - 1

    @property
    def read_noise_dn(self) -> float:
        """Read noise in DN (``sigma_read / gain``)."""
        return self.read_noise_e / self.gain_e_per_dn

    @property
    def clip_dn(self) -> float:
        """Black-subtracted DN where the output stops being linear: the smaller of the full
        well (``full_well_e / gain``) and the ADC top code minus the black level."""
        return float(min(self.full_well_e / self.gain_e_per_dn, self.max_code_dn - self.black_level_dn))

    @property
    def saturation_dn(self) -> float:
        """Black-subtracted DN at or above which a sample is treated as saturated.

        :attr:`clip_dn` minus five read-noise standard deviations and one code: a pixel
        clipped at the full well reads the clip level plus read noise, so a threshold exactly at
        the clip level would let about half of the saturated samples through (five sigma: one
        in 3.5 million slips through).
        """
        return self.clip_dn - 5.0 * self.read_noise_dn - 1.0

    def dark_electrons(self, exposure_us: float | np.ndarray) -> np.ndarray:
        """Mean dark electrons accumulated in ``exposure_us``."""
        return self.dark_current_e_per_s * np.asarray(exposure_us, dtype=np.float64) * 1e-6

    def electrons_from_photons(self, photons: np.ndarray) -> np.ndarray:
        """Mean photo-electrons for a mean photon count (``quantum_efficiency * photons``)."""
        return self.quantum_efficiency * np.asarray(photons, dtype=np.float64)

    # ------------------------------------------------------------------ moments
    def mean_dn(self, mean_electrons: np.ndarray, exposure_us: float) -> np.ndarray:
        """Expected raw code (black level included, ignoring clipping) for ``mean_electrons``
        photo-electrons: ``black + (mu_e + mu_d) / gain``."""
        e = np.asarray(mean_electrons, dtype=np.float64) + self.dark_electrons(exposure_us)
        return self.black_level_dn + e / self.gain_e_per_dn

    def variance_dn2(self, signal_dn: np.ndarray, exposure_us: float | np.ndarray,
                     n_frames: int | np.ndarray = 1) -> np.ndarray:
        """Temporal variance (DN^2) of a black-subtracted signal, averaged over ``n_frames``.

        ``signal_dn`` is the photo-signal in DN (black level and mean dark signal removed;
        negative values, from noise, count as 0). Terms (EMVA 1288): photon shot noise
        ``signal / gain``, dark shot noise ``mu_d / gain^2``, read noise
        ``(sigma_read / gain)^2`` and quantisation ``1/12``; the sum is divided by
        ``n_frames``. Non-finite signals give non-finite variances (mask them upstream).
        """
        s = np.clip(np.asarray(signal_dn, dtype=np.float64), 0.0, None)
        per_dn, offset = self.variance_terms(exposure_us, n_frames)
        return s * per_dn + offset

    def variance_terms(self, exposure_us: float | np.ndarray,
                       n_frames: int | np.ndarray = 1) -> tuple[np.ndarray, np.ndarray]:
        """``(per_dn, offset)`` of the linear variance model: :meth:`variance_dn2` is
        ``max(signal_dn, 0) * per_dn + offset`` (DN^2 per DN, DN^2), for callers that evaluate it
        in their own dtype (e.g. float32 images)."""
        g = self.gain_e_per_dn
        n = np.asarray(n_frames, dtype=np.float64)
        offset = ((self.dark_electrons(exposure_us) + self.read_noise_e**2) / g**2 + 1.0 / 12.0) / n
        return 1.0 / g / n, offset

    # ------------------------------------------------------------------ sampling
    def sample_raw(self, mean_electrons: np.ndarray, rng: np.random.Generator,
                   exposure_us: float) -> np.ndarray:
        """One raw frame (uint16 codes) for per-pixel mean photo-electrons ``mean_electrons``.

        Poisson photo- and dark electrons (clipped at the full well), Gaussian read noise,
        conversion by the gain, black level, rounding to the nearest code and clipping to
        ``0 .. max_code_dn``. Pure: all randomness comes from ``rng`` (same seed, same frame).
        Raises ``ValueError`` for negative (below ``-1e-6``, i.e. beyond rounding) or
        non-finite means.
        """
        mean_e = np.asarray(mean_electrons, dtype=np.float64)
        if not np.isfinite(mean_e).all() or (mean_e < -1e-6).any():
            raise ValueError("mean_electrons must be finite and >= 0")
        mean_e = np.clip(mean_e, 0.0, None)  # rounding-level negatives of computed means
        if not (np.isfinite(exposure_us) and exposure_us >= 0):
            raise ValueError(f"exposure_us must be finite and >= 0, got {exposure_us!r}")
        lam = mean_e + self.dark_electrons(exposure_us)
        electrons = np.minimum(rng.poisson(lam).astype(np.float64), self.full_well_e)
        electrons += rng.normal(0.0, self.read_noise_e, size=lam.shape) if self.read_noise_e > 0 else 0.0
        codes = np.floor(electrons / self.gain_e_per_dn + self.black_level_dn + 0.5)
        return np.clip(codes, 0, self.max_code_dn).astype(np.uint16)
