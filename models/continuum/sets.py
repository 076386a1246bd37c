"""The held-out and search sets, the rig's scenes and poses, and the states and budgets measured.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

import dataclasses
import pathlib
from collections.abc import Sequence

import numpy as np


#: The scene families the network was trained on.
SEEN = ("sphere", "box", "cylinder", "multi")
#: The held-out sets of ``models/MODEL_CARD.md``: name -> (label, generate_dataset arguments).
SETS: dict[str, tuple[str, dict]] = {
    "unseen_terrain": ("unseen families: heightfield, plane (seed 2)", dict(seed=2, holdout=True)),
    "seen_families": ("seen families, new scenes (seed 5)", dict(seed=5, families=SEEN)),
    "unseen_compact": ("unseen compact: blob, torus (seed 7)", dict(seed=7, families=("blob", "torus"))),
    "film_depolarizing": ("films + depolarizing layers (seed 5)", dict(seed=5, families=SEEN, material_mix="heldout")),
    "conductors": ("conductors (seed 5)", dict(seed=5, families=SEEN, material_mix="conductor")),
    "dispersive": ("dispersive dielectrics (seed 5)", dict(seed=5, families=SEEN, material_mix="dispersive")),
    "interreflection_terrain": ("interreflections, heightfield + plane (seed 2)",
                                dict(seed=2, holdout=True, indirect_samples=32)),
    "interreflection_compact": ("interreflections, blob + torus (seed 7)",
                                dict(seed=7, families=("blob", "torus"), indirect_samples=32)),
}
#: The angle search's sets (the uncertainty calibration's scenes, in no reported set).
SEARCH_SETS: dict[str, dict] = {
    "search_all_families": dict(seed=11, families=SEEN + ("blob", "torus")),
    "search_holdout_families": dict(seed=11, holdout=True),
}
SIZE = 64
#: Offsets (deg) from the seen state's angle that frames are made for.
OFFSETS_DEG = tuple(range(0, 180, 15))
FOUR_STATES = (0, 45, 90, 135)
VARIANTS = ("marginal", "naive", "exclude")
#: The adaptive capture's targets measured (relative posterior sigma,
#: :func:`polrig.solve.design.relative_sigma`), its share of object pixels and most states (the
#: capture's defaults: :mod:`polrig.app.adaptive`).
ADAPTIVE_TARGETS = (0.05, 0.03)
#: The exposure bracket of the "Highlights" rows: fractions of the dataset's exposure each
#: state also takes (one frame each), merged with the reference exposure (:func:`sample_frames`).
BRACKET = (1 / 16, 1 / 256)
ADAPTIVE_SHARE = 0.95
ADAPTIVE_MAX_STATES = 4
#: The adaptive rows' second budget of states: the most a capture allows
#: (:data:`polrig.acquisition.plan.ADAPTIVE_MAX_STATES`), where the choice per second of hardware
#: time (:func:`polrig.solve.design.choose_next`) decides more than the fourth, last state.
ADAPTIVE_MORE_STATES = 8
#: The default simulated rig's scenes (``--rig``: those of the single-shot rig benchmark,
#: ``benchmarks/bench_single_shot.py``'s ``RIG_SCENES``) and turntable poses (deg) scored at the
#: rig's size.
RIG_SCENES = ("sphere", "rough_sphere", "checker_sphere", "box", "multi", "heightfield", "plane", "normalmap")
RIG_POSES_DEG = (0.0, 60.0, 120.0, 180.0, 240.0, 300.0)
#: The simulated rig's states searched at 64x64 (``benchmarks/results/continuum.json``): ``--rig``
#: takes them as given.
RIG_TWO, RIG_THREE = (0, 90), (0, 60, 120)
#: The simulated rig's stage acceleration (deg/s^2, :class:`polrig.sim.devices.SimStage`'s
#: default) and camera readout (us per frame, :class:`polrig.sim.devices.SimCamera`'s), for the
#: acquisition time (:func:`acquisition_time_s`).
SIM_STAGE_ACCEL_DEG_S2 = 100.0
SIM_READOUT_US = 13000.0


def rig_size() -> int:
    """The default simulated rig's analyzer grid side (pixels): its sensor's side
    (:data:`polrig.sim.options.DEFAULTS`, 512x512) over its mosaic's period (4x4 for the colour
    IMX250MYR), the grid the networks run on (``--network-binning 1``)."""
    from polrig.sensor.layouts import get_layout
    from polrig.sim.options import DEFAULTS, parse_size

    w, h = parse_size(DEFAULTS["size"])
    ph, pw = get_layout(DEFAULTS["sensor"]).period
    return min(w // pw, h // ph)


def rig_set(name: str, size: int, poses_deg: Sequence[float], seed: int = 0):
    """The named scene ``name`` (:data:`polrig.sim.scene.SCENES`, in the default rig:
    :func:`polrig.sim.scene.make_scene`) at ``size x size`` as a set of one sample per turntable
    angle of ``poses_deg`` (:func:`polrig.sim.dataset.capture_sample`: the dataset's polarizer
    state, exposure and sensor noise drawn from ``(seed, pose index)``); a
    :class:`polrig.models.data.Dataset` in memory."""
    from polrig.models.data import Dataset
    from polrig.sim.dataset import capture_sample, dataset_sensor_model
    from polrig.sim.scene import FAMILIES, make_scene

    model = dataset_sensor_model()
    scene = make_scene(name, size, size)
    family = FAMILIES.index(name) if name in FAMILIES else -1
    samples = [capture_sample(scene, np.random.default_rng([seed, j]), model=model, index=j, family=family,
                              turntable_deg=float(p)) for j, p in enumerate(poses_deg)]
    arrays = {k: np.stack([np.asarray(x[k]) for x in samples]) for k in samples[0]}
    for k in ("analyzer", "normal", "kd", "wi", "wo", "alpha", "s_in", "mueller", "stage_zero_axis", "mask"):
        arrays[k] = np.ascontiguousarray(arrays[k], dtype=np.float32)  # as load_dataset gives them
    return Dataset(arrays, {"noise": {"sensor_model": dataclasses.asdict(model)}, "scene": name,
                            "poses_deg": [float(p) for p in poses_deg], "width": size, "height": size})


def make_set(root: pathlib.Path, name: str, kwargs: dict, count: int) -> pathlib.Path:
    """The set's folder under ``root`` (generated unless already there)."""
    from polrig.sim.dataset import generate_dataset

    out = root / f"{name}_{count}"
    generate_dataset(out, count=count, width=SIZE, progress=False, **kwargs)
    return out


