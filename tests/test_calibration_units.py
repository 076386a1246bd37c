"""Unit tests of the calibration math on synthetic data with known answers."""

from __future__ import annotations

import json
import struct

import cv2
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.calibration import calset, charuco, dofp, light, turntable
from polrig.calibration.errors import (
    BoardNotFound,
    SphereNotFound,
    SphereSaturated,
    TooFewAngles,
)
from polrig.calibration.generator import (
    GeneratorModel,
    check_stage_angles,
    dolp_from_extinction_ratio,
    extinction_ratio_from_dolp,
    fit_generator_from_angles,
)
from polrig.errors import ConfigError, FormatError
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.analyzer import AnalyzerModel, resolve_layout


# ------------------------------------------------------------------------------ generator
def test_generator_stokes_matches_mueller_polarizer():
    g = GeneratorModel(1.7, 800.0)
    th = np.array([0.0, 33.0, 90.0, 171.0])
    expect = polarizer_stokes(np.deg2rad(th + 1.7), 800.0, np.ones(4))
    np.testing.assert_allclose(g.incident_stokes(th), expect, atol=1e-15)
    s = g.incident_stokes(0.0)
    assert s[0] == pytest.approx(0.5 * (1 + 1 / 800))
    assert np.hypot(s[1], s[2]) / s[0] == pytest.approx(g.dolp)


@given(st.floats(1.0001, 1e9))
def test_extinction_ratio_dolp_round_trip(er):
    d = dolp_from_extinction_ratio(er)
    assert 0 < d < 1
    assert float(extinction_ratio_from_dolp(d)) == pytest.approx(er, rel=1e-6)


def test_extinction_ratio_extremes():
    assert float(dolp_from_extinction_ratio(np.inf)) == 1.0
    assert np.isinf(extinction_ratio_from_dolp(1.0))


def test_fit_generator_from_angles_recovers_offset_and_ratio():
    rng = np.random.default_rng(1)
    th = np.arange(0, 180, 5.0)
    off, er = -2.3, 500.0
    d = dolp_from_extinction_ratio(er)
    fang = 12.0
    aolp = (-(th + off) + fang) % 180 + rng.normal(0, 0.01, th.size)  # mirror flips handedness
    g = fit_generator_from_angles(th, aolp, np.full(th.size, d * 0.98), -1.0, fang, 0.98)
    assert g.zero_offset_deg == pytest.approx(off, abs=0.01)
    assert g.extinction_ratio == pytest.approx(er, rel=1e-6)
    assert 0 < g.zero_offset_std_deg < 0.01


@pytest.mark.parametrize("angles", [[0, 10, 20], list(range(0, 60, 5)), [0.0] * 20])
def test_too_few_or_clustered_stage_angles_are_rejected(angles):
    with pytest.raises(TooFewAngles, match="stage angles"):
        check_stage_angles(angles)


# ------------------------------------------------------------------------------ ChArUco
def test_board_spec_validation_names_the_problem():
    with pytest.raises(ConfigError, match="marker_m"):
        charuco.BoardSpec(5, 5, 0.02, 0.03)
    with pytest.raises(ConfigError, match="dictionary"):
        charuco.BoardSpec(dictionary="9X9_9")
    with pytest.raises(ConfigError, match="markers"):
        charuco.BoardSpec(12, 12, 0.02, 0.015, "4X4_50")


def test_board_png_prints_at_the_stated_dpi(tmp_path):
    spec = charuco.BoardSpec(5, 4, 0.03, 0.022)
    path = tmp_path / "board.png"
    w, h = charuco.write_board_png(spec, path, dpi=254.0, margin_m=0.0)
    data = path.read_bytes()
    i = data.index(b"pHYs")
    ppm_x, ppm_y, unit = struct.unpack(">IIB", data[i + 4:i + 13])
    assert unit == 1 and ppm_x == ppm_y == 10000  # 254 dpi = 10000 px/m
    assert (w, h) == (round(0.15 * 10000), round(0.12 * 10000))
    img = cv2.imread(str(path), cv2.IMREAD_GRAYSCALE)
    assert img.shape == (h, w)
    det = charuco.detect(spec, img)
    assert det.count == (5 - 1) * (4 - 1)


