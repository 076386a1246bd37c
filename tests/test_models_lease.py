"""The GPU lease's entry point (issue 32, item 6) end to end at tiny scale on the CPU:
``LEASE_DRY=1 benchmarks/gpu_train.sh`` runs ``python -m polrig.models.lease --dry`` (held-out and
calibration sets made in parallel processes, probe, the three stages planned in the budget,
export and ONNX check, evaluation against the shipped small weights, the shipping rule, the
sigma refitted and its coverage measured) and packs what a lease brings back: five files, each
under 16 MiB. About a minute on two shared cores (the budget: 18 s, overrun by the fixed costs)."""

from __future__ import annotations

import json
import os
import pathlib
import subprocess
import sys
import tarfile

import pytest

torch = pytest.importorskip("torch")
pytest.importorskip("onnxruntime")

from polrig.models import continuation, lease, sizes  # noqa: E402
from polrig.models.train import load_checkpoint  # noqa: E402

REPO = pathlib.Path(__file__).resolve().parents[1]
pytestmark = [pytest.mark.slow, pytest.mark.timeout(900)]


@pytest.fixture(scope="module")
def brought_back(tmp_path_factory):
    out = tmp_path_factory.mktemp("lease-out")
    env = dict(os.environ, OUT=str(out), LEASE_DRY="1", PY=sys.executable)
    run = subprocess.run(["bash", str(REPO / "benchmarks" / "gpu_train.sh"), "0.3", "large"], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=800)
    assert run.returncode == 0, run.stdout[-3000:] + run.stderr[-3000:]
    assert "polrig.models from " in run.stdout  # the links (polrig_path.sh) or this environment's install
    return out, run.stdout


def test_the_links_make_polrig_importable_without_an_install(tmp_path):
    """On a lent machine polrig is not installed: ``benchmarks/polrig_path.sh`` names the
    top-level folders as the install does. Checked with an interpreter that sees no install (no
    site processing: the editable install's finder is not loaded), only the dependencies."""
    deps = [p for p in sys.path if p.endswith("site-packages")]
    code = ("import sys; sys.path.extend(sys.argv[1:]); import polrig.models.lease as m, polrig.sim.dataset; "
            "from polrig.models import sizes; print(m.__file__, sizes.WEIGHTS_ROOT, sizes.is_shipped('small'))")
    run = subprocess.run(["bash", "-c", '. benchmarks/polrig_path.sh "$1" && cd "$1" && shift && "$@"', "_", str(tmp_path),
                          sys.executable, "-S", "-c", code, *deps], cwd=REPO, capture_output=True, text=True,
                         timeout=120, env={k: v for k, v in os.environ.items() if k != "PYTHONPATH"})
    assert run.returncode == 0, run.stderr[-2000:]
    module, weights, shipped = run.stdout.split()
    assert module == str(tmp_path / "shim" / "polrig" / "models" / "lease.py")
    assert weights == str(REPO / "models" / "weights") and shipped == "True"


def test_the_lease_brings_back_five_files_under_the_limits(brought_back):
    out, _ = brought_back
    files = sorted(p.name for p in out.iterdir())
    assert files == ["checkpoint.pt", "lease.log", "run.json", "tables.tar.gz", "weights.tar"]
    assert all((out / f).stat().st_size < lease.MAX_FILE_BYTES for f in files)


