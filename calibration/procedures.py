"""Guided calibration procedures that drive a rig through its HAL devices.

Each procedure takes a rig-like object with ``camera``, ``stage``, ``turntable`` and ``light``
(:mod:`polrig.acquisition.hal` devices, as :func:`polrig.app.rig.open_rig` returns them) and a ``mount``
callback ``mount(target_name, **fixture)`` that asks the operator to put a calibration target
in place (on the simulated rig it swaps the simulated target, :func:`polrig.sim.targets.mount`).
Targets: ``"charuco"`` (board in the turntable fixture, with ``tilt_deg``/``roll_deg``),
``"mirror_plate"`` (polished metal plate in the same fixture), ``"chrome_sphere"`` (chrome
ball of known radius off the turntable axis in front of a white backdrop). Procedures never
look at simulator internals.

Order (each step uses the previous ones): :func:`run_intrinsics` -> :func:`run_turntable` ->
:func:`run_light` -> :func:`run_generator_offset` -> :func:`run_dofp`. Geometry is in the
camera frame (``docs/conventions.md``).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable

import numpy as np

from polrig.acquisition import hal
from polrig.calibration import charuco, dofp, light, rigframes, turntable
from polrig.calibration.errors import (
    BoardNotFound,
    CalibrationError,
    SceneTooDark,
    SphereNotFound,
    SphereSaturated,
    TooFewAngles,
)
from polrig.calibration.generator import (
    GeneratorModel,
    check_stage_angles,
    extinction_ratio_from_dolp,
    wrap_deg,
)
from polrig.calibration.mirror import (
    DEFAULT_MIRROR_METAL,
    DEFAULT_SPHERE_METAL,
    MirrorMetal,
    mirror_mueller,
)
from polrig.sensor.analyzer import AnalyzerModel, layout_name_at, resolve_layout

Mount = Callable[..., None]
Log = Callable[[str], None]

#: Design value of the mean micro-polarizer diattenuation of the IMX250MZR/MYR-class sensor
#: the simulator models. The DoFP light path only measures the product of a pixel's
#: diattenuation and the generator's DoLP, so the generator's extinction ratio is referred to
#: this value; set the camera's own (datasheet / bench measurement) with
#: ``sensor_diattenuation``.
DEFAULT_SENSOR_DIATTENUATION = 0.985

#: Board mounts of the geometric calibration; the first two are also the fixture poses of the
#: DoFP plate (:func:`run_dofp`) and of the grazing-light board (:func:`run_generator_offset`),
#: whose poses then come from the joint bundle adjustment over all their views.
INTRINSIC_MOUNTS: tuple[dict[str, float], ...] = (
    {"tilt_deg": 20.0}, {"tilt_deg": 35.0}, {"tilt_deg": 55.0}, {"tilt_deg": 40.0, "roll_deg": 40.0},
    {"tilt_deg": 40.0, "roll_deg": -40.0}, {"tilt_deg": 60.0, "roll_deg": 20.0})
DOFP_MOUNT_INDEX = 0
OFFSET_MOUNT_INDEX = 0
INTRINSIC_ANGLES_DEG = tuple(float(a) for a in range(-45, 46, 9))
LIGHT_ANGLES_DEG = tuple(float(a) for a in range(0, 360, 30))
#: Two sphere heights on the turntable, for a vertical as well as a horizontal baseline.
LIGHT_MOUNTS: tuple[dict[str, float], ...] = ({"sphere_height_m": 0.01}, {"sphere_height_m": 0.10})
STAGE_ANGLES_DEG = tuple(float(a) for a in range(0, 180, 5))


def _noop(*_a, **_k) -> None:
    return None


# --------------------------------------------------------------------------- capture helpers
def _full_scale(meta) -> float:
    return float((1 << int(meta.bit_depth)) - 1)


def grab_mean(camera, n: int = 1) -> tuple[np.ndarray, Any]:
    """Mean of ``n`` raw frames (float64, black level still in) and the last frame's meta."""
    acc = None
    meta = None
    for _ in range(max(1, int(n))):
        f = camera.grab()
        acc = f.raw.astype(np.float64) if acc is None else acc + f.raw
        meta = f.meta
    return acc / max(1, int(n)), meta


#: Longest exposure the procedures set (us): half the grab timeout of the HAL
#: (:data:`polrig.acquisition.hal.DEFAULT_TIMEOUT_S`, which every ``camera.grab()`` here uses), so that a
#: frame always arrives before the grab gives up. A scene still too dark there is reported
#: (:class:`polrig.calibration.errors.SceneTooDark`) instead of timing out.
MAX_EXPOSURE_US = 0.5 * hal.DEFAULT_TIMEOUT_S * 1e6
#: :func:`auto_expose` gives up (:class:`SceneTooDark`) when, at :data:`MAX_EXPOSURE_US`, the
#: measured level is below this fraction of its target.
TOO_DARK_FRACTION = 0.25