def _project_board(spec, K, R, t, size):
    """Render the board image into a camera by a homography (plane z = 0)."""
    pps = 40
    tex = spec.image(pps)
    s = spec.square_m / pps
    # texture pixel (col, row) centre -> board (x, y) = ((col + 0.5) s, (row + 0.5) s)
    A = np.array([[s, 0, 0.5 * s], [0, s, 0.5 * s], [0, 0, 1.0]])
    H = K @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
    return cv2.warpPerspective(tex, H, size, flags=cv2.INTER_AREA, borderValue=0)


def _pose(rx, ry, dist_m):
    R = cv2.Rodrigues(np.array([rx, ry, 0.0]))[0]
    return R, np.array([-0.1, -0.075, dist_m])


def test_detect_and_pose_on_a_warped_board():
    spec = charuco.BoardSpec(8, 6, 0.025, 0.018)
    K = np.array([[800.0, 0, 319.5], [0, 800.0, 239.5], [0, 0, 1]])
    R, t = _pose(0.3, -0.2, 0.6)
    img = _project_board(spec, K, R, t, (640, 480))
    det = charuco.detect(spec, img)
    assert det.count >= 30
    Rf, tf, rms = charuco.board_pose(det, K)
    assert rms < 0.3
    assert np.degrees(np.arccos((np.trace(Rf @ R.T) - 1) / 2)) < 0.3
    np.testing.assert_allclose(tf, t, atol=2e-3)


def test_intrinsics_from_warped_views():
    spec = charuco.BoardSpec(8, 6, 0.025, 0.018)
    K = np.array([[800.0, 0, 330.0], [0, 810.0, 235.0], [0, 0, 1]])
    dets = []
    for rx, ry in [(0.4, 0), (-0.4, 0.1), (0, 0.45), (0.1, -0.45), (0.3, 0.3), (-0.3, -0.3)]:
        R, t = _pose(rx, ry, 0.6)
        dets.append(charuco.detect(spec, _project_board(spec, K, R, t, (640, 480))))
    res = charuco.calibrate_intrinsics(dets, (640, 480), "none")
    assert res.fx == pytest.approx(800, rel=0.005)
    assert res.fy == pytest.approx(810, rel=0.005)
    assert res.rms_px < 0.3
    assert np.all(res.std_fx_fy_cx_cy > 0)


def test_blank_image_raises_board_not_found_with_advice():
    spec = charuco.BoardSpec()
    with pytest.raises(BoardNotFound, match="into view"):
        charuco.detect(spec, np.full((240, 320), 100, np.uint16))
    with pytest.raises(ValueError, match="3 board views"):
        charuco.calibrate_intrinsics([], (320, 240))


def test_intensity_image_removes_a_mosaic_gain_pattern():
    rng = np.random.default_rng(0)
    scene = cv2.GaussianBlur(rng.uniform(100, 1000, (64, 64)), (0, 0), 3)
    pattern = np.tile(np.array([[1.0, 0.7], [0.9, 1.2]]), (32, 32))
    out = charuco.intensity_image(scene * pattern, "imx250mzr")
    ref = cv2.sepFilter2D(scene, -1, np.array([.25, .5, .25]), np.array([.25, .5, .25]))
    ratio = (out / ref)[4:-4, 4:-4]
    assert ratio.std() / ratio.mean() < 0.01
    assert np.all(np.isfinite(charuco.intensity_image(np.full((8, 8), np.nan), "imx250mzr")))



