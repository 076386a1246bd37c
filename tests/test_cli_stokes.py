"""``polrig stokes``: raw file in, Stokes EXR and previews out; clear errors on bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import cv2
import numpy as np
import pytest

from polrig.cli import main
from polrig.formats.exr import read_stokes_exr
from polrig.formats.rawio import write_raw
from polrig.sensor.analyzer import AnalyzerModel
from polrig.sensor.frame import Frame, FrameMeta


def _polarized_raw(layout="imx250mzr", shape=(32, 40), aolp_deg=30.0, dolp=0.6, s0=2000.0,
                   offset=(0, 0)):
    model = AnalyzerModel.ideal(f"{layout}@{offset[0]},{offset[1]}", shape)
    t = np.deg2rad(2 * aolp_deg)
    c = model.n_colours
    s = np.array([s0, s0 * dolp * np.cos(t), s0 * dolp * np.sin(t)])
    stokes = np.broadcast_to(s[None, :, None, None], (c, 3) + shape)
    return np.round(model.mosaic(stokes)).astype(np.uint16)


@pytest.mark.parametrize("method", ["superpixel", "bilinear", "newton"])
def test_stokes_command_writes_exr_and_previews(tmp_path, method, capsys):
    raw = _polarized_raw()
    src = tmp_path / "frame.png"
    ok, enc = cv2.imencode(".png", raw)
    src.write_bytes(enc.tobytes())
    out = tmp_path / "out.exr"
    rc = main(["stokes", str(src), "--layout", "imx250mzr", "--demosaic", method,
               "--out", str(out)])
    assert rc == 0
    back = read_stokes_exr(out)
    h, w = (16, 20) if method == "superpixel" else (32, 40)
    assert back.stokes.shape == (1, 3, h, w)
    assert back.conventions == "1"
    inner = back.stokes[0, :, 3:-3, 3:-3]
    np.testing.assert_allclose(inner[0], 2000 / 16, rtol=1e-3)  # a 16-bit file: 16 DN per ADC DN
    assert "ADC DN" in back.metadata["units"]
    aolp = back.extra["aolp_deg.Y"][3:-3, 3:-3]
    np.testing.assert_allclose(aolp, 30.0, atol=0.1)
    np.testing.assert_allclose(back.extra["dolp.Y"][3:-3, 3:-3], 0.6, atol=2e-3)
    assert back.extra["valid"].all()
    assert "valid" in back.metadata["planes"]
    assert back.metadata["processing"]["demosaic"] == method
    for suffix in ("_dolp.png", "_aolp.png"):
        img = cv2.imread(str(tmp_path / f"out{suffix}"), cv2.IMREAD_UNCHANGED)
        assert img.shape[:2] == (h, img.shape[1]) and img.shape[1] > w  # legend on the right
        assert img.dtype == np.uint8
    assert "wrote" in capsys.readouterr().out


def test_sidecar_supplies_layout_offset_black_level_and_bit_depth(tmp_path):
    raw = _polarized_raw("imx250myr", (32, 32), offset=(1, 2), s0=1000) + 64
    raw[5, 5] = 4095  # saturated at 12 bits
    meta = FrameMeta(frame_id=7, timestamp_s=1.0, exposure_us=500.0, gain_db=0.0,
                     pixel_format="BayerRGPolarized12p", layout="imx250myr", bit_depth=12,
                     offset_xy=(1, 2), black_level_dn=64.0)
    src = tmp_path / "frame.png"
    write_raw(src, Frame(raw, meta))
    out = tmp_path / "o.exr"
    assert main(["stokes", str(src), "--demosaic", "superpixel", "--out", str(out)]) == 0
    back = read_stokes_exr(out)
    assert back.stokes.shape == (3, 3, 8, 8)
    ok = back.extra["valid"] > 0
    assert not ok[1, 1] and ok.sum() == 63  # the 4x4 cell holding the saturated pixel
    np.testing.assert_allclose(back.stokes[:, 0][:, ok], 1000, rtol=2e-3)
    assert back.metadata["capture"]["frame"]["frame_id"] == 7
    assert back.metadata["processing"]["layout"] == "imx250myr@1,2"


def test_a_frame_without_sidecar_or_layout_gets_a_note_naming_the_assumed_layout(tmp_path, capsys):
    import cv2

    src = tmp_path / "bare.png"
    cv2.imwrite(str(src), _polarized_raw("imx250mzr", (16, 16), s0=1000).astype(np.uint16))
    assert main(["stokes", str(src), "--out", str(tmp_path / "a.exr")]) == 0
    err = capsys.readouterr().err
    assert "bare.png has no sidecar; assuming the imx250mzr mosaic (mono)" in err and "--layout" in err
    assert main(["stokes", str(src), "--layout", "imx250mzr", "--out", str(tmp_path / "b.exr")]) == 0
    assert "note" not in capsys.readouterr().err


def test_roi_offset_changes_the_phase(tmp_path):
    raw = _polarized_raw(offset=(1, 0), aolp_deg=20)
    src = tmp_path / "r.npy"
    np.save(src, raw)
    for offset, expect in (("1,0", 20.0), ("0,0", None)):
        out = tmp_path / f"o{offset[0]}.exr"
        assert main(["stokes", str(src), "--roi-offset", offset, "--demosaic", "superpixel",
                     "--out", str(out)]) == 0
        aolp = read_stokes_exr(out).extra["aolp_deg.Y"]
        if expect is not None:
            np.testing.assert_allclose(aolp, expect, atol=0.05)
        else:
            assert np.abs(aolp - 20).min() > 10  # the wrong phase gives a wrong angle


@pytest.mark.parametrize("args,needle", [
    (["--out", "{tmp}/o.exr", "{tmp}/missing.png"], "missing.png"),
    (["--out", "{tmp}/o.png", "{raw}"], ".exr"),
    (["--out", "{tmp}/o.exr", "--roi-offset", "a,b", "{raw}"], "--roi-offset"),
    (["--out", "{tmp}/o.exr", "{rgb}"], "one channel"),
    (["--out", "{tmp}/nowhere/o.exr", "{raw}"], "does not exist"),
    (["--out", "{tmp}/outdir.exr", "{raw}"], "outdir.exr is a directory"),
    (["--out", "{tmp}/o.exr", "{tmp}/adir.png"], "adir.png: is a directory"),
    (["--out", "{tmp}/o.exr", "--black-level", "1e9", "{raw}"], "--black-level 1e+09 DN is not below"),
    (["--out", "{tmp}/o.exr", "--bit-depth", "8", "{raw}"], "but --bit-depth is 8"),
    (["--out", "{tmp}/o.exr", "--bit-depth", "12", "{raw8}"], "uint8 data, but --bit-depth is 12"),
])
def test_bad_input_gives_one_line_error(tmp_path, capsys, args, needle):
    raw = tmp_path / "raw.png"
    cv2.imwrite(str(raw), _polarized_raw())
    raw8 = tmp_path / "raw8.png"
    cv2.imwrite(str(raw8), np.full((8, 8), 100, np.uint8))
    rgb = tmp_path / "rgb.png"
    cv2.imwrite(str(rgb), np.zeros((8, 8, 3), np.uint8))
    (tmp_path / "outdir.exr").mkdir()
    (tmp_path / "adir.png").mkdir()
    argv = ["stokes"] + [a.format(tmp=tmp_path, raw=raw, raw8=raw8, rgb=rgb) for a in args]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("polrig: error:") and needle in err and "\n" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["adir.png", "outdir.exr", "raw.png",
                                                          "raw8.png", "rgb.png"]


@pytest.mark.parametrize("option,value", [("--black-level", "nan"), ("--black-level", "-5"),
                                          ("--black-level", "inf"), ("--bit-depth", "0"),
                                          ("--bit-depth", "40")])
def test_absurd_numbers_are_usage_errors(tmp_path, capsys, option, value):
    raw = tmp_path / "raw.png"
    cv2.imwrite(str(raw), _polarized_raw())
    with pytest.raises(SystemExit) as exc:  # argparse: exit 2, the error on its last line
        main(["stokes", str(raw), option, value, "--out", str(tmp_path / "o.exr")])
    assert exc.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert last.startswith("polrig stokes: error: argument " + option) and repr(value) in last
    assert not (tmp_path / "o.exr").exists()


def test_a_failed_write_is_one_line_exit_1_and_leaves_no_temporary_file(tmp_path):
    """A write that the operating system refuses (here: the process may not write files over
    4 kB, a full disk in miniature) is one line naming the output, exit 1 (a failure while
    running, not bad input), with nothing left behind."""
    from _cli_helpers import polrig_with_file_size_limit

    raw = np.random.default_rng(0).integers(0, 4000, (32, 40)).astype(np.uint16)
    cv2.imwrite(str(tmp_path / "n.png"), raw)
    out = tmp_path / "o.exr"
    res = polrig_with_file_size_limit(["stokes", tmp_path / "n.png", "--out", out], 4096)
    assert res.returncode == 1, res.stderr
    assert res.stderr == f"polrig: error: {out}: cannot write the OpenEXR file (File too large)\n"
    assert [p.name for p in tmp_path.iterdir()] == ["n.png"]


@pytest.mark.parametrize("key,value,needle", [
    ("black_level_dn", None, "black_level_dn: expected a number, got None"),
    ("black_level_dn", "x", "black_level_dn: expected a number, got 'x'"),
    ("bit_depth", "twelve", "bit_depth: expected an integer, got 'twelve'"),
    ("bit_depth", 8, "uint16 data, but bit_depth in frame.png.json is 8"),
    ("pixel_format", "Mono8", "uint16 data, but pixel_format in frame.png.json is 'Mono8'"),
])
def test_a_bad_sidecar_is_one_line_naming_file_and_key(tmp_path, capsys, key, value, needle):
    meta = FrameMeta(frame_id=7, timestamp_s=1.0, exposure_us=500.0, gain_db=0.0,
                     pixel_format="Mono16", layout="imx250mzr", bit_depth=16, black_level_dn=0.0)
    src = tmp_path / "frame.png"
    write_raw(src, Frame(_polarized_raw(), meta))
    side = tmp_path / "frame.png.json"
    doc = json.loads(side.read_text())
    doc[key] = value
    side.write_text(json.dumps(doc))
    assert main(["stokes", str(src), "--out", str(tmp_path / "o.exr")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "frame.png" in err and needle in err


def test_an_8_bit_frame_with_a_16_bit_sidecar_is_refused(tmp_path, capsys):
    """8-bit data whose sidecar says Mono16 / 16 bits / black level 256 used to give a Stokes
    file with every pixel masked and exit 0."""
    meta = FrameMeta(frame_id=1, timestamp_s=0.0, exposure_us=500.0, gain_db=0.0,
                     pixel_format="Mono16", layout="imx250mzr", bit_depth=16, black_level_dn=256.0)
    src = tmp_path / "frame.png"
    cv2.imwrite(str(src), np.full((16, 16), 120, np.uint8))
    (tmp_path / "frame.png.json").write_text(json.dumps(meta.to_json()))
    assert main(["stokes", str(src), "--out", str(tmp_path / "o.exr")]) == 2
    err = capsys.readouterr().err
    assert "frame.png: the file holds uint8 data, but pixel_format in frame.png.json" in err
    assert not (tmp_path / "o.exr").exists()


def test_console_script_help_lists_stokes():
    out = subprocess.run([sys.executable, "-m", "polrig", "--help"], capture_output=True,
                         text=True, check=True).stdout
    assert "stokes" in out
    out = subprocess.run([sys.executable, "-m", "polrig", "stokes", "--help"],
                         capture_output=True, text=True, check=True).stdout
    for opt in ("--layout", "--demosaic", "--black-level", "--roi-offset", "--out"):
        assert opt in out


def test_calibrated_analyzer_file(tmp_path):
    rng = np.random.default_rng(3)
    ideal = AnalyzerModel.ideal("imx250mzr", (16, 16))
    model = AnalyzerModel(ideal.layout, rng.uniform(0.8, 1.2, (16, 16)),
                          ideal.angle_deg + rng.normal(0, 3, (16, 16)),
                          rng.uniform(0.9, 1.0, (16, 16)), np.zeros((16, 16)))
    model.save(tmp_path / "analyzer.npz")
    s = np.array([1000.0, 250.0, -300.0])
    raw = model.mosaic(np.broadcast_to(s[None, :, None, None], (1, 3, 16, 16)))
    np.save(tmp_path / "raw.npy", np.round(raw * 16).astype(np.uint16))  # 12-bit ADC in 16 bits
    out = tmp_path / "o.exr"
    assert main(["stokes", str(tmp_path / "raw.npy"), "--demosaic", "superpixel",
                 "--analyzer", str(tmp_path / "analyzer.npz"), "--out", str(out)]) == 0
    got = read_stokes_exr(out).stokes[0].reshape(3, -1).T  # ADC DN: the file's / 16
    np.testing.assert_allclose(got, np.broadcast_to(s, got.shape), atol=0.1)
    assert main(["stokes", str(tmp_path / "raw.npy"), "--demosaic", "superpixel",
                 "--out", str(tmp_path / "plain.exr")]) == 0
    plain = read_stokes_exr(tmp_path / "plain.exr").stokes[0].reshape(3, -1).T
    assert np.abs(plain - s).max() > 10  # the calibration matters


def _half_dark_frame(tmp_path, layout="imx250mzr"):
    """A 12-bit frame with a sidecar (black level 64): the left half a polarized object
    (S0 2000 DN, DoLP 0.3), the right half background, both with the sensor's noise."""
    from polrig.sensor.noise import SensorModel

    model = SensorModel(black_level_dn=64.0)
    mean = _polarized_raw(layout, (32, 64), dolp=0.3, s0=2000).astype(np.float64)
    mean[:, 32:] = 0.0
    raw = model.sample_raw(mean * model.gain_e_per_dn, np.random.default_rng(5), 1000.0)
    meta = FrameMeta(frame_id=1, timestamp_s=0.0, exposure_us=1000.0, gain_db=0.0,
                     pixel_format="Mono12", layout=layout, bit_depth=12, black_level_dn=64.0)
    src = tmp_path / "half.png"
    write_raw(src, Frame(raw, meta))
    return src


