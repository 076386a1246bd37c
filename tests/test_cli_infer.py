"""``polrig infer`` on bad input and failed writes: one line, the right exit code, before the
network runs; its summary line gives the size as WxH, like ``polrig stokes`` and ``--size``."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.cli import main

pytest.importorskip("onnxruntime")


@pytest.fixture(scope="module")
def frame(tmp_path_factory):
    """A simulated 128x64 (W x H) colour frame with its sidecar."""
    out = tmp_path_factory.mktemp("render")
    assert main(["sim", "render", "--size", "128x64", "--states", "0", "--no-exr",
                 "--out", str(out)]) == 0
    return next(out.glob("*_state00.png"))


def test_summary_gives_width_x_height(frame, tmp_path, capsys):
    capsys.readouterr()
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(tmp_path / "m.exr")]) == 0
    out = capsys.readouterr().out
    assert out.startswith(f"wrote {tmp_path / 'm.exr'}: 32x16, 3 colour(s)")  # superpixel (4x4 cells) W x H


@pytest.mark.parametrize("option,value,needle", [
    ("--stage-zero-axis", "0,0,0", "must not be zero"),
    ("--stage-zero-axis", "1,nan,0", "values must be finite"),
    ("--stage-zero-axis", "1,2", "expected three comma-separated numbers"),
    ("--black-level", "-1", "must be >= 0"),
    ("--scale", "0", "must be > 0"),
    ("--saturation-dn", "nan", "expected a finite number"),
    ("--state-deg", "inf", "expected a finite number"),
])
def test_absurd_numbers_are_usage_errors(frame, tmp_path, capsys, option, value, needle):
    argv = ["infer", str(frame), "--state-deg", "0", "--out", str(tmp_path / "m.exr")]
    with pytest.raises(SystemExit) as exc:
        main(argv + [option, value])
    assert exc.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith(f"polrig infer: error: argument {option}: ") and needle in last
    assert list(tmp_path.iterdir()) == []


def test_black_level_at_saturation_and_folder_output_are_refused(frame, tmp_path, capsys):
    base = ["infer", str(frame), "--state-deg", "0"]
    assert main(base + ["--black-level", "70000", "--out", str(tmp_path / "m.exr")]) == 2
    err = capsys.readouterr().err
    assert err == ("polrig: error: --black-level 70000 DN is not below the saturation level "
                   "65535 DN\n")
    (tmp_path / "outdir.exr").mkdir()
    assert main(base + ["--out", str(tmp_path / "outdir.exr")]) == 2
    err = capsys.readouterr().err
    assert err == f"polrig: error: --out {tmp_path / 'outdir.exr'} is a directory; give a file name\n"
    assert [p.name for p in tmp_path.iterdir()] == ["outdir.exr"]


def test_a_failed_write_is_one_line_exit_1(frame, tmp_path):
    from _cli_helpers import polrig_with_file_size_limit

    out = tmp_path / "m.exr"
    res = polrig_with_file_size_limit(["infer", frame, "--state-deg", "0", "--out", out], 4096)
    assert res.returncode == 1, res.stderr
    assert res.stderr == f"polrig: error: {out}: cannot write the OpenEXR file (File too large)\n"
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize("size, layout, why", [
    ((64, 48), "imx250myr", "the readout is not inside the calibrated area"),
    ((128, 64), "imx250mzr", "layout imx250mzr is not imx250myr"),
])
def test_a_calibration_set_of_another_camera_is_refused(frame, tmp_path, capsys, size, layout,
                                                        why):
    """``--calibration`` of a set that does not cover the frame (or of a mono sensor for a
    colour frame) used to be applied silently (exit 0)."""
    from _calibration_sets import set_calibrated_on

    set_calibrated_on(tmp_path / "cal", size, layout)
    out = tmp_path / "m.exr"
    rc = main(["infer", str(frame), "--state-deg", "0", "--calibration", str(tmp_path / "cal"),
               "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1, err
    assert err.startswith(f"polrig: error: --calibration {tmp_path / 'cal'}: calibrated on "
                          f"sensor {size[0]}x{size[1]} {layout}")
    assert f"{frame}: sensor imx250myr, readout 128x64 at (0, 0) ({why})" in err
    assert not out.exists()


def test_a_calibration_set_covering_the_frame_is_used(frame, tmp_path, capsys):
    from _calibration_sets import set_calibrated_on

    set_calibrated_on(tmp_path / "cal", (256, 128))  # the frame is its corner (an ROI)
    assert main(["infer", str(frame), "--state-deg", "0", "--calibration", str(tmp_path / "cal"),
                 "--out", str(tmp_path / "m.exr")]) == 0


def test_infer_of_a_sim_render_is_in_the_unit_of_its_truth(tmp_path, capsys):
    """``sim render`` writes Mono16 frames (12-bit codes times 16, black level 256) and its truth
    in 12-bit ADC DN; ``infer`` used to report m00 16 times the truth's. Results are in ADC DN
    (polrig.app.processing.adc_scale): the median m00 of the object, per colour, matches the
    truth's within the network's error (a few per cent; a unit error is a factor 16)."""
    from polrig.formats.exr import read_mueller_exr

    render = tmp_path / "r"
    assert main(["sim", "render", "--size", "128x128", "--states", "0", "--out", str(render)]) == 0
    out = tmp_path / "i.exr"
    assert main(["infer", str(render / "pose0000p00_state00.png"), "--state-deg", "0",
                 "--out", str(out)]) == 0
    got, truth = read_mueller_exr(out), read_mueller_exr(render / "truth_pose0000p00_mueller.exr")
    assert "ADC DN" in got.metadata["units"]
    valid = got.extra["mask.G"] == 0  # reason bits, 0 = valid (as a session's result)
    m00 = np.median(got.mueller[:, 0, 0][:, valid], axis=1)
    t00 = np.median(truth.mueller[:, 0, 0][:, truth.extra["mask"] > 0], axis=1)
    np.testing.assert_allclose(m00, t00, rtol=0.2)


def test_infer_writes_masked_previews_and_counts_the_masked_pixels(frame, tmp_path, capsys):
    """Previews next to the EXR (grid with tile labels and colour bar, polarizance DoLP/AoLP
    with legends); background and pixels below --min-snr are black and counted."""
    import cv2

    capsys.readouterr()
    out = tmp_path / "m.exr"
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(out)]) == 0
    line = capsys.readouterr().out
    assert "masked " in line and " of 512 pixels" in line and "m_grid.png" in line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["m.exr", "m_aolp.png", "m_dolp.png",
                                                          "m_grid.png"]
    grid = cv2.imread(str(tmp_path / "m_grid.png"))
    assert min(grid.shape[:2]) >= 3 * 256  # 32x16 tiles enlarged to be read
    # a folder where a preview goes is refused before the network runs
    (tmp_path / "n_dolp.png").mkdir()
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(tmp_path / "n.exr")]) == 2
    assert not (tmp_path / "n.exr").exists()


def test_sigma_flags_pixels_beyond_its_calibration_on_a_metal(tmp_path, capsys):
    """With ``--sigma`` the EXR has a ``beyond_calibration`` plane (object pixels whose misfit
    lies beyond the sigma's calibration range) and its object fraction in the header; a gold
    sphere, which the networks never saw, is flagged far more than a plastic one and warned
    about, the plastic one is not warned about (4-14 % against 90-95 % measured,
    :data:`polrig.models.uncertainty.BEYOND_WARN_FRACTION`)."""
    from polrig.formats.exr import read_mueller_exr
    from polrig.models.uncertainty import BEYOND_WARN_FRACTION

    fractions = {}
    for scene in ("sphere", "gold_sphere"):
        render = tmp_path / scene
        assert main(["sim", "render", "--scene", scene, "--size", "256x256", "--states", "0",
                     "--no-exr", "--out", str(render)]) == 0
        out = tmp_path / f"{scene}.exr"
        capsys.readouterr()
        assert main(["infer", str(render / "pose0000p00_state00.png"), "--state-deg", "0",
                     "--sigma", "--out", str(out)]) == 0
        err = capsys.readouterr().err
        exr = read_mueller_exr(out)
        flagged = np.stack([exr.extra[f"beyond_calibration.{c}"] for c in "RGB"])
        obj = np.any(exr.mueller != 0, axis=(0, 1, 2))  # the networks' object: Mueller 0 outside
        assert not flagged[:, ~obj].any()  # object pixels only
        fractions[scene] = exr.metadata["beyond_calibration_fraction"]
        assert fractions[scene] == pytest.approx(np.any(flagged > 0, axis=0)[obj].mean())
        assert ("beyond the misfit range" in err) == (fractions[scene] > BEYOND_WARN_FRACTION)
    assert fractions["sphere"] < BEYOND_WARN_FRACTION < fractions["gold_sphere"]


def test_two_runs_write_the_same_bytes(frame, tmp_path):
    """The EXR and previews of ``polrig infer`` hold no time stamps: two runs give the same
    bytes (what ``benchmarks/bench_cli_start.py`` relies on to compare two checkouts' output)."""
    written = []
    for run in ("a", "b"):
        (tmp_path / run).mkdir()
        assert main(["infer", str(frame), "--state-deg", "0", "--device", "cpu",
                     "--out", str(tmp_path / run / "m.exr")]) == 0
        written.append({p.name: p.read_bytes() for p in sorted((tmp_path / run).iterdir())})
    assert sorted(written[0]) == ["m.exr", "m_aolp.png", "m_dolp.png", "m_grid.png"]
    assert written[0] == written[1]


def test_infer_refuses_an_output_that_is_the_raw_frame(frame, tmp_path, capsys):
    """A raw frame named like a preview of ``--out`` (a_grid.png for a.exr): exit 2, one line
    naming both, the frame and its sidecar untouched, before the network runs."""
    import shutil

    raw = tmp_path / "a_grid.png"
    shutil.copy(frame, raw)
    shutil.copy(f"{frame}.json", f"{raw}.json")
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    capsys.readouterr()
    assert main(["infer", str(raw), "--state-deg", "0", "--out", str(tmp_path / "a.exr")]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"polrig: error: --out preview {raw} is the input {raw};")
    assert err.count("\n") == 1
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before


def test_a_layout_contradicting_the_sidecar_is_refused_as_by_stokes(frame, tmp_path, capsys):
    """The frame's sidecar says imx250myr (colour): ``--layout imx250mzr`` is refused with the
    line ``polrig stokes`` gives (the one check, ``check_layout_option``); the same layout is
    accepted."""
    capsys.readouterr()
    out = tmp_path / "m.exr"
    assert main(["infer", str(frame), "--layout", "imx250mzr", "--state-deg", "0",
                 "--out", str(out)]) == 2
    assert capsys.readouterr().err == (
        f"polrig: error: --layout imx250mzr contradicts the sidecar of {frame}, which says "
        f"imx250myr; drop --layout (or fix the sidecar)\n")
    assert list(tmp_path.iterdir()) == []
    assert main(["infer", str(frame), "--layout", "imx250myr", "--state-deg", "0",
                 "--out", str(out)]) == 0


def test_infer_writes_its_exr_and_previews_all_or_none(frame, tmp_path, monkeypatch, capsys):
    """OUT_grid.png cannot be written (a full disk): the EXR and previews of the run before stay
    as they were, nothing new, no temporary; one line naming the preview, exit 1."""
    import pathlib

    import polrig.app.preview
    from polrig.atomic import write_error

    out = tmp_path / "m.exr"
    assert main(["infer", str(frame), "--state-deg", "0", "--out", str(out)]) == 0
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real = polrig.app.preview.atomic_write_bytes

    def full_at_grid(path, data):
        if "_grid" in pathlib.Path(path).name:
            raise write_error(path, OSError(28, "No space left on device"))
        real(path, data)

    monkeypatch.setattr(polrig.app.preview, "atomic_write_bytes", full_at_grid)
    capsys.readouterr()
    assert main(["infer", str(frame), "--state-deg", "90", "--out", str(out)]) == 1
    assert capsys.readouterr().err == (f"polrig: error: {tmp_path / 'm_grid.png'}: cannot write "
                                       f"(No space left on device)\n")
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
