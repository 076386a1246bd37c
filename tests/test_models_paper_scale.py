"""The paper-scale training entry point (:mod:`polrig.models.paper_scale`, issue 22 item 4) end to end
on the CPU at tiny scale: ``polrig sim dataset`` in two processes, the three stages, the ONNX
export and check, the evaluation against the shipped graphs, one small output folder; and
the budget arithmetic of the epoch plan."""

from __future__ import annotations

import json

import numpy as np
import pytest

pytest.importorskip("torch")
pytest.importorskip("onnx")

from polrig.models import paper_scale  # noqa: E402


def test_plan_epochs_scales_the_paper_schedule_to_the_budget():
    # one probe epoch of 16 samples took 1.6 s per stage: 0.1 s per sample-epoch
    secs = dict.fromkeys(paper_scale.STAGE_SHARES, 1.6)
    plan = paper_scale.plan_epochs(secs, 16, 100, 600.0)
    assert plan == {"pipnet": 20, "pmmnet": 10, "direct": 30}  # 2:1 and the baseline as both together
    assert paper_scale.plan_epochs(secs, 16, 100, 1.0) == dict.fromkeys(paper_scale.STAGE_SHARES, 1)


@pytest.mark.slow
def test_tiny_run_end_to_end(tmp_path, capsys):
    out = tmp_path / "out"
    code = paper_scale.main(["--out", str(out), "--budget-min", "0.5", "--size", "32", "--width", "8",
                             "--jobs", "2", "--train-samples", "6", "--holdout-samples", "3", "--epochs", "1",
                             "--work", str(tmp_path)])
    assert code == 0, capsys.readouterr().err
    names = {p.name for p in out.iterdir()}
    assert {"weights", "log.csv", "summary.json", "run.json", "eval_unseen_shapes_new.md",
            "eval_new_scenes_shipped.json"} <= names
    assert {"single_shot.onnx", "direct.onnx", "model.json"} <= {p.name for p in (out / "weights").iterdir()}
    run = json.loads((out / "run.json").read_text())
    assert run["data"]["train_samples"] == 6 and run["training"]["epochs"] == {"pipnet": 1, "pmmnet": 1, "direct": 1}
    assert run["hardware"]["cpu_cores"] >= 1 and isinstance(run["ship"], bool)
    assert paper_scale.folder_bytes(out) < paper_scale.MAX_OUT_BYTES
    assert not list(tmp_path.glob("paper-scale-*"))  # the work folder is gone
    # the exported graph runs with the runtime
    from polrig.models.runtime import SingleShotModel

    assert SingleShotModel.load(out / "weights", threads=1).provider


def test_a_full_output_folder_is_refused_before_any_work(tmp_path, capsys):
    (tmp_path / "x").write_text("")
    assert paper_scale.main(["--out", str(tmp_path), "--size", "32"]) == 2
    assert "not empty" in capsys.readouterr().err
    assert paper_scale.main(["--out", str(tmp_path / "new"), "--size", "36"]) == 2
    assert paper_scale.main(["--out", str(tmp_path / "new"), "--size", "32", "--data-share", "0.9"]) == 2
    assert "--data-share 0.9: must be above 0 and below" in capsys.readouterr().err
    assert not (tmp_path / "new").exists()


def test_training_device_is_checked_before_any_work(tmp_path):
    """``TrainConfig.device``: cpu or cuda; cuda where PyTorch sees no GPU is a one-line
    ConfigError before anything is read or written (the paper-scale run picks cuda only where
    ``torch.cuda.is_available()``)."""
    import torch

    from polrig.errors import ConfigError
    from polrig.models.train import TrainConfig, train

    with pytest.raises(ConfigError, match="device must be cpu or cuda"):
        train(tmp_path / "nodata", tmp_path / "out", TrainConfig(device="tpu"), export=False, echo=lambda s: None)
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA GPU"):
            train(tmp_path / "nodata", tmp_path / "out", TrainConfig(device="cuda"), export=False, echo=lambda s: None)
        assert paper_scale.training_device() == "cpu"
    assert not (tmp_path / "out").exists()


# ----------------------------------------------------------------------------- the plan (pure)

def test_plan_epochs_renormalises_the_shares_over_the_stages_left():
    # after PIPNet: PMMNet and the baseline split the time 1:3, whatever PIPNet's share was
    secs = {"pmmnet": 1.6, "direct": 1.6}
    assert paper_scale.plan_epochs(secs, 16, 100, 400.0) == {"pmmnet": 10, "direct": 30}
    assert paper_scale.plan_epochs({"direct": 1.6}, 16, 100, 400.0) == {"direct": 40}


