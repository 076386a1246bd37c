"""Session-level processing wired to the full-sensor pieces: the banded truth score, the
result EXR's format choice (plan fields, ``capture``/``reconstruct`` options), result files
written in place and hashed from disk, and PNG previews next to every result."""

from __future__ import annotations

import json
import math

import cv2
import numpy as np
import OpenEXR
import pytest

from polrig.acquisition.plan import ExrChoice, PlanError
from polrig.app import processing, reconstruct, result_files
from polrig.app.capture import CapturePlan, create_session, run_session
from polrig.app.rig import open_rig
from polrig.app.session import COMPLETE, Session, sha256_file
from polrig.cli import main
from polrig.errors import FormatError
from polrig.formats.exr import read_exr, read_mueller_exr
from polrig.optics.mueller import polarizer_stokes
from polrig.sensor.demosaic import demosaic_float
from polrig.solve.reference import MuellerEstimate
from polrig.solve.scoring import score_against_truth, truth_on_output_grid

IDEAL = {"stage_zero_offset_deg": 0.0, "extinction_ratio": 1e12, "ideal_analyzer": True}
EXACT = processing.Calibration("ideal")
PREVIEWS = ("mueller_grid.png", "mueller_dolp.png", "mueller_aolp.png")


def sim_rig(size=64, scene="sphere", sensor="imx250myr"):
    return open_rig(None, size=(size, size), sensor=sensor, clock_speed=math.inf, seed=3,
                    scene=scene, noise=True, hidden=dict(IDEAL))


def capture(out, plan: CapturePlan, **kw) -> Session:
    with sim_rig(**kw) as rig:
        processing.check_plan(plan, EXACT)
        session = create_session(out, rig, plan, calibration_id=EXACT.id)
        proc = processing.make_processor(plan, EXACT, processing.session_sensor_model(session))
        assert run_session(rig, session, processor=proc).status == "complete"
    return Session.open(out)


def two_step_score(proc: processing.Processor, session: Session, index: int, result, lay,
                   s_in, states, exposure_us):
    """The score as it was computed before the banded one: the whole truth on the output
    grid, the object mask's demosaic support, :func:`score_against_truth`."""
    img = read_mueller_exr(proc._verified_truth(session, index))
    if states is None:
        t = truth_on_output_grid(img.mueller, lay, proc.output_demosaic,
                                 polarizer_stokes(np.deg2rad([0, 45, 90, 135]), intensity=1),
                                 model=proc.sensor_model, exposure_us=exposure_us)
    else:
        t = truth_on_output_grid(img.mueller, lay, proc.demosaic, s_in, states)
    support = demosaic_float(np.asarray(img.extra["object_mask"], np.float32), lay,
                             proc.output_demosaic)
    return score_against_truth(result, t, support.min(axis=(0, 1)) >= 1.0)


@pytest.mark.parametrize("method", ["superpixel", "bilinear"])
def test_session_score_equals_the_two_step_score(tmp_path, method):
    s = capture(tmp_path / "s", CapturePlan((0.0, 120.0), demosaic=method))
    proc = processing.make_processor(s.plan, EXACT,
                                     processing.session_sensor_model(s))
    for index in (0, 1):
        cf = processing.load_capture_frames(s, index)
        result, s_in, lay, states = processing.process_reference(cf, EXACT, proc.sensor_model,
                                                                 method)
        exposure = processing.noise_exposures_us(cf)[0]
        new = proc.truth_score(proc._verified_truth(s, index), lay, s_in, states,
                               exposure).run(result.estimate())
        old = two_step_score(proc, s, index, result, lay, s_in, states, exposure)
        assert 0 < new["pixels_compared"] < result.mueller[0, 0, 0].size  # the mask matters
        assert new.keys() == old.keys()
        for key, value in old.items():
            if isinstance(value, float) and math.isfinite(value):
                assert new[key] == pytest.approx(value, rel=1e-9, abs=1e-12), key
            else:
                assert new[key] == value, key
        assert s.capture(index)["score"]["rmse"] == pytest.approx(old["rmse"], rel=1e-9)


def test_single_shot_score_uses_the_nominal_weights_on_the_output_grid(tmp_path):
    """The single-shot branch (``states=None``): nominal four-state weights and the noise
    model, scored band by band, equal the two-step score (a reference result stands in for
    the network's, the scoring does not care where it came from)."""
    s = capture(tmp_path / "s", CapturePlan((0.0,)))
    proc = processing.make_processor(s.plan, EXACT,
                                     processing.session_sensor_model(s))
    cf = processing.load_capture_frames(s, 0)
    result, s_in, lay, _ = processing.process_reference(cf, EXACT, proc.sensor_model,
                                                        "superpixel")
    exposure = processing.noise_exposures_us(cf)[0]
    new = proc.truth_score(proc._verified_truth(s, 0), lay, s_in, None, exposure).run(result)
    old = two_step_score(proc, s, 0, result, lay, s_in, None, exposure)
    assert new["pixels_compared"] == old["pixels_compared"] > 0
    for key in ("rmse", "mae", "realizable", "mean_sigma", "within_2sigma"):
        assert new[key] == pytest.approx(old[key], rel=1e-9, abs=1e-12), key


