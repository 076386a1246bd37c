"""The whole training path in seconds: a tiny simulated dataset (polrig.sim.dataset) -> PIPNet ->
PMMNet -> direct -> ONNX, resume, stage retraining, ONNX vs torch agreement, and the runtime on
the exported graphs."""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # no spinning threads on a shared CPU (set before torch)

import csv
import json

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from polrig.models.data import load_dataset  # noqa: E402
from polrig.models.train import TrainConfig, lr_at, train  # noqa: E402
from polrig.sim.dataset import generate_dataset  # noqa: E402

TINY = TrainConfig(pipnet_epochs=2, pmmnet_epochs=2, direct_epochs=1, batch_size=2, width=8, val_fraction=0.25)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    root = tmp_path_factory.mktemp("train")
    data = root / "data"  # 4 random simulated scenes of 32x32, as `polrig sim dataset` writes them
    generate_dataset(data, count=4, width=32, seed=0, shard_size=2, progress=False)
    summary = train(data, root / "run", TINY, echo=lambda s: None)
    return root, data, summary


def test_training_logs_checkpoints_and_exports(trained):
    root, _, summary = trained
    run = root / "run"
    rows = list(csv.DictReader((run / "log.csv").open()))
    assert [r["stage"] for r in rows] == ["pipnet"] * 2 + ["pmmnet"] * 2 + ["direct"]
    assert all(np.isfinite(float(r["train_loss"])) for r in rows)
    assert (run / "checkpoint.pt").is_file()
    for name in ("single_shot.onnx", "direct.onnx"):
        rec = summary["export"][name]
        assert (run / "weights" / name).stat().st_size == rec["bytes"]
        # ONNX graph and PyTorch agree on the same inputs (float32 rounding only).
        assert rec["max_abs_diff"] <= 1e-4 * max(1.0, rec["max_abs_output"])
    meta = json.loads((run / "weights" / "model.json").read_text())
    assert meta["opset"] >= 17 and meta["colours"] == 3


def test_resume_continues_after_the_last_epoch(trained, tmp_path):
    root, data, _ = trained
    import shutil

    run = tmp_path / "run"
    shutil.copytree(root / "run", run)
    ckpt = torch.load(run / "checkpoint.pt", weights_only=False)
    assert (ckpt["stage"], ckpt["epoch"]) == ("direct", 1)
    # Pretend the direct stage was configured longer: resume trains only the missing epoch.
    ckpt["config"]["direct_epochs"] = 2
    torch.save(ckpt, run / "checkpoint.pt")
    train(data, run, resume=True, export=False, echo=lambda s: None)
    rows = list(csv.DictReader((run / "log.csv").open()))
    assert [(r["stage"], r["epoch"]) for r in rows][-2:] == [("direct", "0"), ("direct", "1")]
    assert len(rows) == 6


def test_runtime_on_exported_graph_is_finite_and_in_dn(trained):
    from polrig.models.runtime import SingleShotModel

    root, data, _ = trained
    ds = load_dataset(data)
    model = SingleShotModel.load(root / "run" / "weights")
    scale = 1000.0
    mueller, aux = model.reconstruct(ds["analyzer"][0] * scale, ds["s_in"][0], mask=ds["mask"][0] > 0,
                                     scale=scale, stage_zero_axis=ds["stage_zero_axis"][0])
    assert mueller.shape == (3, 3, 3, 32, 32) and mueller.dtype == np.float32
    assert np.all(np.isfinite(mueller)) and np.all(mueller[..., ds["mask"][0] == 0] == 0)
    # DN scaling: the same capture in other units gives the same matrices in those units.
    m2, _ = model.reconstruct(ds["analyzer"][0], ds["s_in"][0], mask=ds["mask"][0] > 0, scale=1.0,
                              stage_zero_axis=ds["stage_zero_axis"][0])
    np.testing.assert_allclose(mueller, m2 * scale, rtol=1e-4, atol=1e-6 * scale)
    assert 0.01 <= aux["alpha"] <= 1.0
    # An odd size is padded internally and cropped back.
    odd, _ = model.reconstruct(ds["analyzer"][0][..., :29, :27], ds["s_in"][0], scale=1.0)
    assert odd.shape == (3, 3, 3, 29, 27) and np.all(np.isfinite(odd))


