"""ROI statistics and line profiles (issue 34, item 4): masks from geometry with the stated
pixel-centre convention, statistics against closed forms (uniform images, known circular means
of synthetic axial angles incl. the wrap at 0/180, NaN and masked pixels, the standard errors'
coverage), profiles (bilinear, axial interpolation), CSV, and ``polrig stats``."""

from __future__ import annotations

import csv
import io
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.app import roi
from polrig.errors import ConfigError
from polrig.optics import mueller as mu


def row(rows, name, ch=None):
    hits = [r for r in rows if r.quantity == name and (ch is None or r.channel == ch)]
    assert len(hits) == 1, (name, ch, hits)
    return hits[0]


def assert_csv_rows_equal(got: list[dict], want) -> None:
    """The CSV rows ``got`` (``csv.DictReader``) state exactly the statistics ``want``, row by row."""
    for g, r in zip(got, want):
        assert (g["quantity"], g["channel"], int(g["n_counted"]), int(g["n_masked"])) == (
            r.quantity, r.channel, r.n_counted, r.n_masked)
        for k in ("mean", "std", "sem_scatter", "sem_sigma"):
            v = getattr(r, k)
            assert float(g[k]) == v or (math.isnan(v) and g[k] == "nan")


# -- masks --------------------------------------------------------------------------------------
def test_rect_mask_is_the_pixels_whose_centre_is_inside():
    m = roi.roi_mask(roi.RectROI(2, 3, 4, 2), (8, 10))
    expect = np.zeros((8, 10), bool)
    expect[3:5, 2:6] = True
    np.testing.assert_array_equal(m, expect)
    # a fractional corner: centres with 2.6 <= x < 6.6 -> columns 3..6 (centres 3.5 .. 6.5)
    m = roi.roi_mask(roi.RectROI(2.6, 0, 4, 1), (1, 10))
    np.testing.assert_array_equal(np.flatnonzero(m[0]), [3, 4, 5, 6])


def test_ellipse_mask_matches_the_closed_form_and_its_area():
    e = roi.EllipseROI(50, 40, 30, 12)
    m = roi.roi_mask(e, (80, 100))
    v, u = np.mgrid[:80, :100] + 0.5
    np.testing.assert_array_equal(m, ((u - 50) / 30) ** 2 + ((v - 40) / 12) ** 2 <= 1)
    assert abs(m.sum() - math.pi * 30 * 12) < 0.02 * math.pi * 30 * 12


def test_polygon_mask_square_triangle_and_concave():
    sq = roi.roi_mask(roi.PolygonROI(((1, 1), (5, 1), (5, 4), (1, 4))), (6, 7))
    np.testing.assert_array_equal(sq, roi.roi_mask(roi.RectROI(1, 1, 4, 3), (6, 7)))
    tri = roi.roi_mask(roi.PolygonROI(((0, 0), (100, 0), (0, 100))), (100, 100))
    assert abs(tri.sum() - 5000) <= 100  # half the square, up to the diagonal's pixels
    v, u = np.mgrid[:100, :100] + 0.5
    np.testing.assert_array_equal(tri, u + v < 100)  # no centre lies on the hypotenuse
    # concave "U": the notch is outside
    u_shape = roi.PolygonROI(((0, 0), (9, 0), (9, 9), (6, 9), (6, 3), (3, 3), (3, 9), (0, 9)))
    m = roi.roi_mask(u_shape, (9, 9))
    assert m[1, 4] and m[8, 1] and m[8, 7] and not m[5, 4]
    assert m.sum() == 81 - 18


@pytest.mark.parametrize("text, expect", [
    ("rect:1,2,3,4", roi.RectROI(1, 2, 3, 4)),
    ("ellipse:10.5,2,3,1e1", roi.EllipseROI(10.5, 2, 3, 10)),
    ("poly:0,0,4,0,0,4", roi.PolygonROI(((0, 0), (4, 0), (0, 4)))),
])
def test_parse_roi(text, expect):
    assert roi.parse_roi(text) == expect
    assert roi.parse_roi(expect.text()) == expect