@pytest.mark.parametrize("white_share", [0.05, 0.2, 0.45])
def test_class_levels_do_not_depend_on_how_much_of_the_frame_is_bright(white_share):
    """A board that fills the frame, mostly black squares and dark background, with its white
    squares ``white_share`` of the pixels: every class's level is its gain (to 1 %), however
    small the white share (the median over the brighter half once landed on the black
    squares for some classes and on the white for others: levels 6 times apart)."""
    rng = np.random.default_rng(3)
    gains = np.zeros((176, 176))
    for m in resolve_layout("imx250myr").masks(gains.shape).values():  # colour x analyzer
        gains[m] = rng.uniform(0.6, 1.4)
    scene = np.full((176, 176), 30.0)
    scene[8:168, 8:168] = 60.0  # the black squares, 10 x 10 of 16 pixels
    cells = rng.permutation([(r, c) for r in range(10) for c in range(10)])
    n_white = int(round(white_share * 176 * 176 / 256))
    for r, c in cells[:n_white]:
        scene[8 + 16 * r: 24 + 16 * r, 8 + 16 * c: 24 + 16 * c] = 2000.0
    frame = scene * gains + rng.normal(0.0, 2.0, scene.shape)
    levels = charuco.class_scales(frame, "imx250myr")
    ratio = levels / gains
    assert ratio.std() / ratio.mean() < 0.01
    flat = charuco.intensity_image(frame, "imx250myr")[scene == 2000.0]
    assert np.percentile(flat, 95) / np.percentile(flat, 5) < 1.6  # the white squares' edges blur


# ------------------------------------------------------------------------------ turntable
def _turntable_poses(axis, point, angles, R0, t0):
    Rs, ts = [], []
    for a in angles:
        Ra = turntable._axis_rotation(axis, a)
        Rs.append(Ra @ R0)
        ts.append(Ra @ (t0 - point) + point)
    return np.array(Rs), np.array(ts)


@settings(max_examples=20, deadline=None)
@given(st.floats(-1, 1), st.floats(-1, 1), st.floats(-0.5, 0.5))
def test_turntable_axis_from_exact_poses(ax, ay, az):
    axis = np.array([ax, -1.0, az + ay * 0.1])
    axis /= np.linalg.norm(axis)
    point = np.array([0.01, 0.02, 0.5])
    R0 = cv2.Rodrigues(np.array([0.3, -0.2, 0.1]))[0]
    t0 = np.array([-0.05, 0.02, 0.48])
    angles = np.arange(-40, 41, 10.0)
    Rs, ts = _turntable_poses(axis, point, angles, R0, t0)
    res = turntable.fit_turntable_axis(Rs, ts, angles)
    assert turntable.axis_angle_error_deg(res.axis_cam, axis) < 1e-6
    d = res.point_cam_m - point
    assert np.linalg.norm(d - (d @ axis) * axis) < 1e-9
    assert res.angle_scale == pytest.approx(1.0, abs=1e-9)


def test_turntable_needs_three_views_over_twenty_degrees():
    R = np.repeat(np.eye(3)[None], 3, 0)
    with pytest.raises(TooFewAngles, match="add turntable angles"):
        turntable.fit_turntable_axis(R, np.zeros((3, 3)), [0, 5, 10])


# ------------------------------------------------------------------------------ light
def _sphere_edge_rays(c, r, n=200):
    """Unit rays tangent to a sphere (centre c, radius r) seen from the origin."""
    cn = np.linalg.norm(c)
    ch = c / cn
    a = np.arcsin(r / cn)
    u = np.cross(ch, [0, 1.0, 0])
    u /= np.linalg.norm(u)
    v = np.cross(ch, u)
    phi = np.linspace(0, 2 * np.pi, n, endpoint=False)
    return (np.cos(a) * ch[None] + np.sin(a) * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v))


def test_sphere_centre_from_silhouette_rays_is_exact():
    c = np.array([0.07, -0.03, 0.52])
    got, rms = light.fit_sphere_centre(_sphere_edge_rays(c, 0.03), 0.03)
    np.testing.assert_allclose(got, c, atol=1e-12)
    assert rms < 1e-12


def test_light_from_reflected_rays_of_several_spheres():
    L = np.array([0.18, -0.08, 0.05])
    pts, dirs = [], []
    for c in ([0.07, 0.0, 0.5], [-0.05, 0.02, 0.55], [0.0, -0.04, 0.45], [0.03, 0.05, 0.6]):
        c = np.asarray(c)
        # mirror point: normal bisects directions to the camera (origin) and the light
        for _ in range(60):  # fixed-point iteration on the sphere
            p = c + 0.03 * n if _ else c - 0.03 * c / np.linalg.norm(c)
            wo, wi = -p / np.linalg.norm(p), (L - p) / np.linalg.norm(L - p)
            n = (wo + wi) / np.linalg.norm(wo + wi)
        ray = p / np.linalg.norm(p)
        hit, refl = light.reflected_ray(c, 0.03, ray)
        pts.append(hit)
        dirs.append(refl)
    x, cov, dist = light.intersect_rays(np.array(pts), np.array(dirs))
    np.testing.assert_allclose(x, L, atol=1e-6)
    assert np.all(dist < 1e-6)


