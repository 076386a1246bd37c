"""The simulated world shared by the simulated devices: scene, light, polarizer stage,
turntable, sensor and the simulated clock.

Images are produced lazily and cached: a turntable pose is ray-cast once
(:func:`polrig.sim.render.render`, kept in a small LRU cache); a polarizer state recombines the
cached Mueller matrices of the lit pixels with the new incident Stokes vector
(``S_out = M S_in``, 27 multiply-adds per lit pixel, also cached per state); exposure, gain and light level only scale it;
noise is sampled per grab. Units and frames: ``docs/conventions.md``.
"""

from __future__ import annotations

import collections
import threading
from typing import Any, Callable

import numpy as np

from polrig.sim.clock import SimClock
from polrig.sim.generator import Generator
from polrig.sim.motion import Move
from polrig.sim.render import RenderResult, render
from polrig.sim.scene import Scene
from polrig.sim.sensor import DoFPSensor

Roi = tuple[int, int, int, int]  # (width, height, offset_x, offset_y), as polrig.acquisition.hal.Camera.roi


class _Lru:
    def __init__(self, size: int) -> None:
        self.size = size
        self.data: collections.OrderedDict = collections.OrderedDict()

    def get(self, key, make: Callable[[], Any]):
        if key in self.data:
            self.data.move_to_end(key)
            return self.data[key]
        value = make()
        self.data[key] = value
        while len(self.data) > self.size:
            self.data.popitem(last=False)
        return value


def _angle_key(angle_deg: float) -> float:
    return round(float(angle_deg) % 360.0, 9)


def ideal_analyzer_images(stokes: np.ndarray) -> np.ndarray:
    """Ideal analyzer intensities ``(C, 4, H, W)`` (0, 45, 90, 135 deg) of Stokes images
    ``(C, 3, H, W)``: ``I(t) = (S0 + S1 cos 2t + S2 sin 2t) / 2`` (``docs/conventions.md``)."""
    s0, s1, s2 = stokes[:, 0], stokes[:, 1], stokes[:, 2]
    return 0.5 * np.stack([s0 + s1, s0 + s2, s0 - s1, s0 - s2], axis=1)