@pytest.mark.parametrize("text", ["rect:1,2,3", "circle:1,2,3", "rect:1,2,0,4", "poly:0,0,1,1",
                                  "rect:a,b,c,d", "rect", "ellipse:1,2,-3,4"])
def test_parse_roi_refuses_with_one_line_naming_the_option(text):
    with pytest.raises(ConfigError, match="--roi") as e:
        roi.parse_roi(text)
    assert "\n" not in str(e.value)


# -- statistics: closed forms -------------------------------------------------------------------
def uniform_mueller(m3: np.ndarray, h=12, w=16, c=1) -> np.ndarray:
    return np.broadcast_to(np.asarray(m3, np.float32)[None, :, :, None, None],
                           (c, 3, 3, h, w)).copy()


def test_uniform_retarder_image_gives_its_closed_forms_and_the_counts():
    d, q = np.deg2rad(60.0), np.deg2rad(20.0)
    m3 = 800.0 * mu.linear_block(mu.retarder_at(q, d))
    img = uniform_mueller(m3, c=3)
    sigma = np.full(img.shape, 2.0, np.float32)
    valid = np.ones((3, 12, 16), bool)
    valid[1, 5, 5] = False  # one masked pixel in green
    inside = roi.roi_mask(roi.RectROI(2, 2, 10, 8), (12, 16))
    rows = roi.roi_statistics(inside, mueller=img, sigma=sigma, valid=valid)
    r = row(rows, "S0", "R")
    assert r.mean == pytest.approx(800.0, rel=1e-6) and r.std == pytest.approx(0.0, abs=1e-3)
    assert (r.n_counted, r.n_masked) == (80, 0)
    assert row(rows, "S0", "G").n_counted == 79 and row(rows, "S0", "G").n_masked == 1
    # sem from the pixels' sigma: sigma / sqrt(n) for independent equal sigmas
    assert r.sem_sigma == pytest.approx(2.0 / math.sqrt(80), rel=1e-5)
    n = m3 / m3[0, 0]
    for i in range(3):
        for j in range(3):
            if i or j:
                assert row(rows, f"m{i}{j}/m00", "B").mean == pytest.approx(n[i, j], abs=1e-6)
    assert row(rows, "retardance_deg", "R").mean == pytest.approx(60.0, abs=1e-3)
    assert row(rows, "retardance_axis_deg", "R").mean == pytest.approx(20.0, abs=1e-3)
    assert row(rows, "retardance_axis_deg", "R").kind == "axial/90"
    assert row(rows, "DoLP", "R").mean == pytest.approx(0.0, abs=1e-6)
    assert {r.quantity for r in rows} >= {"S0", "DoLP", "AoLP_deg", "DL", "mmt_A", "depolarization"}


def test_polarizer_image_dolp_aolp_are_the_polarizance():
    m3 = 500.0 * mu.linear_block(mu.polarizer_at(np.deg2rad(170.0)))
    rows = roi.roi_statistics(np.ones((12, 16), bool), mueller=uniform_mueller(m3))
    assert row(rows, "DoLP").mean == pytest.approx(1.0, abs=1e-6)
    assert row(rows, "AoLP_deg").mean == pytest.approx(170.0, abs=1e-4)
    assert row(rows, "AoLP_deg").kind == "axial/180"
    assert math.isnan(row(rows, "S0").sem_sigma)  # no sigma planes given