def _sphere_image(shape=(120, 160), centre=(80.3, 60.7), radius=20.0, hl=(85.2, 55.4), peak=3000):
    h, w = shape
    vv, uu = np.mgrid[0:h, 0:w]
    img = np.full(shape, 2000.0) - 3 * vv  # lit backdrop with a gradient
    inside = (uu - centre[0]) ** 2 + (vv - centre[1]) ** 2 <= radius ** 2
    img[inside] = 20.0
    img += peak * np.exp(-((uu - hl[0]) ** 2 + (vv - hl[1]) ** 2) / (2 * 1.2 ** 2)) * inside
    return img


def test_find_sphere_edges_and_subpixel_highlight():
    ob = light.find_sphere(_sphere_image())
    np.testing.assert_allclose(ob.highlight_px, (85.2, 55.4), atol=0.05)
    r = np.hypot(ob.edge_px[:, 0] - 80.3, ob.edge_px[:, 1] - 60.7)
    assert abs(r.mean() - 20.0) < 0.3


def test_find_sphere_errors_name_the_fix():
    with pytest.raises(SphereSaturated, match="exposure"):
        light.find_sphere(np.minimum(_sphere_image(peak=9000), 4095), saturation_dn=4095)
    with pytest.raises(SphereNotFound, match="background"):
        light.find_sphere(np.full((60, 80), 500.0))
    with pytest.raises(TooFewAngles, match="positions"):
        light.fit_light_position([light.find_sphere(_sphere_image())], 0.03, np.eye(3))


# ------------------------------------------------------------------------------ DoFP fit
def test_per_pixel_rows_recovered_from_a_sweep():
    rng = np.random.default_rng(3)
    shape = (8, 12)
    truth = AnalyzerModel("imx250mzr", rng.normal(1, 0.02, shape),
                          AnalyzerModel.ideal("imx250mzr", shape).angle_deg + rng.normal(0, 1, shape),
                          rng.uniform(0.95, 1.0, shape), np.zeros(shape))
    th = np.arange(0, 180, 10.0)
    s_in = GeneratorModel(0.0, 300.0).incident_stokes(th)  # (K, 3)
    radiance = 1000.0 * (1 + 0.2 * np.linspace(0, 1, shape[1]))[None, :] * np.ones(shape)
    frames = np.einsum("hwi,ki->khw", truth.rows(), s_in) * radiance
    fit = dofp.fit_analyzer_rows(frames, s_in, min_signal_dn=1)
    assert fit.valid.all()
    np.testing.assert_allclose(fit.angle_deg, truth.angle_deg % 180, atol=1e-9)
    np.testing.assert_allclose(fit.modulation, truth.diattenuation, rtol=1e-9)
    np.testing.assert_allclose(fit.scale, truth.gain * radiance, rtol=1e-9)
    # states of an assumed ideal generator: the modulation is D times the generator DoLP
    fit2 = dofp.fit_analyzer_rows(frames, GeneratorModel(0.0, np.inf).incident_stokes(th),
                                  min_signal_dn=1)
    np.testing.assert_allclose(fit2.modulation,
                               truth.diattenuation * dolp_from_extinction_ratio(300), rtol=1e-9)
    np.testing.assert_allclose(fit2.angle_deg, truth.angle_deg % 180, atol=1e-9)