class FakeClock:
    """Seconds that pass only when a test says so."""

    def __init__(self, t: float = 1000.0):
        self.t = t

    def __call__(self) -> float:
        return self.t


def run_planner(planner: paper_scale.StagePlanner, clock: FakeClock, real_epoch_s: dict[str, float],
                extra_s: dict[str, float] | None = None) -> dict[str, int]:
    """Drive ``planner`` as polrig.models.train does: each stage asks for its epochs when it starts,
    then takes ``epochs * real_epoch_s[stage]`` (+ ``extra_s``) seconds of the clock."""
    done = {}
    for stage in paper_scale.STAGE_SHARES:
        done[stage] = planner(stage, [])
        clock.t += done[stage] * real_epoch_s[stage] + (extra_s or {}).get(stage, 0.0)
    return done


def test_planner_spends_the_budget_in_the_papers_shares_when_the_estimates_hold():
    clock = FakeClock()
    per_sample = {"pipnet": 1e-3, "pmmnet": 2e-3, "direct": 0.8e-3}  # s per sample-epoch
    planner = paper_scale.StagePlanner(per_sample, 1000, clock.t + 300.0, epoch_overhead_s=0.05, clock=clock)
    epoch = {k: v * 1000 + 0.05 for k, v in per_sample.items()}
    assert planner.initial() == {k: int(share * 300 / epoch[k]) for k, share in paper_scale.STAGE_SHARES.items()}
    done = run_planner(planner, clock, epoch)
    assert done["pipnet"] == int(100 / 1.05) and done["pmmnet"] > 0 and done["direct"] > 0
    # every stage's time as its share says, to within one epoch; the end no later than the deadline
    spent = {k: done[k] * epoch[k] for k in done}
    assert clock.t <= planner.deadline
    assert planner.deadline - clock.t < epoch["direct"] + 1e-9
    for stage, share in paper_scale.STAGE_SHARES.items():
        assert abs(spent[stage] - share * 300) < sum(epoch.values())
    assert [d["correction"] for d in planner.decisions] == pytest.approx([1.0, 1.0, 1.0])


def test_a_stage_that_finishes_early_leaves_its_time_to_the_next_ones():
    """The first GPU run's failure: a probe dominated by warm-up made PIPNet look 25 times
    slower than it was, and its unused time was lost. The re-plan at each stage hands it on."""
    per_sample = {"pipnet": 1e-3, "pmmnet": 2e-3, "direct": 1e-3}
    clock = FakeClock()
    planner = paper_scale.StagePlanner(per_sample, 1000, clock.t + 600.0, clock=clock)
    first = planner.initial()
    real = dict(pipnet=0.5, pmmnet=2.0, direct=1.0)  # PIPNet's epochs take half the estimate
    done = run_planner(planner, clock, real)
    assert done["pipnet"] == first["pipnet"] == 200
    assert planner.decisions[1]["seconds_left"] == pytest.approx(500.0)
    assert planner.decisions[1]["correction"] == 1.0  # faster is not assumed of the next stages
    assert done["pmmnet"] == 500 // 4 // 2 > first["pmmnet"] == 50  # a quarter of the 500 s left
    assert done["direct"] == 500 - 2 * done["pmmnet"] > first["direct"] == 300  # and the rest
    assert planner.deadline - clock.t < real["direct"] + 1e-9  # nothing left unused but a part of an epoch


def test_a_stage_that_runs_slower_makes_the_next_ones_planned_cautiously():
    per_sample = dict.fromkeys(paper_scale.STAGE_SHARES, 1e-3)
    clock = FakeClock()
    planner = paper_scale.StagePlanner(per_sample, 1000, clock.t + 600.0, clock=clock)
    done = run_planner(planner, clock, dict.fromkeys(per_sample, 1.5))  # every epoch 1.5 times the estimate
    assert done["pipnet"] == 200
    assert planner.decisions[1]["correction"] == pytest.approx(1.5)
    assert planner.decisions[1]["seconds_left"] == pytest.approx(300.0)
    assert done["pmmnet"] == int(300 / 4 / 1.5) and done["direct"] == int(225 / 1.5)
    assert clock.t <= planner.deadline + 1e-9  # only PIPNet's own overrun, which nothing could foresee, is late