def test_stokes_statistics_linear_closed_forms_and_nan_pixels():
    rng = np.random.default_rng(1)
    h, w = 20, 30
    s0 = rng.uniform(100, 200, (h, w))
    a = np.deg2rad(30.0)
    stokes = np.stack([s0, 0.4 * s0 * np.cos(2 * a), 0.4 * s0 * np.sin(2 * a)])[None].astype(np.float32)
    stokes[0, :, 10, 15] = np.nan  # a NaN pixel is masked, never a NaN mean
    inside = roi.roi_mask(roi.EllipseROI(15, 10, 8, 6), (h, w))
    rows = roi.roi_statistics(inside, stokes=stokes)
    r = row(rows, "S0")
    ref = s0[inside & ~((np.arange(h)[:, None] == 10) & (np.arange(w) == 15))]
    assert r.n_counted == ref.size and r.n_masked == inside.sum() - ref.size
    assert r.mean == pytest.approx(ref.astype(np.float32).mean(), rel=1e-6)
    assert r.std == pytest.approx(ref.astype(np.float32).std(ddof=1), rel=1e-5)
    assert r.sem_scatter == pytest.approx(r.std / math.sqrt(ref.size))
    assert row(rows, "DoLP").mean == pytest.approx(0.4, abs=1e-5)
    assert r.n_masked == 1
    assert row(rows, "AoLP_deg").mean == pytest.approx(30.0, abs=0.01)  # cv2.phase: < 0.01 deg
    assert row(rows, "AoLP_deg").std == pytest.approx(0.0, abs=0.05)
    # S0's sigma from the signal-to-noise: sigma = S0 / snr
    snr = np.full((1, h, w), 50.0)
    r = row(roi.roi_statistics(inside, stokes=stokes, snr=snr), "S0")
    assert r.sem_sigma == pytest.approx(np.sqrt(np.sum((ref / 50.0) ** 2)) / ref.size, rel=1e-5)


def axial_quantities(angles_deg: np.ndarray, sigma_deg=None) -> roi.Quantities:
    a = np.asarray(angles_deg, float)[None, None, :]
    sig = {} if sigma_deg is None else {"AoLP_deg": np.broadcast_to(sigma_deg, a.shape)}
    return roi.Quantities({"AoLP_deg": a}, sig, np.ones(a.shape, bool), {"AoLP_deg": 180.0},
                          {"AoLP_deg": 0.0}, ("Y",), {})


@pytest.mark.parametrize("centre", [0.0, 1.0, 90.0, 179.0])
def test_circular_mean_across_the_wrap_at_0_and_180(centre):
    offsets = np.array([-8.0, -3.0, 0.0, 3.0, 8.0])  # symmetric: circular mean 0
    angles = (centre + offsets) % 180.0
    r = roi.statistics_of(axial_quantities(angles), np.ones((1, 5), bool))[0]
    assert r.mean == pytest.approx(centre % 180.0, abs=1e-9) or r.mean == pytest.approx(
        centre + 180.0, abs=1e-9)
    # circular standard deviation of the doubled angles, halved (Mardia and Jupp eq. 2.3.11)
    phi = np.deg2rad(2 * offsets)
    rbar = np.hypot(np.cos(phi).mean(), np.sin(phi).mean())
    assert r.std == pytest.approx(np.rad2deg(np.sqrt(-2 * np.log(rbar))) / 2, rel=1e-9)
    assert r.std < 7  # a linear std of angles near 0/180 would be ~90


def test_axial_wrap_gives_0_not_90_and_uniform_angles_have_no_mean():
    r = roi.statistics_of(axial_quantities(np.array([179.0, 1.0])), np.ones((1, 2), bool))[0]
    assert min(r.mean, 180 - r.mean) == pytest.approx(0.0, abs=1e-9)
    uniform = np.arange(0.0, 180.0, 15.0)
    r = roi.statistics_of(axial_quantities(uniform), np.ones((1, uniform.size), bool))[0]
    assert math.isnan(r.mean) and r.std == math.inf