def exposure_range_us(camera) -> tuple[float, float]:
    """``(shortest, longest)`` exposure the procedures use on ``camera``: its declared range
    (:attr:`polrig.acquisition.hal.CameraCapabilities.exposure_range_us`), the longest capped at
    :data:`MAX_EXPOSURE_US`."""
    lo, hi = camera.capabilities.exposure_range_us
    return float(lo), min(float(hi), MAX_EXPOSURE_US)


def auto_expose(camera, *, percentile: float = 99.5, target: float = 0.6,
                mask: np.ndarray | None = None, iterations: int = 12) -> float:
    """Set the exposure so that the ``percentile`` of the (masked) black-subtracted raw frame
    is ``target`` of the full scale; returns the exposure in microseconds.

    Raises :class:`SceneTooDark` when the longest usable exposure
    (:func:`exposure_range_us`) still leaves the level below :data:`TOO_DARK_FRACTION` of
    the target (light off or far too dim)."""
    lo, hi = exposure_range_us(camera)
    if camera.exposure_us > hi:
        camera.set_exposure_us(hi)
    for _ in range(iterations):
        f = camera.grab()
        full = _full_scale(f.meta) - f.meta.black_level_dn
        a = f.raw.astype(np.float64) - f.meta.black_level_dn
        v = float(np.percentile(a[mask] if mask is not None else a, percentile))
        if v >= 0.98 * full:  # saturated: shorten a lot and retry
            new = camera.exposure_us / 10.0
        elif v <= 0:
            new = camera.exposure_us * 8.0
        else:
            new = camera.exposure_us * target * full / v
            if abs(new / camera.exposure_us - 1.0) < 0.1:
                return camera.exposure_us
        if new > hi and camera.exposure_us >= hi:  # no longer exposure left to try
            if v < TOO_DARK_FRACTION * target * full:
                raise SceneTooDark(
                    f"scene too dark at the longest usable exposure {hi:g} us (the "
                    f"{percentile:g}th percentile reaches {100 * max(v, 0.0) / full:.1f} % of "
                    f"full scale, {100 * target:.0f} % wanted); is the light on?")
            return camera.exposure_us
        camera.set_exposure_us(float(np.clip(new, lo, hi)))
    return camera.exposure_us


def _layout(camera) -> str:
    w, h, ox, oy = camera.roi
    return layout_name_at(camera.layout, ox, oy)


def _move(dev, angle_deg: float) -> None:
    dev.move_to(float(angle_deg), wait=True, timeout_s=120.0)


def _board_image(camera, n: int = 1) -> np.ndarray:
    raw, meta = grab_mean(camera, n)
    return charuco.intensity_image(raw, _layout(camera), meta.black_level_dn)


# --------------------------------------------------------------------------- intrinsics
@dataclasses.dataclass
class IntrinsicsRun:
    """Zhang intrinsics and the board views ``(mount index, turntable angle, detection)``."""

    result: charuco.IntrinsicsResult
    views: list
    skipped: list[str]


def fixture_words(fixture: dict[str, Any]) -> str:
    """A target's fixture position in words: ``{"distance_m": 0.3, "tilt_deg": 10}`` ->
    ``"distance 0.3 m, tilt 10 deg"`` (units from the key's suffix), not a Python dict."""
    out = []
    for key, value in fixture.items():
        name, unit = key, ""
        for suffix, u in (("_deg", "deg"), ("_mm", "mm"), ("_m", "m"), ("_us", "us")):
            if key.endswith(suffix):
                name, unit = key[: -len(suffix)], u
                break
        if isinstance(value, (list, tuple)):
            value = ", ".join(f"{v:g}" if isinstance(v, float) else str(v) for v in value)
        elif isinstance(value, float):
            value = f"{value:g}"
        out.append(f"{name.replace('_', ' ')} {value}" + (f" {unit}" if unit else ""))
    return ", ".join(out)


def capture_board_views(rig, mount: Mount, spec: charuco.BoardSpec, mounts, angles_deg,
                        log: Log = _noop) -> tuple[list, list[str]]:
    """Board views over fixture mounts and turntable angles; views where the board is not
    found are skipped and listed."""
    views, skipped = [], []
    cam = rig.camera
    for i, m in enumerate(mounts):
        mount("charuco", **m)
        log(f"board mounted: {fixture_words(m) or 'default position'}")
        _move(rig.turntable, 0.0)
        auto_expose(cam, percentile=99.0, target=0.7)
        for a in angles_deg:
            _move(rig.turntable, a)
            try:
                views.append((i, float(a), charuco.detect(spec, _board_image(cam))))
            except BoardNotFound as exc:
                skipped.append(f"{fixture_words(m) or 'default position'} at {a:g} deg: {exc}")
    return views, skipped