def test_dofp_fit_is_finite_on_dark_and_nonfinite_pixels():
    th = np.arange(0, 180, 20.0)
    s_in = GeneratorModel(0.0, np.inf).incident_stokes(th)
    frames = np.zeros((th.size, 4, 4))
    frames[:, 0, 0] = np.nan
    frames[:, 1, 1] = np.inf
    fit = dofp.fit_analyzer_rows(frames, s_in)
    assert not fit.valid.any()
    for f in (fit.angle_deg, fit.modulation, fit.scale, fit.angle_std_deg):
        assert np.all(np.isfinite(f))
    with pytest.raises(TooFewAngles):
        dofp.fit_analyzer_rows(frames[:3], s_in[:3])


def test_relative_gain_separates_pixel_gain_from_smooth_radiance():
    rng = np.random.default_rng(5)
    shape = (40, 48)
    g = rng.normal(1, 0.01, shape)
    vv, uu = np.mgrid[0:shape[0], 0:shape[1]]
    smooth = 500 * np.exp(-((uu - 20) ** 2 + (vv - 25) ** 2) / 2000.0)
    est = dofp.relative_gain(g * smooth, np.ones(shape, bool), "imx250mzr")
    err = est / g - 1
    assert np.sqrt(np.mean(err ** 2)) < 0.002


# ------------------------------------------------------------------------------ files
def _small_set():
    shape = (4, 8)
    cs = calset.CalibrationSet()
    cs.params["intrinsics"] = {"K": np.eye(3).tolist(), "dist": [0.0] * 5,
                               "std_fx_fy_cx_cy_px": [0.1] * 4}
    cs.params["generator"] = {"zero_offset_deg": 1.5, "zero_offset_std_deg": 0.01,
                              "extinction_ratio": float("inf"), "extinction_ratio_std": 0.0,
                              "stage_zero_axis_cam": [1.0, 0.0, 0.0]}
    cs.analyzer = AnalyzerModel.ideal("imx250myr", shape)
    cs.dofp_maps = {"valid": np.ones(shape, bool)}
    return cs


def test_calibration_set_round_trip_and_id(tmp_path):
    cs = _small_set()
    cid = cs.save(tmp_path)
    assert len(cid) == 16
    back = calset.load(tmp_path)
    assert back.id == cid
    np.testing.assert_allclose(back.incident_stokes([0, 45]), GeneratorModel(1.5, np.inf).incident_stokes([0, 45]))
    assert back.analyzer_model.layout == "imx250myr"
    np.testing.assert_array_equal(back.intrinsics["K"], np.eye(3))
    doc = json.loads((tmp_path / "calibration.json").read_text())
    assert doc["generator"]["extinction_ratio"] == "inf"
    cs.params["generator"]["zero_offset_deg"] = 1.6
    assert cs.compute_id() != cid
    with pytest.raises(Exception, match="run 'polrig calibrate light'"):
        back.light_position_m


def test_edited_calibration_set_is_rejected(tmp_path):
    _small_set().save(tmp_path)
    p = tmp_path / "calibration.json"
    p.write_text(p.read_text().replace('"zero_offset_deg": 1.5', '"zero_offset_deg": 1.0'))
    with pytest.raises(FormatError, match="does not match its id"):
        calset.load(tmp_path)
    with pytest.raises(FileNotFoundError, match="calibrate all"):
        calset.load(tmp_path / "nothing")


@settings(max_examples=25, deadline=None)
@given(st.floats(-90, 90), st.floats(0.5, 1.0), st.floats(0.5, 1.5), st.floats(1.5, 1e6))
def test_rows_recovered_for_any_analyzer_and_generator(angle, dia, gain, er):
    """Property: an exact sweep gives back any analyzer row (orientation, diattenuation from
    0.5 to 1, gain) whatever the generator's extinction ratio (with its states known)."""
    th = np.arange(0, 180, 15.0)
    s_in = GeneratorModel(3.0, er).incident_stokes(th)
    t = np.deg2rad(2 * angle)
    row = 0.5 * gain * np.array([1, dia * np.cos(t), dia * np.sin(t)])
    frames = (s_in @ row * 800.0)[:, None, None]
    fit = dofp.fit_analyzer_rows(frames, s_in)
    assert fit.valid.all()
    assert ((fit.angle_deg[0, 0] - angle + 90) % 180 - 90) == pytest.approx(0, abs=1e-7)
    assert fit.modulation[0, 0] == pytest.approx(dia, rel=1e-9)
    assert fit.scale[0, 0] == pytest.approx(800 * gain, rel=1e-9)