def test_axial_standard_errors_cover_the_mean_of_sampled_angles():
    """von Mises scatter (kappa 20 on the doubled angle) about 175 deg: the scatter sem and
    the sigma sem both describe the spread of the circular mean over repetitions."""
    rng = np.random.default_rng(7)
    n, reps, true = 40, 400, 175.0
    errs, sems, sems_sigma = [], [], []
    for _ in range(reps):
        phi = rng.vonmises(np.deg2rad(2 * true), 20.0, n)
        a = np.rad2deg(phi) / 2 % 180.0
        sig = np.full(n, np.rad2deg(1 / np.sqrt(20.0)) / 2)  # the von Mises sigma, halved
        r = roi.statistics_of(axial_quantities(a, sig), np.ones((1, n), bool))[0]
        errs.append((r.mean - true + 90) % 180 - 90)
        sems.append(r.sem_scatter)
        sems_sigma.append(r.sem_sigma)
    spread = np.std(errs)
    assert np.median(sems) == pytest.approx(spread, rel=0.15)
    assert np.median(sems_sigma) == pytest.approx(spread, rel=0.15)


@settings(max_examples=40, deadline=None)
@given(st.floats(-1e6, 1e6), st.integers(1, 30))
def test_linear_mean_of_a_constant_image_is_the_constant(value, n):
    q = roi.Quantities({"x": np.full((1, 1, n), value)}, {}, np.ones((1, 1, n), bool), {}, {},
                       ("Y",), {})
    r = roi.statistics_of(q, np.ones((1, n), bool))[0]
    assert r.mean == pytest.approx(value, rel=1e-12, abs=1e-9)
    assert (r.n_counted, r.n_masked) == (n, 0)
    assert (n == 1 and math.isnan(r.std)) or r.std == pytest.approx(0.0, abs=1e-6 * abs(value) + 1e-12)


def test_empty_roi_and_all_masked_roi_give_nan_and_counts():
    img = uniform_mueller(100 * np.eye(3))
    rows = roi.roi_statistics(np.zeros((12, 16), bool), mueller=img)
    assert all(r.n_counted == 0 and r.n_masked == 0 and math.isnan(r.mean) for r in rows)
    inside = roi.roi_mask(roi.RectROI(0, 0, 3, 3), (12, 16))
    rows = roi.roi_statistics(inside, mueller=img, valid=np.zeros((1, 12, 16), bool))
    assert all(r.n_counted == 0 and r.n_masked == 9 for r in rows)


# -- line profiles --------------------------------------------------------------------------------
def test_profile_spacing_and_bilinear_values_of_a_linear_ramp():
    h, w = 10, 20
    ramp = np.broadcast_to(np.arange(w, dtype=float) * 3.0 + 1.0, (h, w))[None]
    q = roi.Quantities({"x": ramp}, {}, np.ones((1, h, w), bool), {}, {}, ("Y",), {})
    p = roi.line_profile(q, 2.5, 4.5, 12.5, 4.5)  # along a row of centres, 10 px long
    np.testing.assert_allclose(p.s, np.arange(11.0))
    np.testing.assert_allclose(p.x, np.arange(2.5, 13.0))
    # bilinear on a linear ramp is exact: value at x is 3 (x - 0.5) + 1
    np.testing.assert_allclose(p.values["x"][0], 3 * (p.x - 0.5) + 1)
    p = roi.line_profile(q, 1.0, 1.0, 4.0, 5.0, spacing=0.5)  # length 5
    assert p.s.size == 11 and p.s[-1] == pytest.approx(5.0)
    np.testing.assert_allclose(p.values["x"][0], 3 * (p.x - 0.5) + 1)


def test_profile_nan_outside_and_next_to_masked_pixels():
    v = np.ones((1, 5, 5))
    ok = np.ones((1, 5, 5), bool)
    ok[0, 2, 2] = False
    q = roi.Quantities({"x": v}, {}, ok, {}, {}, ("Y",), {})
    p = roi.line_profile(q, 0.5, 2.5, 5.5, 2.5, spacing=0.5)  # x = 0.5, 1.0, ..., 5.5
    x = p.values["x"][0]
    assert np.isnan(x[4]) and np.isnan(x[10])  # the masked pixel's centre; outside the image
    assert np.isnan(x[[3, 5]]).all()  # half-way to the masked pixel
    np.testing.assert_array_equal(x[[0, 1, 2, 6, 7, 8, 9]], 1.0)  # 5.0: the image's edge


