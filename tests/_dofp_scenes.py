"""Synthetic full-resolution Stokes scenes for the DoFP tests (shared helpers, not tests)."""

from __future__ import annotations

import numpy as np

from polrig.sensor.layouts import ANALYZER_ANGLES_DEG


def smooth_stokes(n_colours: int, shape: tuple[int, int], *, freq: float = 0.05,
                  seed: int = 0) -> np.ndarray:
    """Smooth Stokes images ``(C, 3, H, W)`` with S0 in [1, 3] and DoLP <= 0.6."""
    rng = np.random.default_rng(seed)
    v, u = np.mgrid[0 : shape[0], 0 : shape[1]].astype(float)
    out = []
    for _ in range(n_colours):
        p = rng.uniform(0, 2 * np.pi, 4)
        s0 = 2 + 0.5 * np.sin(freq * u + p[0]) + 0.5 * np.cos(0.8 * freq * v + p[1])
        dolp = 0.3 + 0.3 * np.sin(0.7 * freq * (u + v) + p[2])
        aolp = np.pi / 2 * (1 + np.sin(0.6 * freq * (u - v) + p[3]))
        out.append([s0, s0 * dolp * np.cos(2 * aolp), s0 * dolp * np.sin(2 * aolp)])
    return np.asarray(out)


def analyzer_truth(stokes: np.ndarray) -> np.ndarray:
    """Ideal analyzer images ``(C, 4, H, W)`` of Stokes images (``docs/conventions.md``)."""
    t = np.deg2rad(2 * np.asarray(ANALYZER_ANGLES_DEG, float))
    return 0.5 * (stokes[:, None, 0] + stokes[:, None, 1] * np.cos(t)[None, :, None, None]
                  + stokes[:, None, 2] * np.sin(t)[None, :, None, None])


def cell_constant(stokes_small: np.ndarray, period: tuple[int, int]) -> np.ndarray:
    """Repeat each pixel of ``(C, 3, h, w)`` over a ``period`` cell (exact superpixel input)."""
    return np.repeat(np.repeat(stokes_small, period[0], axis=-2), period[1], axis=-1)