def _channels(path) -> dict[str, str]:
    """``{channel: pixel type}`` of an EXR file, and its compression."""
    f = OpenEXR.File(str(path), separate_channels=True)
    header = f.header()
    out = {name: str(ch.pixels.dtype) for name, ch in f.channels().items()}
    out["<compression>"] = str(header["compression"])
    return out


def test_capture_previews_and_records(tmp_path):
    """Every result of a capture has its three previews, recorded with their checksums; the
    result file's record is the file on disk; the session verifies."""
    s = capture(tmp_path / "s", CapturePlan((0.0, 90.0)))
    assert s.verify() == []
    for cap in s.captures:
        files = cap["files"]
        for role, name in zip(result_files.PREVIEW_ROLES, PREVIEWS):
            rec = files[role]
            assert rec["path"] == f"{cap['name']}/{name}"
            img = cv2.imread(str(s.root / rec["path"]))
            assert img is not None and img.shape[0] >= 64 and img.std() > 0
        rec = files["mueller"]
        path = s.root / rec["path"]
        assert rec["sha256"] == sha256_file(path) and rec["bytes"] == path.stat().st_size
        assert files["uncertainty"]["channels"].count("sigma") == 2
    assert not list(s.root.rglob("*.tmp*"))


def test_exr_choice_is_planned_written_and_viewed(tmp_path):
    plan = CapturePlan((0.0,), exr_planes=("sigma", "mueller"), exr_uncertainty="half",
                       exr_compression="piz")
    assert plan.exr_planes == ("mueller", "sigma")
    s = capture(tmp_path / "s", plan)
    assert s.plan.exr_planes == ("mueller", "sigma")
    assert (s.plan.exr_uncertainty, s.plan.exr_compression) == ("half", "piz")
    files = s.capture(0)["files"]
    chans = _channels(s.root / files["mueller"]["path"])
    assert "PIZ" in chans.pop("<compression>")
    sigma = {k: v for k, v in chans.items() if k.startswith("sigma.")}
    n = sum(k.startswith("M00.") for k in chans)
    assert len(sigma) == 9 * n and set(sigma.values()) == {"float16"}
    assert {v for k, v in chans.items() if k.startswith("M")} == {"float32"}
    assert not [k for k in chans if k.split(".")[0] in ("mask", "residual", "sigma_noise")]
    assert files["uncertainty"]["channels"] == "sigma.M{row}{col}.{colour}"
    assert "mask" not in files  # no view of a plane not written
    header = read_exr(s.root / files["mueller"]["path"]).metadata
    assert set(header["planes"]) == {"sigma.M{rc}"}
    assert header["uncertainty_precision"] == "half"
    assert s.verify() == []


def test_mueller_only_has_no_uncertainty_view(tmp_path):
    s = capture(tmp_path / "s", CapturePlan((0.0,), exr_planes=("mueller",),
                                            exr_compression="none"))
    files = s.capture(0)["files"]
    assert "uncertainty" not in files and "mask" not in files
    chans = _channels(s.root / files["mueller"]["path"])
    n = sum(k.startswith("M00.") for k in chans)
    assert "NO_COMPRESSION" in chans.pop("<compression>") and len(chans) == 9 * n


def test_a_plan_without_the_fields_reads_back_with_the_choice_it_was_written_with():
    """A session's plan older than the EXR fields (schema version 1) was written with float32
    uncertainty and ZIP (LEGACY_EXR), not today's default (half, ZIP): its migration says so,
    so it resumes to the same files. Version 2 states every field: none is defaulted."""
    from polrig.app.manifest import LEGACY_EXR, migrate_v1, plan_json, read_plan

    old = plan_json(CapturePlan((0.0,)))
    for key in ("exr_planes", "exr_uncertainty", "exr_compression"):
        del old[key]
    plan = read_plan(migrate_v1({"plan": old, "captures": []})["plan"])
    assert plan.exr == ExrChoice(uncertainty="float", compression="zip")
    assert LEGACY_EXR["exr_uncertainty"] == "float"
    assert plan.exr != ExrChoice() and ExrChoice().uncertainty == "half"
    assert plan.exr.planes == ("mueller", "sigma", "sigma_noise", "mask", "residual")
    new = CapturePlan((0.0,))
    assert read_plan(plan_json(new)).exr == new.exr == ExrChoice()