def test_profile_interpolates_axial_angles_through_the_wrap():
    a = np.array([[[179.0, 1.0]]])
    q = axial_quantities(np.zeros(1))
    q = roi.Quantities({"AoLP_deg": a}, {}, np.ones(a.shape, bool), {"AoLP_deg": 180.0},
                       {"AoLP_deg": 0.0}, ("Y",), {})
    p = roi.line_profile(q, 0.5, 0.5, 1.5, 0.5, spacing=0.5)
    mid = p.values["AoLP_deg"][0, 1]
    assert min(mid, 180 - mid) == pytest.approx(0.0, abs=1e-9)


@pytest.mark.parametrize("segment", [(3.2, 4.7, 20.9, 15.1), (0.0, 0.0, 30.0, 24.0),
                                     (-5.0, 10.0, 40.0, 10.0), (12.5, 3.5, 12.5, 3.5)])
def test_profile_of_on_the_segments_box_equals_the_whole_image(segment):
    rng = np.random.default_rng(2)
    m = (uniform_mueller(300 * mu.linear_block(mu.retarder_at(0.3, 1.0)), h=24, w=30)
         + rng.normal(0, 2, (1, 3, 3, 24, 30))).astype(np.float32)
    sigma = np.full(m.shape, 2.0, np.float32)
    valid = rng.uniform(size=(1, 24, 30)) > 0.1
    whole = roi.line_profile(roi.mueller_quantities(m, sigma, valid), *segment, spacing=0.7)
    got = roi.profile_of(segment, mueller=m, sigma=sigma, valid=valid, spacing=0.7)
    np.testing.assert_allclose(got.x, whole.x)
    np.testing.assert_allclose(got.y, whole.y)
    for name in whole.values:
        np.testing.assert_allclose(got.values[name], whole.values[name], rtol=1e-12,
                                   atol=1e-9, err_msg=name)  # the same up to rounding


# -- CSV ------------------------------------------------------------------------------------------
def test_csv_round_trips_the_rows_at_full_precision():
    m3 = 300.0 * mu.linear_block(mu.polarizer_at(0.3))
    rows = roi.roi_statistics(np.ones((12, 16), bool), mueller=uniform_mueller(m3))
    text = roi.stats_csv(rows, {"source": "x.exr", "roi": "rect:0,0,16,12"})
    assert text.startswith("# source: x.exr\n# roi: rect:0,0,16,12\n")
    body = [line for line in text.splitlines() if not line.startswith("#")]
    got = list(csv.DictReader(io.StringIO("\n".join(body))))
    assert len(got) == len(rows) and tuple(got[0]) == roi.STATS_COLUMNS
    for g, r in zip(got, rows):
        assert g["quantity"] == r.quantity and int(g["n_counted"]) == r.n_counted
        assert float(g["mean"]) == r.mean or (math.isnan(r.mean) and g["mean"] == "nan")


# -- polrig stats -----------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def session(tmp_path_factory):
    from polrig.cli import main

    from test_cli_capture import sim_config

    tmp = tmp_path_factory.mktemp("stats")
    cfg = sim_config(tmp / "rig.toml")
    out = tmp / "run"
    assert main(["capture", "--poses", "0,90", "--config", str(cfg), "--out", str(out),
                 "--no-progress"]) == 0
    return out


def read_csv_blocks(path):
    """Rows of a stats CSV (comment lines and repeated headers skipped), with their header."""
    blocks, header = [], {}
    for line in path.read_text().splitlines():
        if line.startswith("# "):
            k, _, v = line[2:].partition(": ")
            header[k] = v
        elif line.startswith("quantity,"):
            blocks.append((header, []))
            header = {}
        else:
            blocks[-1][1].append(dict(zip(roi.STATS_COLUMNS, next(csv.reader([line])))))
    return blocks