def test_lr_schedule_constant_then_linear_decay():
    cfg = TrainConfig(lr=1.0, decay_start=0.5, lr_final_fraction=0.1)
    lrs = [lr_at(cfg, e, 10) for e in range(10)]
    assert lrs[:5] == [1.0] * 5
    assert all(a > b for a, b in zip(lrs[4:], lrs[5:])) and lrs[-1] == pytest.approx(0.1)


def test_retrain_one_stage_on_networks_of_another_run(trained, tmp_path):
    root, data, _ = trained
    summary = train(data, tmp_path / "run", init_from=root / "run" / "checkpoint.pt", stages=("pmmnet",),
                    export=False, echo=lambda s: None)
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert {r["stage"] for r in rows} == {"pmmnet"} and len(rows) == TINY.pmmnet_epochs
    donor = torch.load(root / "run" / "checkpoint.pt", weights_only=False)
    mine = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=False)
    for k, v in donor["models"]["pipnet"].items():
        assert torch.equal(v, mine["models"]["pipnet"][k])
    assert summary["stages_trained"] == ["pmmnet"] and summary["config"]["direct_epochs"] == TINY.direct_epochs
    with pytest.raises(ValueError):
        train(data, tmp_path / "bad", stages=("nonsense",), echo=lambda s: None)


def test_warm_start_fine_tunes_from_the_donor_weights(trained, tmp_path):
    """With ``warm_start`` the trained stage starts at the donor's weights (lr 0 keeps them
    exactly); without it the stage starts from a fresh initialization."""
    root, data, _ = trained
    donor = torch.load(root / "run" / "checkpoint.pt", weights_only=False)["models"]["direct"]
    for warm, run in ((True, "warm"), (False, "cold")):
        train(data, tmp_path / run, init_from=root / "run" / "checkpoint.pt", stages=("direct",), warm_start=warm,
              overrides={"lr": 0.0}, export=False, echo=lambda s: None)
        mine = dict(torch.load(tmp_path / run / "checkpoint.pt", weights_only=False)["models"]["direct"])
        same = all(torch.equal(v, mine[k]) for k, v in donor.items() if k.endswith("weight") and v.dim() == 4)
        assert same == warm
    with pytest.raises(ValueError, match="init_from"):
        train(data, tmp_path / "bad", warm_start=True, echo=lambda s: None)


def test_window_crop_cuts_rectangles_for_the_requested_fraction():
    from polrig.models.train import window_crop

    mask = torch.ones(400, 1, 32, 32)
    gen = torch.Generator().manual_seed(0)
    win = window_crop(mask, 0.5, gen)
    cropped = win.sum((1, 2, 3)) < 32 * 32
    assert 0.4 < float(cropped.float().mean()) < 0.6
    for w in win[cropped]:  # one axis-aligned rectangle between 1/4 and 3/4 of each side
        rows, cols = torch.nonzero(w[0].sum(1))[:, 0], torch.nonzero(w[0].sum(0))[:, 0]
        assert 8 <= len(rows) <= 24 and 8 <= len(cols) <= 24
        assert float(w.sum()) == len(rows) * len(cols)
    assert torch.equal(window_crop(mask, 0.0, gen), mask)


def test_training_with_crops_runs_and_is_reproducible(trained, tmp_path):
    root, data, _ = trained
    losses = []
    for run in ("a", "b"):
        train(data, tmp_path / run, TINY, overrides={"crop_fraction": 1.0, "pmmnet_epochs": 0, "direct_epochs": 0},
              stages=("pipnet",), init_from=root / "run" / "checkpoint.pt", export=False, echo=lambda s: None)
        losses.append([r["train_loss"] for r in csv.DictReader((tmp_path / run / "log.csv").open())])
    assert losses[0] == losses[1] and len(losses[0]) == TINY.pipnet_epochs


def test_sfp_supervision_is_logged_and_changes_the_training(trained, tmp_path):
    root, data, _ = trained
    logs = {}
    for run, weight in (("plain", 0.0), ("supervised", 1.0)):
        train(data, tmp_path / run, TINY, overrides={"sfp_supervision": weight, "pmmnet_epochs": 0, "direct_epochs": 0},
              stages=("pipnet",), init_from=root / "run" / "checkpoint.pt", export=False, echo=lambda s: None)
        logs[run] = list(csv.DictReader((tmp_path / run / "log.csv").open()))
    assert "bce_trust" in json.loads(logs["supervised"][0]["details"])
    assert "bce_trust" not in json.loads(logs["plain"][0]["details"])
    assert logs["plain"][-1]["train_loss"] != logs["supervised"][-1]["train_loss"]


