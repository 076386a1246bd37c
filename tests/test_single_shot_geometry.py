"""The single-shot networks' geometry as EXR planes on request (issue 34, item 3): ``polrig infer
--geometry`` and a single-shot capture with ``--exr-planes ...,geometry`` write the normal,
albedo, roughness and light direction; the normals are unit vectors near the simulator's truth;
nothing changes without the request; the request is refused where the planes cannot be had."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.acquisition.plan import CapturePlan, PlanError, SingleShotOptions
from polrig.cli import main
from polrig.formats.exr import read_exr, read_mueller_exr

from test_cli_capture import sim_config

pytest.importorskip("onnxruntime")

GEOMETRY = {"geometry.normal.X", "geometry.normal.Y", "geometry.normal.Z", "geometry.light.X",
            "geometry.light.Y", "geometry.light.Z", "geometry.roughness"}


def angle_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    c = np.sum(a * b, axis=0) / (np.linalg.norm(a, axis=0) * np.linalg.norm(b, axis=0))
    return np.rad2deg(np.arccos(np.clip(c, -1, 1)))


@pytest.fixture(scope="module")
def render(tmp_path_factory):
    out = tmp_path_factory.mktemp("render")
    assert main(["sim", "render", "--size", "128x128", "--states", "0", "--out", str(out)]) == 0
    return out


def test_infer_geometry_planes_against_the_truth(render, tmp_path, capsys):
    plain, geo = tmp_path / "plain.exr", tmp_path / "geo.exr"
    raw = str(render / "pose0000p00_state00.png")
    assert main(["infer", raw, "--state-deg", "0", "--out", str(plain)]) == 0
    assert main(["infer", raw, "--state-deg", "0", "--out", str(geo), "--geometry"]) == 0
    p, g = read_exr(plain), read_exr(geo)
    assert not any(k.startswith("geometry.") for k in p.planes)  # only on request
    names = set(g.planes)
    assert GEOMETRY | {"geometry.albedo.R", "geometry.albedo.G", "geometry.albedo.B"} <= names
    # the Mueller image is the frame graph's, bit for bit
    np.testing.assert_array_equal(read_mueller_exr(geo).mueller, read_mueller_exr(plain).mueller)
    assert g.metadata["roughness_alpha"] > 0 and "geometry.normal.{X,Y,Z}" in g.metadata["planes"]
    normal = np.stack([g.planes[f"geometry.normal.{a}"] for a in "XYZ"])
    light = np.stack([g.planes[f"geometry.light.{a}"] for a in "XYZ"])
    obj = np.isfinite(normal).all(axis=0)
    assert obj.sum() > 100 and np.isnan(normal[:, ~obj]).all()  # NaN outside the object
    np.testing.assert_allclose(np.linalg.norm(normal[:, obj], axis=0), 1.0, atol=1e-3)
    np.testing.assert_allclose(np.linalg.norm(light[:, obj], axis=0), 1.0, atol=1e-3)
    assert np.all(normal[2, obj] < 0.2)  # towards the camera (camera Z forward)
    np.testing.assert_allclose(g.planes["geometry.roughness"][obj], g.metadata["roughness_alpha"], rtol=1e-6)
    # against the truth normals on the output grid (4x4 sensor cells wholly on the object)
    t = read_mueller_exr(render / "truth_pose0000p00_mueller.exr")
    tn = np.stack([t.extra[f"normal.{c}"] for c in "RGB"]).reshape(3, 32, 4, 32, 4).mean(axis=(2, 4))
    whole = (t.extra["mask"] > 0).reshape(32, 4, 32, 4).all(axis=(1, 3)) & obj
    err = angle_deg(normal[:, whole], tn[:, whole])
    facing = angle_deg(np.array([0.0, 0.0, -1.0])[:, None], tn[:, whole])  # the "facing the camera" guess
    print("geometry normal error median", np.median(err), "p90", np.percentile(err, 90),
          "facing-the-camera guess", np.median(facing), whole.sum())
    # measured on this render (sphere, 128x128, 177 cells): median 17.7 deg, 90 % 30.9 deg
    assert whole.sum() > 100 and np.median(err) < 25.0 and np.median(err) < np.median(facing) - 5.0


def test_single_shot_capture_writes_geometry_planes(tmp_path):
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    out = tmp_path / "run"
    assert main(["capture", "--poses", "0", "--mode", "single-shot", "--config", str(cfg), "--out",
                 str(out), "--no-progress", "--exr-planes", "mueller,mask,geometry"]) == 0
    f = read_exr(out / "c000_pose000.0" / "mueller.exr")
    assert GEOMETRY | {"geometry.albedo.Y", "mask.Y", "M00.Y"} <= set(f.planes)  # mono sensor
    assert not any(k.startswith("sigma.") for k in f.planes)
    import polrig

    ds = polrig.open_session(out)  # the openers read past the extra planes
    assert set(ds.data_vars) == {"mueller", "mask"}


@pytest.mark.parametrize("settings,needle", [
    ({"mode": "reference"}, "single-shot method's network outputs"),
    ({"mode": "hybrid", "states_deg": (0.0, 90.0)}, "single-shot method's network outputs"),
    ({"mode": "single-shot", "resolution": "full"}, "networks' own grid only"),
    ({"mode": "single-shot", "network_binning": 2}, "networks' own grid only"),
])
def test_geometry_is_refused_where_it_cannot_be_had(settings, needle):
    with pytest.raises(PlanError, match=needle) as exc:
        CapturePlan(poses_deg=(0.0,), exr_planes=("mueller", "geometry"), **settings)
    assert exc.value.field == "exr_planes"
    with pytest.raises(PlanError) as exc:
        SingleShotOptions(resolution="full", geometry=True)
    assert exc.value.field == "geometry"
    assert CapturePlan(poses_deg=(0.0,), mode="single-shot", exr_planes=("geometry", "mueller")
                       ).exr_planes == ("mueller", "geometry")


def test_capture_option_names_the_flag(tmp_path, capsys):
    cfg = sim_config(tmp_path / "rig.toml", noise=False)
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(tmp_path / "r"),
                 "--no-progress", "--exr-planes", "mueller,geometry"]) == 2
    err = capsys.readouterr().err
    assert "--exr-planes" in err and "single-shot" in err and not (tmp_path / "r").exists()
