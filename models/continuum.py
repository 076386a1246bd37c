"""From one state to four: single-shot, hybrid and reference on the held-out sets (issue 33,
item 4).

``python -m polrig.models.continuum [--count N] [--out FILE.md]`` generates the model card's
held-out sets at 64x64 (``polrig.sim.dataset``; the first ``--count`` samples of each, the same
scenes as the first samples of the card's 256-sample sets), runs the shipped single-shot
network on each sample's own frame (onnxruntime, read only) with its calibrated sigma, and
compares, with the metrics of :mod:`polrig.models.evaluate`:

* **single-shot**: the network's estimate and sigma;
* **hybrid N** (:func:`polrig.solve.hybrid.solve_hybrid`): the network as the prior, the
  sample's own frame as the seen state, plus ``N - 1`` more states;
* **reference N** (:func:`polrig.solve.reference.solve_reference`): the same frames, no prior.

**States.** Offsets from the seen state's polarizer angle (every sample has its own), on a
15 deg grid. The best 2- and 3-state sets (``0/d``, ``0/d1/d2``) are searched by the hybrid's
mean matrix PSNR (over pixels unclipped in every state) on sets none of the reported ones
holds (the uncertainty calibration's scenes, seed 11: all six families, and the held-out
families); four states are 0/45/90/135.

**Frames.** The seen frame is the dataset's own (the simulator's sensor model: shot, read, dark
and quantisation noise, clipping). The other states' frames are rendered from the truth and
sampled with the same sensor model and exposure (:meth:`polrig.sensor.noise.SensorModel.sample_raw`,
as the dataset does), so every state has the same noise and clips where the sensor would. Each
sample's variance is the sensor model's at its measured value, samples at or above the
saturation level are excluded (as :mod:`polrig.app.processing` does). So the reference rows
differ from the card's "four-state reference" row, which adds Gaussian noise of a fitted
model and never clips.

**Equal capture time.** The hybrid with 3 states of 4 frames each against 4 states of 3 (the
rendered frames averaged, their variance the sensor model's for the mean of that many; the
seen state's first frame is the network's input); every other row has one frame per state.

**The prior** is the one captures use: the calibration's joint prior (``joint_prior`` in
``uncertainty.json``, :mod:`polrig.solve.hybrid` "Joint prior") where it holds one, else the
per-element sigma; every hybrid row, the adaptive one and the two-state model rows use it
(``--joint-compare`` measures the two against each other). Tables written before the joint
prior say "per element". Its sigma is scaled per sample as captures scale it (:func:`scaled_sigma`,
:mod:`polrig.solve.prior_scale`: by the states after the seen one; factor 1 at one state), in
every hybrid row, the adaptive capture's solve and design and the two-state model rows; the
rows ``hybrid<N>_calibrated`` (the "prior's scale" table) and the :data:`VARIANTS` keep it as
calibrated, as does ``--joint-compare``. Tables written before the scale have no such table.

**Metrics.** Matrix PSNR (peak the largest true ``|m|`` on the object, over the object mask;
and over the object's pixels with no clipped sample in any frame of any state: a highlight
clipped in every state, a few tenths of a per cent of the pixels, is recovered by no number of
states and sets the first PSNR of every method alike), forward Stokes relative L2 over the 11 held-out incident states
(:func:`polrig.models.evaluate.forward_l2`), and coverage: the fraction of the elements of the
object's pixels (per colour) whose error is within 2 sigma, over pixels whose seen frame is
not clipped (as the single-shot sigma's coverage is measured) and that the solve did not mask
``ILL_CONDITIONED``. Each coverage figure comes with its 90 % bootstrap interval over the set's
samples and the 10th-90th percentile of the samples' own coverage
(:mod:`polrig.models.scene_bootstrap`; ``coverage_interval``, ``coverage_scenes``): a scene's
errors cover or miss together, so how far a set's figure can be trusted is set by how many
scenes it holds, not by its pixels.

**Highlights** (:data:`BRACKET`, the "Highlights" table): single-shot, hybrid 1 and hybrid 2
with every state's frame merged with shorter exposures (:func:`sample_frames`' ``bracket``); the
network sees the reference exposure and, where it clipped but a shorter exposure measured the
pixel, its estimate takes the measured intensity (:func:`bracket_prior`,
:mod:`polrig.models.highlights`), as the capture's single-shot route does with
``--exposure T,T/16,T/256``. Scored as above (``clean`` the reference exposure's), plus the
coverage at those highlights. ``--fit-highlights`` fits their sigma factor
(:func:`fit_highlight_factor`) on the calibration scenes.

**Adaptive** (issue 33 item 2; :func:`adaptive`): the adaptive capture's rule on each sample,
at each of ``--targets`` (relative posterior sigma; 95 % of the object pixels, at most 4
states), the equiangular set through the seen state first, then choosing among the 15 deg
offsets (one frame each; :func:`polrig.solve.design.next_candidates`). **Acquisition time**
(:func:`acquisition_time_s`): the simulated rig's hardware time of one pose taking a method's
states (stage motion, exposure, readout), with its states per pose.

**The rig's size** (``--rig-scenes [LIST] [--rig-poses 0,60,...] [--size N]``, :func:`rig_set`):
instead of the held-out sets, the default simulated rig's named scenes (:data:`RIG_SCENES`) at
its analyzer grid (:func:`rig_size`: 128x128, its 512x512 colour sensor over the 4x4 mosaic), one
sample per turntable angle, with the dataset's random polarizer state, exposure and noise
(:func:`polrig.sim.dataset.capture_sample`) and the states searched at 64x64 (:data:`RIG_TWO`,
:data:`RIG_THREE`).

**The trade plot** (:func:`plot_trade`, written beside ``--out`` as ``.png``; ``--plot-only
FILE.json`` redraws it from a results JSON alone): matrix PSNR and forward Stokes L2 against the
acquisition time per pose, a point per set and method and the median over the sets with its
range.

**Lower-order models at two states** (``--models-only`` runs only this; the full run adds it as
its last table; :func:`models_rows`): at the 2-state set, single-shot, hybrid 2 and hybrid 2 with
:func:`polrig.solve.model_selection.select_models` (the network's prior given: at two states the
test runs on the hybrid's posterior system), scored over every object pixel and over those where
a lower-order model holds (:func:`model_holds`: the truth within :data:`HOLDS_REL` relative
Frobenius of its nearest candidate in every colour, the pixel lit, :func:`lit_pixels`, and
unclipped), with the share given a reduced model and the false acceptance where the truth is
detectably off every candidate (:func:`detectably_off_every_model`); and the selection's result
with the direction the two states leave open predicted from the diffuse term's geometry where it
chose ``rank_one`` (:func:`polrig.solve.diffuse_geometry.complete_diffuse`; the geometry of
:func:`frame_geometry`: the intrinsics' view directions, two candidate light fields per sample,
the network's normals as the first pass's guess, the neighbours' mean as the second's).

**Variants of the seen state's treatment** (the double-counting question of
:mod:`polrig.solve.hybrid`), at 1 and 2 states: ``marginal`` (the plain marginal on the
unobserved plane, without the row's prior variance along the seen direction kept in it),
``naive`` (the whole prior and
every frame: the seen frame counted twice) and ``exclude`` (the whole prior, the seen frame
dropped).
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import os
import pathlib
import sys
import time
from collections.abc import Sequence

import numpy as np

from polrig.models.scene_bootstrap import coverage_interval, scene_spread

#: The held-out sets of ``models/MODEL_CARD.md``: name -> (label, generate_dataset arguments).
SEEN = ("sphere", "box", "cylinder", "multi")
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


@dataclasses.dataclass
class Frames:
    """One sample: truth, network prior and a frame per offset (normalised units)."""

    truth: np.ndarray  # (C, 3, 3, H, W)
    mask: np.ndarray  # (H, W)
    use: np.ndarray  # (C, H, W) object pixels whose seen frame is not clipped
    clean: np.ndarray  # (H, W) object pixels with no clipped sample in any frame of any state
    prior: np.ndarray
    sigma: np.ndarray
    states: dict[int, np.ndarray]  # offset -> (3,)
    meas: dict[int, np.ndarray]  # offset -> (C, 4, H, W)
    var: dict[int, np.ndarray]
    valid: dict[int, np.ndarray]
    #: the noise model's linear terms for one state's (averaged) frames in these units:
    #: variance = max(I, 0) * per + offset (:meth:`polrig.sensor.noise.SensorModel.variance_terms`)
    noise_terms: tuple[float, float] = (0.0, 0.0)
    #: the network's light spread over the object (rad, :func:`polrig.models.uncertainty.light_spread`;
    #: the calibrated sigma's factor), None where not known
    light_spread: float | None = None
    #: what the rig knows of the geometry (:func:`frame_geometry`), for the diffuse completion at
    #: two states (:func:`polrig.solve.diffuse_geometry.complete_diffuse`); None where not known
    geometry: object | None = None


def rotated_state(s: np.ndarray, offset_deg: float) -> np.ndarray:
    """The state of the same polarizer turned by ``offset_deg`` (its Stokes vector rotated)."""
    t = np.deg2rad(2.0 * offset_deg)
    c, sn = np.cos(t), np.sin(t)
    return np.array([s[0], c * s[1] - sn * s[2], sn * s[1] + c * s[2]])


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


def network_prior(ds, i: int, net) -> tuple[np.ndarray, np.ndarray, float | None, np.ndarray | None]:
    """The network's estimate and calibrated sigma for sample ``i``'s own frame (0 off the
    object), its light spread over the object (the sigma's factor) and its normals ``(H, W, 3)``
    (camera frame; None where the graph has none)."""
    from polrig.models.evaluate import network_inputs
    from polrig.sensor.stokes import stokes_from_analyzers

    mask = ds["mask"][i] > 0
    s0 = ds["s_in"][i].astype(np.float64)
    from polrig.models.uncertainty import light_spread

    res = net.run_rig_frame(*network_inputs(ds, i))
    pred = res["mueller"][0].astype(np.float64)
    spread = light_spread(res["wi"][0], mask)
    sigma = net.uncertainty.sigma(pred, s0, mask, stokes_from_analyzers(ds["analyzer"][i].astype(np.float64)),
                                  light_spread=spread)
    normal = np.moveaxis(res["normal"][0].astype(np.float64), 0, -1) if "normal" in res else None
    return np.where(mask, pred, 0.0), np.where(mask, sigma.astype(np.float64), 0.0), spread, normal


def light_over_depth(wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """The point light's position ``(3,)`` over the object's depth (camera frame, the camera at
    the origin) that best explains the light directions ``wi`` ``(P, 3)`` (surface -> light)
    seen from the surface points ``-wo`` ``(P, 3)`` at unit depth: ``(L + wo) x wi = 0``, linear
    least squares in ``L``. What the rig's calibration gives (the light's position, the
    turntable's distance); the simulator's sets do not record it."""
    wi = np.asarray(wi, np.float64)
    z = np.zeros(len(wi))
    skew = np.stack([np.stack([z, -wi[:, 2], wi[:, 1]], -1), np.stack([wi[:, 2], z, -wi[:, 0]], -1),
                     np.stack([-wi[:, 1], wi[:, 0], z], -1)], -2)  # skew(wi) L = wi x L
    return np.linalg.lstsq(skew.reshape(-1, 3), np.cross(np.asarray(wo, np.float64), wi).reshape(-1), rcond=None)[0]


def frame_geometry(ds, i: int, normal_guess: np.ndarray | None):
    """What the rig knows of sample ``i``'s geometry
    (:class:`polrig.solve.diffuse_geometry.DiffuseGeometry`): the view directions (the
    intrinsics'), the polarizer stage's zero axis (calibration) and two candidate light fields
    from the light's position over the object's depth (:func:`light_over_depth`, 3 numbers
    fitted to the truth's directions as the rig's calibration would give them): the surface at
    one depth (:func:`polrig.solve.diffuse_geometry.light_directions`: median 1-2 deg from the
    truth's directions on the held-out seen families, where one direction over the object is
    2-5 deg off) and one direction, the truth's mean over the object (the light seen from the
    object's centre; where the depth varies over the image, a terrain's ground, the one-depth
    fit is biased and this is the better of the two); the network's normals as the guess. None
    where the set has no directions."""
    from polrig.solve.diffuse_geometry import DiffuseGeometry, light_directions

    if not all(k in ds.arrays for k in ("wi", "wo", "stage_zero_axis")):
        return None
    mask = ds["mask"][i] > 0
    view = np.moveaxis(ds["wo"][i].astype(np.float64), 0, -1)
    wi = ds["wi"][i].astype(np.float64)[:, mask].T
    centre = wi.mean(axis=0)
    at_depth = light_directions(light_over_depth(wi, view[mask]), view)
    return DiffuseGeometry(view=view, light=(at_depth, centre / np.linalg.norm(centre)),
                           stage_zero_axis=ds["stage_zero_axis"][i].astype(np.float64), normal_guess=normal_guess)


def sample_frames(ds, i: int, prior: tuple, sensor, rng: np.random.Generator, *,
                  offsets: Sequence[int] = OFFSETS_DEG, frames_per_state: int = 1,
                  bracket: Sequence[float] = ()) -> Frames:
    """The frames of sample ``i`` at ``offsets`` (0 first: the seen state), each the mean of
    ``frames_per_state`` frames (the seen state's: the dataset's own frame and
    ``frames_per_state - 1`` more); a sample is excluded where any of its frames saturates.

    ``bracket``: fractions of the dataset's exposure (e.g. :data:`BRACKET`) at which each state
    also takes ``frames_per_state`` frames, merged with the reference exposure's by
    :func:`polrig.solve.reference.merge_hdr` (as :func:`polrig.solve.radiometry.state_radiance`
    merges a capture's bracket): a sample is then excluded only where every exposure
    saturates. ``use`` and ``clean`` stay the reference exposure's; the prior is the network's
    on the reference exposure (:func:`bracket_prior` carries it to the measured highlights)."""
    from polrig.sim.dataset import DATASET_EXPOSURE_US
    from polrig.solve.reference import forward_measurements, merge_hdr

    k = int(frames_per_state)
    mask = ds["mask"][i] > 0
    truth = ds["mueller"][i].astype(np.float64)
    s0 = ds["s_in"][i].astype(np.float64)
    scale = float(ds["scale"][i])
    seen_dn = ds["analyzer"][i].astype(np.float64) * scale
    dark_dn = float(sensor.dark_electrons(DATASET_EXPOSURE_US) / sensor.gain_e_per_dn)
    states = {d: rotated_state(s0, d) for d in offsets}
    clean_e = np.clip(forward_measurements(truth, np.stack([states[d] for d in offsets])) * scale, 0, None) \
        * sensor.gain_e_per_dn
    meas, var, valid, ref_valid = {}, {}, {}, {}
    for j, d in enumerate(offsets):
        frames = [sensor.sample_raw(clean_e[j], rng, DATASET_EXPOSURE_US).astype(np.float64)
                  - sensor.black_level_dn - dark_dn for _ in range(k - 1 if d == 0 else k)]
        if d == 0:
            frames.insert(0, seen_dn)
        stack = np.stack(frames)
        mean_dn = stack.mean(axis=0)
        meas[d] = mean_dn / scale
        var[d] = sensor.variance_dn2(mean_dn, DATASET_EXPOSURE_US, k) / scale**2
        valid[d] = ref_valid[d] = (stack < sensor.saturation_dn).all(axis=0)
        if bracket:
            merged = [(np.where(valid[d], mean_dn, np.inf), DATASET_EXPOSURE_US)]
            for f in bracket:
                t = DATASET_EXPOSURE_US * float(f)
                short = np.stack([sensor.sample_raw(clean_e[j] * float(f), rng, t).astype(np.float64)
                                  - sensor.black_level_dn - sensor.dark_electrons(t) / sensor.gain_e_per_dn
                                  for _ in range(k)])
                merged.append((np.where((short < sensor.saturation_dn).all(axis=0), short.mean(axis=0), np.inf), t))
            rad, v, ok = merge_hdr(merged, sensor.saturation_dn, sensor, reference_exposure_us=DATASET_EXPOSURE_US,
                                   n_frames=k)
            meas[d], var[d], valid[d] = rad / scale, v / scale**2, ok
    use = mask[None] & (seen_dn < sensor.saturation_dn).all(axis=1)
    clean = mask & np.all([v.all(axis=(0, 1)) for v in ref_valid.values()], axis=0)
    per_dn, offset = sensor.variance_terms(DATASET_EXPOSURE_US, k)
    return Frames(truth, mask, use, clean, prior[0], prior[1], states, meas, var, valid,
                  (float(per_dn) / scale, float(offset) / scale**2),
                  light_spread=prior[2] if len(prior) > 2 else None,
                  geometry=frame_geometry(ds, i, prior[3]) if len(prior) > 3 else None)


def _measured_highlights(fr: Frames, uncertainty):
    """``(M', sigma, rescaled)`` of a bracketed sample: the network's estimate rescaled where
    the seen frame clipped and the bracket measured it
    (:func:`polrig.models.highlights.measured_highlights`), and the calibrated model's sigma on
    it (factor 1; None where nothing was rescaled)."""
    from polrig.models.highlights import measured_highlights
    from polrig.sensor.stokes import stokes_from_analyzers

    stokes = stokes_from_analyzers(np.where(fr.valid[0], fr.meas[0], np.nan))
    mean, rescaled = measured_highlights(fr.prior, fr.states[0], stokes, fr.mask[None] & ~fr.use)
    if not rescaled.any():
        return mean, None, rescaled
    sigma = uncertainty.sigma(mean, fr.states[0], fr.mask, stokes, light_spread=fr.light_spread)
    return mean, sigma.astype(np.float64), rescaled


def bracket_prior(fr: Frames, uncertainty) -> Frames:
    """``fr`` (its frames bracketed: :func:`sample_frames`' ``bracket``) with the prior carried
    to the highlights the bracket measured (:func:`_measured_highlights`, their sigma times
    :data:`polrig.models.highlights.SIGMA_FACTOR`), as the capture's single-shot route does
    (:meth:`polrig.app.single_shot.SingleShot.state`)."""
    from polrig.models.highlights import highlight_sigma

    mean, sigma, rescaled = _measured_highlights(fr, uncertainty)
    if sigma is None:
        return fr
    sigma = highlight_sigma(fr.sigma, sigma, rescaled)
    return dataclasses.replace(fr, prior=np.where(fr.mask, mean, 0.0), sigma=np.where(fr.mask, sigma, 0.0))


def fit_highlight_factor(root, net, *, count: int = 128, seed: int = 0, echo=print) -> dict:
    """The sigma factor at the highlights a bracket measured
    (:data:`polrig.models.highlights.SIGMA_FACTOR`), fitted on the uncertainty calibration's
    scenes (:data:`SEARCH_SETS`, ``count`` samples of the all-family set and half as many of the
    held-out families; no reported set): half the 95.45 % quantile of ``|M' - M_true| / sigma``
    over the rescaled pixels' elements, ``sigma`` the calibrated model's on the rescaled
    estimate (factor 1). Returns the factor, the elements it rests on and each set's quantile."""
    ratios, per_set = [], {}
    for tag, (name, kw) in enumerate(SEARCH_SETS.items()):
        d = make_set(pathlib.Path(root), name, kw, count if "all" in name else max(1, count // 2))
        got = []
        for ds, sensor, i, prior in _samples(d, net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, 200 + tag, i]), offsets=(0,),
                               bracket=BRACKET)
            mean, sigma, rescaled = _measured_highlights(fr, net.uncertainty)
            if sigma is not None:
                with np.errstate(divide="ignore", invalid="ignore"):
                    e = np.abs(mean - fr.truth) / sigma
                got.append(e.transpose(1, 2, 0, 3, 4)[:, :, rescaled].ravel())
        r = np.concatenate(got) if got else np.zeros(0)
        per_set[name] = {"elements": int(r.size), "factor": float(np.quantile(r, 0.9545) / 2) if r.size else None}
        ratios.append(r)
    r = np.concatenate(ratios)
    out = {"factor": float(np.quantile(r, 0.9545) / 2), "elements": int(r.size), "sets": per_set,
           "bracket": list(BRACKET), "count": count}
    echo(json.dumps(out, indent=1))
    return out


def _stack(fr: Frames, offsets: Sequence[int]):
    return (np.stack([fr.states[d] for d in offsets]), np.stack([fr.meas[d] for d in offsets]),
            np.stack([fr.var[d] for d in offsets]), np.stack([fr.valid[d] for d in offsets]))


def marginal_sigma(fr: Frames) -> np.ndarray:
    """Prior sigma that makes the hybrid solve with ``plane_variance="scalar"`` use the plain
    marginal on the unobserved plane (``sigma sqrt(g_r)``: the Schur complement scales with the
    precision, ``g_r`` does not)."""
    from polrig.solve.hybrid import observed_direction

    u2 = observed_direction(fr.states[0]) ** 2
    v = fr.sigma**2
    tot = v.sum(axis=2, keepdims=True)
    g = np.where(tot > 0, np.einsum("crahw,a->crhw", v, 1.0 - u2)[:, :, None] / np.where(tot > 0, tot, 1.0), 1.0)
    return fr.sigma * np.sqrt(g)


def scaled_sigma(fr: Frames, offsets: Sequence[int]) -> np.ndarray:
    """The prior's sigma as captures take it for the states ``offsets`` (the seen state first):
    ``fr.sigma`` times the factor of :func:`polrig.solve.prior_scale.prior_scale` (1 at one state),
    as :func:`polrig.solve.radiometry.prior_scale_from_frames` finds it on a capture's frames."""
    from polrig.solve.prior_scale import prior_scale

    factor = prior_scale(*_stack(fr, offsets), fr.prior, fr.sigma, 0).factor
    return fr.sigma if factor == 1.0 else fr.sigma * factor


def open_factor(fr: Frames, offsets: Sequence[int], sigma: np.ndarray, correlation: np.ndarray | None = None
                ) -> float:
    """The factor on the hybrid prior's standard deviation along the direction two states leave
    open, as captures with :data:`polrig.choices.DEFAULT_PRIOR_SCALE` find it (``geometry``:
    :mod:`polrig.solve.open_scale` on the whole frame, the network's object, the prior's sigma
    ``sigma`` as scaled by :func:`scaled_sigma`); 1 at another number of states, without the
    frame's geometry, or with another default."""
    from polrig.choices import DEFAULT_PRIOR_SCALE
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.open_scale import open_scale_of, open_values

    if DEFAULT_PRIOR_SCALE != "geometry" or len(offsets) != 2 or fr.geometry is None:
        return 1.0
    s, meas, var, valid = _stack(fr, offsets)
    prior = dict(prior_mean=fr.prior, prior_sigma=sigma, seen_state=0, prior_correlation=correlation)
    r = solve_hybrid(s, meas, var, valid, dtype=np.float64, **prior)
    return open_scale_of(*open_values(r, s, meas, var, valid, fr.geometry, mask=fr.mask, **prior)).factor


def estimate(fr: Frames, offsets: Sequence[int], method: str, correlation: np.ndarray | None = None,
             seen_share: Sequence[float] | None = None, prior_scale: bool = True):
    """``(mueller, sigma, solved)`` of ``method`` (``single``, ``hybrid``, ``reference`` or a
    :data:`VARIANTS` name) from the frames at ``offsets`` (the seen state first); ``correlation``:
    the hybrid's joint prior (:func:`polrig.solve.hybrid.solve_hybrid`'s ``prior_correlation``;
    None the per-element prior); ``seen_share``: the hybrid's (``solve_hybrid``'s; None: the
    row's whole variance along the seen direction kept); ``prior_scale``: the hybrid's prior
    sigma scaled as captures scale it (:func:`scaled_sigma` and, at two states, :func:`open_factor`;
    the default) or as calibrated (False; the :data:`VARIANTS` study the calibrated sigma)."""
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.reference import ILL_CONDITIONED, solve_reference

    if method == "single":
        return fr.prior, fr.sigma, np.ones(fr.use.shape, bool)
    s, meas, var, valid = _stack(fr, offsets)
    kw = dict(prior_mean=fr.prior, dtype=np.float64)
    if method == "hybrid":
        sigma = scaled_sigma(fr, offsets) if prior_scale else fr.sigma
        factor = open_factor(fr, offsets, sigma, correlation) if prior_scale else 1.0
        r = solve_hybrid(s, meas, var, valid, prior_sigma=sigma, seen_state=0, prior_correlation=correlation,
                         seen_share=seen_share, open_factor=factor, **kw)
    elif method == "marginal":
        r = solve_hybrid(s, meas, var, valid, prior_sigma=marginal_sigma(fr), seen_state=0, plane_variance="scalar",
                         **kw)
    elif method == "naive":
        r = solve_hybrid(s, meas, var, valid, prior_sigma=fr.sigma, seen_state=None, **kw)
    elif method == "exclude":
        if len(offsets) == 1:
            return fr.prior, fr.sigma, np.ones(fr.use.shape, bool)
        r = solve_hybrid(s[1:], meas[1:], var[1:], valid[1:], prior_sigma=fr.sigma, seen_state=None, **kw)
    elif method == "reference":
        r = solve_reference(s, meas, var, valid, dtype=np.float64, max_condition=np.inf)
    elif method == "hybrid_models":
        return hybrid_with_models(fr, offsets, correlation)[:3]
    else:
        raise ValueError(method)
    return r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0


def hybrid_models_result(fr: Frames, offsets: Sequence[int], correlation: np.ndarray | None = None,
                         prior_scale: bool = True):
    """The hybrid solve of ``offsets`` then the lower-order model selection
    (:func:`polrig.solve.model_selection.select_models` with the network as the prior: at two
    states it tests on the hybrid's posterior system, samples and prior): the
    :class:`polrig.solve.reference.ReferenceResult` (its ``models`` the maps) and the states
    ``(N, 3)``; the prior's sigma scaled as captures scale it (:func:`scaled_sigma`) or, with
    ``prior_scale`` False, as calibrated."""
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.model_selection import select_models

    s, meas, var, valid = _stack(fr, offsets)
    sigma = scaled_sigma(fr, offsets) if prior_scale else fr.sigma
    r = solve_hybrid(s, meas, var, valid, prior_mean=fr.prior, prior_sigma=sigma, seen_state=0,
                     dtype=np.float64, prior_correlation=correlation)
    r, _ = select_models(s, meas, var, valid, None, r, prior=(fr.prior, sigma), seen_state=0,
                         prior_correlation=correlation)
    return r, s


def hybrid_with_models(fr: Frames, offsets: Sequence[int], correlation: np.ndarray | None = None):
    """:func:`hybrid_models_result` as ``(mueller, sigma, solved, model codes (C, H, W))``."""
    from polrig.solve.reference import ILL_CONDITIONED

    r, _ = hybrid_models_result(fr, offsets, correlation)
    return r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0, r.models.code


def reference_with_models(fr: Frames, offsets: Sequence[int]):
    """The reference solve of ``offsets`` (no prior) then the lower-order model selection
    (:func:`polrig.solve.model_selection.select_models`, the samples alone):
    ``(mueller, sigma, solved, model codes (C, H, W))``. At four states it is the bound the
    two-state rows are read against: the same candidates fitted to twice the samples."""
    from polrig.solve.model_selection import select_models
    from polrig.solve.reference import ILL_CONDITIONED, solve_reference

    s, meas, var, valid = _stack(fr, offsets)
    r = solve_reference(s, meas, var, valid, dtype=np.float64, max_condition=np.inf)
    r, maps = select_models(s, meas, var, valid, None, r)
    return r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0, maps.code


#: "A lower-order model holds" at a pixel (from the hidden truth): in every colour the truth's
#: nearest block of some candidate model (:data:`polrig.solve.reduced_models.MODELS`, Frobenius
#: distance) is within this share of the truth's Frobenius norm.
HOLDS_REL = 0.01


def model_holds(truth: np.ndarray, mask: np.ndarray, rel: float = HOLDS_REL) -> np.ndarray:
    """``(H, W)`` object pixels where a lower-order model holds (:data:`HOLDS_REL`): the least
    relative Frobenius distance of the truth ``(C, 3, 3, H, W)`` from each model (its fit with
    the identity metric, :func:`polrig.solve.reduced_models.fit_model`) at most ``rel`` in
    every colour."""
    from polrig.solve.reduced_models import MODELS, fit_model

    ys, xs = np.nonzero(mask)
    blocks = np.moveaxis(truth[..., ys, xs], -1, 1).reshape(-1, 9).astype(np.float64)  # (C*P, 9)
    eye = np.broadcast_to(np.eye(9), (len(blocks), 9, 9))
    dist = np.full(len(blocks), np.inf)
    for model in MODELS:
        _, q, _ = fit_model(model, blocks, eye)
        dist = np.fmin(dist, np.sqrt(np.clip(q, 0.0, None)))
    ok = (dist <= rel * np.linalg.norm(blocks, axis=1)).reshape(truth.shape[0], -1).all(axis=0)
    out = np.zeros(mask.shape, bool)
    out[ys, xs] = ok
    return out


@functools.lru_cache(maxsize=16)
def _detectable(df: int) -> float:
    from polrig.solve.model_selection import detectable_noncentrality

    return detectable_noncentrality(df)


def detectably_off_every_model(fr: Frames, offsets: Sequence[int], correlation: np.ndarray | None = None
                               ) -> np.ndarray:
    """``(C, H, W)``: the object's unclipped pixels whose truth the selection at ``offsets``
    could tell from every candidate model (:mod:`polrig.solve.model_selection`'s false-acceptance
    definition on the hybrid's posterior system: the noncentrality, each model's fit to the
    truth in the metric ``N'`` of the noise-free samples and the network's prior sigma, at least
    :func:`polrig.solve.model_selection.detectable_noncentrality`)."""
    from polrig.solve import model_selection as ms
    from polrig.solve.reduced_models import MODELS, fit_model
    from polrig.solve.reference import forward_measurements

    s, _, var, valid = _stack(fr, offsets)
    clean = forward_measurements(fr.truth, s)
    out = np.zeros(fr.use.shape, bool)
    h, w = fr.mask.shape
    for c in range(fr.truth.shape[0]):
        ys, xs = np.nonzero(fr.use[c] & fr.clean & (fr.sigma[c] > 0).all(axis=(0, 1)))
        if not len(ys):
            continue
        rs = ms.row_space_equations(s, clean, var, valid, None, c, ys * w + xs)
        ok = (rs.rank >= ms.MIN_RANK) & (rs.rank < 9) & rs.used[:, :4].all(axis=1)
        truth = fr.truth[c][:, :, ys, xs].reshape(9, -1).T
        sd = fr.sigma[c][:, :, ys, xs].reshape(9, -1).T
        normal, m_post = ms.posterior_system(rs.normal, np.where(ok[:, None], rs.m_hat, 0.0), truth, sd, s[0],
                                             correlation)
        det = ok.copy()
        for model in MODELS:
            _, lam, _ = fit_model(model, m_post, normal)
            det &= lam >= _detectable(9 - model.n_params)
        out[c, ys, xs] = det
    return out


def score_where_models_hold(fr: Frames, mueller: np.ndarray, holds: np.ndarray) -> dict[str, float]:
    """Matrix PSNR over the object pixels where a lower-order model holds (:func:`model_holds`)
    and have no clipped sample (``fr.clean``), and their count (the peak of :func:`score`)."""
    from polrig.models.evaluate import psnr

    sel = holds & fr.clean
    pred = (mueller * fr.mask).astype(np.float32)
    peak = float(np.abs(fr.truth[..., fr.mask]).max())
    return {"psnr_holds": psnr(pred, fr.truth, sel, peak) if sel.any() else float("nan"),
            "holds_pixels": float(sel.sum()), "object_pixels": float((fr.mask & fr.clean).sum())}


#: The four-state bound of the model comparison (:func:`models_rows`' ``reference4`` rows).
FOUR_STATES = (0, 45, 90, 135)


def models_rows(fr: Frames, two: Sequence[int], correlation: np.ndarray | None = None,
                keys: Sequence[str] = ("single", "hybrid2", "hybrid2_models", "hybrid2_geometry", "hybrid2_diffuse",
                                       "reference4", "reference4_models"),
                prior_scale: bool = True) -> dict[str, dict[str, float]]:
    """One sample's rows of the lower-order model comparison at the 2-state set ``two``:
    single-shot, hybrid 2 and hybrid 2 with the model selection (:func:`hybrid_with_models`),
    each with :func:`score` and :func:`score_where_models_hold` over the pixels where a model
    holds (:func:`model_holds`) that are lit in every colour (:func:`lit_pixels`: in a shadow a
    model holds trivially, the truth is about 0, the network returns about 0 and one frame's
    noise is all there is: single-shot PSNRs of 90 dB); the selection's row also the share of
    scored colour-pixels given a reduced model, overall and where one holds. The bound they are
    read against: ``reference4``, the four-state reference solve (:data:`FOUR_STATES`, no prior),
    and ``reference4_models``, the same with the selection (:func:`reference_with_models`), scored
    alike. ``hybrid2_geometry``: the selection's result with the diffuse completion
    (:func:`polrig.solve.diffuse_geometry.complete_diffuse`, the frames' ``geometry``; the share of
    scored colour-pixels it completed as ``accepted``; absent without a geometry).
    ``hybrid2_diffuse``: hybrid 2 with the diffuse term where the two states' samples alone accept
    it (:func:`polrig.solve.diffuse_test.complete_tested_diffuse`; no selection), ``accepted`` the
    share of scored colour-pixels, its false acceptance where the samples can tell
    (:func:`detectably_off_diffuse`) and in the prior's metric (:func:`detectably_off_every_model`,
    as the selection's); absent without a geometry.
    ``correlation``: the hybrid's joint prior (None: per element); ``keys``: the rows wanted;
    ``prior_scale``: the hybrid rows' prior sigma scaled as captures scale it (:func:`scaled_sigma`)
    or as calibrated (False; the diffuse row is the capture's route, always scaled)."""
    holds = model_holds(fr.truth, fr.mask) & lit_pixels(fr).all(axis=0)
    rows = {}
    for key, method, offs in (("single", "single", two), ("hybrid2", "hybrid", two),
                              ("reference4", "reference", FOUR_STATES)):
        if key in keys:
            est = estimate(fr, offs, method, correlation, prior_scale=prior_scale)
            rows[key] = score(fr, *est) | score_where_models_hold(fr, est[0], holds)
    if "reference4_models" in keys:
        *est, code = reference_with_models(fr, FOUR_STATES)
        rows["reference4_models"] = score(fr, *est) | score_where_models_hold(fr, est[0], holds)
    if "hybrid2_models" not in keys:
        return rows
    from polrig.solve.diffuse_geometry import complete_diffuse
    from polrig.solve.reference import ILL_CONDITIONED

    r, s = hybrid_models_result(fr, two, correlation, prior_scale)
    code = r.models.code
    est = (r.mueller, r.sigma, (r.mask & ILL_CONDITIONED) == 0)
    sel = fr.use & est[2]
    if "hybrid2_geometry" in keys and fr.geometry is not None:
        g, completed, _ = complete_diffuse(r, s, fr.geometry)
        rows["hybrid2_geometry"] = (score(fr, g.mueller, g.sigma, est[2])
                                    | score_where_models_hold(fr, g.mueller, holds)
                                    | {"accepted": float(completed[sel].mean()) if sel.any() else float("nan")})
    reduced = (code != 0) & (code != 255)
    det = detectably_off_every_model(fr, two, correlation) & sel
    if "hybrid2_diffuse" in keys and fr.geometry is not None:
        rows["hybrid2_diffuse"] = diffuse_row(fr, two, correlation, holds, sel, det)
    rows["hybrid2_models"] = (score(fr, *est) | score_where_models_hold(fr, est[0], holds)
                              | {"accepted": float(reduced[sel].mean()) if sel.any() else float("nan"),
                                 "accepted_holds": float(reduced[sel & holds[None]].mean())
                                 if (sel & holds[None]).any() else float("nan"),
                                 "detectable": float(det.sum()), "falsely_accepted": float(reduced[det].sum())})
    return rows


def _truth_system(fr: Frames, two: Sequence[int], test, ys: np.ndarray, xs: np.ndarray):
    """What the diffuse test ``test`` saw at pixels ``ys``, ``xs``, with the truth's noise-free
    Stokes in place of the measured ones: ``(clean (C, 2, 3, P), information (C, 2, 3, 3, P),
    states (2, 3), view (P, 3), light (P, 3), specular block (P, 3, 3) or None, (stage zero axis,
    camera x axis))`` (the frames' information, the test's light and ``eta``)."""
    from polrig.solve.diffuse_geometry import light_fields, specular_block
    from polrig.solve.diffuse_test import state_stokes

    states = np.stack([fr.states[d] for d in two])
    truth = fr.truth[..., ys, xs]
    clean = np.stack([np.einsum("crkp,k->crp", truth, st) for st in states], axis=1)
    info = np.stack([state_stokes(fr.meas[d], fr.var[d], fr.valid[d])[1][..., ys, xs] for d in two], axis=1)
    g = fr.geometry
    light, view, fixed = light_fields(g, ys, xs)[test.light], g.view[ys, xs], (g.stage_zero_axis, g.camera_x_axis)
    spec = None if test.specular_albedo is None else specular_block(light, view, test.eta, *fixed)
    return clean, info, states, view, light, spec, fixed


def detectably_off_diffuse(fr: Frames, two: Sequence[int], test) -> np.ndarray:
    """``(H, W)``: the pixels the diffuse test ``test`` (:func:`polrig.solve.diffuse_test.test_diffuse`
    of the states ``two``) tested whose truth its samples can tell from the diffuse term: the
    truth's own statistic (noise-free Stokes, the frames' information, the test's ``eta`` and
    light) at least the level's 95 % power point (:mod:`polrig.solve.diffuse_test`, "False
    acceptance"); where the test had the specular term, from both of its models (the diffuse
    term alone and with the specular term), each at its own degrees of freedom. The power point
    is the noncentral chi-square's, which overstates the test's power where the misfit is flat in
    the normal (:func:`diffuse_test_power`)."""
    from polrig.solve.diffuse_test import degrees_of_freedom, diffuse_statistic
    from polrig.solve.model_selection import detectable_noncentrality

    out = np.zeros(fr.mask.shape, bool)
    ys, xs = np.nonzero(test.tested)
    if not len(ys) or test.eta is None:
        return out
    clean, info, states, view, light, spec, fixed = _truth_system(fr, two, test, ys, xs)
    lam, _, _ = diffuse_statistic(clean, info, states, view, light, test.eta, *fixed)
    off = lam >= detectable_noncentrality(test.df, test.alpha)
    if spec is not None:
        lam_s, _, _ = diffuse_statistic(clean, info, states, view, light, test.eta, *fixed, specular=spec)
        off &= lam_s >= detectable_noncentrality(degrees_of_freedom(clean.shape[0], True), test.alpha)
    out[ys, xs] = off
    return out


#: The power at which a truth counts as one the samples can tell from the model (as the selection's
#: noncentral power point, :func:`polrig.solve.model_selection.detectable_noncentrality`).
DETECTABLE_POWER = 0.95
#: Noise draws per pixel of the diffuse test's Monte Carlo power (:func:`diffuse_test_power`).
POWER_DRAWS = 200
#: Pixels x draws per call of the compiled statistic in :func:`diffuse_test_power`.
_POWER_BATCH = 100_000


def diffuse_test_power(fr: Frames, two: Sequence[int], test, ys: np.ndarray, xs: np.ndarray, *,
                       draws: int = POWER_DRAWS, seed: int = 0) -> np.ndarray:
    """``(P,)``: the share of ``draws`` noise draws on which the diffuse test ``test`` rejects at
    the pixels ``ys``, ``xs``: its statistics (:func:`polrig.solve.diffuse_test.diffuse_statistic`,
    at the test's ``eta`` and light, with the specular term where the test had it) and its
    decision (:func:`polrig.solve.diffuse_test.decide`) on the truth's noise-free Stokes of each
    state plus Gaussian noise of the frames' information. Its power where the truth is off the
    model, its level where the truth is on it.

    Why not the noncentrality alone (:func:`detectably_off_diffuse`): ``T`` minimises over the
    normal, and where the misfit is flat in the normal while the residual turns with it, the
    noise's cross term with the residual is absorbed by the choice of normal, so ``T`` falls
    below the noncentral chi-square's. Measured (64 samples of four Baek sets, 200 draws): at
    the pixels past the noncentral 95 % power point the test accepts 12-26 % of the draws, and
    12-28 % of the real samples."""
    from polrig.solve.diffuse_test import decide, diffuse_statistic

    ys, xs = np.asarray(ys), np.asarray(xs)
    if not len(ys) or test.eta is None:
        return np.zeros(len(ys))
    clean, info, states, view, light, spec, fixed = _truth_system(fr, two, test, ys, xs)
    n_col, p = clean.shape[0], len(ys)
    chol = np.linalg.cholesky(np.linalg.inv(np.moveaxis(info, -1, 2)))  # (C, 2, P, 3, 3): the noise's
    rng = np.random.default_rng(seed)
    rejected = np.zeros(p)
    per_call = max(1, _POWER_BATCH // p)
    for start in range(0, int(draws), per_call):
        k = min(per_call, int(draws) - start)
        noise = np.einsum("cjpab,cjpkb->cjakp", chol, rng.standard_normal((n_col, 2, p, k, 3)))
        stokes = (clean[..., None, :] + noise).reshape(n_col, 2, 3, k * p)  # draw-major pixels
        tile = lambda a: np.tile(a, (k,) + (1,) * (a.ndim - 1))  # noqa: E731
        system = (np.tile(info, k), states, tile(view), tile(light), test.eta, *fixed)
        t_d, _, _ = diffuse_statistic(stokes, *system)
        t_s = None if spec is None else diffuse_statistic(stokes, *system, specular=tile(spec))[0]
        accepted, _ = decide(t_d, t_s, n_col, test.alpha)
        rejected += (~accepted).reshape(k, p).sum(axis=0)
    return rejected / int(draws)


def diffuse_row(fr: Frames, two: Sequence[int], correlation, holds: np.ndarray, sel: np.ndarray,
                det_prior: np.ndarray) -> dict[str, float]:
    """:func:`models_rows`' ``hybrid2_diffuse`` row: scores, where a model holds, the accepted
    share of the scored colour-pixels ``sel`` ``(C, H, W)``, and the false acceptance counts where
    the samples can tell: past the noncentral power point (:func:`detectably_off_diffuse`; keys
    ``detectable``, ``falsely_accepted``) and, of those, where the test's Monte Carlo power is at
    least :data:`DETECTABLE_POWER` (:func:`diffuse_test_power`; ``_mc``), and in the prior's
    metric (``det_prior``, :func:`detectably_off_every_model`; ``_prior``)."""
    from polrig.solve.diffuse_test import complete_tested_diffuse
    from polrig.solve.hybrid import solve_hybrid
    from polrig.solve.reference import ILL_CONDITIONED

    s, meas, var, valid = _stack(fr, two)
    sigma = scaled_sigma(fr, two)  # as the capture's route (polrig.app.diffuse_route)
    r = solve_hybrid(s, meas, var, valid, prior_mean=fr.prior, prior_sigma=sigma, seen_state=0,
                     dtype=np.float64, prior_correlation=correlation,
                     open_factor=open_factor(fr, two, sigma, correlation))
    g, test, _ = complete_tested_diffuse(r, s, meas, var, valid, fr.geometry, prior=(fr.prior, sigma),
                                         seen_state=0, prior_correlation=correlation, mask=fr.mask, specular=True)
    solved = (r.mask & ILL_CONDITIONED) == 0
    accepted = np.broadcast_to(test.accepted[None], sel.shape)
    specular = accepted & (test.specular_albedo > 0)
    off = detectably_off_diffuse(fr, two, test) & sel.any(axis=0)
    ys, xs = np.nonzero(off)
    strong = np.zeros_like(off)
    strong[ys, xs] = diffuse_test_power(fr, two, test, ys, xs) >= DETECTABLE_POWER
    det = np.broadcast_to(off[None], sel.shape) & sel
    det_mc = np.broadcast_to(strong[None], sel.shape) & sel
    return (score(fr, g.mueller, g.sigma, solved) | score_where_models_hold(fr, g.mueller, holds)
            | {"accepted": float(accepted[sel].mean()) if sel.any() else float("nan"),
               "accepted_holds": float(accepted[sel & holds[None]].mean()) if (sel & holds[None]).any()
               else float("nan"),
               "specular": float(specular[sel].mean()) if sel.any() else float("nan"),
               "detectable": float(det.sum()), "falsely_accepted": float(accepted[det].sum()),
               "detectable_mc": float(det_mc.sum()), "falsely_accepted_mc": float(accepted[det_mc].sum()),
               "detectable_prior": float(det_prior.sum()), "falsely_accepted_prior": float(accepted[det_prior].sum())})


#: The priors of the joint comparison (:func:`joint_priors`): the per-element prior, the joint
#: one (the fitted correlation ``K``) and the joint one with the whitened errors' scale measured
#: on the calibration scenes (``S K S``, ``S`` the file's ``coverage_scale``).
JOINT_PRIORS = ("diagonal", "joint", "joint_scaled")


def joint_priors(uncertainty) -> dict[str, np.ndarray | None]:
    """:data:`JOINT_PRIORS` -> the hybrid's ``prior_correlation`` of an
    :class:`polrig.models.uncertainty.UncertaintyModel` with a joint prior."""
    k = uncertainty.joint_correlation
    scale = np.asarray(uncertainty.joint["coverage_scale"], np.float64)
    return dict(zip(JOINT_PRIORS, (None, k, scale[:, None] * k * scale[None, :])))


def joint_rows(fr: Frames, offsets: dict[str, tuple[int, ...]], priors: dict[str, np.ndarray | None]
               ) -> dict[str, dict[str, float]]:
    """One sample's rows of the joint-prior comparison (``--joint-compare``): for each of
    ``priors`` (name -> ``prior_correlation``, :func:`joint_priors`), the hybrid at 1, 2, 3 and 4
    states (``offsets``: ``two``, ``three``, ``four``) with :func:`score`, and at two states with
    the lower-order model selection (:func:`models_rows`: its false acceptance and share
    accepted); keys ``<prior>_hybrid<N>`` and ``<prior>_models``. The prior's sigma as calibrated
    (the comparison is of the correlation; ``benchmarks/results/continuum_joint.md`` was measured
    so, before captures scaled it)."""
    rows = {}
    for name, k in priors.items():
        for n, offs in ((1, (0,)), (2, offsets["two"]), (3, offsets["three"]), (4, offsets["four"])):
            rows[f"{name}_hybrid{n}"] = score(fr, *estimate(fr, offs, "hybrid", k, prior_scale=False)) | {
                "states": n, "time_s": 0.0}
        rows[f"{name}_models"] = models_rows(fr, offsets["two"], k, keys=("hybrid2_models",),
                                             prior_scale=False)["hybrid2_models"] \
            | {"states": 2, "time_s": 0.0}
    return rows


def acquisition_time_s(offsets: Sequence[float], frames_per_state: int = 1, bracket: Sequence[float] = ()) -> float:
    """The simulated rig's hardware time of one pose that takes the states ``offsets`` (deg from
    the seen state, in that order; the stage starts at the first, each move to the nearer of the
    two equivalent angles: :func:`polrig.acquisition.plan.nearest_stage_angle`): the stage's
    trapezoidal moves (:mod:`polrig.sim.motion`, the simulated rig's speed and acceleration) and
    ``frames_per_state`` frames of the dataset's exposure plus readout per state, and as many
    again at each ``bracket`` fraction of it
    (:func:`polrig.acquisition.plan.step_durations` of
    :func:`polrig.acquisition.plan.adaptive_pose_steps`: the plan's own hardware time)."""
    from polrig.acquisition.plan import CapturePlan, adaptive_pose_steps, step_durations
    from polrig.sim.dataset import DATASET_EXPOSURE_US

    plan = CapturePlan((0.0,), frames_per_state=int(frames_per_state))
    exposures = [DATASET_EXPOSURE_US] + [DATASET_EXPOSURE_US * float(f) for f in bracket]
    return float(sum(step_durations(adaptive_pose_steps(plan, 0, exposures, stage_angles(offsets)),
                                    sim_hardware_model())))


def stage_angles(offsets: Sequence[float]) -> list[float]:
    """The stage angles of a pose that takes the states ``offsets`` in that order: the first as
    given, each next at the nearer of its two equivalent angles
    (:func:`polrig.acquisition.plan.nearest_stage_angle`)."""
    from polrig.acquisition.plan import nearest_stage_angle

    angles = [float(offsets[0])]
    for d in offsets[1:]:
        angles.append(nearest_stage_angle(d, angles[-1]))
    return angles


def sim_hardware_model():
    """The simulated rig's :class:`polrig.acquisition.plan.HardwareModel` at the sets' exposure:
    trapezoidal moves (:mod:`polrig.sim.motion`, the simulated rig's default speeds and
    :data:`SIM_STAGE_ACCEL_DEG_S2`), :data:`SIM_READOUT_US` per frame, no settle frames, both
    axes at 0."""
    from polrig.acquisition.plan import HardwareModel
    from polrig.sim.dataset import DATASET_EXPOSURE_US
    from polrig.sim.motion import Move
    from polrig.sim.options import DEFAULTS

    speed = {"stage": DEFAULTS["stage_speed_deg_s"], "turntable": DEFAULTS["turntable_speed_deg_s"]}
    return HardwareModel(lambda a, f, t: Move(f, t, 0.0, speed[a], SIM_STAGE_ACCEL_DEG_S2).duration_s
                         if f != t else 0.0, SIM_READOUT_US, 0, {"stage": 0.0, "turntable": 0.0},
                         DATASET_EXPOSURE_US)


def lit_pixels(fr: Frames) -> np.ndarray:
    """``(C, H, W)``: the seen frame not clipped and its ``S0`` at least
    :data:`polrig.solve.reference.MIN_SNR` of its noise sigma (the adaptive capture's object
    pixels per colour)."""
    from polrig.solve.reference import MIN_SNR

    s0 = fr.meas[0].sum(axis=1) / 2.0
    return fr.use & (s0 >= MIN_SNR * np.sqrt(fr.var[0].sum(axis=1) / 4.0))


def adaptive(fr: Frames, target: float, *, share: float = ADAPTIVE_SHARE,
             max_states: int = ADAPTIVE_MAX_STATES, min_states: int | None = None,
             correlation: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray, list[int]]:
    """The adaptive capture on one sample (:mod:`polrig.app.adaptive`'s rule and criterion on
    the sample's frames): from the seen state, while less than ``share`` of the object pixels
    (those whose seen frame is not clipped and has some colour above its noise floor, ``S0`` at
    least :data:`polrig.solve.reference.MIN_SNR` sigmas; the colours below it do not count) have
    a relative posterior sigma at most ``target``, or fewer than ``min_states`` states are taken
    (default the capture's, :data:`polrig.acquisition.plan.ADAPTIVE_MIN_STATES`; designed then for
    every object pixel), and fewer than ``max_states`` states are taken, the A-optimal next offset
    (:func:`polrig.solve.design.a_optimal_next`, under the joint prior ``correlation`` where
    given) among the candidates of :func:`polrig.solve.design.next_candidates` not taken yet
    (the equiangular set through the seen state first, then the 15 deg offsets; one frame each
    exists), chosen as the capture chooses (:func:`polrig.solve.design.choose_next`, timed by
    :func:`sim_hardware_model` and :data:`polrig.solve.design.DECISION_S`; the time reported is
    the hardware time alone, as for every method). Returns the hybrid estimate of the states taken (``estimate``'s three arrays, with
    the joint prior ``correlation`` where given, as the capture's) and the offsets taken, in
    order."""
    from polrig.acquisition.plan import ADAPTIVE_MIN_STATES, CapturePlan, nearest_stage_angle, state_time_s
    from polrig.sim.dataset import DATASET_EXPOSURE_US
    from polrig.solve.design import (
        DECISION_S,
        DESIGN_PIXELS,
        a_optimal_next,
        choose_next,
        next_candidates,
        predicted_share,
        relative_sigma,
        share_at_target,
    )

    # the capture's object pixels: the seen frame not clipped, some colour above its noise floor
    lit = lit_pixels(fr)
    obj = fr.use.all(axis=0) & lit.any(axis=0)
    plan, exposures, model = CapturePlan((0.0,)), [DATASET_EXPOSURE_US], sim_hardware_model()
    taken = [0]
    while True:
        prior_sigma = scaled_sigma(fr, taken)  # the solve's and the design's, as the capture's
        mueller, sigma, solved = estimate(fr, taken, "hybrid", correlation)  # prior_sigma and, at two, the open factor
        got, met = share_at_target(relative_sigma(sigma, mueller, lit), obj, target)
        least = len(taken) >= (ADAPTIVE_MIN_STATES if min_states is None else min_states)
        if (got >= share and least) or len(taken) >= max_states:
            return mueller, sigma, solved, taken
        m00 = mueller[:, 0, 0]
        above = obj & np.all((m00 > 0) & np.isfinite(m00), axis=0)
        at_target = 0.0  # as the capture: below its least states, designed for every object pixel
        if got < share:
            above &= ~met
            at_target = got
        ys, xs = np.nonzero(above)
        if len(ys) == 0:
            return mueller, sigma, solved, taken
        stride = max(1, -(-len(ys) // DESIGN_PIXELS))
        ys, xs = ys[::stride], xs[::stride]
        px = lambda a: np.moveaxis(np.asarray(a, np.float64)[..., ys, xs], -1, 0)  # noqa: E731
        cands = [int(round(a)) for a in next_candidates(taken, OFFSETS_DEG)]
        scores = a_optimal_next(px(prior_sigma), fr.states[0], [(fr.states[d], px(fr.var[d]), px(fr.valid[d]) > 0)
                                                            for d in taken],
                                px(mueller), np.stack([fr.states[d] for d in cands]), *fr.noise_terms,
                                correlation=correlation)
        # the capture's choice (polrig.app.adaptive): the cheapest state predicted to finish, else at the
        # last state the least criterion, else the greatest reduction per second of hardware time
        here = stage_angles(taken)[-1]
        cost = [state_time_s(plan, exposures, here, nearest_stage_angle(c, here), model) + DECISION_S for c in cands]
        m = px(mueller)
        after = predicted_share(scores.trace.reshape(len(cands), *m.shape[:2]), m[..., 0, 0], px(lit) > 0,
                                target, at_target, int(above.sum()) / int(obj.sum()))
        taken.append(cands[choose_next(scores, cost, after, share, last=len(taken) + 1 >= max_states)])


def score(fr: Frames, mueller: np.ndarray, sigma: np.ndarray, solved: np.ndarray,
          clean: np.ndarray | None = None, cover: np.ndarray | None = None) -> dict[str, float]:
    """Matrix PSNR (over the object, and over its pixels unclipped in every state: ``clean``,
    default ``fr.clean``), forward L2 and the counts of elements within 2 sigma (module
    docstring; over ``cover`` ``(C, H, W)`` instead of the pixels whose seen frame is not
    clipped, if given)."""
    from polrig.models.evaluate import forward_l2, psnr

    clean = fr.clean if clean is None else clean
    pred = (mueller * fr.mask).astype(np.float32)
    peak = float(np.abs(fr.truth[..., fr.mask]).max())
    sel = (fr.use if cover is None else cover) & solved
    inside = (np.abs(mueller - fr.truth) <= 2.0 * sigma).transpose(1, 2, 0, 3, 4)[:, :, sel]
    return {"matrix_psnr": psnr(pred, fr.truth, fr.mask, peak),
            "matrix_psnr_unclipped": psnr(pred, fr.truth, clean, peak) if clean.any() else float("nan"),
            "fwd_l2": forward_l2(pred, fr.truth, fr.mask),
            "inside": float(inside.sum()), "elements": float(inside.size)}


def _mean(rows: list[dict[str, float]]) -> dict[str, float]:
    keys = ("matrix_psnr", "matrix_psnr_unclipped", "fwd_l2", "states", "time_s", "psnr_holds", "accepted",
            "accepted_holds", "specular")
    out = {k: float(np.nanmean([r[k] for r in rows])) for k in keys if rows and k in rows[0]}
    n = sum(r["elements"] for r in rows)
    out["coverage"] = sum(r["inside"] for r in rows) / n if n else float("nan")
    if rows:
        inside, elements = [r["inside"] for r in rows], [r["elements"] for r in rows]
        out["coverage_interval"] = list(coverage_interval(inside, elements))
        out["coverage_scenes"] = list(scene_spread(inside, elements))
    if rows and "hl_elements" in rows[0]:
        n = sum(r["hl_elements"] for r in rows)
        out["coverage_highlights"] = sum(r["hl_inside"] for r in rows) / n if n else float("nan")
        out["highlight_elements"] = float(n)
    for metric in ("", "_mc", "_prior"):  # the false acceptance in each metric a row counts
        if rows and f"detectable{metric}" in rows[0]:
            det = sum(r[f"detectable{metric}"] for r in rows)
            out[f"false_acceptance{metric}"] = (sum(r[f"falsely_accepted{metric}"] for r in rows) / det if det
                                                else float("nan"))
            out[f"detectable{metric}_share"] = det / n * 9 if n else float("nan")
    if rows and "holds_pixels" in rows[0]:
        total = sum(r["object_pixels"] for r in rows)
        out["holds_share"] = sum(r["holds_pixels"] for r in rows) / total if total else float("nan")
    return out


def _samples(data, net):
    """``(dataset, sensor model, [(index, network prior)])`` of a set's lit samples (``data``: a
    dataset folder or a :class:`polrig.models.data.Dataset`)."""
    from polrig.models.data import (
        Dataset,
        check_network_size,
        lit_samples,
        load_dataset,
    )
    from polrig.sensor.noise import SensorModel

    data_dir = data if not isinstance(data, Dataset) else f"scene {data.manifest.get('scene', '?')}"
    ds = data if isinstance(data, Dataset) else load_dataset(data)
    check_network_size(ds, data_dir)
    sensor = SensorModel(**ds.manifest["noise"]["sensor_model"])
    for i in lit_samples(ds):
        yield ds, sensor, i, network_prior(ds, i, net)


def search_states(dirs: Sequence[pathlib.Path], net, seed: int, echo=print,
                  correlation: np.ndarray | None = None) -> dict:
    """Mean hybrid matrix PSNR (over pixels unclipped in every state) of every 2- and 3-state
    set on the search sets; the best of each. ``correlation``: the hybrid's joint prior (None:
    per element)."""
    two = [(0, d) for d in OFFSETS_DEG[1:]]
    three = [(0, a, b) for a in OFFSETS_DEG[1:] for b in OFFSETS_DEG[1:] if a < b]
    acc: dict[tuple, list[float]] = {k: [] for k in two + three}
    n = 0
    for tag, d in enumerate(dirs):
        for ds, sensor, i, prior in _samples(d, net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, 100 + tag, i]))
            n += 1
            for key in acc:
                acc[key].append(score(fr, *estimate(fr, key, "hybrid", correlation))["matrix_psnr_unclipped"])
    mean = {k: float(np.nanmean(v)) for k, v in acc.items()}
    best2 = max(two, key=mean.get)
    best3 = max(three, key=mean.get)
    echo(f"search: {n} samples; best 2 states {best2} {mean[best2]:.2f} dB, best 3 {best3} {mean[best3]:.2f} dB")
    return {"samples": n, "two": {"/".join(map(str, k)): mean[k] for k in two},
            "three": {"/".join(map(str, k)): mean[k] for k in three}, "best_two": list(best2),
            "best_three": list(best3)}


def evaluate_set(data_dir, net, offsets: dict[str, tuple[int, ...]], seed: int, tag: int,
                 targets: Sequence[float] = ADAPTIVE_TARGETS, only_models: bool = False,
                 correlation: np.ndarray | None = None) -> dict:
    """Every method's mean metrics on one set (module docstring), the adaptive capture at each of
    ``targets`` included; with each method's states per pose and acquisition time
    (:func:`acquisition_time_s`; the adaptive's per sample). Also the lower-order model
    comparison at two states (:func:`models_rows`: keys ``holds_single``, ``holds_hybrid2``,
    ``hybrid2_models``); ``only_models``: that alone. ``correlation``: the hybrid's joint prior
    for every hybrid row (the :data:`VARIANTS` rows keep the per-element prior they study); None
    per element."""
    plan = {} if only_models else {"single": ("single", (0,)), "hybrid1": ("hybrid", (0,)), "hybrid2": ("hybrid", offsets["two"]),
            "hybrid3": ("hybrid", offsets["three"]), "hybrid4": ("hybrid", offsets["four"]),
            "reference3": ("reference", offsets["three"]), "reference4": ("reference", offsets["four"])}
    for v in VARIANTS if not only_models else ():
        plan[f"{v}1"] = (v, (0,))
        plan[f"{v}2"] = (v, offsets["two"])
    # the hybrid with the sigma as calibrated (captures scale it: polrig.solve.prior_scale)
    calibrated = {} if only_models else {f"hybrid{n}_calibrated": offsets[k]
                                         for n, k in ((2, "two"), (3, "three"), (4, "four"))}
    # equal capture time: 3 states of 4 frames against 4 states of 3 (12 frames each)
    timed = {} if only_models else {"hybrid3_4frames": (offsets["three"], 4),
                                    "hybrid4_3frames": (offsets["four"], 3)}
    adaptive_keys = {} if only_models else {adaptive_key(t, n): (t, n) for n in (ADAPTIVE_MAX_STATES, ADAPTIVE_MORE_STATES)
                                            for t in targets}
    # an exposure bracket at every state (the "Highlights" rows): the network sees the reference exposure
    bracketed = {} if only_models else {"single_bracket": ("single", (0,)), "hybrid1_bracket": ("hybrid", (0,)),
                                        "hybrid2_bracket": ("hybrid", offsets["two"])}
    model_keys = {"holds_single": "single", "holds_hybrid2": "hybrid2", "hybrid2_models": "hybrid2_models",
                  "hybrid2_geometry": "hybrid2_geometry", "hybrid2_diffuse": "hybrid2_diffuse",
                  "holds_reference4": "reference4",
                  "reference4_models": "reference4_models"}
    rows: dict[str, list] = {k: [] for k in (*plan, *calibrated, *timed, *adaptive_keys, *model_keys, *bracketed)}
    time_s = {key: acquisition_time_s(offs) for key, (_, offs) in plan.items()}
    time_s |= {key: acquisition_time_s(offs) for key, offs in calibrated.items()}
    time_s |= {key: acquisition_time_s(offs, k) for key, (offs, k) in timed.items()}
    time_s |= {key: acquisition_time_s(offs, bracket=BRACKET) for key, (_, offs) in bracketed.items()}
    t0 = time.perf_counter()
    for ds, sensor, i, prior in _samples(data_dir, net):
        fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i]))
        for key, (method, offs) in plan.items():
            rows[key].append(score(fr, *estimate(fr, offs, method, correlation))
                             | {"states": len(offs), "time_s": time_s[key]})
        for key, offs in calibrated.items():
            rows[key].append(score(fr, *estimate(fr, offs, "hybrid", correlation, prior_scale=False))
                             | {"states": len(offs), "time_s": time_s[key]})
        for key, (offs, k) in timed.items():
            frk = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i, k]), offsets=offs,
                                frames_per_state=k)
            rows[key].append(score(frk, *estimate(frk, offs, "hybrid", correlation), clean=fr.clean)
                             | {"states": len(offs), "time_s": time_s[key]})
        if bracketed:
            frb = bracket_prior(sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i, 99]),
                                              offsets=offsets["two"], bracket=BRACKET), net.uncertainty)
            highlights = frb.mask[None] & ~frb.use & frb.valid[0].all(axis=1)  # clipped, the bracket measured
        for key, (method, offs) in bracketed.items():
            est = estimate(frb, offs, method, correlation)
            hl = score(frb, *est, clean=fr.clean, cover=highlights)
            rows[key].append(score(frb, *est, clean=fr.clean) | {"states": len(offs), "time_s": time_s[key]}
                             | {"hl_inside": hl["inside"], "hl_elements": hl["elements"]})
        for key, (target, most) in adaptive_keys.items():
            *est, taken = adaptive(fr, target, max_states=most, correlation=correlation)
            rows[key].append(score(fr, *est) | {"states": len(taken), "time_s": acquisition_time_s(taken)})
        two_rows = models_rows(fr, offsets["two"], correlation)
        for key, k in model_keys.items():
            if k not in two_rows:
                continue
            n_states = {"single": 1, "reference4": 4, "reference4_models": 4}.get(k, 2)
            rows[key].append(two_rows[k] | {"states": n_states, "time_s": acquisition_time_s(
                {1: (0,), 4: FOUR_STATES}.get(n_states, offsets["two"]))})
    n = len(rows["hybrid2_models"])
    return {"data": str(data_dir) if not hasattr(data_dir, "manifest") else
            f"scene {data_dir.manifest.get('scene')} at poses {data_dir.manifest.get('poses_deg')}", "samples": n, "methods": {k: _mean(v) for k, v in rows.items()},
            "seconds": time.perf_counter() - t0}