def test_rotation_matrices_are_rotations_by_the_angle():
    from polrig.models.train import rotation_matrices

    gen = torch.Generator().manual_seed(1)
    axis = torch.nn.functional.normalize(torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=1)
    angle = torch.rand(50, generator=gen, dtype=torch.float64) * np.pi
    r = rotation_matrices(axis, angle)
    assert torch.allclose(r @ r.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(50, 3, 3), atol=1e-12)
    assert torch.allclose(torch.linalg.det(r), torch.ones(50, dtype=torch.float64), atol=1e-12)
    assert torch.allclose(torch.einsum("bij,bj->bi", r, axis), axis, atol=1e-12)  # the axis stays
    perp = torch.nn.functional.normalize(torch.linalg.cross(axis, torch.randn(50, 3, generator=gen, dtype=torch.float64)), dim=1)
    turned = torch.einsum("bij,bj->bi", r, perp)
    assert torch.allclose(torch.acos((turned * perp).sum(1).clamp(-1, 1)), angle, atol=1e-6)
    # right-handed: a quarter turn about z takes x to y
    q = rotation_matrices(torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64), torch.tensor([np.pi / 2], dtype=torch.float64))
    assert torch.allclose(q[0] @ torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64),
                          torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-12)


def test_perturbed_geometry_turns_normals_and_light_together_within_the_bounds():
    from polrig.models.train import perturbed_geometry

    gen = torch.Generator().manual_seed(2)
    normal = torch.nn.functional.normalize(torch.randn(64, 3, 8, 8, generator=gen, dtype=torch.float64), dim=1)
    wi = torch.nn.functional.normalize(torch.randn(64, 3, 8, 8, generator=gen, dtype=torch.float64), dim=1)
    angle = lambda a, b: torch.rad2deg(torch.acos((a * b).sum(1).clamp(-1, 1)))  # noqa: E731
    n2, w2 = perturbed_geometry(normal, wi, gen, 40.0, 0.0)
    assert torch.allclose(n2.norm(dim=1), torch.ones(64, 8, 8, dtype=torch.float64))
    assert torch.allclose(w2.norm(dim=1), torch.ones(64, 8, 8, dtype=torch.float64))
    turned = angle(w2, wi)
    assert float(turned.max()) <= 40.0 + 1e-6 and float(turned.mean()) > 5.0
    # one rigid rotation per image: angles between the light directions of two pixels are kept
    assert torch.allclose((w2[:, :, 0, 0] * w2[:, :, 3, 5]).sum(1), (wi[:, :, 0, 0] * wi[:, :, 3, 5]).sum(1), atol=1e-9)
    # the light alone turns further, by at most the sum of the two bounds
    _, w3 = perturbed_geometry(normal, wi, gen, 10.0, 20.0)
    assert float(angle(w3, wi).max()) <= 30.0 + 1e-6 and float(angle(w3, wi).max()) > 10.0
    # without rotations only the smooth noise bends the normals, and the light is untouched
    n4, w4 = perturbed_geometry(normal, wi, gen, 0.0, 0.0)
    assert torch.allclose(w4, wi) and float(angle(n4, normal).max()) > 1.0


def test_geometry_toward_view_pulls_normal_and_light_by_one_fraction_per_image():
    from polrig.models.train import geometry_toward_view

    gen = torch.Generator().manual_seed(3)
    unit = lambda x: torch.nn.functional.normalize(x, dim=1)  # noqa: E731
    normal, wi = (unit(torch.randn(32, 3, 4, 4, generator=gen, dtype=torch.float64)) for _ in range(2))
    wo = unit(torch.randn(32, 3, 4, 4, generator=gen, dtype=torch.float64) * 0.2 + torch.tensor([0.0, 0.0, -1.0],
                                                                                              dtype=torch.float64)[:, None, None])
    n2, w2 = geometry_toward_view(normal, wi, wo, gen, 1.0)
    angle = lambda a, b: torch.acos((a * b).sum(1).clamp(-1, 1))  # noqa: E731
    for v, v2 in ((normal, n2), (wi, w2)):
        assert torch.all(angle(v2, wo) <= angle(v, wo) + 1e-9)  # never further from the view
        assert torch.allclose(torch.linalg.det(torch.stack([v, wo, v2], 1).permute(0, 3, 4, 1, 2)),
                              torch.zeros(32, 4, 4, dtype=torch.float64), atol=1e-9)  # in the plane of v and wo

    def fraction(v, v2):  # t of normalize(v + t (wo - v)) recovered from the result
        a, b = torch.linalg.cross(v2, v, dim=1).norm(dim=1), torch.linalg.cross(v2, wo, dim=1).norm(dim=1)
        return a / (a + b)
    t_n, t_w = fraction(normal, n2), fraction(wi, w2)
    assert torch.allclose(t_n, t_w, atol=1e-6)  # one pull per image for normal and light
    assert torch.allclose(t_n, t_n[:, :1, :1].expand_as(t_n), atol=1e-6)
    assert float(t_n.max()) <= 1.0 and float(t_n.std()) > 0.1
    same = geometry_toward_view(normal, wi, wo, gen, 0.0)
    assert torch.allclose(same[0], normal) and torch.allclose(same[1], wi)