def set_label(key: str) -> str:
    """A set's row label: :data:`SETS`' label, or ``"<scene> (default rig)"`` for ``rig_<scene>``."""
    if key in SETS:
        return SETS[key][0]
    return f"{key[len('rig_'):]} (default rig)" if key.startswith("rig_") else key


def adaptive_key(target: float, max_states: int = ADAPTIVE_MAX_STATES) -> str:
    """The result key of the adaptive capture at ``target`` with at most ``max_states`` states:
    ``adaptive_<target>``, with ``_max<n>`` beyond :data:`ADAPTIVE_MAX_STATES`."""
    return f"adaptive_{target:g}" + ("" if max_states == ADAPTIVE_MAX_STATES else f"_max{max_states}")


def adaptive_budget(key: str) -> int:
    """The most states of an :func:`adaptive_key`."""
    parts = key.split("_")
    return int(parts[2][len("max"):]) if len(parts) > 2 else ADAPTIVE_MAX_STATES


def adaptive_label(key: str) -> str:
    """``adaptive 0.05`` (:data:`ADAPTIVE_MAX_STATES` states at most), ``adaptive 0.05, <= 8
    states``: an :func:`adaptive_key`'s label in tables and the plot."""
    n = adaptive_budget(key)
    return f"adaptive {key.split('_')[1]}" + ("" if n == ADAPTIVE_MAX_STATES else f", <= {n} states")