def markdown(result: dict) -> str:
    off = result["offsets"]
    name = lambda k: "/".join(map(str, off[k]))  # noqa: E731
    cols = [("single", "single-shot"), ("hybrid1", "hybrid 1 (0)"), ("hybrid2", f"hybrid 2 ({name('two')})"),
            ("hybrid3", f"hybrid 3 ({name('three')})"), ("hybrid4", f"hybrid 4 ({name('four')})"),
            ("reference3", "reference 3"), ("reference4", "reference 4")]
    first = next(iter(result["sets"].values()))["methods"]
    adaptive_cols = [(k, adaptive_label(k)) for k in first if k.startswith("adaptive_")]
    cols += adaptive_cols
    lines = []
    for metric, title, fmt in (("matrix_psnr", "Matrix PSNR (dB), object pixels", "{:.2f}"),
                               ("matrix_psnr_unclipped", "Matrix PSNR (dB), object pixels with no clipped sample in "
                                                         "any state", "{:.2f}"),
                               ("fwd_l2", "Forward Stokes L2 (rel.)", "{:.4f}"),
                               ("coverage", "Within 2 sigma", "{:.1%}")):
        psnr_table = metric.startswith("matrix_psnr")
        extra = (" | hybrid 2 - single | hybrid 4 - hybrid 3 | same, equal time (4 vs 3 frames per state) |"
                 if psnr_table else " |")
        lines += [f"**{title}**", "", "| set | scored | " + " | ".join(c[1] for c in cols) + extra,
                  "|---|---:|" + "---:|" * len(cols) + ("---:|---:|---:|" if psnr_table else "")]
        for key, r in result["sets"].items():
            m = r["methods"]
            cells = [fmt.format(m[c][metric]).replace("%", " %") for c, _ in cols]
            row = f"| {set_label(key)} | {r['samples']} | " + " | ".join(cells) + " |"
            if psnr_table:
                row += (f" {m['hybrid2'][metric] - m['single'][metric]:+.2f} |"
                        f" {m['hybrid4'][metric] - m['hybrid3'][metric]:+.2f} |"
                        f" {m['hybrid4_3frames'][metric] - m['hybrid3_4frames'][metric]:+.2f} |")
            lines.append(row)
        lines.append("")
    if "coverage_interval" in first["single"]:
        lines += coverage_interval_table(result, [c for c in cols if not c[0].startswith("reference")])
    if "time_s" in first["single"]:
        timed = [("single", "single-shot"), ("hybrid2", "hybrid 2"), ("hybrid3", "hybrid 3"),
                 ("hybrid4", "hybrid 4"), ("hybrid3_4frames", "hybrid 3, 4 frames each"),
                 ("hybrid4_3frames", "hybrid 4, 3 frames each"), *adaptive_cols]
        lines += ["**States per pose and acquisition time** (mean states / seconds per pose on the simulated rig: "
                  "stage motion, exposure and readout, `acquisition_time_s`; the adaptive capture stops when "
                  f"{100 * ADAPTIVE_SHARE:.0f} % of the object pixels have a relative posterior sigma at most its target "
                  f"with at least {result.get('adaptive_min_states', 1)} states taken, at most {ADAPTIVE_MAX_STATES} "
                  f"states)", "",
                  "| set | " + " | ".join(c[1] for c in timed) + " |", "|---|" + "---:|" * len(timed)]
        for key, r in result["sets"].items():
            m = r["methods"]
            lines.append(f"| {set_label(key)} | " + " | ".join(f"{m[c]['states']:.2f} / {m[c]['time_s']:.2f} s"
                                                           for c, _ in timed) + " |")
        lines.append("")
    if "hybrid2_bracket" in first:
        br = " / ".join(["1"] + [f"1/{1 / f:g}" for f in BRACKET])
        lines += [f"**Highlights: an exposure bracket at every state** ({br} of the exposure, merged; the network "
                  "sees the reference exposure, and where it clipped but a shorter exposure measured the pixel its "
                  "estimate takes the measured intensity with a calibrated sigma: `polrig.models.highlights`). "
                  "Matrix PSNR (dB) over the object / within 2 sigma (pixels whose seen frame did not clip) / within "
                  "2 sigma at the highlights the bracket measured / seconds per pose", "",
                  "| set | single-shot | single-shot, bracket | hybrid 1, bracket | hybrid 2 | hybrid 2, bracket | "
                  "hybrid 2 bracket - single-shot | hybrid 2 bracket - single-shot bracket |", "|---|" + "---:|" * 7]
        for key, r in result["sets"].items():
            m = r["methods"]
            cell = lambda k: (f"{m[k]['matrix_psnr']:.2f} / {100 * m[k]['coverage']:.1f} % / "  # noqa: E731
                              + (f"{100 * m[k]['coverage_highlights']:.1f} %" if m[k].get("highlight_elements") else "-")
                              + f" / {m[k]['time_s']:.2f} s")
            plain = lambda k: f"{m[k]['matrix_psnr']:.2f} / {100 * m[k]['coverage']:.1f} % / - / {m[k]['time_s']:.2f} s"  # noqa: E731
            lines.append(f"| {set_label(key)} | {plain('single')} | {cell('single_bracket')} | {cell('hybrid1_bracket')} | "
                         f"{plain('hybrid2')} | {cell('hybrid2_bracket')} | "
                         f"{m['hybrid2_bracket']['matrix_psnr'] - m['single']['matrix_psnr']:+.2f} | "
                         f"{m['hybrid2_bracket']['matrix_psnr'] - m['single_bracket']['matrix_psnr']:+.2f} |")
        lines.append("")
    if "hybrid2_calibrated" in first:
        lines += prior_scale_table(result)
    two_shipped = "hybrid2_calibrated" if "hybrid2_calibrated" in first else "hybrid2"
    lines += ["**The seen state's treatment** (matrix PSNR dB / within 2 sigma; 1 state, and 2 states "
              f"{name('two')}; every column with the sigma as calibrated)", "",
              "| set | hybrid (shipped) 1 | marginal 1 | naive 1 | exclude 1 (= single-shot) | hybrid (shipped) 2 | "
              "marginal 2 | naive 2 | exclude 2 |", "|---|" + "---:|" * 8]
    for key, r in result["sets"].items():
        m = r["methods"]
        cell = lambda k: f"{m[k]['matrix_psnr']:.2f} / {100 * m[k]['coverage']:.1f} %"  # noqa: E731
        keys = ("hybrid1", "marginal1", "naive1", "exclude1", two_shipped, "marginal2", "naive2", "exclude2")
        lines.append(f"| {set_label(key)} | " + " | ".join(cell(k) for k in keys) + " |")
    if "hybrid2_models" in first:
        lines += ["", models_markdown(result)]
    return "\n".join(lines)