def run_intrinsics(rig, mount: Mount, spec: charuco.BoardSpec, *,
                   mounts=INTRINSIC_MOUNTS, angles_deg=INTRINSIC_ANGLES_DEG,
                   distortion: str = "k1", log: Log = _noop) -> IntrinsicsRun:
    """Board at several fixture tilts/rolls and turntable angles -> pinhole intrinsics
    (Zhang's method; :func:`run_turntable` refines them together with the turntable axis)."""
    views, skipped = capture_board_views(rig, mount, spec, mounts, angles_deg, log)
    w, h = rig.camera.roi[:2]
    res = charuco.calibrate_intrinsics([d for _, _, d in views], (w, h), distortion)
    log(f"intrinsics (Zhang): {len(views)} views, fx={res.fx:.2f}±{res.std_fx_fy_cx_cy[0]:.2f} "
        f"px, fy={res.fy:.2f}±{res.std_fx_fy_cx_cy[1]:.2f} px, cx={res.K[0, 2]:.2f}, "
        f"cy={res.K[1, 2]:.2f}, reprojection RMS {res.rms_px:.3f} px")
    return IntrinsicsRun(res, views, skipped)


# --------------------------------------------------------------------------- turntable
def run_turntable(rig, mount: Mount, spec: charuco.BoardSpec, intrinsics: IntrinsicsRun | None,
                  K: np.ndarray | None = None, dist: np.ndarray | None = None, *,
                  mounts=INTRINSIC_MOUNTS, angles_deg=INTRINSIC_ANGLES_DEG,
                  distortion: bool | int = True, log: Log = _noop) -> turntable.JointRigResult:
    """Turntable axis (and refined intrinsics) from board views at several turntable angles
    and fixture mounts: a linear axis estimate from one mount's PnP poses, then the joint
    bundle adjustment :func:`polrig.calibration.turntable.refine_rig`. Reuses the views of
    ``intrinsics`` when given, otherwise captures them (with ``K``, ``dist`` as the start)."""
    if intrinsics is not None:
        views = intrinsics.views
        K, dist = intrinsics.result.K, intrinsics.result.dist
    else:
        if K is None:
            raise CalibrationError("turntable calibration needs intrinsics: run 'intrinsics' "
                                   "first or pass a calibration set that has them")
        views, _ = capture_board_views(rig, mount, spec, mounts, angles_deg, log)
    counts = {}
    for m, _, _ in views:
        counts[m] = counts.get(m, 0) + 1
    if not counts:
        raise TooFewAngles("no board views: bring the board into view")
    m_best = max(counts, key=counts.get)
    Rs, ts, angs = [], [], []
    for m, a, d in views:
        if m != m_best:
            continue
        R, t, _ = charuco.board_pose(d, K, dist)
        Rs.append(R)
        ts.append(t)
        angs.append(a)
    lin = turntable.fit_turntable_axis(np.array(Rs), np.array(ts), np.array(angs))
    res = turntable.refine_rig(views, K, dist, lin.axis_cam, lin.point_cam_m,
                               fit_distortion=distortion)
    ax = dataclasses.replace(res.axis, angle_scale=lin.angle_scale,
                             zero_angle_deg=lin.zero_angle_deg,
                             angle_residuals_deg=lin.angle_residuals_deg,
                             circle_residual_rms_m=lin.circle_residual_rms_m)
    res = dataclasses.replace(res, axis=ax)
    sf = res.std_fx_fy_cx_cy
    log(f"turntable: {len(views)} views, axis {np.round(ax.axis_cam, 5).tolist()} ± "
        f"{ax.axis_std_deg:.3f} deg, point {np.round(ax.point_cam_m, 4).tolist()} m; refined "
        f"fx={res.K[0, 0]:.2f}±{sf[0]:.2f}, fy={res.K[1, 1]:.2f}±{sf[1]:.2f}, "
        f"cx={res.K[0, 2]:.2f}±{sf[2]:.2f}, cy={res.K[1, 2]:.2f}±{sf[3]:.2f} px, "
        f"RMS {res.rms_px:.3f} px")
    return res


# --------------------------------------------------------------------------- light
def highlight_scales(scales: np.ndarray, layout, metal: MirrorMetal) -> np.ndarray:
    """Class levels ``(H, W)`` for a metal ball's highlight: the white backdrop's
    (:func:`polrig.calibration.charuco.class_scales` of the silhouette frame) times, on a colour
    sensor, the metal's normal-incidence reflectance of each pixel's colour
    (:meth:`polrig.calibration.mirror.MirrorMetal.reflectance_rgb`), so that the highlight of a
    coloured metal is grey after division (:func:`run_light`). ``layout``: the readout's
    layout (name or :class:`polrig.sensor.layouts.MosaicLayout`)."""
    mosaic = resolve_layout(layout)
    if not mosaic.is_colour:
        return scales
    return scales * metal.reflectance_rgb()[mosaic.colour_map(np.shape(scales))]