class SimWorld:
    """State and image formation of the simulated rig.

    Motion: ``stage_move`` and ``turntable_move`` are the current :class:`polrig.sim.motion.Move` of
    each axis (the simulated devices replace them); positions are read on ``clock``.
    """

    def __init__(self, scene: Scene, sensor: DoFPSensor, generator: Generator, *,
                 clock: SimClock | None = None, seed: int = 0, noise: bool = True,
                 distribution: str = "ggx", indirect_samples: int = 0) -> None:
        if sensor.shape != (scene.camera.height, scene.camera.width):
            raise ValueError(f"sensor {sensor.shape[::-1]} and camera "
                             f"{scene.camera.width}x{scene.camera.height} sizes differ")
        self.scene = scene
        self.sensor = sensor
        self.generator = generator
        self.clock = clock or SimClock()
        self.seed = int(seed)
        self.rng = np.random.default_rng(self.seed)
        self.noise = bool(noise)
        self.distribution = distribution
        if int(indirect_samples) < 0:
            raise ValueError(f"indirect_samples must be >= 0, got {indirect_samples}")
        #: Monte Carlo samples per pixel of one-bounce interreflections (0: direct light only).
        self.indirect_samples = int(indirect_samples)
        self.light_on = True
        self.light_level = 1.0
        self.stage_move = Move(0.0, 0.0, 0.0, 1.0, 1.0)
        self.turntable_move = Move(0.0, 0.0, 0.0, 1.0, 1.0)
        self._lock = threading.RLock()
        self._poses = _Lru(4)
        self._states = _Lru(16)
        self.render_count = 0
        self._repeats: dict[tuple, int] = {}
        self._last_condition: tuple | None = None
        self._runs: dict[tuple, int] = {}

    # -- reproducible noise -------------------------------------------------------------------
    def note_motion(self, turntable: bool = False) -> None:
        """A motion command was issued: the next grab starts a new run of repeated frames.
        A turntable motion also starts a new capture as far as the noise is concerned (the
        run counts of :meth:`grab_rng` start again)."""
        with self._lock:
            self._repeats.clear()
            self._last_condition = None
            if turntable:
                self._runs.clear()

    def grab_rng(self, condition: tuple[float | int, ...]) -> np.random.Generator:
        """The noise generator of the next grab under ``condition`` (pose, state, exposure, ...).

        Noise is keyed by ``(seed, condition, repeat index, run)``, where the repeat index
        counts the grabs since the condition last changed or a motion command was issued, and
        ``run`` counts the earlier runs of the same condition since the turntable last moved
        (a plan that visits one polarizer state twice, ``--states 0,0,45,90``, gets
        independent noise on the second visit; the first run keeps the key without ``run``).
        A session that is interrupted and resumed (a capture is redone from its turntable
        move) therefore sees exactly the noise an uninterrupted one would have seen, while
        repeated frames of one state still get independent noise.
        """
        key = tuple(int(round(float(v) * 1e4)) % (1 << 63) for v in condition)
        with self._lock:
            if key != self._last_condition:
                self._repeats.clear()
                self._last_condition = key
            n = self._repeats.get(key, 0)
            if n == 0:
                self._runs[key] = self._runs.get(key, -1) + 1
            run = self._runs[key]
            self._repeats[key] = n + 1
        entropy = [self.seed, n, *key] + ([run] if run else [])
        return np.random.default_rng(np.random.SeedSequence(entropy))

    def set_scene(self, scene: Scene) -> None:
        """Replace the scene (e.g. swap a calibration target in) and drop every cached image.
        The camera must keep the sensor's size."""
        if self.sensor.shape != (scene.camera.height, scene.camera.width):
            raise ValueError(f"scene camera {scene.camera.width}x{scene.camera.height} does not "
                             f"match the {self.sensor.shape[1]}x{self.sensor.shape[0]} sensor")
        with self._lock:
            self.scene = scene
            self._poses.data.clear()
            self._states.data.clear()

    # -- motion state -----------------------------------------------------------------------
    def stage_angle_deg(self) -> float:
        return self.stage_move.position(self.clock.now())

    def turntable_angle_deg(self) -> float:
        return self.turntable_move.position(self.clock.now())

    @property
    def full_roi(self) -> Roi:
        h, w = self.sensor.shape
        return (w, h, 0, 0)

    # -- image formation --------------------------------------------------------------------
    def render_pose(self, turntable_deg: float) -> RenderResult:
        """Ground truth of the full sensor at a turntable angle (cached)."""
        key = _angle_key(turntable_deg)

        def make() -> RenderResult:
            self.render_count += 1
            return render(self.scene, key, distribution=self.distribution,
                          indirect_samples=self.indirect_samples, indirect_seed=self.seed)

        with self._lock:
            return self._poses.get(key, make)

    def radiance_mueller(self, turntable_deg: float) -> np.ndarray:
        """Radiance Mueller image ``(3, 3, 3, H, W)`` per unit radiant intensity (cached)."""
        key = ("M", _angle_key(turntable_deg))
        with self._lock:
            return self._states.get(key, lambda: self.render_pose(turntable_deg).radiance_mueller())

    def radiance_state(self, turntable_deg: float, stage_deg: float) -> np.ndarray:
        """Radiance Stokes image ``(3, 3, H, W)`` for the polarizer at ``stage_deg`` per unit
        radiant intensity (cached per pose and state)."""
        key = ("S", _angle_key(turntable_deg), round(float(stage_deg), 9))

        def make() -> np.ndarray:
            s_in = self.generator.incident_stokes(stage_deg)
            return self.render_pose(turntable_deg).radiance_state(s_in)

        with self._lock:
            return self._states.get(key, make)

    def _scale(self, radiance: np.ndarray, exposure_us: float, gain_db: float,
               level: float | None, on: bool | None) -> np.ndarray:
        """Per-colour scaling of a radiance image ``(3, ...)`` to DN ``(C, ...)``."""
        level = self.light_level if level is None else level
        on = self.light_on if on is None else on
        i = self.scene.light.radiant_intensity_rgb(level, on)
        resp = self.sensor.response_dn(exposure_us, gain_db)
        if self.sensor.n_colours == 3:
            s = (i * resp).astype(np.float32)
            return radiance * s.reshape((3,) + (1,) * (radiance.ndim - 1))
        w = (np.asarray(self.sensor.mono_weights) * i * resp[0]).astype(np.float32)
        return np.tensordot(w, radiance, axes=(0, 0))[None]

    def mueller_dn(self, turntable_deg: float, exposure_us: float, gain_db: float = 0.0,
                   roi: Roi | None = None, *, level: float | None = None,
                   on: bool | None = None) -> np.ndarray:
        """The truth Mueller image ``(C, 3, 3, h, w)`` float32 in DN per unit incident S0
        (``docs/conventions.md``) for a ROI, exposure, gain and light level (default: the
        world's current light state)."""
        m = self._scale(self.radiance_mueller(turntable_deg), exposure_us, gain_db, level, on)
        return np.ascontiguousarray(_crop(m, roi or self.full_roi), dtype=np.float32)

    def stokes_dn(self, turntable_deg: float, stage_deg: float, exposure_us: float,
                  gain_db: float = 0.0, roi: Roi | None = None, *, level: float | None = None,
                  on: bool | None = None) -> np.ndarray:
        """Noise-free black-subtracted emergent Stokes images ``(C, 3, h, w)`` (DN) that the
        sensor sees: ``mueller_dn @ incident_stokes(stage_deg)``."""
        s = self._scale(self.radiance_state(turntable_deg, stage_deg), exposure_us, gain_db,
                        level, on)
        return np.ascontiguousarray(_crop(s, roi or self.full_roi), dtype=np.float32)

    def analyzer_images(self, turntable_deg: float, stage_deg: float, exposure_us: float,
                        gain_db: float = 0.0, roi: Roi | None = None, **kw) -> np.ndarray:
        """Noise-free full-resolution ideal-analyzer images ``(C, 4, h, w)`` (DN)."""
        return ideal_analyzer_images(self.stokes_dn(turntable_deg, stage_deg, exposure_us,
                                                    gain_db, roi, **kw))

    def raw(self, *, turntable_deg: float, stage_deg: float, exposure_us: float,
            gain_db: float, roi: Roi, noise: bool | None = None,
            rng: np.random.Generator | None = None) -> np.ndarray:
        """A raw mosaic ``(h, w)`` of the ROI: ``uint16`` with noise, float64 mean without."""
        s = self.stokes_dn(turntable_deg, stage_deg, exposure_us, gain_db, roi)
        signal = self.sensor.signal_mosaic(s, roi)
        noise = self.noise if noise is None else noise
        with self._lock:
            return self.sensor.expose(signal, exposure_us=exposure_us, gain_db=gain_db,
                                      rng=rng or self.rng, noise=noise)


def _crop(img: np.ndarray, roi: Roi) -> np.ndarray:
    w, h, ox, oy = roi
    return img[..., oy:oy + h, ox:ox + w]