def prior_scale_table(result: dict) -> list[str]:
    """The hybrid at 2, 3 and 4 states with the prior's sigma as calibrated against scaled as
    captures scale it (:func:`scaled_sigma`, and at two states :func:`open_factor`): matrix PSNR
    and within 2 sigma, per set."""
    head = [f"{n} states: {what}" for n in (2, 3, 4) for what in ("PSNR dB", "within 2 sigma")]
    lines = ["**The prior's scale** (`polrig.solve.prior_scale`, `polrig.solve.open_scale`; the captures' default): "
             "the hybrid with the network's sigma as calibrated -> scaled per sample by the states after the seen one "
             "and, at two states, along the direction they leave open by the diffuse term's geometry", "",
             "| set | " + " | ".join(head) + " |", "|---|" + "---:|" * len(head)]
    for key, r in result["sets"].items():
        m = r["methods"]
        cells = []
        for n in (2, 3, 4):
            a, b = m[f"hybrid{n}_calibrated"], m[f"hybrid{n}"]
            cells += [f"{a['matrix_psnr']:.2f} -> {b['matrix_psnr']:.2f}",
                      f"{100 * a['coverage']:.1f} -> {100 * b['coverage']:.1f} %"]
        lines.append(f"| {set_label(key)} | " + " | ".join(cells) + " |")
    return lines + [""]