@pytest.mark.parametrize("field, value", [("exr_planes", ("mueller", "dolp")),
                                          ("exr_uncertainty", "double"),
                                          ("exr_compression", "b44")])
def test_a_bad_choice_is_a_plan_error_naming_its_field(field, value):
    with pytest.raises(PlanError) as info:
        CapturePlan((0.0,), **{field: value})
    assert info.value.field == field


def test_reconstruct_revision_has_its_choice_and_previews(tmp_path):
    s = capture(tmp_path / "s", CapturePlan((0.0, 90.0), exr_uncertainty="half"))
    s.lock()
    try:
        rev1 = reconstruct.reprocess_session(s, exr={"planes": ("mask",), "compression": "none"})
        rev2 = reconstruct.reprocess_session(s)  # the session plan's choice
    finally:
        s.unlock()
    s = Session.open(s.root)
    settings = {r["name"]: r for r in s.manifest["revisions"]}
    assert settings[rev1]["exr_planes"] == ["mueller", "mask"]
    assert (settings[rev1]["exr_uncertainty"],
            settings[rev1]["exr_compression"]) == ("half", "none")
    assert settings[rev2]["exr_planes"] == list(ExrChoice().planes)
    assert settings[rev2]["exr_uncertainty"] == "half"
    for cap in s.captures:
        for rev in (rev1, rev2):
            files = cap["revisions"][rev]["files"]
            assert cap["revisions"][rev]["status"] == COMPLETE
            for role, name in zip(result_files.PREVIEW_ROLES, PREVIEWS):
                assert files[role]["path"] == f"{cap['name']}/{rev}/{name}"
        assert "uncertainty" not in cap["revisions"][rev1]["files"]
        chans = _channels(s.root / cap["revisions"][rev1]["files"]["mueller"]["path"])
        assert {v for k, v in chans.items() if k.startswith("mask.")} == {"float16"}
    assert s.verify() == []


def new_revision(s: Session) -> tuple[str, processing.Processor]:
    """A new reference revision of locked session ``s`` with capture 0 started in it, and the
    session plan's processor."""
    settings, _, _ = reconstruct.revision_plan(s, "reference", None, None, EXACT)
    rev = s.new_revision(settings)
    s.start_revision(0, rev)
    return rev, processing.make_processor(s.plan, EXACT,
                                          processing.session_sensor_model(s))


def test_the_truth_file_is_compressed_as_the_plan_says(tmp_path):
    """The simulator's truth follows the plan's ``exr_compression`` (the fast choice writes
    and reads it uncompressed) and scores the same either way."""
    scores = {}
    for comp in ("none", "zip"):
        s = capture(tmp_path / comp, CapturePlan((0.0,), exr_compression=comp))
        chans = _channels(s.root / s.capture(0)["files"]["truth_mueller"]["path"])
        assert ("NO_COMPRESSION" if comp == "none" else "ZIP") in chans["<compression>"]
        scores[comp] = s.capture(0)["score"]
    assert scores["none"] == scores["zip"]


def test_write_and_score_releases_the_diagnostics_and_cleans_up_a_failed_score(tmp_path):
    """The file is written from the whole result; the score runs on its estimate alone (the
    diagnostic planes already released) and equals the score of the whole result; a score
    that fails (a truth file damaged after the check) leaves no result file behind."""
    s = capture(tmp_path / "s", CapturePlan((0.0,)))
    s.lock()
    try:
        rev, proc = new_revision(s)
        out = proc.solve(s, 0, rev)
        whole = out.truth.run(out.result)
        records, score = result_files.write_and_score(s.root, out, proc.exr)
        assert isinstance(out.result, MuellerEstimate)
        assert score == whole and score["pixels_compared"] > 0
        chans = _channels(s.root / records["mueller"]["path"])
        assert "residual.R" in chans and "sigma_noise.M00.R" in chans  # written before release
        result_files.remove_files(s.root / r["path"] for r in records.values())

        out = proc.solve(s, 0, rev)
        truth = out.truth.truth_path
        truth.write_bytes(truth.read_bytes()[:4096])  # truncated after the checksum check
        with pytest.raises(FormatError, match="truth_mueller.exr"):
            result_files.write_and_score(s.root, out, proc.exr)
        assert not any((s.capture_dir(0) / rev).glob("mueller*"))
    finally:
        s.unlock()


