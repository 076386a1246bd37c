"""One sample's frames: truth, the network's prior and a frame per polarizer state.

Part of :mod:`polrig.models.continuum` (its docstring says what is measured and how)."""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from polrig.models.continuum.sets import OFFSETS_DEG


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


def measured_highlights(fr: Frames, uncertainty):
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
    to the highlights the bracket measured (:func:`measured_highlights`, their sigma times
    :data:`polrig.models.highlights.SIGMA_FACTOR`), as the capture's single-shot route does
    (:meth:`polrig.app.single_shot.SingleShot.state`)."""
    from polrig.models.highlights import highlight_sigma

    mean, sigma, rescaled = measured_highlights(fr, uncertainty)
    if sigma is None:
        return fr
    sigma = highlight_sigma(fr.sigma, sigma, rescaled)
    return dataclasses.replace(fr, prior=np.where(fr.mask, mean, 0.0), sigma=np.where(fr.mask, sigma, 0.0))


def stack_states(fr: Frames, offsets: Sequence[int]):
    """The states ``(N, 3)`` and their frames' samples, variances and valid flags ``(N, C, 4, H,
    W)`` at ``offsets``, stacked in that order (the solves' inputs)."""
    return (np.stack([fr.states[d] for d in offsets]), np.stack([fr.meas[d] for d in offsets]),
            np.stack([fr.var[d] for d in offsets]), np.stack([fr.valid[d] for d in offsets]))


def lit_pixels(fr: Frames) -> np.ndarray:
    """``(C, H, W)``: the seen frame not clipped and its ``S0`` at least
    :data:`polrig.solve.reference.MIN_SNR` of its noise sigma (the adaptive capture's object
    pixels per colour)."""
    from polrig.solve.reference import MIN_SNR

    s0 = fr.meas[0].sum(axis=1) / 2.0
    return fr.use & (s0 >= MIN_SNR * np.sqrt(fr.var[0].sum(axis=1) / 4.0))


def set_samples(data, net):
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