def coverage_interval_table(result: dict, cols: Sequence[tuple[str, str]]) -> list[str]:
    """The coverage table's figures with their 90 % scene-bootstrap intervals and the middle 80 % of
    the samples' own coverage (:mod:`polrig.models.scene_bootstrap`), as Markdown lines."""
    unit = ("the scene's poses: with a handful of them a rough guide, and silent on other scenes" if result.get("rig")
            else "the set's scenes")
    lines = [f"**Within 2 sigma, how sure each figure is**: the set's coverage [its 90 % bootstrap interval, "
             f"resampling {unit}] (the 10th-90th percentile of the samples' own coverage). Issue 33 asks for "
             "93-97 %.", "",
             "| set | " + " | ".join(c[1] for c in cols) + " |", "|---|" + "---:|" * len(cols)]
    for key, r in result["sets"].items():
        m = r["methods"]
        cells = [f"{100 * m[c]['coverage']:.1f} [{100 * m[c]['coverage_interval'][0]:.1f}, "
                 f"{100 * m[c]['coverage_interval'][1]:.1f}] ({100 * m[c]['coverage_scenes'][0]:.0f}-"
                 f"{100 * m[c]['coverage_scenes'][1]:.0f})" for c, _ in cols]
        lines.append(f"| {set_label(key)} | " + " | ".join(cells) + " |")
    return lines + [""]