def test_a_stage_that_overruns_takes_from_the_next_ones_but_each_keeps_an_epoch():
    per_sample = dict.fromkeys(paper_scale.STAGE_SHARES, 1e-3)
    clock = FakeClock()
    planner = paper_scale.StagePlanner(per_sample, 1000, clock.t + 60.0, clock=clock)
    done = run_planner(planner, clock, dict.fromkeys(per_sample, 1.0), extra_s={"pipnet": 100.0})
    assert done["pipnet"] == 20 and done["pmmnet"] == 1 and done["direct"] == 1
    assert planner.decisions[1]["seconds_left"] == 0.0
    assert planner.decisions[1]["correction"] == 4.0  # clipped: one odd stage does not wreck the plan


def test_estimate_correction_is_the_ratio_of_the_finished_stages_sums():
    est = {"pipnet": 2.0, "pmmnet": 4.0}
    assert paper_scale.estimate_correction(est, []) == 1.0
    assert paper_scale.estimate_correction(est, [("pipnet", 10, 30.0)]) == pytest.approx(1.5)
    assert paper_scale.estimate_correction(est, [("pipnet", 10, 10.0), ("pmmnet", 5, 50.0)]) == pytest.approx(1.5)
    assert paper_scale.estimate_correction(est, [("pipnet", 10, 10.0)]) == 1.0  # faster: not assumed of the next
    assert paper_scale.estimate_correction(est, [("pipnet", 10, 0.1)]) == 1.0
    assert paper_scale.estimate_correction(est, [("pipnet", 10, 1e4)]) == 4.0


@pytest.mark.slow
def test_the_data_processes_make_samples_until_the_share_is_up(tmp_path):
    """Without a count, every process makes samples until the data share's end and is stopped;
    the shards it finished are the training set (whole shards only), the held-out sets are
    made whole."""
    from polrig.models.data import load_dataset

    # 15 s: the processes' start-up took about 3 s on the loaded 2-core machine, where about
    # 80 samples a second followed (170 samples in 5 s, 580 in 10 s; a shard is 2 samples), but
    # more than 7 s with the test suite and four other jobs on the same two cores (no sample
    # made in a 6 s budget)
    data = paper_scale.generate_data(tmp_path, size=16, seconds=15.0, jobs=2, seed=0, train_samples=None,
                                     holdout_samples=3, echo=lambda s: None)
    assert data["stopped_at_share"] == 2 and data["train_seconds"] >= 15.0
    n = data["train_samples"]
    assert n >= 1 and n % paper_scale.OPEN_SHARD_SIZE == 0  # stopped processes leave whole shards
    ds = load_dataset(tmp_path / "train")
    assert len(ds) == n == json.loads((tmp_path / "train" / "manifest.json").read_text())["count"]
    assert all(len(load_dataset(tmp_path / name)) == 3 for name in paper_scale.HOLDOUT_SETS)
    assert not list(tmp_path.glob("train-part*"))
    with pytest.raises(RuntimeError, match="no training sample"):
        paper_scale.generate_data(tmp_path / "none", size=16, seconds=0.0, jobs=1, seed=0, train_samples=None,
                                  holdout_samples=1, echo=lambda s: None)


def test_each_held_out_set_gets_an_equal_part_of_the_evaluation_half_for_the_new_graphs():
    assert paper_scale.evaluation_deadline(100.0, 140.0, 2) == pytest.approx(110.0)
    assert paper_scale.evaluation_deadline(110.0, 140.0, 1) == pytest.approx(125.0)
    assert paper_scale.evaluation_deadline(150.0, 140.0, 1) == 150.0  # time up: stop at once (after the minimum)


def test_the_data_share_is_checked():
    from polrig.errors import ConfigError

    assert paper_scale.check_data_share(paper_scale.DATA_SHARE) == paper_scale.DATA_SHARE
    for bad in (0.0, 1 - paper_scale.EVAL_SHARE - paper_scale.MARGIN_SHARE, 1.5):
        with pytest.raises(ConfigError, match="--data-share"):
            paper_scale.check_data_share(bad)


# ----------------------------------------------------------------------------- on real data

@pytest.fixture(scope="module")
def holdout_sets(tmp_path_factory):
    """A work folder with both held-out sets (6 samples at 32x32 each: more than the minimum
    the deadline tests score, 3 and 2), as phase 1 makes them."""
    from polrig.sim.dataset import generate_dataset

    work = tmp_path_factory.mktemp("work")
    for name, flag in paper_scale.HOLDOUT_SETS.items():
        generate_dataset(work / name, count=6, width=32, seed=paper_scale.HOLDOUT_SEEDS[name], holdout=flag,
                         shard_size=4, compress=False, progress=False)
    return work