def run_light(rig, mount: Mount, K: np.ndarray, dist: np.ndarray, radius_m: float, *,
              angles_deg=LIGHT_ANGLES_DEG, mounts=LIGHT_MOUNTS,
              intrinsics_std_px: np.ndarray | None = None,
              dist_std: np.ndarray | None = None, sphere_metal: MirrorMetal | None = None,
              log: Log = _noop) -> light.LightFit:
    """Chrome sphere on the turntable at several angles -> light position (camera frame).

    The ball is a real metal (``sphere_metal``, default
    :data:`polrig.calibration.mirror.DEFAULT_SPHERE_METAL`), not grey: on a colour sensor its
    highlight's colour classes are divided by the metal's normal-incidence reflectance per
    colour on top of the white backdrop's class levels. Otherwise the colour quadrants of
    the mosaic cell differ by several percent inside a highlight of a few pixels (chrome: 64,
    67, 70 % for R, G, B), a fixed pattern that pulls the centroid towards the brighter
    colour (on the simulated rig about 1 mm of bias in the light's depth at 0.5 m; the
    highlight is too small to measure its colour from the data, which scatters by +-40 %).
    The backdrop is taken as grey (white).

    The sphere is mounted at each of ``mounts`` (heights) in turn. Per angle: a long exposure (background at mid scale) for the silhouette and a short one
    (highlight below saturation) for the highlight, each the sum of stage angles 0 and 90 deg
    so that the light is unpolarized and the mosaic does not bias the centroid. A ``light:
    warning:`` line says when the fit's uncertainty does not assure the acceptance
    (:meth:`polrig.calibration.light.LightFit.acceptance`)."""
    cam = rig.camera
    lay = _layout(cam)
    metal = MirrorMetal.named(DEFAULT_SPHERE_METAL) if sphere_metal is None else sphere_metal
    obs = []
    for m, a in [(m, a) for m in mounts for a in angles_deg]:
        if a == angles_deg[0]:
            mount("chrome_sphere", **m)
        _move(rig.turntable, a)
        frames = {}
        for name, (pct, tgt) in {"silhouette": (50.0, 0.5), "highlight": (100.0, 0.6)}.items():
            _move(rig.stage, 0.0)
            auto_expose(cam, percentile=pct, target=tgt)
            for _ in range(6):
                _move(rig.stage, 0.0)
                r0, meta = grab_mean(cam)
                _move(rig.stage, 90.0)
                r90, _ = grab_mean(cam)
                peak = max(float(r0.max()), float(r90.max()))
                full = _full_scale(meta)
                # a highlight of a few pixels is polarized: the pixel class crossed at 0 deg
                # can be the brightest at 90 deg, far above the level set at 0 deg
                if name == "silhouette" or peak < 0.9 * full:
                    break
                lo = exposure_range_us(cam)[0]
                if cam.exposure_us <= lo:
                    break
                cam.set_exposure_us(max(lo, cam.exposure_us * 0.5 * full / peak
                                        if peak < 0.98 * full else cam.exposure_us / 10.0))
            frames[name] = (r0 + r90 - 2 * meta.black_level_dn, meta, peak)
        sil, meta, _ = frames["silhouette"]
        hil, hmeta, peak = frames["highlight"]
        if peak >= 0.98 * _full_scale(hmeta):
            raise SphereSaturated(f"sphere highlight saturated even at {cam.exposure_us:g} us "
                                  f"exposure; lower the light level or use a smaller sphere")
        scales = charuco.class_scales(sil, lay)
        hl_scales = highlight_scales(scales, lay, metal)
        try:
            ob = light.find_sphere(charuco.intensity_image(sil, lay, scales=scales),
                                   highlight_image=charuco.intensity_image(hil, lay,
                                                                           scales=hl_scales),
                                   edge_image=sil / scales)
        except SphereNotFound as exc:
            log(f"light: sphere at {fixture_words(m) or 'default position'}, turntable "
                f"{a:g} deg, skipped: {exc}")
            continue
        obs.append(ob)
    fit = light.fit_light_position(obs, radius_m, K, dist)
    if intrinsics_std_px is not None or dist_std is not None:
        # add the intrinsics' uncertainty (fx, fy, cx, cy, distortion), propagated by finite
        # differences (parameters taken as independent)
        cov = fit.covariance_m2.copy()
        dist0 = np.zeros(5) if dist is None else np.asarray(dist, float).reshape(-1)
        perturb = []
        if intrinsics_std_px is not None:
            for (i, j), sd in zip(((0, 0), (1, 1), (0, 2), (1, 2)),
                                  np.asarray(intrinsics_std_px, float)[:4]):
                dk = np.zeros((3, 3))
                dk[i, j] = sd
                perturb.append((dk, np.zeros_like(dist0)))
        if dist_std is not None:
            for i, sd in enumerate(np.asarray(dist_std, float)[:dist0.size]):
                if sd > 0:
                    dd = np.zeros_like(dist0)
                    dd[i] = sd
                    perturb.append((np.zeros((3, 3)), dd))
        for dk, dd in perturb:
            d = 0.5 * (light.fit_light_position(obs, radius_m, K + dk, dist0 + dd, fit.views).position_cam_m
                       - light.fit_light_position(obs, radius_m, K - dk, dist0 - dd, fit.views).position_cam_m)
            cov += np.outer(d, d)
        fit = dataclasses.replace(fit, covariance_m2=cov)
    dist_m = np.linalg.norm(fit.position_cam_m)
    log(f"light: {len(obs)} sphere views, position {np.round(fit.position_cam_m, 4).tolist()} m "
        f"(camera frame) ± {np.round(fit.std_m * 1000, 2).tolist()} mm, distance {dist_m:.4f} m")
    acc = fit.acceptance()
    if not acc["assured"]:
        log(f"light: warning: the {100 * acc['limit_rel']:g} % acceptance is not assured: 2 sigma "
            f"along the least certain direction is {1000 * acc['two_sigma_m']:.1f} mm, "
            f"{100 * acc['two_sigma_rel']:.2f} % of the {acc['distance_m']:.3f} m from the light "
            f"to the sphere positions (intrinsics and sphere views set it: a larger image or "
            f"more board and sphere views narrow it)")
    return fit


