"""Exports (issue 34, item 6): a session and a result as OME-Zarr, read back by the ``ome-zarr``
reader (the oracle: axes, scale, channel names, values), and as OME-TIFF, read back by tifffile
(series, axes, shape, OME-XML channel names and physical sizes); the sample metadata given at
capture reach both; bad requests are one line."""

from __future__ import annotations

import json
import pathlib
import xml.etree.ElementTree as ET

import numpy as np
import pytest

import polrig
from polrig.cli import main
from polrig.formats.exr import read_mueller_exr
from polrig.formats.ome import OmeImage, write_ome_zarr

from test_cli_capture import sim_config

ome_zarr = pytest.importorskip("ome_zarr")
tifffile = pytest.importorskip("tifffile")


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("export")
    cfg = sim_config(tmp / "rig.toml", noise=False)
    out = tmp / "run"
    assert main(["capture", "--poses", "0,90", "--config", str(cfg), "--out", str(out),
                 "--no-progress", "--sample", "gold foil", "--operator", "ada", "--note", "export",
                 "--md", "lot=7", "--exr-planes", "mueller,sigma,mask"]) == 0
    return out


def read_ngff(path: pathlib.Path):
    """Every node the ome-zarr reader finds, by its path relative to ``path``."""
    from ome_zarr.io import parse_url
    from ome_zarr.reader import Reader

    loc = parse_url(str(path))
    assert loc is not None, f"{path}: not an OME-Zarr"
    return list(Reader(loc)())


@pytest.mark.parametrize("version", ["0.4", "0.5"])
def test_session_to_ome_zarr_reads_back_with_axes_scale_channels_and_values(session, tmp_path, version):
    out = tmp_path / "s.zarr"
    assert main(["export", str(session), "--format", "ome-zarr", "-o", str(out),
                 "--pixel-size", "12.5,10", "--ngff", version]) == 0
    nodes = read_ngff(out)
    image = nodes[0]
    md = image.metadata
    assert [a["name"] for a in md["axes"]] == ["t", "c", "y", "x"]
    assert [a["type"] for a in md["axes"]] == ["time", "channel", "space", "space"]
    assert md["axes"][2]["unit"] == md["axes"][3]["unit"] == "micrometer"
    assert md["coordinateTransformations"][0][0] == {"type": "scale", "scale": [1.0, 1.0, 12.5, 10.0]}
    assert md["channel_names"][:3] == ["M00.Y", "M01.Y", "M02.Y"] and len(md["channel_names"]) == 9
    assert md["visible"] == [True] + [False] * 8  # M00 shown first
    data = np.asarray(image.data[0])
    assert data.shape == (2, 9, 32, 32)
    f = read_mueller_exr(session / "c001_pose090.0" / "mueller.exr")
    np.testing.assert_array_equal(data[1], f.mueller.reshape(9, 32, 32))  # mono: M{i}{j}.Y
    # the other quantities: image groups of their own, same axes and scale
    sigma = read_ngff(out / "sigma")[0]
    assert sigma.metadata["channel_names"][4] == "sigma.M11.Y"
    assert sigma.metadata["coordinateTransformations"] == md["coordinateTransformations"]
    np.testing.assert_array_equal(np.asarray(sigma.data[0])[1, 5], f.extra["sigma.M12.Y"])
    mask = read_ngff(out / "mask")[0]
    assert mask.metadata["channel_names"] == ["mask.Y"] and mask.data[0].dtype == np.uint8
    # metadata: the root's polrig attributes
    import zarr

    attrs = zarr.open_group(str(out), mode="r").attrs["polrig"]
    assert attrs["sample_metadata"] == {"sample": "gold foil", "operator": "ada", "note": "export",
                                        "lot": "7"}
    assert [c["pose_deg"] for c in attrs["captures"]] == [0.0, 90.0]
    assert attrs["pixel_size"] == {"y": 12.5, "x": 10.0, "unit": "micrometer"}
    assert attrs["plan"]["poses_deg"] == [0.0, 90.0]