def test_background_noise_is_masked_in_the_previews_and_counted(tmp_path, capsys):
    """Dark background used to show as full-scale DoLP speckle; now pixels whose S0 is below
    --min-snr noise sigmas (noise model) are black in the previews and counted."""
    src = _half_dark_frame(tmp_path)
    out = tmp_path / "o.exr"
    assert main(["stokes", str(src), "--demosaic", "superpixel", "--out", str(out)]) == 0
    line = capsys.readouterr().out
    assert "masked 256 of 512 pixels (dark 256 below SNR 3)" in line  # 16x32 output, right half
    assert "clipped at" not in line
    dolp = cv2.imread(str(tmp_path / "o_dolp.png"))[:, :32]  # the image left of its legend
    assert (dolp[:, 16:] == 0).all() and (dolp[:, :16] > 0).all()
    snr = read_stokes_exr(out).extra["snr.Y"]
    assert (snr[:, :16] > 50).all() and (np.abs(snr[:, 16:]) < 5).all()
    # --min-snr 0 masks nothing that has signal: the background's positive noise shows again
    assert main(["stokes", str(src), "--demosaic", "superpixel", "--min-snr", "0",
                 "--out", str(tmp_path / "z.exr")]) == 0
    shown = capsys.readouterr().out
    assert "masked 256 of 512" not in shown
    assert cv2.imread(str(tmp_path / "z_dolp.png"))[:, 16:32].max() > 0