def test_stats_cli_equals_the_core_on_a_result_and_per_capture_of_a_session(session, tmp_path, capsys):
    from polrig.cli import main
    from polrig.cli.commands.stats import load_result

    result = session / "c001_pose090.0" / "mueller.exr"
    mueller, sigma, valid = load_result(result)
    assert sigma is not None and sigma.shape == mueller.shape
    h, w = mueller.shape[-2:]
    shape = f"ellipse:{w / 2},{h / 2},{w / 4},{h / 5}"
    out = tmp_path / "one.csv"
    assert main(["stats", str(result), "--roi", shape, "--csv", str(out),
                 "--profile", f"2,3,{w - 2},{h - 5}"]) == 0
    [(header, got)] = read_csv_blocks(out)
    assert header["roi"] == roi.parse_roi(shape).text()
    inside = roi.roi_mask(roi.parse_roi(shape), (h, w))
    want = roi.roi_statistics(inside, mueller=mueller, sigma=sigma, valid=valid)
    assert len(got) == len(want)
    assert_csv_rows_equal(got, want)
    assert sum(int(g["n_counted"]) + int(g["n_masked"]) for g in got[:1]) == inside.sum()
    prof = (tmp_path / "one_profile.csv").read_text().splitlines()
    cols = [line for line in prof if line.startswith("s,x,y")][0].split(",")
    assert "AoLP_deg.Y" in cols and "retardance_deg.Y" in cols
    # a session: one table, a capture column naming each row's capture
    out = tmp_path / "session.csv"
    assert main(["stats", str(session), "--roi", "rect:4,4,8,8", "--csv", str(out),
                 "--profile", "1,1,9,9"]) == 0
    text = out.read_text()
    comments = [line for line in text.splitlines() if line.startswith("#")]
    assert f"# source: {session}" in comments and "# roi: rect:4,4,8,8" in comments
    assert any(c.startswith("# capture c001_pose090.0: source ") for c in comments)
    table = list(csv.DictReader(line for line in text.splitlines() if not line.startswith("#")))
    assert tuple(table[0]) == ("capture",) + roi.STATS_COLUMNS
    assert sum(line.startswith("capture,") for line in text.splitlines()) == 1  # one header
    names = [r["capture"] for r in table]
    assert sorted(set(names)) == ["c000_pose000.0", "c001_pose090.0"]
    assert names.count("c000_pose000.0") == names.count("c001_pose090.0") == len(want)
    assert all(int(r["n_counted"]) + int(r["n_masked"]) == 64 for r in table)
    c1 = [r for r in table if r["capture"] == "c001_pose090.0"]
    want1 = roi.roi_statistics(roi.roi_mask(roi.parse_roi("rect:4,4,8,8"), (h, w)),
                               mueller=mueller, sigma=sigma, valid=valid)
    assert_csv_rows_equal(c1, want1)
    prof_text = (tmp_path / "session_profile.csv").read_text().splitlines()
    prof = list(csv.DictReader(line for line in prof_text if not line.startswith("#")))
    assert list(prof[0])[:4] == ["capture", "s", "x", "y"]
    assert sum(line.startswith("capture,") for line in prof_text) == 1
    assert {r["capture"] for r in prof} == {"c000_pose000.0", "c001_pose090.0"}
    capsys.readouterr()
    assert main(["stats", str(result), "--roi", "rect:4,4,8,8"]) == 0  # a printed table
    printed = capsys.readouterr().out
    assert "AoLP_deg" in printed and "sem_sigma" in printed


@pytest.mark.parametrize("argv, words", [
    (["--roi", "rect:1,2,3"], "--roi"),
    (["--roi", "rect:0,0,4,4", "--profile", "1,2,3"], "--profile"),
    (["--roi", "rect:0,0,4,4", "--csv", "x.txt"], "--csv"),
    (["--roi", "rect:100000,100000,5,5"], "no pixel centre of the"),  # off the image: not NaN statistics
    (["--roi", "rect:0,0,4,4", "--profile", "1000,1000,2000,1000"], "the line does not cross"),
])
def test_stats_cli_bad_input_is_one_line(session, argv, words, capsys):
    from polrig.cli import main

    rc = main(["stats", str(session / "c000_pose000.0" / "mueller.exr"), *argv])
    err = capsys.readouterr().err
    assert rc != 0 and words in err and len(err.strip().splitlines()) == 1