# --------------------------------------------------------------------------- generator offset
@dataclasses.dataclass
class OffsetRun:
    zero_offset_deg: float
    zero_offset_std_deg: float
    turntable_deg: float
    incidence_deg: float
    pixels: int
    per_pixel_deg: np.ndarray  # (N,) offsets of the pixels used
    modulation: np.ndarray  # (N,) measured relative modulation
    stage_zero_axis_cam: np.ndarray
    zero_offset_std_bound_deg: float = 0.0


def harmonic_fit(stage_angles_deg: np.ndarray, frames: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per-pixel ``I = A + B cos 2 theta + C sin 2 theta`` over frames ``(K, ...)``: returns
    ``(A, B, C)``."""
    th = np.deg2rad(np.asarray(stage_angles_deg, float)) * 2
    X = np.stack([np.ones_like(th), np.cos(th), np.sin(th)], axis=1)
    coef = np.linalg.pinv(X) @ frames.reshape(len(th), -1)
    return tuple(c.reshape(frames.shape[1:]) for c in coef)


def _choose_angle(n0, p0, axis, point, light_cam, want_incidence_deg, max_view_deg=60.0,
                  candidates=np.arange(-90.0, 90.1, 2.5)):
    best, best_err = None, np.inf
    for a in candidates:
        Ra = turntable._axis_rotation(axis, a)
        n = Ra @ n0
        p = Ra @ (p0 - point) + point
        wi = light_cam - p
        wi /= np.linalg.norm(wi)
        wo = -p / np.linalg.norm(p)
        ci, co = n @ wi, n @ wo
        if ci <= 0 or co <= np.cos(np.deg2rad(max_view_deg)):
            continue
        err = abs(np.degrees(np.arccos(ci)) - want_incidence_deg)
        if err < best_err:
            best, best_err = a, err
    if best is None:
        raise CalibrationError("no turntable angle shows the board to both the light and the "
                               "camera; check the light position and the board fixture")
    return float(best)


def run_generator_offset(rig, mount: Mount, spec: charuco.BoardSpec,
                         geometry: turntable.JointRigResult, light_cam_m: np.ndarray, *,
                         stage_angles_deg=STAGE_ANGLES_DEG, incidence_deg: float = 85.0,
                         max_view_deg: float = 75.0, frames_per_angle: int = 2,
                         mounts=INTRINSIC_MOUNTS, mount_index: int = OFFSET_MOUNT_INDEX,
                         light_cov_m2: np.ndarray | None = None,
                         log: Log = _noop) -> OffsetRun:
    """Stage zero offset from the polarization-dependent Fresnel transmission into the matte
    board lit at grazing incidence.

    The diffuse light leaving a matte dielectric is depolarized inside it, so every sensor
    pixel reads ``c_p (a + b S1_sp(theta))`` with ``a, b`` the Fresnel transmission of the
    incident light (``b = (Ts - Tp) / 2 < 0``) and ``S1_sp`` the incident Stokes ``S1`` in the
    s/p basis of the plane of incidence: ``d cos 2 (theta + offset - psi_s)``. The phase of the
    ``cos 2 theta`` response is therefore ``psi_s - offset + 90 deg``, independent of the
    analyzer, gain or colour of the pixel; ``psi_s`` (the s direction in the incident frame)
    follows from the board pose, the light position and the stage zero axis. The board pose
    is the fixture pose of the joint bundle adjustment (``geometry``, mount ``mount_index``)
    turned to the chosen turntable angle: one PnP pose has a normal error of about 0.1 deg,
    which would go straight into the offset. The uncertainty combines the scatter of the
    per-pixel offsets with the propagated uncertainty of the light position
    (``light_cov_m2``); ``zero_offset_std_bound_deg`` adds the turntable axis and board normal
    uncertainties as if independent (an upper bound). References: Baek et al., "Simultaneous
    acquisition of polarimetric SVBRDF and normals", ACM TOG 37(6), 2018 (diffuse term
    ``T_out D T_in``); Collett 2005 (Fresnel transmission Mueller matrix).
    """
    th = check_stage_angles(stage_angles_deg)
    K, dist, axis = geometry.K, geometry.dist, geometry.axis
    if mount_index >= len(geometry.mount_poses):
        raise CalibrationError(f"the geometric calibration has no pose for board mount "
                               f"{mount_index}; run 'turntable' with the default mounts")
    mount("charuco", **mounts[mount_index])
    cam = rig.camera
    R0, t0 = geometry.pose_at(mount_index, 0.0)
    p0, n0 = rigframes.board_plane(R0, t0)
    a_sel = _choose_angle(n0, p0, axis.axis_cam, axis.point_cam_m, light_cam_m, incidence_deg,
                          max_view_deg)
    _move(rig.turntable, a_sel)
    _move(rig.stage, 0.0)
    auto_expose(cam, percentile=99.0, target=0.35)
    R, t = geometry.pose_at(mount_index, a_sel)
    pb, nb = rigframes.board_plane(R, t)
    frames = []
    for a in th:
        _move(rig.stage, a)
        raw, meta = grab_mean(cam, frames_per_angle)
        frames.append(raw - meta.black_level_dn)
    frames = np.array(frames)
    full = _full_scale(meta) - meta.black_level_dn
    A, B, C = harmonic_fit(th, frames)
    h, w = A.shape
    rays = rigframes.pixel_rays_grid(K, dist, (h, w))
    P = rigframes.intersect_plane(rays, pb, nb)
    # pixels on the white print of the board, 1 mm or more from any black (board model)
    pb_board = np.einsum("ji,hwj->hwi", R, P - t)  # board coordinates R^T (P - t)
    pps = 64
    tex = spec.image(pps)
    margin = max(1, int(round(0.001 / spec.square_m * pps)))
    from cv2 import erode

    tex_w = erode(tex, np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)) > 127
    col = np.floor(np.nan_to_num(pb_board[..., 0], nan=-1.0) / spec.square_m * pps).astype(int)
    row = np.floor(np.nan_to_num(pb_board[..., 1], nan=-1.0) / spec.square_m * pps).astype(int)
    inside = (col >= 0) & (row >= 0) & (col < tex.shape[1]) & (row < tex.shape[0])
    bright = np.zeros_like(inside)
    bright[inside] = tex_w[row[inside], col[inside]]
    sat = (frames.max(axis=0) >= 0.98 * full)
    use = inside & bright & ~sat & np.isfinite(P).all(-1) & (A > 0)  # A: mean signal, the modulation's divisor
    if use.sum() < 50:
        raise CalibrationError(f"only {int(use.sum())} usable board pixels at grazing light; "
                               "raise the light level or exposure")
    Pu = P[use]
    phase = np.rad2deg(0.5 * np.arctan2(C[use], B[use]))
    amp = np.hypot(B[use], C[use])
    wgt = amp ** 2 / np.sum(amp ** 2)

    def offsets(light_m, axis_dir, normal):
        wi = light_m - Pu
        wi = wi / np.linalg.norm(wi, axis=1, keepdims=True)
        zero = rigframes.stage_zero_axis_cam(light_m, axis.point_cam_m, axis_dir)
        s_dir = np.cross(-wi, normal)
        s_dir /= np.linalg.norm(s_dir, axis=1, keepdims=True)
        psi_s = rigframes.incident_basis_angle_deg(wi, zero, s_dir)
        o_px = wrap_deg(psi_s - phase + 90.0, 180.0)
        z = np.sum(wgt * np.exp(2j * np.deg2rad(o_px)))
        return float(np.rad2deg(np.angle(z)) / 2), o_px, zero, wi

    off, off_px, zero, wi = offsets(light_cam_m, axis.axis_cam, nb)
    res = wrap_deg(off_px - off, 180.0)
    n_eff = 1.0 / np.sum(wgt ** 2)
    var = float(np.sum(wgt * res ** 2) / max(n_eff - 1, 1))
    # propagate the geometric uncertainties (light position covariance, turntable axis and
    # board normal directions) by finite differences
    if light_cov_m2 is not None:
        cov = np.asarray(light_cov_m2, float)
        J = np.empty(3)
        for i in range(3):
            h = np.zeros(3)
            h[i] = 1e-4
            J[i] = (offsets(light_cam_m + h, axis.axis_cam, nb)[0]
                    - offsets(light_cam_m - h, axis.axis_cam, nb)[0]) / 2e-4
        var += float(J @ cov @ J)
    std = float(np.sqrt(var))
    # axis and board-normal uncertainties, propagated as if independent: an upper bound, since
    # both come from one bundle adjustment and a common error (e.g. of the principal point)
    # turns axis, board and light together without changing their relation
    normal_std = (geometry.mount_rotation_std_deg[mount_index]
                  if len(geometry.mount_rotation_std_deg) > mount_index else axis.axis_std_deg)
    var_geo = 0.0
    for vec, sd_deg, which in ((axis.axis_cam, axis.axis_std_deg, "axis"),
                               (nb, normal_std, "normal")):
        u1, u2 = turntable._perp_basis(vec)
        for u in (u1, u2):
            d = vec + np.deg2rad(sd_deg) / np.sqrt(2) * u
            d = d / np.linalg.norm(d)
            o2 = offsets(light_cam_m, d, nb)[0] if which == "axis" else \
                offsets(light_cam_m, axis.axis_cam, d)[0]
            var_geo += wrap_deg(o2 - off, 180.0) ** 2
    std_bound = float(np.sqrt(var + var_geo))
    inc = float(np.degrees(np.arccos(np.clip(np.median(np.sum(wi * nb, axis=1)), -1, 1))))
    log(f"generator offset: {off:.3f} ± {std:.3f} deg (pixels and light position; ± "
        f"{std_bound:.3f} deg bound with the axis and board pose) from {int(use.sum())} board "
        f"pixels at turntable {a_sel:.1f} deg, light incidence {inc:.1f} deg")
    return OffsetRun(off, std, a_sel, inc, int(use.sum()), off_px, amp / A[use], zero, std_bound)


# --------------------------------------------------------------------------- DoFP analyzer
@dataclasses.dataclass
class DofpRun:
    analyzer: AnalyzerModel
    fit: dofp.DofpFit
    generator: GeneratorModel
    dark_dn: np.ndarray
    flat_scale: np.ndarray
    turntable_deg: float
    exposure_us: float
    #: angle of incidence on the plate's microfacets at the plate centre (deg): half the angle
    #: between the directions to the light and to the camera; the metal's departure from an
    #: ideal mirror grows as its square (:mod:`polrig.calibration.mirror`)
    mirror_incidence_deg: float = 0.0


def mirror_states(K, dist, shape, plane_point, plane_normal, light_cam_m, zero_axis,
                  generator: GeneratorModel, stage_angles_deg, alpha: float = 0.3,
                  metal: MirrorMetal | None = None,
                  channel: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Relative Stokes ``(K, 3, H, W)`` reaching each pixel from the rough metal plate: the
    plate's Mueller matrix (:func:`polrig.calibration.mirror.mirror_mueller`: complex-index Fresnel
    reflection of ``metal``, default :data:`polrig.calibration.mirror.DEFAULT_MIRROR_METAL`, with its
    diattenuation and retardance) in the rig frames, normalised by ``m00``, times the
    generator's incident states; and the modelled relative radiance ``(H, W)``
    (``m00 / r^2``) of each pixel. ``channel`` ``(H, W)``: each pixel's colour channel
    (``None``: mono sensor)."""
    metal = MirrorMetal.named(DEFAULT_MIRROR_METAL) if metal is None else metal
    h, w = shape
    rays = rigframes.pixel_rays_grid(K, dist, shape).reshape(-1, 3)
    P = rigframes.intersect_plane(rays, plane_point, plane_normal)
    ok = np.isfinite(P).all(-1)
    P = np.where(ok[:, None], P, rays)
    wi = light_cam_m - P
    wi /= np.linalg.norm(wi, axis=1, keepdims=True)
    m, m00 = mirror_mueller(plane_normal, wi, -rays, metal, alpha=alpha,
                            stage_zero_axis=zero_axis, camera_x_axis=np.array([1.0, 0.0, 0.0]),
                            channel=None if channel is None else np.asarray(channel).reshape(-1))
    good = ok & (m00 > 0)
    m = np.where(good[:, None, None], m, np.nan)
    s_in = generator.incident_stokes(np.asarray(stage_angles_deg, float))  # (K, 3)
    st = np.einsum("pij,kj->kip", m, s_in)
    # modelled radiance factor (mirror m00 times inverse-square falloff), for the flat field
    r2 = np.sum((light_cam_m - P) ** 2, axis=1)
    radiance = np.where(good, m00 / r2, np.nan).reshape(h, w)
    return st.reshape(len(s_in), 3, h, w), radiance