def test_summary_says_what_it_counts(tmp_path, capsys):
    """"DoLP clipped at 0" meant zero pixels were clipped; the line now names its counts."""
    raw = tmp_path / "raw.png"
    cv2.imwrite(str(raw), _polarized_raw())
    assert main(["stokes", str(raw), "--layout", "imx250mzr", "--out", str(tmp_path / "o.exr")]) == 0
    line = capsys.readouterr().out
    assert "clipped at" not in line and "masked 0 of 1280 pixels" in line


def test_layout_contradicting_the_sidecar_is_refused(tmp_path, capsys):
    src = _half_dark_frame(tmp_path, "imx250myr")
    assert main(["stokes", str(src), "--layout", "imx250mzr", "--out", str(tmp_path / "o.exr")]) == 2
    err = capsys.readouterr().err
    assert err == (f"polrig: error: --layout imx250mzr contradicts the sidecar of {src}, which "
                   f"says imx250myr; drop --layout (or fix the sidecar)\n")
    assert not (tmp_path / "o.exr").exists()
    assert main(["stokes", str(src), "--layout", "imx250myr", "--out", str(tmp_path / "o.exr")]) == 0


def test_a_text_file_as_analyzer_is_polrigs_own_one_line_error(tmp_path, capsys):
    raw = tmp_path / "raw.png"
    cv2.imwrite(str(raw), _polarized_raw())
    notes = tmp_path / "notes.txt"
    notes.write_text("calibrated on Monday\n")
    assert main(["stokes", str(raw), "--analyzer", str(notes), "--out", str(tmp_path / "o.exr")]) == 2
    err = capsys.readouterr().err
    assert err == (f"polrig: error: --analyzer {notes}: not a polrig analyzer model (an .npz "
                   f"file written by polrig calibrate)\n")
    assert "pickle" not in err