def test_roi_means_cover_the_simulators_truth_with_their_sigma_sem(session):
    """Hidden truth: over 4x4-pixel rectangles tiling both captures, the ROI mean of ``S0`` and
    of every ``m_ij/m00`` differs from the same ROI's mean of the truth (as a perfect rig
    measures it, :func:`polrig.solve.scoring.truth_on_output_grid`) by at most 2 ``sem_sigma``
    (from the ``sigma_noise`` planes: the ideal rig has no calibration error) in 92-98 % of
    the ROIs, pooled (about 640 ROI means: 95 % +- 3 binomial standard deviations), and the
    errors in units of ``sem_sigma`` have a standard deviation of 1 +- 0.1. Measured: 93.7 %,
    1.05."""
    from polrig.cli.commands.stats import load_result
    from polrig.formats.exr import read_mueller_exr
    from polrig.sensor.noise import SensorModel
    from polrig.solve.scoring import truth_on_output_grid

    names = ["S0"] + [f"m{i}{j}/m00" for i in range(3) for j in range(3) if i or j]
    within = []
    for cap in ("c000_pose000.0", "c001_pose090.0"):
        mueller, sigma, valid = load_result(session / cap / "mueller.exr", "sigma_noise")
        md = read_mueller_exr(session / cap / "mueller.exr").metadata
        t = truth_on_output_grid(read_mueller_exr(session / cap / "truth_mueller.exr").mueller,
                                 md["layout"] + "@0,0", md["demosaic"],
                                 np.array(md["incident_state"]), model=SensorModel(),
                                 exposure_us=md["exposure_us"])
        h, w = mueller.shape[-2:]
        for y in range(0, h, 4):
            for x in range(0, w, 4):
                inside = roi.roi_mask(roi.RectROI(x, y, 4, 4), (h, w))
                # count the same pixels in both: valid in the result and in the truth
                ok = valid & (t[:, 0, 0] > 0)
                est = roi.roi_statistics(inside, mueller=mueller, sigma=sigma, valid=ok)
                ref = roi.roi_statistics(inside, mueller=t, valid=ok)
                for n in names:
                    e, r = row(est, n), row(ref, n)
                    if e.n_counted >= 8 and e.n_counted == r.n_counted:
                        within.append((e.mean - r.mean) / e.sem_sigma)
    z = np.array(within)
    cover = float((np.abs(z) <= 2).mean())
    print(f"\n{z.size} ROI means, {cover:.3f} within 2 sem_sigma of the truth, sd(z) {z.std():.3f}")
    assert z.size >= 600
    assert 0.92 <= cover <= 0.98
    assert 0.9 <= z.std() <= 1.1


def test_a_pixel_without_sigma_still_counts_and_makes_sem_sigma_honest():
    x = np.array([[[1.0, 2.0, 3.0, 4.0]]])
    s = np.array([[[0.1, 0.1, np.inf, 0.1]]])
    q = roi.Quantities({"x": x}, {"x": s}, np.ones(x.shape, bool), {}, {}, ("Y",), {})
    r = roi.statistics_of(q, np.ones((1, 4), bool))[0]
    assert r.n_counted == 4 and r.mean == 2.5 and r.sem_sigma == math.inf
    q.sigma = {}
    assert roi.statistics_of(q, np.ones((1, 4), bool))[0].mean == 2.5