def test_a_result_not_recorded_leaves_no_file(tmp_path):
    """The manifest save fails after the result files were written (a full disk): they are
    removed again, the manifest in memory does not name them, the capture can be processed
    again."""
    s = capture(tmp_path / "s", CapturePlan((0.0,)))
    s.lock()
    try:
        rev, proc = new_revision(s)

        def full(path, data):
            if path.name == "session.json":
                raise OSError(28, "No space left on device", str(path))

        s.write_hook = full
        with pytest.raises(OSError):
            proc.process(s, 0, revision=rev)
        s.write_hook = None
        folder = s.capture_dir(0) / rev
        assert not folder.exists() or not any(folder.iterdir())
        assert s.capture(0)["revisions"][rev]["files"] == {}
        proc.process(s, 0, revision=rev)  # nothing in the way
    finally:
        s.unlock()
    assert Session.open(s.root).verify() == []


def test_cli_options_reach_the_plan_and_the_revision(tmp_path, capsys):
    cfg = tmp_path / "rig.toml"
    cfg.write_text('[sim]\nsize = "64x64"\nsensor = "imx250mzr"\nclock_speed = inf\nseed = 2\n'
                   'scene = "sphere"\n[sim.hidden]\nstage_zero_offset_deg = 0.0\n'
                   'extinction_ratio = 1e12\nideal_analyzer = true\n')
    out = tmp_path / "s"
    assert main(["capture", "--poses", "0", "--config", str(cfg), "--out", str(out),
                 "--exr-planes", "sigma,mask", "--exr-uncertainty", "half",
                 "--exr-compression", "none", "--no-progress"]) == 0
    plan = json.loads((out / "session.json").read_text())["plan"]
    assert (plan["exr_planes"], plan["exr_uncertainty"], plan["exr_compression"]) == (
        ["mueller", "sigma", "mask"], "half", "none")
    # a resume asking for the same planes in another order and spelling is the same plan
    assert main(["capture", "--config", str(cfg), "--out", str(out), "--resume",
                 "--exr-planes", "mask,sigma,mueller", "--no-progress"]) == 0
    assert main(["reconstruct", str(out), "--exr-compression", "zip", "--no-progress"]) == 0
    rev = Session.open(out).manifest["revisions"][-1]
    assert (rev["exr_planes"], rev["exr_uncertainty"], rev["exr_compression"]) == (
        ["mueller", "sigma", "mask"], "half", "zip")
    assert "--exr-compression" in rev["command_line"]
    capsys.readouterr()
    assert main(["reconstruct", str(out), "--exr-planes", "sigma,dolp", "--no-progress"]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "--exr-planes" in err and "dolp" in err, err
    assert len(Session.open(out).manifest["revisions"]) == 1  # nothing recorded


def test_single_shot_captures_record_the_fraction_beyond_the_sigma_calibration(tmp_path):
    """A single-shot capture's EXR header records the object's fraction whose misfit lies
    beyond the sigma's calibration range: small on a plastic sphere, most of a gold one
    (:data:`polrig.models.uncertainty.BEYOND_WARN_FRACTION` separates them)."""
    pytest.importorskip("onnxruntime")
    from polrig.models.uncertainty import BEYOND_WARN_FRACTION

    got, counts = {}, {}
    for scene in ("sphere", "gold_sphere"):
        s = capture(tmp_path / scene, CapturePlan((0.0,), mode="single-shot"), size=256,
                    scene=scene)
        exr = read_exr(s.root / s.capture(0)["files"]["mueller"]["path"])
        got[scene] = exr.metadata["beyond_calibration_fraction"]
        # the per-pixel flags (as polrig infer --sigma writes them): 0 or 1, described in the header
        flagged = np.stack([exr.planes[f"beyond_calibration.{c}"] for c in "RGB"])
        assert set(np.unique(flagged)) <= {0.0, 1.0}
        counts[scene] = int(np.any(flagged > 0, axis=0).sum())
        assert "beyond_calibration" in exr.metadata["planes"]
    assert 0 <= got["sphere"] < BEYOND_WARN_FRACTION < got["gold_sphere"] <= 1
    assert counts["gold_sphere"] > counts["sphere"]  # the flags are where the fraction says
    # without the sigma group the flags are not written (they qualify the sigma)
    s = capture(tmp_path / "nosigma", CapturePlan((0.0,), mode="single-shot", exr_planes=("mueller", "mask")),
                size=256, scene="gold_sphere")
    exr = read_exr(s.root / s.capture(0)["files"]["mueller"]["path"])
    assert not any(k.startswith("beyond_calibration") for k in exr.planes)
    assert "beyond_calibration" not in exr.metadata["planes"]


def test_capture_help_states_the_default_exr_choice(capsys):
    """``polrig capture --help`` names ExrChoice's defaults (written out there, so that the
    command line does not import the plan module at start-up)."""
    with pytest.raises(SystemExit):
        main(["capture", "--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert f"default {ExrChoice().uncertainty})" in text and f"default {ExrChoice().compression})" in text