def run_dofp(rig, mount: Mount, geometry: turntable.JointRigResult, light_cam_m: np.ndarray,
             zero_offset_deg: float, *, stage_angles_deg=STAGE_ANGLES_DEG,
             frames_per_angle: int = 6, sensor_diattenuation: float = DEFAULT_SENSOR_DIATTENUATION,
             mounts=INTRINSIC_MOUNTS, mount_index: int = DOFP_MOUNT_INDEX, dark_frames: int = 8,
             mirror: MirrorMetal | None = None, log: Log = _noop) -> DofpRun:
    """Per-pixel analyzer calibration from the polished plate under the rotating polarizer.

    The plate sits in the board fixture; its pose is the board pose of the same fixture from
    the joint bundle adjustment (``geometry``, mount ``mount_index``), turned to the
    turntable angle that centres the specular lobe. A dark frame (light off) gives the
    offsets; the stage
    sweep, with the generator's offset and the plate's Mueller matrix in the rig frames (the
    metal ``mirror``, default :data:`polrig.calibration.mirror.DEFAULT_MIRROR_METAL`: its
    diattenuation and retardance at each pixel's angle of incidence,
    :mod:`polrig.calibration.mirror`), gives each pixel's analyzer row (:mod:`polrig.calibration.dofp`).
    The fitted modulation is the pixel's diattenuation times the generator DoLP; the
    generator's extinction ratio follows from the mean modulation and
    ``sensor_diattenuation`` (see :data:`DEFAULT_SENSOR_DIATTENUATION`)."""
    th = check_stage_angles(stage_angles_deg)
    mirror = MirrorMetal.named(DEFAULT_MIRROR_METAL) if mirror is None else mirror
    K, dist, axis = geometry.K, geometry.dist, geometry.axis
    if mount_index >= len(geometry.mount_poses):
        raise CalibrationError(f"the geometric calibration has no pose for board mount "
                               f"{mount_index}; run 'turntable' with the default mounts")
    fixture = dict(mounts[mount_index])
    cam = rig.camera
    R0, t0 = geometry.pose_at(mount_index, 0.0)
    p0, n0 = rigframes.board_plane(R0, t0)
    # turn the plate so that its normal bisects the directions to the light and the camera
    best, best_c = 0.0, -2.0
    for a in np.arange(-45.0, 45.1, 1.0):
        Rm, tm = geometry.pose_at(mount_index, a)
        pm, nm = rigframes.board_plane(Rm, tm)
        bis = (light_cam_m - pm) / np.linalg.norm(light_cam_m - pm) - pm / np.linalg.norm(pm)
        c = nm @ (bis / np.linalg.norm(bis))
        if c > best_c:
            best, best_c = float(a), c
    _move(rig.turntable, best)
    R, t = geometry.pose_at(mount_index, best)
    pb, nb = rigframes.board_plane(R, t)
    to_light = (light_cam_m - pb) / np.linalg.norm(light_cam_m - pb)
    incidence = 0.5 * float(np.degrees(np.arccos(np.clip(to_light @ (-pb / np.linalg.norm(pb)),
                                                         -1.0, 1.0))))
    mount("mirror_plate", **fixture)
    _move(rig.stage, 0.0)
    auto_expose(cam, percentile=99.0, target=0.75)
    rig.light.set_on(False)
    dark, meta = grab_mean(cam, dark_frames)
    rig.light.set_on(True)
    frames = []
    for a in th:
        _move(rig.stage, a)
        raw, meta = grab_mean(cam, frames_per_angle)
        frames.append(raw - dark)
    frames = np.array(frames)
    full = _full_scale(meta)
    sat = (np.max(frames + dark, axis=0) >= 0.98 * full)
    zero = rigframes.stage_zero_axis_cam(light_cam_m, axis.point_cam_m, axis.axis_cam)
    lay = resolve_layout(_layout(cam))
    channel = lay.colour_map(frames.shape[1:]) if lay.is_colour else None
    states, radiance = mirror_states(K, dist, frames.shape[1:], pb, nb, light_cam_m, zero,
                                     GeneratorModel(zero_offset_deg, np.inf), th,
                                     metal=mirror, channel=channel)
    states = np.where(np.isfinite(states), states, 0.0)
    fit = dofp.fit_analyzer_rows(frames, states)
    # flat field: divide the fitted scale by the modelled radiance first, so the smooth fit
    # only has to absorb what the model misses (light falloff errors, exposure)
    fit = dataclasses.replace(fit, scale=np.where(np.isfinite(radiance) & (radiance > 0),
                                                  fit.scale / np.where(radiance > 0, radiance, 1),
                                                  fit.scale),
                              valid=fit.valid & np.isfinite(radiance))
    if sat.any():
        fit = dataclasses.replace(fit, valid=fit.valid & ~sat)
    if fit.valid.mean() < 0.5:
        raise CalibrationError(f"only {fit.valid.mean():.0%} of the pixels give a valid DoFP fit; "
                               "the polished plate must fill the view (check the fixture)")
    mod = float(np.mean(fit.modulation[fit.valid]))
    d_gen = min(mod / float(sensor_diattenuation), 1.0 - 1e-9)
    mod_std = float(np.std(fit.modulation[fit.valid]) / np.sqrt(fit.valid.sum()))
    er = float(extinction_ratio_from_dolp(d_gen))
    er_std = float(2.0 / (1.0 - d_gen) ** 2 * mod_std / sensor_diattenuation)
    offset_dn = dark - meta.black_level_dn
    model = dofp.analyzer_model_from_fit(fit, _layout(cam), d_gen, offset_dn)
    gen = GeneratorModel(zero_offset_deg, er, 0.0, er_std)
    log(f"dofp: {int(fit.valid.sum())} pixels, median angle std "
        f"{np.median(fit.angle_std_deg[fit.valid]):.3f} deg, generator DoLP {d_gen:.5f} "
        f"(extinction ratio {er:.0f} ± {er_std:.0f}, referred to sensor D={sensor_diattenuation}; "
        f"{mirror.name} mirror at {incidence:.1f} deg incidence)")
    return DofpRun(model, fit, gen, dark, fit.scale, best, cam.exposure_us, incidence)
