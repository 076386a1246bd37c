"""Tiny datasets in the ``polrig sim dataset`` format for the model tests.

``make_tiny_dataset`` uses the simulator's dataset API when it is importable and otherwise a
small physically consistent stand-in (spheres lit by a point light, Mueller truth from
:func:`polrig.pbrdf.linear_rig_mueller`, analyzer images from the ideal analyzer model).
"""

from __future__ import annotations

import pathlib

import numpy as np

from polrig import pbrdf


def _sphere_sample(rng: np.random.Generator, size: int):
    f = 1.2 * size
    v, u = np.mgrid[0:size, 0:size] + 0.5
    ray = np.stack([(u - size / 2) / f, (v - size / 2) / f, np.ones_like(u)], -1)
    ray /= np.linalg.norm(ray, axis=-1, keepdims=True)
    centre = np.array([rng.uniform(-0.05, 0.05), rng.uniform(-0.05, 0.05), 1.0])
    radius = rng.uniform(0.2, 0.3)
    b = ray @ centre
    disc = b * b - (centre @ centre - radius**2)
    mask = disc > 0
    t = np.where(mask, b - np.sqrt(np.maximum(disc, 0)), 0)
    p = ray * t[..., None]
    normal = np.where(mask[..., None], (p - centre) / radius, 0)
    light = np.array([rng.uniform(-1, 1), rng.uniform(-1, 0), rng.uniform(-0.5, 0.5)])
    wi = light - p
    wi /= np.linalg.norm(wi, axis=-1, keepdims=True)
    wo = -ray
    kd = rng.uniform(0.1, 0.9, size=3)
    alpha = rng.uniform(0.1, 0.5)
    stage = np.array([1.0, 0.0, 0.0])
    m = pbrdf.linear_rig_mueller(normal, wi, wo, kd=np.broadcast_to(kd, mask.shape + (3,)), alpha=alpha,
                                 stage_zero_axis=stage, camera_x_axis=[1.0, 0, 0])
    m = np.where(mask[..., None, None, None], m, 0)  # (H, W, C, 3, 3)
    theta = rng.uniform(0, np.pi)
    s_in = np.array([0.5, 0.5 * np.cos(2 * theta), 0.5 * np.sin(2 * theta)])
    s_out = m @ s_in  # (H, W, C, 3)
    angles = np.deg2rad([0, 45, 90, 135])
    ana = 0.5 * (s_out[..., :1] + s_out[..., 1:2] * np.cos(2 * angles) + s_out[..., 2:3] * np.sin(2 * angles))
    ana = ana + rng.normal(0, 0.002, ana.shape)
    hw = lambda a: np.moveaxis(a, (0, 1), (-2, -1)).astype(np.float32)  # noqa: E731
    return {"analyzer": hw(ana), "mask": mask.astype(np.uint8), "normal": hw(normal),
            "kd": np.broadcast_to(kd[:, None, None], (3, size, size)).astype(np.float32) * mask,
            "alpha": np.float32(alpha), "wi": hw(wi), "wo": hw(wo), "s_in": s_in.astype(np.float32),
            "mueller": hw(m), "family": np.int64(0), "scale": np.float32(1.0),
            "stage_zero_axis": stage.astype(np.float32)}


def make_tiny_dataset(folder: pathlib.Path, count: int = 4, size: int = 32, seed: int = 0) -> pathlib.Path:
    from models.data import write_dataset

    rng = np.random.default_rng(seed)
    samples = [_sphere_sample(rng, size) for _ in range(count)]
    arrays = {k: np.stack([s[k] for s in samples]) for k in samples[0]}
    write_dataset(folder, arrays, {"generator": "tests/models_fixtures.py", "seed": seed, "size": size})
    return folder