def test_pmmnet_on_perturbed_initializations_trains_reproducibly_and_differs(trained, tmp_path):
    root, data, _ = trained
    losses = {}
    for run, fraction in (("plain", 0.0), ("perturbed", 1.0), ("again", 1.0)):
        train(data, tmp_path / run, TINY, overrides={"init_perturb_fraction": fraction},
              stages=("pmmnet",), init_from=root / "run" / "checkpoint.pt", export=False, echo=lambda s: None)
        losses[run] = [r["train_loss"] for r in csv.DictReader((tmp_path / run / "log.csv").open())]
    assert losses["perturbed"] == losses["again"] and len(losses["plain"]) == TINY.pmmnet_epochs
    assert losses["perturbed"] != losses["plain"]


@pytest.mark.parametrize("flag, value", [("--init-perturb-fraction", "1.5"), ("--init-perturb-deg", "-1"),
                                         ("--init-perturb-light-deg", "200"), ("--init-perturb-toward-view", "2")])
def test_cli_rejects_out_of_range_perturbation_in_one_line(tmp_path, capsys, flag, value):
    from polrig.cli import main

    assert main(["train", "--data", str(tmp_path), "--out", str(tmp_path / "run"), flag, value]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("polrig: error: " + flag) and "\n" not in err
    assert not (tmp_path / "run").exists()  # rejected before anything is written


def test_cli_perturbation_flags_reach_the_run_config(trained, tmp_path):
    from polrig.cli import main

    root, data, _ = trained
    out = tmp_path / "run"
    assert main(["train", "--data", str(data), "--out", str(out), "--init-from", str(root / "run" / "checkpoint.pt"),
                 "--warm-start", "--stages", "pmmnet", "--pmmnet-epochs", "1", "--init-perturb-fraction", "0.5",
                 "--init-perturb-deg", "25", "--init-perturb-light-deg", "10", "--init-perturb-toward-view", "0.3",
                 "--no-export"]) == 0
    config = json.loads((out / "summary.json").read_text())["config"]
    assert (config["init_perturb_fraction"], config["init_perturb_deg"], config["init_perturb_light_deg"],
            config["init_perturb_toward_view"]) == (0.5, 25.0, 10.0, 0.3)


def test_fine_tune_from_a_weights_folder(trained, tmp_path):
    """``init_from`` a weights folder (the ONNX graphs only, as the repository ships them): the
    networks are recovered (polrig.models.recover), the trained stage's batch norms are set on the
    data, and the networks taken unchanged export to graphs computing what the donor's do."""
    import onnxruntime as ort

    from polrig.models.evaluate import network_inputs

    root, data, _ = trained
    said = []
    summary = train(data, tmp_path / "run", init_from=root / "run" / "weights", stages=("pmmnet",), warm_start=True,
                    echo=said.append)
    assert any("batch-norm statistics" in s for s in said)
    rows = list(csv.DictReader((tmp_path / "run" / "log.csv").open()))
    assert [r["stage"] for r in rows] == ["pmmnet"] * TINY.pmmnet_epochs
    assert summary["config"]["pipnet_epochs"] == TINY.pipnet_epochs  # the donor's lineage is kept
    ds = load_dataset(data)
    feed = dict(zip(("analyzer", "mask", "s_in", "wo", "stage_zero_axis"), network_inputs(ds, 0)))

    def run(weights, graph):
        sess = ort.InferenceSession(str(weights / graph), providers=["CPUExecutionProvider"])
        return sess.run(None, {i.name: feed[i.name] for i in sess.get_inputs()})

    old, new = run(root / "run" / "weights", "direct.onnx"), run(tmp_path / "run" / "weights", "direct.onnx")
    np.testing.assert_allclose(new[0], old[0], atol=1e-5 * max(1.0, float(np.abs(old[0]).max())))
    old, new = run(root / "run" / "weights", "single_shot.onnx"), run(tmp_path / "run" / "weights", "single_shot.onnx")
    np.testing.assert_allclose(new[2], old[2], atol=1e-5)  # PIPNet's normals: PIPNet was not trained
    assert not np.allclose(new[0], old[0])  # PMMNet was


def test_mirrored_training_sample_is_the_simulated_mirror_scene(trained):
    """A mirrored training sample is what the simulator renders for the mirrored geometry: its
    truth is the pBRDF of the mirrored normals, light and view (the rendering is ``D M D``), and
    its analyzer images are the mirrored matrix rendered under the mirrored incident state."""
    from polrig.models import train as tr
    from polrig.models.evaluate import render_analyzer
    from polrig.optics import pbrdf

    _, data, _ = trained
    ds = load_dataset(data)
    t = tr._tensors(ds)
    t["eta"] = torch.from_numpy(ds["eta"])
    keys = ("analyzer", "mask", "s_in", "wo", "normal", "wi", "kd", "alpha", "mueller", "stage_zero_axis")
    idx = torch.tensor([0, 1])
    plain = dict(zip(keys, tr._pick(t, idx, keys)))
    flipped = dict(zip(keys, tr._pick(t, idx, keys, torch.tensor([True, False]))))
    for k in keys:  # the second sample is untouched, the dataset too
        assert torch.equal(flipped[k][1], plain[k][1]) and torch.equal(t[k][idx][0], plain[k][0])
    f = {k: v[0].double().numpy() for k, v in flipped.items()}
    on = lambda v: np.moveaxis(v, 0, -1)  # noqa: E731  (3, H, W) -> (H, W, 3)
    m = f["mask"][0] > 0
    got = np.moveaxis(f["mueller"], (-2, -1), (0, 1))[m]
    errors = []
    for ks in (1.0, 0.0):  # the simulator draws ks = 0 for one material in ten and does not store it
        truth = pbrdf.linear_rig_mueller(on(f["normal"])[m], on(f["wi"])[m], on(f["wo"])[m], kd=on(f["kd"])[m],
                                         alpha=float(f["alpha"]), eta=float(t["eta"][0]), ks=ks,
                                         stage_zero_axis=f["stage_zero_axis"], camera_x_axis=[1.0, 0.0, 0.0])
        # The data carry the light's fall-off, colour and the exposure per pixel: compare the
        # matrices normalised by m00, where both are lit.
        lit = (truth[..., 0, 0] > 1e-6 * truth[..., 0, 0].max()) & (got[..., 0, 0] > 1e-6 * got[..., 0, 0].max())
        assert lit.sum() > 30
        norm = lambda x: x[lit] / x[lit][:, 0, 0][:, None, None]  # noqa: E731
        assert np.abs(norm(got)[:, :, 2]).max() > 0.01  # column 2 is not trivially zero
        errors.append(np.abs(norm(got) - norm(truth)).max())
    assert min(errors) < 1e-3, errors
    # analyzer images: the mirrored truth under the mirrored state, up to the sensor noise
    clean = render_analyzer(f["mueller"], f["s_in"])[..., m]
    assert np.corrcoef(clean.ravel(), f["analyzer"][..., m].ravel())[0, 1] > 0.95
    wrong = render_analyzer(f["mueller"], f["s_in"] * [1, 1, -1])[..., m]  # the state not mirrored
    assert np.abs(clean - f["analyzer"][..., m]).mean() < np.abs(wrong - f["analyzer"][..., m]).mean()


def test_training_with_mirrored_samples_is_reproducible_and_differs(trained, tmp_path):
    root, data, _ = trained
    losses = {}
    for run, fraction in (("plain", 0.0), ("mirrored", 0.5), ("again", 0.5)):
        train(data, tmp_path / run, TINY, overrides={"mirror_fraction": fraction, "direct_epochs": 0},
              stages=("pipnet", "pmmnet"), init_from=root / "run" / "checkpoint.pt", export=False,
              echo=lambda s: None)
        losses[run] = [r["train_loss"] for r in csv.DictReader((tmp_path / run / "log.csv").open())]
    assert losses["mirrored"] == losses["again"] and losses["mirrored"] != losses["plain"]