def test_result_to_ome_zarr_without_pixel_size_is_unitless(session, tmp_path):
    out = polrig.export(session / "c000_pose000.0" / "mueller.exr", tmp_path / "r.zarr")
    md = read_ngff(out)[0].metadata
    assert [a["name"] for a in md["axes"]] == ["c", "y", "x"]
    assert all("unit" not in a for a in md["axes"])
    assert md["coordinateTransformations"][0][0]["scale"] == [1.0, 1.0, 1.0]
    import zarr

    attrs = zarr.open_group(str(out), mode="r").attrs["polrig"]
    assert attrs["pixel_size"].startswith("not known") and attrs["sample"] == "gold foil"
    # exported again over itself: replaced; over another folder: refused
    polrig.export(session / "c000_pose000.0" / "mueller.exr", out)
    (tmp_path / "keep").mkdir()
    with pytest.raises(FileExistsError, match="not a Zarr store"):
        polrig.export(session / "c000_pose000.0" / "mueller.exr", tmp_path / "keep")


def test_session_to_ome_tiff_reads_back_as_hyperstack_series(session, tmp_path):
    out = tmp_path / "s.ome.tif"
    assert main(["export", str(session), "--format", "ome-tiff", "-o", str(out),
                 "--pixel-size", "8"]) == 0
    with tifffile.TiffFile(out) as tif:
        assert tif.is_ome
        names = [s.name for s in tif.series]
        assert names == ["mueller", "sigma", "mask"]
        mueller = tif.series[0]
        assert mueller.axes == "TCYX" and mueller.shape == (2, 9, 32, 32)
        f = read_mueller_exr(session / "c001_pose090.0" / "mueller.exr")
        np.testing.assert_array_equal(mueller.asarray()[1], f.mueller.reshape(9, 32, 32))
        assert tif.series[2].dtype == np.uint8
        root = ET.fromstring(tif.ome_metadata)
    ns = {"o": root.tag.split("}")[0].strip("{")}
    images = root.findall("o:Image", ns)
    pixels = images[0].find("o:Pixels", ns)
    assert float(pixels.get("PhysicalSizeX")) == 8.0 and pixels.get("PhysicalSizeXUnit") == "µm"
    assert [c.get("Name") for c in pixels.findall("o:Channel", ns)][:2] == ["M00.Y", "M01.Y"]
    description = json.loads(images[0].find("o:Description", ns).text)
    assert description["sample"] == "gold foil" and description["lot"] == "7"
    pairs = {m.get("K"): m.text for m in root.iter(f"{{{ns['o']}}}M")}
    assert pairs == {"sample": "gold foil", "operator": "ada", "note": "export", "lot": "7"}


def test_colour_result_channels_are_element_major(tmp_path):
    rng = np.random.default_rng(0)
    mueller = rng.normal(size=(2, 9, 3, 4, 5)).astype(np.float32)  # (T, elements, colour, y, x)
    names = tuple(f"M{i}{j}.{s}" for i in range(3) for j in range(3) for s in "RGB")
    write_ome_zarr(tmp_path / "c.zarr", [OmeImage("mueller", mueller.reshape(2, 27, 4, 5), names)])
    node = read_ngff(tmp_path / "c.zarr")[0]
    assert node.metadata["channel_names"][:4] == ["M00.R", "M00.G", "M00.B", "M01.R"]
    assert [c[1] for c in node.metadata["colormap"][:3]] == [[1, 0, 0], [0, 1, 0], [0, 0, 1]]
    np.testing.assert_array_equal(np.asarray(node.data[0]), mueller.reshape(2, 27, 4, 5))


def test_bad_requests_are_one_line(session, tmp_path, capsys):
    assert main(["export", str(tmp_path / "nothing"), "-o", str(tmp_path / "o.zarr")]) != 0
    assert "no such session folder or result file" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["export", str(session), "-o", str(tmp_path / "o.zarr"), "--pixel-size=-1"])
    assert "must be > 0" in capsys.readouterr().err
    assert main(["export", str(session), "-o", str(tmp_path / "no" / "o.zarr")]) != 0
    assert "does not exist" in capsys.readouterr().err and not (tmp_path / "no").exists()
    with pytest.raises(ValueError, match="unknown export format"):
        polrig.export(session, tmp_path / "x", "png")