# -- polrig stats of a Stokes EXR -------------------------------------------------------------------
def test_stats_cli_reads_a_stokes_exr_like_the_viewer(tmp_path, capsys):
    """A ``polrig stokes`` EXR of a noisy uniformly polarized frame (AoLP 30 deg, DoLP 0.6) with
    one saturated raw sample: ``polrig stats`` gives :func:`polrig.app.roi.roi_statistics` of
    its Stokes images over the ROI, counting the pixels the file says are valid (the saturated
    cell is masked), with ``sem_sigma`` from the ``snr`` planes; the Viewer's ROI statistics
    of the same file (no signal threshold) are the same numbers."""
    from polrig.cli import main
    from polrig.formats.exr import read_stokes_exr
    from polrig.formats.rawio import write_raw
    from polrig.gui import pipeline
    from polrig.gui.viewer import load_exr
    from polrig.sensor.analyzer import AnalyzerModel
    from polrig.sensor.frame import Frame, FrameMeta

    shape = (48, 64)
    model = AnalyzerModel.ideal("imx250mzr@0,0", shape)
    t = np.deg2rad(60.0)
    s = np.array([2000.0, 1200.0 * np.cos(t), 1200.0 * np.sin(t)])
    clean = model.mosaic(np.broadcast_to(s[None, :, None, None], (1, 3) + shape))
    raw = np.random.default_rng(5).poisson(clean).astype(np.float64) + 64
    raw[10, 10] = 4095  # saturated at 12 bits
    meta = FrameMeta(frame_id=1, timestamp_s=0.0, exposure_us=1000.0, gain_db=0.0,
                     pixel_format="Mono12", layout="imx250mzr", bit_depth=12, black_level_dn=64.0)
    src = tmp_path / "frame.png"
    write_raw(src, Frame(np.clip(raw, 0, 4095).astype(np.uint16), meta))
    exr = tmp_path / "stokes.exr"
    assert main(["stokes", str(src), "--demosaic", "superpixel", "--out", str(exr)]) == 0
    back = read_stokes_exr(exr)
    h, w = back.stokes.shape[-2:]
    region = "ellipse:12,10,9,7"
    out = tmp_path / "s.csv"
    assert main(["stats", str(exr), "--roi", region, "--csv", str(out),
                 "--profile", f"1,2,{w - 3},{h - 2}"]) == 0
    [(header, got)] = read_csv_blocks(out)
    assert header["sigma"] == "snr planes"
    inside = roi.roi_mask(roi.parse_roi(region), (h, w))
    valid = (back.extra["valid"] > 0)[None] & (back.stokes[:, 0] > 0)
    snr = back.extra["snr.Y"][None]
    want = roi.roi_statistics(inside, stokes=back.stokes, valid=valid, snr=snr)
    assert [g["quantity"] for g in got] == ["S0", "DoLP", "AoLP_deg"]
    assert_csv_rows_equal(got, want)
    s0, dolp_row, aolp_row = want
    assert s0.n_masked == 1 and s0.n_counted + 1 == inside.sum()  # the saturated cell
    assert abs(dolp_row.mean - 0.6) < 0.01 and abs(aolp_row.mean - 30.0) < 0.5
    assert np.isfinite(s0.sem_sigma) and s0.sem_sigma > 0
    # the Viewer's statistics of the same file, without a signal threshold
    data = load_exr(exr)
    data.min_snr = 0.0
    gui = pipeline.roi_statistics(data, inside)
    assert len(gui) == len(want)
    for a, b in zip(gui, want):
        np.testing.assert_equal(a.as_tuple(), b.as_tuple())  # NaN equal to NaN
    prof = (tmp_path / "s_profile.csv").read_text().splitlines()
    assert "AoLP_deg.Y" in next(line for line in prof if line.startswith("s,x,y")).split(",")
    capsys.readouterr()
    assert main(["stats", str(exr)]) == 0  # the whole image, printed
    assert "DoLP" in capsys.readouterr().out


def test_stats_cli_refuses_an_exr_that_is_neither_mueller_nor_stokes(tmp_path, capsys):
    from polrig.cli import main
    from polrig.formats.exr import write_exr

    path = tmp_path / "maps.exr"
    write_exr(path, {"retardance_deg.Y": np.zeros((4, 4), np.float32)})
    assert main(["stats", str(path)]) != 0
    err = capsys.readouterr().err
    assert "neither a Mueller result" in err and len(err.strip().splitlines()) == 1