def two_state_bound_db(single_db: float, four_models_db: float) -> float:
    """The matrix PSNR (dB) two states could reach at best where a lower-order model holds,
    from two measured rows: the single-shot estimate (``single_db``) and the four-state
    reference with the selection (``four_models_db``). Half its samples leave an estimate of the
    same model ``10 log10 2`` dB worse (variance inversely proportional to the samples);
    combined with the single-shot one as two independent unbiased estimates (inverse-variance
    weights, the most two such estimates give), the mean squared errors add as reciprocals:
    ``10^(P/10) = 10^(P_single/10) + 10^((P_four - 10 log10 2)/10)`` at the same peak. Ideal on
    both counts (the model known, the errors independent): a bound, not an estimate."""
    half = four_models_db - 10.0 * np.log10(2.0)
    return float(10.0 * np.log10(10.0 ** (single_db / 10.0) + 10.0 ** (half / 10.0)))


def models_markdown(result: dict) -> str:
    """The lower-order model comparison at two states (:func:`models_rows`) as a Markdown table."""
    two = "/".join(map(str, result["offsets"]["two"]))
    lines = [f"**Lower-order models at two states ({two})**: single-shot, hybrid 2 and hybrid 2 with the model "
             "selection (`select_models` with the network's prior: at two states the test runs on the hybrid's "
             "posterior system). \"holds\": object pixels with no clipped sample, lit in every colour (`lit_pixels`), "
             f"where in every colour the truth is within {100 * HOLDS_REL:g} % (relative Frobenius) of its nearest "
             "candidate model (`model_holds`); \"all\": every object pixel. Matrix PSNR in dB; \"reduced\": share of the "
             "scored colour-pixels given a reduced model. False acceptance: a reduced model chosen where the "
             "truth is detectably off every candidate (`detectably_off_every_model`: noncentrality on the hybrid's "
             "posterior system with the network's sigma at least the test's 95 % power point), of that share of the "
             "scored colour-pixels. The bound: the four-state reference solve (0/45/90/135, no prior) and the same "
             "with the selection, scored alike; \"single + 6\" is the PSNR the issue's +6 dB asks for; \"two-state "
             "bound\": the most two states could give where a model holds (`two_state_bound_db`: the four-state "
             "selection with half its samples, combined with the single-shot estimate as independent). \"+ geometry\": "
             "hybrid 2 + models with the direction the two states leave open predicted from the diffuse term's "
             "geometry where the selection chose `rank_one` (`complete_diffuse`: of two light fields per image the one of least cost, "
             "normals and one refractive index fitted to the measured ratios in their noise, pulled first towards the network's "
             "normals, then towards the 3x3 neighbours' mean), \"completed\" the share of "
             "the scored colour-pixels it changed.", "",
             "| set | scored | holds (share of pixels) | single-shot, holds | hybrid 2, holds | hybrid 2 + models, holds "
             "| + models - single, holds | + geometry, holds | + geometry - single, holds | single + 6, holds "
             "| reference 4 / + models, holds | two-state bound, holds "
             "| hybrid 2, all | "
             "hybrid 2 + models / + geometry, all | + models / + geometry - single, all | "
             "reduced, all / holds; completed, all | within 2 sigma, hybrid 2 / + models / + geometry / reference 4 + models | "
             "false acceptance (detectably off every model) |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    nan = {"psnr_holds": float("nan"), "coverage": float("nan"), "matrix_psnr": float("nan"), "accepted": float("nan")}
    for key, r in result["sets"].items():
        m = r["methods"]
        sgl, hyb, sel = m["holds_single"], m["holds_hybrid2"], m["hybrid2_models"]
        ref4, ref4m = m.get("holds_reference4", nan), m.get("reference4_models", nan)
        geo = nan | m.get("hybrid2_geometry", {})
        lines.append(
            f"| {set_label(key)} | {r['samples']} | {100 * sel.get('holds_share', float('nan')):.1f} % | "
            f"{sgl['psnr_holds']:.2f} | {hyb['psnr_holds']:.2f} | {sel['psnr_holds']:.2f} | "
            f"{sel['psnr_holds'] - sgl['psnr_holds']:+.2f} | {geo['psnr_holds']:.2f} | "
            f"{geo['psnr_holds'] - sgl['psnr_holds']:+.2f} | {sgl['psnr_holds'] + 6:.2f} | "
            f"{ref4['psnr_holds']:.2f} / {ref4m['psnr_holds']:.2f} | "
            f"{two_state_bound_db(sgl['psnr_holds'], ref4m['psnr_holds']):.2f} | {hyb['matrix_psnr']:.2f} | "
            f"{sel['matrix_psnr']:.2f} / {geo['matrix_psnr']:.2f} | {sel['matrix_psnr'] - sgl['matrix_psnr']:+.2f} / "
            f"{geo['matrix_psnr'] - sgl['matrix_psnr']:+.2f} | "
            f"{100 * sel['accepted']:.0f} / {100 * sel['accepted_holds']:.0f} / {100 * geo['accepted']:.0f} % | "
            f"{100 * hyb['coverage']:.1f} / {100 * sel['coverage']:.1f} / {100 * geo['coverage']:.1f} / "
            f"{100 * ref4m['coverage']:.1f} % | "
            f"{100 * sel.get('false_acceptance', float('nan')):.1f} % of "
            f"{100 * sel.get('detectable_share', float('nan')):.0f} % |")
    return "\n".join(lines + diffuse_markdown(result))


def diffuse_markdown(result: dict) -> list[str]:
    """The lines of the diffuse route's table (:func:`diffuse_row`), none where no set has it."""
    if not any("hybrid2_diffuse" in r["methods"] for r in result["sets"].values()):
        return []
    lines = ["", "**The diffuse term, with the specular term where significant, tested on the two states' samples "
             "alone** (`polrig.solve.diffuse_test`: no model selection, no prior in the test; hybrid 2 with the "
             "specular term the test fitted taken off, the rank-one estimate and the diffuse completion of the rest, "
             "and the specular term put back, where the test accepts: `complete_tested_diffuse(specular=True)`). "
             "Columns as above; \"accepted\": share of the scored colour-pixels; \"with the specular term\": of "
             "them, those where it was significant; false acceptance where the samples can tell: accepted, of the "
             "colour-pixels where the test rejects at least 95 % of 200 noise draws about the truth "
             "(`diffuse_test_power`: its Monte Carlo power), and of those where the truth's own statistic is at "
             "least the noncentral chi-square's 95 % power point under both models (`detectably_off_diffuse`: "
             "it overstates the power where the misfit is flat in the normal, which the choice of normal "
             "absorbs), each with its share of the scored colour-pixels; the selection's false acceptance "
             "(above, noncentral) alongside. (The prior's metric of the selection, off every one of its "
             "candidates, does not apply: the diffuse + specular block is none of them.)", "",
             "| set | accepted, all / holds | with the specular term | PSNR, holds | - single, holds | single + 6, holds "
             "| PSNR, all | - single, all | - hybrid 2 + models / + geometry, all | within 2 sigma "
             "| false acceptance where the samples can tell: Monte Carlo / noncentral / the selection's |",
             "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for key, r in result["sets"].items():
        m = r["methods"]
        if "hybrid2_diffuse" not in m:
            continue
        d, sgl, sel = m["hybrid2_diffuse"], m["holds_single"], m["hybrid2_models"]
        geo = m.get("hybrid2_geometry", {"matrix_psnr": float("nan")})
        lines.append(
            f"| {set_label(key)} | {100 * d['accepted']:.0f} / {100 * d['accepted_holds']:.0f} % | "
            f"{100 * d.get('specular', float('nan')):.0f} % | {d['psnr_holds']:.2f} | {d['psnr_holds'] - sgl['psnr_holds']:+.2f} | {sgl['psnr_holds'] + 6:.2f} | "
            f"{d['matrix_psnr']:.2f} | {d['matrix_psnr'] - sgl['matrix_psnr']:+.2f} | "
            f"{d['matrix_psnr'] - sel['matrix_psnr']:+.2f} / {d['matrix_psnr'] - geo['matrix_psnr']:+.2f} | "
            f"{100 * d['coverage']:.1f} % | "
            f"{100 * d.get('false_acceptance_mc', float('nan')):.1f} % of {100 * d.get('detectable_mc_share', float('nan')):.1f} % / "
            f"{100 * d.get('false_acceptance', float('nan')):.1f} % of {100 * d.get('detectable_share', float('nan')):.1f} % / "
            f"{100 * sel.get('false_acceptance', float('nan')):.1f} % |")
    return lines


def joint_compare(root, out_md, *, count: int, sets: Sequence[str], seed: int = 0, weights_dir=None,
                  two=None, three=None, echo=print, rig_scenes: Sequence[str] | None = None,
                  rig_poses: Sequence[float] = RIG_POSES_DEG, size: int | None = None) -> dict:
    """The per-element prior against the joint one (``--joint-compare``, :func:`joint_rows`) on
    ``count`` samples of each of ``sets``, the states ``two``/``three`` (default
    :data:`RIG_TWO`, :data:`RIG_THREE`, as the continuum run found them) and
    :data:`FOUR_STATES`; the frames as :func:`evaluate_set` makes them (same seeds). Writes
    ``out_md`` and its ``.json`` when given. ``rig_scenes``: instead of ``sets``, the default
    rig's named scenes at ``size`` (default :func:`rig_size`), one sample per turntable angle of
    ``rig_poses`` (:func:`rig_set`). :class:`polrig.errors.ConfigError` where the calibration has
    no joint prior (``python -m polrig.models.uncertainty_fit --joint``)."""
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.evaluate import results_paths
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    unknown = [s for s in sets if s not in SETS] if rig_scenes is None else []
    if unknown or count < 1:
        raise ConfigError(f"unknown set(s) {', '.join(unknown)} or --count {count} < 1; sets are {', '.join(SETS)}")
    net = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    k = None if net.uncertainty is None else net.uncertainty.joint_correlation
    if k is None:
        raise ConfigError("the single-shot calibration has no joint prior (python -m polrig.models.uncertainty_fit "
                          "--data DIR [DIR ...] --joint --write)")
    offsets = {"two": tuple(two or RIG_TWO), "three": tuple(three or RIG_THREE), "four": FOUR_STATES}
    size = (rig_size() if size is None else int(size)) if rig_scenes is not None else SIZE
    result: dict = {"count": count if rig_scenes is None else len(rig_poses), "size": size, "seed": seed,
                    "offsets": {a: list(b) for a, b in offsets.items()}, "correlation": k.tolist(), "sets": {}}
    t0 = time.perf_counter()
    names = [n for n in SETS if n in sets] if rig_scenes is None else [f"rig_{n}" for n in rig_scenes]
    for name in names:
        tag = list(SETS).index(name) if rig_scenes is None else names.index(name)
        data = (make_set(pathlib.Path(root), name, SETS[name][1], count) if rig_scenes is None
                else rig_set(name[len("rig_"):], size, rig_poses, seed))
        rows: dict[str, list] = {}
        for ds, sensor, i, prior in _samples(data, net):
            fr = sample_frames(ds, i, prior, sensor, np.random.default_rng([seed, tag, i]))
            for key, row in joint_rows(fr, offsets, joint_priors(net.uncertainty)).items():
                rows.setdefault(key, []).append(row)
        result["sets"][name] = {"samples": len(rows.get("joint_models", [])),
                                "methods": {key: _mean(v) for key, v in rows.items()}}
        m = result["sets"][name]["methods"]
        echo(f"{name}: false acceptance " + " / ".join(f"{100 * m[f'{p}_models']['false_acceptance']:.1f}"
                                                     for p in JOINT_PRIORS) + " %; coverage 1-4 "
             + "; ".join(" / ".join(f"{100 * m[f'{p}_hybrid{n}']['coverage']:.1f}" for p in JOINT_PRIORS)
                         for n in range(1, 5)))
    result["seconds"] = time.perf_counter() - t0
    table = joint_markdown(result)
    echo(table)
    if out_md is not None:
        out_md, out_json = results_paths(out_md)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        what = (f"--count {count} --sets {','.join(sets)}` (models/continuum.py `joint_rows`); {count} samples per set"
                if rig_scenes is None else
                f"--rig-scenes {','.join(rig_scenes)} --rig-poses {','.join(f'{p:g}' for p in rig_poses)}` "
                "(models/continuum.py `joint_rows`); the default simulated rig's scenes, one sample per turntable "
                "angle")
        atomic_write_text(out_md, "# The network's prior: per element against joint\n\n`python -m polrig.models.continuum "
                          f"--joint-compare {what} at {size}x{size} (those with a lit object pixel scored); "
                          f"{result['seconds']:.0f} s on {os.cpu_count()} CPUs.\n\n" + table + "\n")
    return result


def joint_markdown(result: dict) -> str:
    """:func:`joint_compare`'s result as Markdown tables: per set, each prior's
    (:data:`JOINT_PRIORS`) false acceptance at two states, coverage within 2 sigma and matrix
    PSNR at 1 to 4 states."""
    off = result["offsets"]
    first = next(iter(result["sets"].values()))["methods"]
    priors = [p for p in JOINT_PRIORS if f"{p}_models" in first]
    head = " / ".join(priors)
    lines = ["**False acceptance of the two-state model test** "
             f"({'/'.join(map(str, off['two']))}; a reduced model chosen where the truth is detectably off every "
             "candidate in the test's own metric, of that share of the scored colour-pixels), the share given a "
             "reduced model where one holds, and the matrix PSNR there (hybrid 2 + models)", "",
             "| set | scored | " + " | ".join(f"false acceptance, {p}" for p in priors)
             + f" | reduced where one holds, {head} | PSNR where one holds, {head} (dB) |",
             "|---|---:|" + "---:|" * (len(priors) + 2)]
    for key, r in result["sets"].items():
        m = [r["methods"][f"{p}_models"] for p in priors]
        lines.append(f"| {set_label(key)} | {r['samples']} | "
                     + " | ".join(f"{100 * x['false_acceptance']:.1f} % of {100 * x['detectable_share']:.0f} %"
                                  for x in m)
                     + " | " + " / ".join(f"{100 * x['accepted_holds']:.0f}" for x in m) + " % | "
                     + " / ".join(f"{x['psnr_holds']:.2f}" for x in m) + " |")
    states = [(1, "0"), (2, "/".join(map(str, off["two"]))), (3, "/".join(map(str, off["three"]))),
              (4, "/".join(map(str, off["four"])))]
    for metric, title, fmt in (("coverage", "Within 2 sigma, hybrid", "{:.1%}"),
                               ("matrix_psnr", "Matrix PSNR (dB), hybrid, object pixels", "{:.2f}")):
        lines += ["", f"**{title}**: {head}" + (" (each joint prior - diagonal)" if metric == "matrix_psnr" else ""),
                  "", "| set | " + " | ".join(f"{n} ({o})" for n, o in states) + " |",
                  "|---|" + "---:|" * len(states)]
        for key, r in result["sets"].items():
            m = r["methods"]
            cells = []
            for n, _ in states:
                vals = [m[f"{p}_hybrid{n}"][metric] for p in priors]
                cell = " / ".join(fmt.format(v) for v in vals).replace("%", " %")
                if metric == "matrix_psnr":
                    cell += " (" + ", ".join(f"{v - vals[0]:+.2f}" for v in vals[1:]) + ")"
                cells.append(cell)
            lines.append(f"| {set_label(key)} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def run(root, out_md, *, count: int, search_count: int, sets: Sequence[str], seed: int = 0,
        weights_dir=None, two=None, three=None, echo=print,
        targets: Sequence[float] = ADAPTIVE_TARGETS, rig_scenes: Sequence[str] | None = None,
        rig_poses: Sequence[float] = RIG_POSES_DEG, size: int | None = None, only_models: bool = False) -> dict:
    """Generate the sets, search the states (unless ``two`` and ``three`` are given), evaluate,
    write ``out_md``, its ``.json`` and the accuracy-against-time plot (:func:`plot_trade`,
    ``.png``) when given.

    ``rig_scenes``: instead of ``sets``, the default rig's named scenes at ``size`` (default
    :func:`rig_size`), one sample per turntable angle of ``rig_poses`` (:func:`rig_set`), with
    the states ``two`` and ``three`` (default :data:`RIG_TWO`, :data:`RIG_THREE`: not searched).
    ``only_models``: only the lower-order model comparison at ``two`` (default :data:`RIG_TWO`,
    not searched; :func:`models_rows`, :func:`models_markdown`), no plot."""
    from polrig.acquisition.plan import ADAPTIVE_MIN_STATES
    from polrig.atomic import atomic_write_text
    from polrig.errors import ConfigError
    from polrig.models.evaluate import results_paths
    from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

    if count < 1 or search_count < 1:
        raise ConfigError(f"--count and --search-count must be >= 1, got {count} and {search_count}")
    unknown = [s for s in sets if s not in SETS]
    if unknown and rig_scenes is None:
        raise ConfigError(f"unknown set(s) {', '.join(unknown)}; sets are {', '.join(SETS)}")
    if rig_scenes is not None:
        from polrig.sim.scene import SCENES

        bad = [n for n in rig_scenes if n not in SCENES]
        if bad or not rig_scenes:
            raise ConfigError(f"--rig-scenes: unknown scene(s) {', '.join(bad) or '(none given)'}; scenes are "
                              f"{', '.join(SCENES)}")
        if not rig_poses:
            raise ConfigError("--rig-poses: give at least one turntable angle")
        size = rig_size() if size is None else int(size)
        if size < 8 or size % 8:
            raise ConfigError(f"--size must be a positive multiple of 8 (the networks' size multiple), got {size}")
        two, three = two or RIG_TWO, three or RIG_THREE
        sets = [f"rig_{n}" for n in rig_scenes]
    elif size is not None:
        raise ConfigError("--size goes with --rig-scenes (the held-out sets are 64x64)")
    if out_md is not None:
        out_md, out_json = results_paths(out_md)
    root = pathlib.Path(root)
    net = SingleShotModel.load(weights_dir if weights_dir is not None else WEIGHTS_DIR)
    if net.uncertainty is None:
        raise ConfigError("the single-shot graph has no calibrated uncertainty (models/weights/uncertainty.json)")
    # the prior the captures use: the calibration's joint prior where it holds one
    correlation = net.uncertainty.joint_correlation
    t0 = time.perf_counter()
    result: dict = {"count": count if rig_scenes is None else len(rig_poses), "size": size or SIZE, "seed": seed, "offsets_deg": list(OFFSETS_DEG),
                    "adaptive_targets": list(targets), "adaptive_min_states": ADAPTIVE_MIN_STATES,
                    "prior": "per element" if correlation is None else "joint"}
    if only_models:
        two, three = two or RIG_TWO, three or RIG_THREE
    if two is None or three is None:
        dirs = [make_set(root, name, kw, search_count if "all" in name else max(1, search_count // 2))
                for name, kw in SEARCH_SETS.items()]
        result["search"] = search_states(dirs, net, seed, echo, correlation)
        two = two or tuple(result["search"]["best_two"])
        three = three or tuple(result["search"]["best_three"])
    result["offsets"] = {"two": list(two), "three": list(three), "four": list(FOUR_STATES)}
    if rig_scenes is not None:
        result["rig"] = {"scenes": list(rig_scenes), "poses_deg": [float(p) for p in rig_poses]}
    result["sets"] = {}
    for tag, name in enumerate(sets):
        d = (make_set(root, name, SETS[name][1], count) if rig_scenes is None
             else rig_set(name[len("rig_"):], size, rig_poses, seed))
        r = evaluate_set(d, net, {k: tuple(v) for k, v in result["offsets"].items()}, seed, tag, targets,
                         only_models, correlation)
        result["sets"][name] = r
        m = r["methods"]
        if only_models:
            echo(f"{name}: {r['samples']} scored; PSNR where a model holds: single "
                 f"{m['holds_single']['psnr_holds']:.2f}, hybrid 2 {m['holds_hybrid2']['psnr_holds']:.2f}, "
                 f"+ models {m['hybrid2_models']['psnr_holds']:.2f}, + geometry "
                 f"{m.get('hybrid2_geometry', {}).get('psnr_holds', float('nan')):.2f}")
            continue
        echo(f"{name}: {r['samples']} scored; PSNR single {m['single']['matrix_psnr']:.2f}, hybrid 1-4 "
             + " / ".join(f"{m[f'hybrid{k}']['matrix_psnr']:.2f}" for k in range(1, 5))
             + f", reference 3/4 {m['reference3']['matrix_psnr']:.2f} / {m['reference4']['matrix_psnr']:.2f}; "
             + "coverage " + " / ".join(f"{100 * m[k]['coverage']:.1f}" for k in
                                         ("single", "hybrid1", "hybrid2", "hybrid3", "hybrid4")))
    result["seconds"] = time.perf_counter() - t0
    table = models_markdown(result) if only_models else markdown(result)
    echo(table)
    if out_md is not None and only_models:
        out_md.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        atomic_write_text(out_md, "# Lower-order models at two states\n\n`python -m polrig.models.continuum "
                          f"--models-only --count {count} --sets {','.join(sets)}` (models/continuum.py "
                          f"`models_rows`); {count} samples per set at {result['size']}x{result['size']} "
                          f"(those with a lit object pixel scored); {result['seconds']:.0f} s on "
                          f"{os.cpu_count()} CPUs; the hybrid's prior {_prior_words(result)}.\n\n" + table + "\n")
    elif out_md is not None:
        out_md.parent.mkdir(parents=True, exist_ok=True)
        atomic_write_text(out_json, json.dumps(result, indent=1) + "\n")
        plot_trade(result, out_md.with_suffix(".png"))
        n = result["size"]
        command = (f"--count {count} --search-count {search_count}" if rig_scenes is None else
                   f"--rig-scenes {','.join(rig_scenes)} --rig-poses {','.join(f'{p:g}' for p in rig_poses)} "
                   f"--size {n} --two {','.join(map(str, two))} --three {','.join(map(str, three))}")
        what = (f"{count} samples per set at {n}x{n}" if rig_scenes is None else
                f"the default simulated rig's scenes at {n}x{n}"
                + (" (the analyzer grid of its 512x512 colour sensor)" if n == rig_size() else "")
                + f", one sample per turntable angle {', '.join(f'{p:g}' for p in rig_poses)} deg "
                "(models/continuum.py `rig_set`)")
        atomic_write_text(out_md, "# From one state to four: single-shot, hybrid, reference\n\n"
                          f"`python -m polrig.models.continuum {command}"
                          f" --targets {','.join(f'{t:g}' for t in targets)}`"
                          " (models/continuum.py: sets, frames, metrics and variants in its docstring). "
                          f"{what} (those with a lit object pixel scored); "
                          f"{_search_line(result)}{result['seconds']:.0f} s on {os.cpu_count()} CPUs "
                          "(shipped network on onnxruntime, CPU); the hybrid's prior "
                          f"{_prior_words(result)}.\n\n" + table + "\n")
    return result


def _prior_words(result: dict) -> str:
    """How a run's hybrid rows used the network's prior (the captures' choice)."""
    if result.get("prior") == "joint":
        return ("jointly calibrated (the calibration's `joint_prior`, as captures use it; "
                "`--joint-compare` sets it against the per-element one)")
    return "per element (the calibration holds no joint prior)"


def set_label(key: str) -> str:
    """A set's row label: :data:`SETS`' label, or ``"<scene> (default rig)"`` for ``rig_<scene>``."""
    if key in SETS:
        return SETS[key][0]
    return f"{key[len('rig_'):]} (default rig)" if key.startswith("rig_") else key


def _search_line(result: dict) -> str:
    s = result.get("search")
    if not s:
        return "states given, not searched; "
    best = lambda part: sorted(s[part].items(), key=lambda kv: -kv[1])[:3]  # noqa: E731
    return ("states searched on " + f"{s['samples']} samples (PSNR over unclipped pixels; best 2-state sets "
            + ", ".join(f"{k} {v:.2f}" for k, v in best("two")) + " dB; best 3-state sets "
            + ", ".join(f"{k} {v:.2f}" for k, v in best("three")) + " dB); ")


#: The methods of the trade plot (:func:`trade_points`): result key, label, marker; then one
#: row per adaptive target (``adaptive_<t>``) in the result.
TRADE_METHODS = (("single", "single-shot", "o"), ("hybrid1", "hybrid 1", "v"), ("hybrid2", "hybrid 2", "s"),
                 ("hybrid3", "hybrid 3", "^"), ("hybrid4", "hybrid 4", "D"), ("reference3", "reference 3", "<"),
                 ("reference4", "reference 4", ">"), ("hybrid3_4frames", "hybrid 3 x 4 frames", "P"),
                 ("hybrid4_3frames", "hybrid 4 x 3 frames", "X"))
#: The trade plot's panels: result metric, axis label.
TRADE_METRICS = (("matrix_psnr", "matrix PSNR (dB), object pixels"), ("fwd_l2", "forward Stokes L2 (rel.)"))


def trade_methods(result: dict) -> list[tuple[str, str, str]]:
    """``(key, label, marker)`` of the methods :func:`trade_points` plots: those of
    :data:`TRADE_METHODS` every set of ``result`` holds, then its adaptive targets."""
    sets = list(result["sets"].values())
    have = lambda k: all(k in s["methods"] for s in sets)  # noqa: E731
    rows = [m for m in TRADE_METHODS if have(m[0])]
    adaptive_keys = sorted((k for k in (sets[0]["methods"] if sets else {}) if k.startswith("adaptive_") and have(k)),
                           key=lambda k: (adaptive_budget(k), -float(k.split("_")[1])))
    return rows + [(k, adaptive_label(k), m) for k, m in zip(adaptive_keys, "*hpd")]


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


def trade_points(result: dict) -> list[dict]:
    """The trade's points: one per set and method (:func:`trade_methods`) of a :func:`run`
    result (or its JSON), each ``{"set", "method", "label", "time_s", "states"}`` and the
    :data:`TRADE_METRICS` (time in seconds per pose, :func:`acquisition_time_s`).
    :class:`ValueError` when there is none (no set, or no trade method every set holds)."""
    if not trade_methods(result) or not result["sets"]:
        raise ValueError("no set holds the trade's methods (" + ", ".join(k for k, _, _ in TRADE_METHODS) + ")")
    out = []
    for name, r in result["sets"].items():
        for key, label, _ in trade_methods(result):
            m = r["methods"][key]
            out.append({"set": name, "method": key, "label": label, "time_s": float(m["time_s"]),
                        "states": float(m["states"])} | {k: float(m[k]) for k, _ in TRADE_METRICS})
    return out


def trade_figure(result: dict):
    """The accuracy-against-time figure of a :func:`run` result: one panel per
    :data:`TRADE_METRICS` against the acquisition time per pose (the L2 on a log axis); a small point per set
    (one colour per set) and method (one marker per method), and per method the median over the
    sets with its range (min..max, both axes). Returns ``(figure, points)`` (:func:`trade_points`)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.lines import Line2D

    points = trade_points(result)
    methods = trade_methods(result)
    sets = list(result["sets"])
    colours = {s: plt.get_cmap("tab10")(i % 10) for i, s in enumerate(sets)}
    fig, axes = plt.subplots(1, len(TRADE_METRICS), figsize=(12, 5.2), constrained_layout=True)
    for ax, (metric, title) in zip(np.atleast_1d(axes), TRADE_METRICS):
        for key, label, marker in methods:
            rows = [p for p in points if p["method"] == key]
            t = np.array([p["time_s"] for p in rows])
            y = np.array([p[metric] for p in rows])
            ax.scatter(t, y, s=14, marker=marker, c=[colours[p["set"]] for p in rows], alpha=0.8, linewidths=0)
            tm, ym = float(np.median(t)), float(np.median(y))
            ax.errorbar([tm], [ym], xerr=[[tm - t.min()], [t.max() - tm]], yerr=[[ym - y.min()], [y.max() - ym]],
                        fmt=marker, ms=8, mfc="none", mec="black", ecolor="0.35", elinewidth=0.8, capsize=2)
        ax.set_xlim(left=-0.3)
        ax.set_xlabel("acquisition time per pose (s, simulated rig)")
        ax.set_ylabel(title)
        ax.grid(True, which="both", alpha=0.3)
        ax.axvline(0.0, color="0.6", lw=0.5)
        if metric == "fwd_l2":
            ax.set_yscale("log")
    handles = [Line2D([], [], ls="none", marker=m, mfc="none", mec="black", ms=7, label=lab) for _, lab, m in methods]
    handles += [Line2D([], [], ls="none", marker="o", color=colours[s], ms=6, label=set_label(s)) for s in sets]
    fig.legend(handles=handles, loc="outside right center", fontsize=7, frameon=False)
    fig.suptitle(f"Speed against accuracy: {len(sets)} sets at {result.get('size', SIZE)}x{result.get('size', SIZE)}"
                 " (open black: median over the sets, bars: min..max)", fontsize=10)
    return fig, points


def plot_trade(result: dict, path) -> list[dict]:
    """Write :func:`trade_figure` of ``result`` to ``path`` (PNG); returns its points."""
    import io

    import matplotlib.pyplot as plt

    from polrig.atomic import atomic_write_bytes

    fig, points = trade_figure(result)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    plt.close(fig)
    atomic_write_bytes(pathlib.Path(path), buf.getvalue())
    return points


def plot_from_json(path) -> pathlib.Path:
    """Draw :func:`plot_trade` of a results JSON (:func:`run`'s) next to it as ``.png``; returns
    the PNG's path. :class:`polrig.errors.ConfigError` (one line naming the file) unless it is a
    readable results JSON."""
    from polrig.errors import ConfigError

    path = pathlib.Path(path)
    try:
        result = json.loads(path.read_text())
        trade_points(result)
    except FileNotFoundError:
        raise ConfigError(f"--plot-only {path}: no such file") from None
    except (OSError, UnicodeDecodeError, ValueError, KeyError, TypeError, AttributeError) as exc:
        raise ConfigError(f"--plot-only {path}: not a continuum results JSON ({type(exc).__name__}: {exc})") from None
    png = path.with_suffix(".png")
    plot_trade(result, png)
    return png


def _offsets(text: str | None, n: int) -> tuple[int, ...] | None:
    from polrig.errors import ConfigError

    if text is None:
        return None
    try:
        vals = tuple(int(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"give {n} comma-separated offsets in degrees, got {text!r}") from None
    if len(vals) != n or vals[0] != 0 or any(v not in OFFSETS_DEG for v in vals):
        raise ConfigError(f"give {n} offsets from {OFFSETS_DEG}, the first 0, got {text!r}")
    return vals


def main(argv: Sequence[str] | None = None) -> int:
    from polrig.models._cli import run_main

    ap = argparse.ArgumentParser(prog="python -m polrig.models.continuum", description=__doc__.split("\n\n")[0])
    ap.add_argument("--count", type=int, default=16, help="samples per held-out set (default 16)")
    ap.add_argument("--search-count", type=int, default=16,
                    help="samples of the state search's all-family set (half as many of its held-out families)")
    ap.add_argument("--sets", default=",".join(SETS), help=f"comma-separated, of: {', '.join(SETS)}")
    ap.add_argument("--root", default="runs/continuum", help="where the sets are generated (default runs/continuum)")
    ap.add_argument("--out", default=None, help="Markdown file for the tables (the numbers go next to it as .json)")
    ap.add_argument("--weights", default=None, help="weights folder (default: the shipped one)")
    ap.add_argument("--seed", type=int, default=0, help="noise seed of the rendered states' frames")
    ap.add_argument("--two", default=None, help="the 2-state offsets instead of searching, e.g. 0,90")
    ap.add_argument("--three", default=None, help="the 3-state offsets instead of searching, e.g. 0,60,120")
    ap.add_argument("--targets", default=",".join(f"{t:g}" for t in ADAPTIVE_TARGETS),
                    help="the adaptive capture's relative sigma targets, comma separated (default "
                         + ",".join(f"{t:g}" for t in ADAPTIVE_TARGETS) + ")")
    ap.add_argument("--rig-scenes", default=None, nargs="?", const=",".join(RIG_SCENES),
                    help="score the default rig's named scenes at its size instead of the held-out sets "
                         f"(default {','.join(RIG_SCENES)}; states --two/--three default "
                         f"{','.join(map(str, RIG_TWO))} and {','.join(map(str, RIG_THREE))}, not searched)")
    ap.add_argument("--rig-poses", default=",".join(f"{p:g}" for p in RIG_POSES_DEG),
                    help="turntable angles (deg) of --rig-scenes, one sample each (default "
                         + ",".join(f"{p:g}" for p in RIG_POSES_DEG) + ")")
    ap.add_argument("--size", type=int, default=None,
                    help="image side of --rig-scenes (default: the rig's analyzer grid, 128)")
    ap.add_argument("--models-only", action="store_true",
                    help="only the lower-order model comparison at two states (--two, default "
                         + ",".join(map(str, RIG_TWO)) + "): single-shot, hybrid 2, hybrid 2 + models")
    ap.add_argument("--plot-only", metavar="JSON", default=None,
                    help="only draw the accuracy-against-time plot of a results JSON (written next to it as .png)")
    ap.add_argument("--fit-highlights", action="store_true",
                    help="only fit the sigma factor at the highlights a bracket measured "
                         "(polrig.models.highlights.SIGMA_FACTOR) on the calibration scenes, --count samples")
    ap.add_argument("--joint-compare", action="store_true",
                    help="only the per-element prior against the joint one (uncertainty.json's joint_prior): the "
                         "two-state model test's false acceptance, coverage and PSNR at 1 to 4 states")
    args = ap.parse_args(argv)
    if args.joint_compare:
        return run_main(ap.prog, lambda: (joint_compare(args.root, args.out, count=args.count,
                                                        sets=[s for s in args.sets.split(",") if s], seed=args.seed,
                                                        weights_dir=args.weights, two=_offsets(args.two, 2),
                                                        three=_offsets(args.three, 3),
                                                        rig_scenes=None if args.rig_scenes is None else
                                                        [n for n in args.rig_scenes.split(",") if n],
                                                        rig_poses=_poses(args.rig_poses), size=args.size), 0)[1])
    if args.fit_highlights:
        from polrig.models.runtime import WEIGHTS_DIR, SingleShotModel

        return run_main(ap.prog, lambda: fit_highlight_factor(
            args.root, SingleShotModel.load(args.weights or WEIGHTS_DIR), count=args.count, seed=args.seed) and 0)
    if args.plot_only is not None:
        return run_main(ap.prog, lambda: print(plot_from_json(args.plot_only)) or 0)
    return run_main(ap.prog, lambda: (run(args.root, args.out, count=args.count, search_count=args.search_count,
                                          sets=[s for s in args.sets.split(",") if s], seed=args.seed,
                                          weights_dir=args.weights, two=_offsets(args.two, 2),
                                          three=_offsets(args.three, 3), targets=_targets(args.targets),
                                          rig_scenes=None if args.rig_scenes is None else
                                          [n for n in args.rig_scenes.split(",") if n],
                                          rig_poses=_poses(args.rig_poses), size=args.size,
                                          only_models=args.models_only), 0)[1])


def _poses(text: str) -> tuple[float, ...]:
    from polrig.errors import ConfigError

    try:
        return tuple(float(v) for v in text.split(",") if v.strip())
    except ValueError:
        raise ConfigError(f"--rig-poses: give turntable angles in degrees, comma separated, got {text!r}") from None


def _targets(text: str) -> tuple[float, ...]:
    from polrig.errors import ConfigError

    try:
        vals = tuple(float(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--targets: give relative sigmas in (0, 1], comma separated, got {text!r}") from None
    if not vals or not all(0 < v <= 1 for v in vals):
        raise ConfigError(f"--targets: give relative sigmas in (0, 1], comma separated, got {text!r}")
    return vals


if __name__ == "__main__":
    sys.exit(main())