def test_the_run_trained_every_stage_exported_and_judged(brought_back, tmp_path):
    out, stdout = brought_back
    run = json.loads((out / "run.json").read_text())
    assert run["size"] == "large" and run["dry"] and run["device"] == "cpu" and run["baseline"] == "small"
    assert set(run["training"]["epochs"]) == {"pipnet", "pmmnet", "direct"}
    assert all(e >= 1 for e in run["training"]["epochs"].values())
    assert [d["stage"] for d in run["training"]["plan"]] == ["pipnet", "pmmnet", "direct"]
    # the verdict: a width-4 network of seconds does not beat the shipped small one anywhere
    for s in ("unseen_shapes", "mm_conductor"):
        assert run["scores"]["new"][s]["matrix_psnr"] < run["scores"]["baseline"][s]["matrix_psnr"]
        assert run["scores"]["new"][s]["samples"] == run["scores"]["baseline"][s]["samples"] >= 1
    assert run["ship"] is False and "ship: no" in stdout
    # the sigma refitted on the calibration set, its coverage measured on every verdict set
    assert set(run["sigma"]["within_2sigma"]) >= {"unseen_shapes", "mm_conductor"}
    with tarfile.open(out / "weights.tar") as t:
        t.extractall(tmp_path, filter="data")
    w = tmp_path / "weights"
    meta = json.loads((w / "model.json").read_text())
    assert meta["size"] == "large" and meta["width"] == lease.PROFILES["dry"]["width"]
    assert [e["network"] for e in meta["training"]["lineage"]] == ["pipnet", "pmmnet", "direct"]
    assert meta["export_check"]["single_shot.onnx"]["max_abs_diff"] <= meta["export_tolerance"]
    assert json.loads((w / "uncertainty.json").read_text())["checks"]
    record = sizes.model_record(w)
    assert record["size"] == "large" and record["training_hardware"].startswith("CPU")
    with tarfile.open(out / "tables.tar.gz") as t:
        names = set(t.getnames())
    assert {"eval_unseen_shapes_new.md", "eval_unseen_shapes_baseline.md", "log.csv", "summary.json"} <= names


def test_its_checkpoint_continues_the_next_lease(brought_back, tmp_path):
    """The checkpoint brought back is the committed form, with the optimizers' states: a later
    run continues it (here on the CPU, on-device scenes) and counts on."""
    from polrig.models.train_on_device import train_on_device

    out, _ = brought_back
    ck = load_checkpoint(out / "checkpoint.pt")
    assert ck["size"] == "large" and ck["optimizers"] and ck["storage"]["weights"] == "float32"
    assert (out / "checkpoint.pt").stat().st_size < continuation.MAX_COMMIT_BYTES
    steps = ck["totals"]["pipnet"]["steps"]
    summary = train_on_device(tmp_path / "next", None, overrides=dict(pipnet_epochs=1, pmmnet_epochs=1,
                                                                      direct_epochs=1),
                              size=32, steps_per_epoch=1, val_samples=2, continue_from=out / "checkpoint.pt",
                              export=False, echo=lambda s: None)
    assert summary["config"]["width"] == lease.PROFILES["dry"]["width"]
    assert load_checkpoint(tmp_path / "next" / "checkpoint.pt")["totals"]["pipnet"]["steps"] == steps + 1


def test_bad_sets_are_one_line(tmp_path, capsys):
    assert lease.main(["--out", str(tmp_path / "o"), "--dry", "--sets", "nope"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown set(s) ['nope']" in err[0]


def test_ship_copies_a_passed_run_and_refuses_the_rest(brought_back, tmp_path, monkeypatch):
    """``--ship``: a dry run (or one that failed the rule) is refused in one line, nothing
    copied; a run whose record says it passed lands in the size's folder and the results."""
    import shutil

    out, _ = brought_back
    monkeypatch.setitem(sizes.SIZE_FOLDERS, "large", tmp_path / "large")
    assert lease.main(["--ship", str(out)]) == 2
    assert not (tmp_path / "large").exists()
    passed = tmp_path / "passed"
    shutil.copytree(out, passed)
    record = json.loads((passed / "run.json").read_text())
    (passed / "run.json").write_text(json.dumps(dict(record, dry=False, ship=True)))
    results = tmp_path / "results"
    results.mkdir()
    written = lease.ship(passed, results)
    assert sizes.is_shipped("large") and (tmp_path / "large" / "checkpoint.pt").is_file()
    assert sizes.model_record(tmp_path / "large")["size"] == "large"
    assert {p.name for p in results.iterdir()} >= {"single_shot_large_unseen_shapes.json",
                                                   "single_shot_large_mm_conductor.md"}
    assert len(written) == len(set(written))
