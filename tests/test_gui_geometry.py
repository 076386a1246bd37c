"""The Viewer's geometry layer (issue 34, item 3; pytest-qt, offscreen): a result EXR written by
``polrig infer --geometry`` shows the networks' normal as the RGB normal map of its planes and
the albedo as colour, with the normal, light direction, roughness and albedo in the readout; a
maps EXR of ``polrig analyze --normals`` shows the shape-from-polarization candidate the
selector picks, with its zenith and azimuth; files without geometry planes offer no layer.

The data: a 128x128 simulated render (as tests/test_single_shot_geometry.py makes it), one
frame through the single-shot networks on the CPU."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("PySide6")
pytest.importorskip("pytestqt")
pytest.importorskip("onnxruntime")

from polrig.app import preview
from polrig.cli import main
from polrig.formats.exr import read_exr, write_mueller_exr
from polrig.gui import pipeline
from polrig.gui.qtimage import from_qimage
from test_gui import open_and_wait

pytestmark = pytest.mark.gui


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """``(infer --geometry result, analyze --normals maps EXR of it)``."""
    out = tmp_path_factory.mktemp("geo")
    assert main(["sim", "render", "--size", "128x128", "--states", "0", "--out", str(out)]) == 0
    result = out / "geo.exr"
    assert main(["infer", str(out / "pose0000p00_state00.png"), "--state-deg", "0", "--out",
                 str(result), "--geometry"]) == 0
    maps = out / "geo_maps.exr"
    assert main(["analyze", str(result), "--normals", "--ior", "1.5", "--out", str(maps)]) == 0
    return result, maps


def expected_normal_map(x, y, z):
    """The usual RGB normal map of camera-frame planes (X right, Y down, Z forward), shown in the
    viewer's frame (x right, y up, z towards the viewer): ``round(255 (n' + 1) / 2)``, black
    where a component is NaN."""
    n = np.stack([x, -y, -z]).astype(np.float64)
    rgb = np.rint((np.nan_to_num(n) + 1) / 2 * 255).clip(0, 255).astype(np.uint8)
    rgb = np.moveaxis(rgb, 0, -1)
    rgb[~np.isfinite(n).all(axis=0)] = 0
    return rgb


@pytest.fixture
def viewer(qtbot, viewer_panel):

    v = viewer_panel((1400, 800))
    v.messages = []
    v.message.connect(lambda lvl, t: v.messages.append((lvl, t)))
    return v


def test_network_geometry_layer_shows_the_normal_map_albedo_and_readout(qtbot, viewer, files):
    result, _ = files
    planes = read_exr(result)
    p, md = planes.planes, planes.metadata
    assert open_and_wait(qtbot, viewer, result)
    assert viewer.display.findData("geometry") >= 0 and viewer.display.findData("mueller") >= 0
    assert [viewer.geometry_choice.itemData(i) for i in range(viewer.geometry_choice.count())] == [
        "normal", "albedo"]
    viewer.display.setCurrentIndex(viewer.display.findData("geometry"))
    viewer.geometry_choice.setCurrentIndex(viewer.geometry_choice.findData("normal"))
    shown = from_qimage(viewer.view.image())
    want = expected_normal_map(p["geometry.normal.X"], p["geometry.normal.Y"], p["geometry.normal.Z"])
    np.testing.assert_array_equal(shown, want)
    obj = np.isfinite(p["geometry.normal.X"])
    assert obj.sum() > 100 and (~obj).sum() > 100
    # normals face the camera (Z < 0): the blue channel is above the middle on the object
    assert np.median(shown[obj][:, 2]) > 200 and not shown[~obj].any()
    # the albedo, as colour (all three colours for the luminance choice)
    viewer.geometry_choice.setCurrentIndex(viewer.geometry_choice.findData("albedo"))
    albedo = np.stack([p[f"geometry.albedo.{c}"] for c in "RGB"])
    np.testing.assert_array_equal(from_qimage(viewer.view.image()),
                                  preview.tone_map(albedo, white=1.0, valid=obj))
    # the readout: the networks' numbers at an object pixel, and outside it
    v, u = np.argwhere(obj)[len(np.argwhere(obj)) // 2]
    viewer._hovered(int(u), int(v))
    text = viewer.readout.text()
    n = [p[f"geometry.normal.{a}"][v, u] for a in "XYZ"]
    light = [p[f"geometry.light.{a}"][v, u] for a in "XYZ"]
    assert "normal (" + ", ".join(f"{c:+.3f}" for c in n) + ")" in text
    assert "light direction (" + ", ".join(f"{c:+.3f}" for c in light) + ")" in text
    assert f"roughness alpha {md['roughness_alpha']:.4g}" in text
    assert f"albedo R {albedo[0, v, u]:.4g}, G {albedo[1, v, u]:.4g}" in text
    assert f"Mueller at (u={u}, v={v})" in text  # the usual readout below it
    v0, u0 = np.argwhere(~obj)[0]
    viewer._hovered(int(u0), int(v0))
    assert "no normal (outside the object)" in viewer.readout.text()
    # the histogram: the normals' angle to the optical axis
    viewer.geometry_choice.setCurrentIndex(viewer.geometry_choice.findData("normal"))
    counts, edges, label = pipeline.histogram(viewer.data, "geometry", options=viewer.options())
    assert "angle" in label and counts.sum() == obj.sum()
    assert counts[edges[:-1] >= 90.0].sum() == 0  # every normal faces the camera
    assert not [m for m in viewer.messages if m[0] == "error"]


def test_shape_from_polarization_candidates_by_the_selector(qtbot, viewer, files):
    _, maps = files
    got = read_exr(maps)
    p = got.planes
    assert open_and_wait(qtbot, viewer, maps)  # a maps EXR: geometry only
    assert [viewer.display.itemData(i) for i in range(viewer.display.count())] == ["geometry"]
    keys = [viewer.geometry_choice.itemData(i) for i in range(viewer.geometry_choice.count())]
    assert keys == ["sfp0", "sfp1"]  # diffuse: the azimuth's pi ambiguity
    assert "AoLP + 180" in viewer.geometry_choice.itemText(1)
    for colour, ch in ((pipeline.LUMINANCE, "G"), (0, "R"), (2, "B")):  # luminance: green
        viewer.colour.setCurrentIndex(viewer.colour.findData(colour))
        for k in (0, 1):
            viewer.geometry_choice.setCurrentIndex(k)
            want = expected_normal_map(*(p[f"sfp_normal{k}.{a}.{ch}"] for a in "XYZ"))
            np.testing.assert_array_equal(from_qimage(viewer.view.image()), want)
    # the two candidates mirror each other about the viewing direction (orthographic view)
    n0 = np.stack([p[f"sfp_normal0.{a}.G"] for a in "XYZ"])
    n1 = np.stack([p[f"sfp_normal1.{a}.G"] for a in "XYZ"])
    ok = np.isfinite(n0).all(axis=0)
    assert ok.sum() > 100
    np.testing.assert_allclose(n1[:2, ok], -n0[:2, ok], atol=1e-5)
    np.testing.assert_allclose(n1[2, ok], n0[2, ok], atol=1e-6)
    # the readout: candidate 1 of every colour, its zenith and azimuth (+ 180 deg)
    v, u = np.argwhere(ok)[0]
    viewer._hovered(int(u), int(v))
    text = viewer.readout.text()
    assert "shape from polarization (diffuse, n = 1.5), candidate k = 1" in text
    for ch in "RGB":
        n = [p[f"sfp_normal1.{a}.{ch}"][v, u] for a in "XYZ"]
        if not np.isfinite(n).all():
            continue
        az = np.mod(p[f"sfp_azimuth_deg.{ch}"][v, u] + 180.0, 360.0)
        assert (f"{ch}: normal (" + ", ".join(f"{c:+.3f}" for c in n)
                + f"), zenith {p[f'sfp_zenith_deg0.{ch}'][v, u]:.2f} deg, image azimuth {az:.2f} deg"
                ) in text
    assert not [m for m in viewer.messages if m[0] == "error"]


def test_no_geometry_planes_no_layer(qtbot, tmp_path, viewer):
    from polrig.gui.viewer import load_exr

    path = tmp_path / "m.exr"
    m = np.zeros((1, 3, 3, 6, 8), np.float32)
    m[:, 0, 0] = 100.0
    write_mueller_exr(path, m)
    data = load_exr(path)
    assert data.geometry is None and "geometry" not in data.available()
    assert open_and_wait(qtbot, viewer, path)
    assert viewer.display.findData("geometry") < 0 and not viewer.geometry_choice.isEnabled()


def test_specular_candidates_name_their_zenith_and_azimuth(qtbot, viewer, files, tmp_path):
    """A specular maps EXR has four candidates (two zeniths about Brewster's angle, each with
    the pi azimuth ambiguity): candidate 3's readout gives zenith 1 (above Brewster) and the
    azimuth of candidate 0 (AoLP + 90 deg) + 180 deg."""
    result, _ = files
    maps = tmp_path / "spec.exr"
    assert main(["analyze", str(result), "--normals", "--ior", "1.5", "--reflection", "specular",
                 "--out", str(maps)]) == 0
    p = read_exr(maps).planes
    assert open_and_wait(qtbot, viewer, maps)
    labels = [viewer.geometry_choice.itemText(i) for i in range(viewer.geometry_choice.count())]
    assert len(labels) == 4 and "above Brewster, azimuth = AoLP + 270 deg" in labels[3]
    viewer.colour.setCurrentIndex(viewer.colour.findData(0))
    viewer.geometry_choice.setCurrentIndex(3)
    np.testing.assert_array_equal(from_qimage(viewer.view.image()),
                                  expected_normal_map(*(p[f"sfp_normal3.{a}.R"] for a in "XYZ")))
    ok = np.isfinite(p["sfp_normal3.X.R"])
    v, u = np.argwhere(ok)[0]
    viewer._hovered(int(u), int(v))
    az = np.mod(p["sfp_azimuth_deg.R"][v, u] + 180.0, 360.0)
    assert (f"zenith {p['sfp_zenith_deg1.R'][v, u]:.2f} deg, image azimuth {az:.2f} deg"
            in viewer.readout.text())
    assert p["sfp_zenith_deg1.R"][v, u] > np.rad2deg(np.arctan(1.5)) > p["sfp_zenith_deg0.R"][v, u]


def test_normal_map_colours_at_the_extremes():
    """Facing the camera is (128, 128, 255); the axes reach 0 and 255; NaN is black."""
    from polrig.gui.geometry_layer import normal_rgb

    n = np.array([[0.0, 1.0, -1.0, 0.0, np.nan],
                  [0.0, 0.0, 0.0, -1.0, 0.0],
                  [-1.0, 0.0, 0.0, 0.0, -1.0]])[:, None, :]
    rgb = normal_rgb(n)[0]
    np.testing.assert_array_equal(rgb, [[128, 128, 255], [255, 128, 128], [0, 128, 128],
                                        [128, 255, 128], [0, 0, 0]])