def test_export_refuses_its_source_wrong_names_and_ngff_with_tiff(session, tmp_path, capsys):
    """One line, exit 2, nothing written or replaced: an output that is the source (its own
    name, a link to it), a name without the format's ending, --ngff with ome-tiff; an unknown
    revision's line keeps its quotes."""
    import shutil

    src = tmp_path / "m.exr"
    shutil.copy(session / "c000_pose000.0" / "mueller.exr", src)
    (tmp_path / "m.ome.tif").symlink_to(src)
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    cases = [
        (["-o", src, "--format", "ome-tiff"], f"-o {src} is the input {src};"),
        (["-o", tmp_path / "m.ome.tif", "--format", "ome-tiff"],
         f"-o {tmp_path / 'm.ome.tif'} is the input {src};"),
        (["-o", tmp_path / "x.tif", "--format", "ome-tiff"],
         f"-o {tmp_path / 'x.tif'}: an ome-tiff output's name must end in .ome.tif or .ome.tiff"),
        (["-o", tmp_path / "x.exr"], f"-o {tmp_path / 'x.exr'}: an ome-zarr output's name must end in .zarr"),
        (["-o", tmp_path / "x.ome.tif", "--format", "ome-tiff", "--ngff", "0.5"],
         "--ngff 0.5 applies to --format ome-zarr only, not ome-tiff"),
    ]
    for argv, message in cases:
        capsys.readouterr()
        assert main(["export", str(src), *map(str, argv)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"polrig: error: {message}") and err.count("\n") == 1, err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    assert main(["export", str(session), "--revision", "rev9", "-o", str(tmp_path / "r.zarr")]) == 2
    assert capsys.readouterr().err == (f"polrig: error: {session}: no revision 'rev9' "
                                       f"(revisions: none)\n")
    assert main(["export", str(src), "--format", "ome-tiff", "-o", str(tmp_path / "ok.ome.tiff")]) == 0


@pytest.mark.parametrize("fmt, name", [("ome-tiff", "o.ome.tif"), ("ome-zarr", "o.zarr")])
def test_a_full_disk_names_the_export(session, tmp_path, fmt, name):
    from _cli_helpers import polrig_with_file_size_limit

    out = tmp_path / name
    res = polrig_with_file_size_limit(["export", session / "c000_pose000.0" / "mueller.exr",
                                       "--format", fmt, "-o", out], 2048)
    assert res.returncode == 1, res.stderr
    assert res.stderr == f"polrig: error: {out}: cannot write (File too large)\n"
    assert list(tmp_path.iterdir()) == []


def test_a_full_disk_names_the_export_in_the_python_api_too(session, tmp_path):
    """``polrig.export(...)`` raises the same ``OSError`` naming the output (the command line
    only prints it), not tifffile's line without a file."""
    from _cli_helpers import run_with_file_size_limit

    out = tmp_path / "o.ome.tif"
    code = (f"import errno, polrig\ntry:\n    polrig.export({str(session / 'c000_pose000.0' / 'mueller.exr')!r}, "
            f"{str(out)!r}, 'ome-tiff')\nexcept OSError as e:\n    print(e.errno == errno.EFBIG, e)\n")
    res = run_with_file_size_limit(code, 2048)
    assert res.stdout == f"True {out}: cannot write (File too large)\n", res.stderr


def test_ome_zarr_reads_each_capture_once(session, tmp_path, monkeypatch):
    from polrig.app import dataset

    reads = []
    real = dataset.read_mueller_exr
    monkeypatch.setattr(dataset, "read_mueller_exr", lambda p: reads.append(p.parent.name) or real(p))
    polrig.export(session, tmp_path / "once.zarr")
    assert sorted(reads) == ["c000_pose000.0", "c001_pose090.0"]  # mueller, sigma, mask: one read


def test_ome_tiff_reads_each_capture_once_and_writes_every_series_as_the_files_hold_it(
        session, tmp_path, monkeypatch):
    """OME-TIFF series follow one another; the session is still read a capture at a time, once
    (the later series spilled beside the output and read back), with nothing left behind."""
    from polrig.app import dataset

    reads = []
    real = dataset.read_mueller_exr
    monkeypatch.setattr(dataset, "read_mueller_exr", lambda p: reads.append(p.parent.name) or real(p))
    out = polrig.export(session, tmp_path / "once.ome.tif", "ome-tiff")
    captures = ["c000_pose000.0", "c001_pose090.0"]
    assert sorted(reads) == captures  # mueller, sigma, mask: one read per capture
    with tifffile.TiffFile(out) as tif:
        series = {s.name: s.asarray() for s in tif.series}
    assert [v.shape for v in series.values()] == [(2, 9, 32, 32), (2, 9, 32, 32), (2, 32, 32)]  # C=1 squeezed
    for t, cap in enumerate(captures):
        f = real(session / cap / "mueller.exr")
        np.testing.assert_array_equal(series["mueller"][t], f.mueller.reshape(9, 32, 32))
        sigma = np.stack([f.extra[f"sigma.M{i}{j}.Y"] for i in range(3) for j in range(3)])
        np.testing.assert_array_equal(series["sigma"][t], sigma)
        np.testing.assert_array_equal(series["mask"][t], f.extra["mask.Y"].astype(np.uint8))
    assert not np.array_equal(series["mueller"][0], series["mueller"][1])  # two captures, not one twice
    assert sorted(p.name for p in tmp_path.iterdir()) == ["once.ome.tif"]  # no spill folder left


def test_pixel_size_from_the_calibration_set(tmp_path, session, capsys):
    """The pixel size at the turntable axis: depth 0.5 m where the axis crosses the optical axis,
    f = 600 px, a superpixel of the mono layout is 2x2 sensor pixels: 0.5 / 600 * 2 m."""
    from polrig.calibration.calset import CalibrationSet
    from polrig.sensor.analyzer import AnalyzerModel

    cs = CalibrationSet()
    cs.params["camera"] = {"layout": "imx250mzr", "readout": [64, 64, 0, 0], "sensor_size": [64, 64]}
    cs.params["intrinsics"] = {"K": [[600.0, 0, 32.0], [0, 600.0, 32.0], [0, 0, 1]],
                               "dist": [0.0] * 5, "image_size": [64, 64]}
    cs.params["turntable"] = {"axis_cam": [0.0, -0.97, 0.26], "point_cam_m": [0.0, 0.3, 0.5 - 0.3 * 0.26 / 0.97],
                              "axis_std_deg": 0.05}
    cs.params["generator"] = {"zero_offset_deg": 0.0, "extinction_ratio": 1e6,
                              "stage_zero_axis_cam": [1.0, 0.0, 0.0]}
    cs.analyzer = AnalyzerModel.ideal("imx250mzr", (64, 64))
    cs.dofp_maps = {"valid": np.ones((64, 64), bool)}
    cal = tmp_path / "cal"
    cs.save(cal)
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    run = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(run), "--no-progress",
                 "--calibration", str(cal), "--exr-planes", "mueller,mask"]) == 0
    out = polrig.export(run, tmp_path / "cal.zarr", calibration=cal)
    md = read_ngff(out)[0].metadata
    expected = 0.5 / 600 * 2 * 1e6  # micrometres
    np.testing.assert_allclose(md["coordinateTransformations"][0][0]["scale"][2:], [expected] * 2, rtol=1e-9)
    assert md["axes"][3]["unit"] == "micrometer"
    # a result header knows its own layout and demosaic too
    one = polrig.export(run / "c000_pose000.0" / "mueller.exr", tmp_path / "one.ome.tif", "ome-tiff",
                        calibration=cal)
    with tifffile.TiffFile(one) as tif:
        assert float(ET.fromstring(tif.ome_metadata).find(".//{*}Pixels").get("PhysicalSizeX")) == pytest.approx(expected)
    # a session captured with another calibration (the nominal one): refused, nothing written
    with pytest.raises(ValueError, match="the source was captured with 'nominal'"):
        polrig.export(session, tmp_path / "x.zarr", calibration=cal)
    assert not (tmp_path / "x.zarr").exists()
    # the command's line ends with the closing quote
    assert main(["export", str(session), "--calibration", str(cal), "-o", str(tmp_path / "x.zarr")]) == 2
    assert capsys.readouterr().err.endswith("the source was captured with 'nominal'\n")