def test_find_sphere_tolerates_nonfinite_pixels():
    img = _sphere_image()
    img[0:5, 0:5] = np.nan
    img[100, 3] = np.inf
    ob = light.find_sphere(img)
    assert np.all(np.isfinite(ob.edge_px)) and np.all(np.isfinite(ob.highlight_px))
    np.testing.assert_allclose(ob.highlight_px, (85.2, 55.4), atol=0.1)


def test_simulated_board_is_the_calibration_default_board():
    from polrig.calibration.runner import Options
    from polrig.sim import targets

    spec = Options().board
    o = targets.DEFAULTS
    assert (spec.squares_x, spec.squares_y, spec.square_m, spec.marker_m, spec.dictionary) == \
        (o["squares_x"], o["squares_y"], o["square_m"], o["marker_m"], o["dictionary"])
    np.testing.assert_array_equal(
        targets.board_image(o["squares_x"], o["squares_y"], o["square_m"], o["marker_m"],
                            o["dictionary"], 32), spec.image(32))


def test_the_light_fit_keeps_the_views_it_is_given():
    """A view whose silhouette fits badly (merged with a shadow) is left out of the fit, and the
    views kept are recorded; a fit told the views (the uncertainty's fits at perturbed
    intrinsics) uses exactly those, so a view at the margin cannot come and go between the fit
    and its perturbations (at 256x256 one did, and the light's sigma read 0.23 m)."""
    K = np.array([[400.0, 0, 80], [0, 400.0, 60], [0, 0, 1]])
    clean = [_sphere_image(centre=(60 + 12 * k, 50 + 5 * k), hl=(64 + 12 * k, 46 + 5 * k)) for k in range(4)]
    bad = _sphere_image(centre=(80.3, 60.7), hl=(85.2, 55.4))
    bad[60:75, 80:120] = 20.0  # a shadow merged with the outline
    obs = [light.find_sphere(im) for im in (*clean, bad)]
    fit = light.fit_light_position(obs, 0.03, K)
    assert fit.views == (0, 1, 2, 3) and len(fit.spheres) == 4
    every = light.fit_light_position(obs, 0.03, K, views=(0, 1, 2, 3, 4))
    assert every.views == (0, 1, 2, 3, 4) and len(every.spheres) == 5
    assert light.fit_light_position(obs, 0.03, K * 1.01 + np.diag([0, 0, -0.01]), views=fit.views).views == fit.views


def test_the_light_covariance_holds_the_sphere_models_systematic():
    """The covariance is the rays' scatter plus the sphere model's own systematic, a Type B
    term of :data:`~polrig.calibration.light.MODEL_SYSTEMATIC_REL` of the light's distance
    from the mean sphere centre on each axis: rays that meet exactly (no scatter) still leave
    it, which the scatter alone reported as zero. On the simulated rig at 320x240 the
    scatter alone left the error's Mahalanobis distance squared at 4.5-21.7 over 8 turntable
    placements (its thin directions 0.2-0.45 mm against errors of 0.6-1.3 mm there); with
    the term, 0.5-9.6 over 8 others (docs/calibration.md)."""
    K = np.array([[400.0, 0, 80], [0, 400.0, 60], [0, 0, 1]])
    L = np.array([0.18, -0.07, 0.05])
    obs = []
    for c in ([0.02, 0.0, 0.45], [-0.03, 0.02, 0.5], [0.0, -0.03, 0.55], [0.03, 0.03, 0.48]):
        c = np.asarray(c)
        hit = c - 0.03 * c / np.linalg.norm(c)
        for _ in range(200):  # the specular point: its normal halves the way to L and to the camera
            n = (L - hit) / np.linalg.norm(L - hit) - hit / np.linalg.norm(hit)
            hit = c + 0.03 * n / np.linalg.norm(n)
        uv = (K @ (hit / hit[2]))[:2]
        obs.append(light.SphereObservation(_silhouette_px(c, 0.03, K), uv, 0.01, 1000.0))
    fit = light.fit_light_position(obs, 0.03, K)
    np.testing.assert_allclose(fit.position_cam_m, L, atol=2e-5)
    x, scatter, _ = light.intersect_rays(np.array([f.hit_cam_m for f in fit.spheres]),
                                        np.array([f.reflected_dir for f in fit.spheres]))
    distance = np.linalg.norm(x - np.mean([f.centre_cam_m for f in fit.spheres], axis=0))
    np.testing.assert_allclose(fit.covariance_m2 - scatter,
                               (light.MODEL_SYSTEMATIC_REL * distance) ** 2 * np.eye(3), atol=1e-15)
    assert np.all(fit.std_m >= light.MODEL_SYSTEMATIC_REL * distance)