def test_the_verdicts_subset_scores_the_full_model_exactly_as_the_whole_evaluation(holdout_sets):
    """The methods subset and the deadline: matrix PSNR of the full model (the verdict's number)
    is the same as in the seven-method evaluation of the same samples, and ``limit =
    samples_visited`` repeats exactly the samples a deadline stopped at."""
    from polrig.models.evaluate import METHODS, evaluate

    data = holdout_sets / "new_scenes"
    cut = evaluate(data, methods=paper_scale.EVAL_METHODS, deadline=0.0, min_samples=3, echo=lambda s: None)
    assert cut["samples"] == 3 and 3 <= cut["samples_visited"] < 6
    assert set(cut["methods"]) == set(paper_scale.EVAL_METHODS) and cut["noise_model"] is None
    again = evaluate(data, methods=paper_scale.EVAL_METHODS, limit=cut["samples_visited"], echo=lambda s: None)
    whole = evaluate(data, limit=cut["samples_visited"], echo=lambda s: None)
    assert set(whole["methods"]) == set(METHODS)
    for m in paper_scale.EVAL_METHODS:
        assert again["methods"][m]["matrix_psnr"] == cut["methods"][m]["matrix_psnr"]
        assert whole["methods"][m]["matrix_psnr"] == pytest.approx(cut["methods"][m]["matrix_psnr"], rel=1e-12)
    everything = evaluate(data, methods=("full",), deadline=None, echo=lambda s: None)
    assert everything["samples_visited"] == 6


def test_an_unknown_method_is_refused(holdout_sets):
    from polrig.errors import ConfigError
    from polrig.models.evaluate import evaluate

    with pytest.raises(ConfigError, match="unknown method"):
        evaluate(holdout_sets / "new_scenes", methods=("full", "fancy"), echo=lambda s: None)


def test_the_evaluation_stops_at_its_end_and_compares_the_same_samples(holdout_sets, tmp_path, monkeypatch):
    """With the budget's end already past, each set is scored on the minimum of samples only,
    the new and the shipped graphs on the same ones; with no end, on all of them."""
    from polrig.models.runtime import WEIGHTS_DIR

    monkeypatch.setattr(paper_scale, "MIN_EVAL_SAMPLES", 2)
    late = paper_scale.evaluate_against_shipped(holdout_sets, WEIGHTS_DIR, tmp_path, end=0.0, echo=lambda s: None)
    for name in paper_scale.HOLDOUT_SETS:
        assert late["eval_samples"][name]["scored"] == 2
        new = json.loads((tmp_path / f"eval_{name}_new.json").read_text())
        shipped = json.loads((tmp_path / f"eval_{name}_shipped.json").read_text())
        assert new["samples"] == shipped["samples"] == 2
        assert new["samples_visited"] == shipped["samples_visited"]
        # the same graphs on the same samples: the same score, so the verdict is "do not ship"
        assert late["matrix_psnr_db"][name]["new"] == late["matrix_psnr_db"][name]["shipped"]
    assert late["ship"] is False
    full = paper_scale.evaluate_against_shipped(holdout_sets, WEIGHTS_DIR, tmp_path, end=None, echo=lambda s: None)
    assert all(v["visited"] == v["of"] == 6 for v in full["eval_samples"].values())


def test_parts_are_moved_into_one_set_in_order(tmp_path):
    from polrig.models.data import load_dataset
    from polrig.sim.dataset import generate_dataset

    parts = [tmp_path / "a", tmp_path / "b"]
    for d, count, seed in zip(parts, (2, 5), (7, 8)):
        generate_dataset(d, count=count, width=16, seed=seed, shard_size=2, compress=False, progress=False)
    before = [load_dataset(d) for d in parts]
    assert paper_scale.merge_parts(parts, tmp_path / "train") == 7
    merged = load_dataset(tmp_path / "train")
    for k in ("analyzer", "mueller", "mask"):
        np.testing.assert_array_equal(merged[k], np.concatenate([b[k] for b in before]))
    manifest = json.loads((tmp_path / "train" / "manifest.json").read_text())
    assert manifest["count"] == 7 and manifest["merged_seeds"] == [7, 8] and manifest["n_shards"] == 4
    assert set(manifest["families_present"]) == {f for b in before for f in b.manifest["families_present"]}
    assert not list(tmp_path.glob("[ab]/shard-*.npz"))  # moved, not copied