def _silhouette_px(centre: np.ndarray, radius_m: float, K: np.ndarray, n: int = 96) -> np.ndarray:
    """Pixel points of a sphere's exact silhouette (the cone from the camera at the origin
    tangent to it), ``(n, 2)``."""
    c = np.asarray(centre, float)
    d = c / np.linalg.norm(c)
    sin_a = radius_m / np.linalg.norm(c)
    cos_a = np.sqrt(1 - sin_a ** 2)
    e1 = np.cross(d, [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(d, e1)
    t = np.linspace(0, 2 * np.pi, n, endpoint=False)
    rays = cos_a * d[None] + sin_a * (np.cos(t)[:, None] * e1 + np.sin(t)[:, None] * e2)
    return (rays @ K.T)[:, :2] / (rays @ K.T)[:, 2:]


def _light_fit(sigmas_m, distance_m=0.5185, seed=3) -> light.LightFit:
    """A light fit whose covariance has the 1-sigma ``sigmas_m`` along random principal
    directions, ``distance_m`` from the mean of four sphere centres."""
    rng = np.random.default_rng(seed)
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    cov = q @ np.diag(np.square(sigmas_m)) @ q.T
    centres = np.array([[0.05, 0.0, 0.48], [-0.05, 0.0, 0.52], [0.0, 0.04, 0.5], [0.0, -0.04, 0.5]])
    mid = centres.mean(axis=0)
    pos = mid + distance_m * np.array([0.6, -0.48, -0.64])
    spheres = tuple(light.SphereFit(c, 0.03, 0.0, c, np.array([0.0, 0.0, -1.0])) for c in centres)
    return light.LightFit(pos, cov, np.zeros(4), spheres, (0, 1, 2, 3))


def test_the_light_fit_says_whether_its_uncertainty_assures_the_acceptance(tmp_path):
    """The acceptance is the light within 1 % of its distance; at 256x256 the light was 1.0-1.6 %
    off (seeds 0-6, before the board corners were mended) while nothing said so, although its
    reported uncertainty (1 sigma 3.9 mm along its least certain direction, 2 sigma 1.5 % of
    0.52 m) did not allow 1 %. The
    uncertainty along the least certain direction (not the per-axis std) is what counts."""
    from polrig.calibration.report import write_report

    wide = _light_fit([0.0005, 0.0008, 0.00385]).acceptance()
    assert wide["two_sigma_m"] == pytest.approx(0.0077)
    assert wide["distance_m"] == pytest.approx(0.5185)
    assert wide["two_sigma_rel"] == pytest.approx(0.0077 / 0.5185)
    assert wide["limit_rel"] == light.ACCEPTANCE_REL == 0.01 and not wide["assured"]
    narrow = _light_fit([0.0004, 0.0008, 0.002]).acceptance()  # the 320x240 rig's
    assert narrow["assured"] and narrow["two_sigma_rel"] == pytest.approx(0.004 / 0.5185)
    cs = calset.CalibrationSet()
    cs.params["light"] = _light_fit([0.0005, 0.0008, 0.00385]).to_json()
    assert cs.params["light"]["acceptance"] == wide
    cs.save(tmp_path)
    assert calset.load(tmp_path).params["light"]["acceptance"] == wide
    report = write_report(tmp_path, cs).read_text()
    assert ("- acceptance (1 % of the 0.518 m from the light to the sphere positions): **not "
            "assured** by the uncertainty (2 sigma along its least certain direction: 7.7 mm, "
            "1.49 %)") in report