def test_train_asks_the_plan_for_each_stages_epochs(tmp_path):
    """``polrig.models.train.train(plan_stage=...)``: called once per stage, in order, before its first
    epoch with the log so far; its answer is what the stage runs and what the summary records."""
    from polrig.models.train import TrainConfig, train
    from polrig.sim.dataset import generate_dataset

    generate_dataset(tmp_path / "data", count=4, width=16, seed=3, shard_size=4, progress=False)
    calls = []

    def plan(stage, rows):
        calls.append((stage, [(r["stage"], r["epoch"]) for r in rows]))
        return {"pipnet": 2, "pmmnet": 1, "direct": 3}[stage]

    config = TrainConfig(width=4, pipnet_epochs=9, pmmnet_epochs=9, direct_epochs=9, threads=1)
    summary = train(tmp_path / "data", tmp_path / "run", config, export=False, echo=lambda s: None, plan_stage=plan)
    assert calls == [("pipnet", []), ("pmmnet", [("pipnet", 0), ("pipnet", 1)]),
                     ("direct", [("pipnet", 0), ("pipnet", 1), ("pmmnet", 0)])]
    assert {k: summary["config"][f"{k}_epochs"] for k in ("pipnet", "pmmnet", "direct")} == \
        {"pipnet": 2, "pmmnet": 1, "direct": 3}
    with pytest.raises(ValueError, match="plan_stage returned 0"):
        train(tmp_path / "data", tmp_path / "run2", config, export=False, echo=lambda s: None,
              plan_stage=lambda stage, rows: 0)


@pytest.mark.slow
def test_a_planned_training_probes_then_plans_every_stage(tmp_path):
    """The probe (warm epoch and per-epoch overhead) and the plan on a tiny set, end to end:
    every stage planned once, in order, with at least one epoch; what ran is what was planned."""
    from polrig.sim.dataset import generate_dataset

    generate_dataset(tmp_path / "train", count=6, width=16, seed=5, shard_size=3, compress=False, progress=False)
    got = paper_scale.train_in_budget(tmp_path, seconds=paper_scale.EXPORT_RESERVE_S + 6.0, width=4, seed=0,
                                      echo=lambda s: None)
    assert [d["stage"] for d in got["plan"]] == list(paper_scale.STAGE_SHARES)
    assert got["epochs"] == {d["stage"]: d["epochs"] for d in got["plan"]}
    assert all(d["epochs"] >= 1 and d["wall_s"] > 0 for d in got["plan"])
    probe = got["probe"]
    assert probe["samples"] == 6 and probe["epoch_overhead_s"] >= 0
    assert all(v > 0 for v in probe["seconds_per_sample_epoch"].values())
    assert (tmp_path / "run" / "weights" / "single_shot.onnx").is_file()


def test_samples_that_fit_give_every_stage_its_fewest_epochs():
    per_sample = {"pipnet": 1e-3, "pmmnet": 2e-3, "direct": 1e-3}
    n = paper_scale.samples_that_fit(per_sample, 0.5, 600.0)
    # PMMNet binds: its 100 s share in MIN_EPOCHS epochs of 0.5 s + n * 2 ms
    assert n == int((600 / 6 / paper_scale.MIN_EPOCHS["pmmnet"] - 0.5) / 2e-3)
    clock = FakeClock()
    planner = paper_scale.StagePlanner(per_sample, n, clock.t + 600.0, epoch_overhead_s=0.5, clock=clock)
    plan = planner.initial()
    assert all(plan[k] >= paper_scale.MIN_EPOCHS[k] for k in plan)
    planner = paper_scale.StagePlanner(per_sample, n + 100, clock.t + 600.0, epoch_overhead_s=0.5, clock=clock)
    assert planner.initial()["pmmnet"] < paper_scale.MIN_EPOCHS["pmmnet"]
    assert paper_scale.samples_that_fit(per_sample, 100.0, 600.0) == 0


def test_samples_that_fit_memory_leave_room_for_the_initialization_and_the_rest():
    mb = 2**20
    # 13 MB a sample on disk (256x256), 78 GiB free: 0.6 * 78 GiB / (1.6 * 13 MB)
    n = paper_scale.samples_that_fit_memory(13 * mb, 78 * 2**30)
    assert n == int(paper_scale.MEMORY_SHARE * 78 * 2**30 / (paper_scale.SAMPLE_MEMORY_FACTOR * 13 * mb))
    assert 2000 < n < 3000
    assert paper_scale.samples_that_fit_memory(13 * mb, 0) == 0
    assert paper_scale.available_memory("cpu") > 0
