"""Calibrate the simulated rig and print every error against its hidden truth, the run time of
each step, and how much the calibration improves reference Mueller acquisition.

Usage: ``python benchmarks/bench_calibration.py [--size 320x240] [--seed 0] [--light X,Y,Z]``.
Prints Markdown tables and writes them to ``benchmarks/results/calibration.md`` (quoted in
``docs/calibration.md``; ``calibration_light.md`` with ``--light``). The DoFP step is run a
second time with the aluminium plate taken as an ideal mirror (the model before the targets
became real metals), to show what modelling its diattenuation and retardance buys.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import tempfile
import time

import numpy as np

from polrig import calibration
from polrig.app.rig import open_rig
from polrig.calibration import evaluate, procedures, runner
from polrig.calibration.calset import CalibrationSet
from polrig.calibration.mirror import IDEAL, MirrorMetal


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--size", default="320x240")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--frames", type=int, default=8, help="frames per state, evaluation")
    ap.add_argument("--light", default=None, metavar="X,Y,Z",
                    help="hidden light position (world metres) instead of the default rig's; "
                         "e.g. 0.5,0,0.1 puts the DoFP plate at about 42 deg incidence; the "
                         "tables then go to calibration_light.md")
    args = ap.parse_args()
    hidden = {} if args.light is None else {
        "light_position_m": tuple(float(v) for v in args.light.split(","))}
    rig = open_rig(None, size=args.size, seed=args.seed, clock_speed=float("inf"), hidden=hidden)
    rig.open()

    def mount(name, **kw):
        rig.truth.mount_target(name, **kw)

    cs, extras, times = CalibrationSet(), {}, {}
    for step in runner.STEPS:
        t0 = time.perf_counter()
        runner.run_steps([step], rig, mount, cs, extras=extras, log=lambda s: None)
        times[step] = time.perf_counter() - t0
    e = runner.errors_against_truth(cs, rig.truth.rig_parameters(), rig.truth.analyzer())
    # the same DoFP step with the plate taken as an ideal mirror (no diattenuation, no
    # retardance: the model before the plate became aluminium), on a copy of the set
    with tempfile.TemporaryDirectory() as tmp:
        cs.save(tmp)
        cs_ideal = calibration.load(tmp)
    t0 = time.perf_counter()
    runner.run_steps(["dofp"], rig, mount, cs_ideal, extras={}, log=lambda s: None,
                     options=runner.Options(mirror=MirrorMetal.named(IDEAL)))
    times["dofp_ideal"] = time.perf_counter() - t0
    e_ideal = runner.errors_against_truth(cs_ideal, rig.truth.rig_parameters(),
                                          rig.truth.analyzer())
    g = cs.generator
    L = cs.params["light"]
    rows = [
        ("intrinsics fx", f"{e['intrinsics']['fx_rel_error'] * 100:+.3f} %",
         f"± {cs.params['intrinsics']['std_fx_fy_cx_cy_px'][0]:.2f} px", "0.5 %", times["intrinsics"]),
        ("turntable axis", f"{e['turntable']['axis_error_deg']:.3f} deg",
         f"± {cs.params['turntable']['axis_std_deg']:.3f} deg", "0.2 deg", times["turntable"]),
        ("light position", f"{e['light']['rel_error_of_illumination_distance'] * 100:.2f} % "
                           f"({e['light']['error_norm_m'] * 1000:.2f} mm)",
         f"± {np.round(np.asarray(L['std_m']) * 1000, 2).tolist()} mm", "1 %", times["light"]),
        ("generator zero offset", f"{e['generator']['zero_offset_error_deg']:+.3f} deg",
         f"± {g.zero_offset_std_deg:.3f} deg", "0.1 deg", times["stokes"]),
        ("generator extinction ratio", f"{e['generator']['extinction_ratio_rel_error'] * 100:+.2f} %",
         f"± {g.extinction_ratio_std:.0f} (of {g.extinction_ratio:.0f})", "10 %", 0.0),
        ("micro-polarizer angles (RMS)", f"{e['dofp']['angle_rms_error_deg']:.3f} deg "
                                         f"(nominal: {e['dofp']['ideal_model_angle_rms_error_deg']:.3f})",
         f"median ± {cs.params['dofp']['angle_std_deg_median']:.3f} deg", "0.2 deg", times["dofp"]),
        ("micro-polarizer gains (RMS)", f"{e['dofp']['gain_rms_rel_error'] * 100:.3f} % "
                                        f"(nominal: {e['dofp']['ideal_model_gain_rms_rel_error'] * 100:.2f} %)",
         "", "0.5 %", 0.0),
        ("micro-polarizer diattenuation (RMS)", f"{e['dofp']['diattenuation_rms_error']:.4f}", "", "", 0.0),
        ("generator extinction ratio, plate taken as ideal mirror",
         f"{e_ideal['generator']['extinction_ratio_rel_error'] * 100:+.2f} %",
         f"± {cs_ideal.generator.extinction_ratio_std:.0f} (of {cs_ideal.generator.extinction_ratio:.0f})",
         "10 %", times["dofp_ideal"]),
        ("micro-polarizer angles (RMS), plate taken as ideal mirror",
         f"{e_ideal['dofp']['angle_rms_error_deg']:.3f} deg", "", "0.2 deg", 0.0),
        ("micro-polarizer gains (RMS), plate taken as ideal mirror",
         f"{e_ideal['dofp']['gain_rms_rel_error'] * 100:.3f} %", "", "0.5 %", 0.0),
    ]
    out: list[str] = []
    emit = out.append
    with tempfile.TemporaryDirectory() as tmp:
        cid = cs.save(tmp)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    where = "" if args.light is None else f", light moved to {args.light} m (world)"
    emit(f"Simulated rig {args.size} (colour IMX250MYR layout){where}, seed {args.seed}, default noise, "
         f"calibration set {cid}; load average {load:.1f} on {os.cpu_count()} cores. Targets: "
         f"chrome (Cr) sphere, bare aluminium DoFP plate (at "
         f"{cs.params['dofp']['mirror_incidence_deg']:.1f} deg incidence), modelled as such unless a row says "
         f"otherwise (the ideal-mirror rows rerun the DoFP step with the plate taken as an ideal "
         f"mirror, the assumption before the targets became real metals).\n")
    emit("| quantity | error vs truth | reported uncertainty | limit | step time (s) |")
    emit("|---|---|---|---|---|")
    for name, err, unc, lim, t in rows:
        emit(f"| {name} | {err} | {unc} | {lim} | {t:.1f} |" if t else f"| {name} | {err} | {unc} | {lim} | |")
    emit("\nReference acquisition (6 states 0..150 deg, superpixel, "
         f"{args.frames} frames per state), relative Mueller RMSE over cells where the truth is "
         "uniform:\n")
    emit("| scene | noise | Mueller RMSE, nominal model | nominal analyzer + fitted generator | "
         "calibrated | improvement | calibrated, plate taken as ideal mirror |")
    emit("|---|---|---|---|---|---|---|")
    for scene, noise in (("mirror_plate", True), ("plane", True), ("plane", False)):
        r2 = open_rig(None, size=args.size, seed=args.seed, clock_speed=float("inf"),
                      scene="sphere" if scene == "mirror_plate" else scene, noise=noise,
                      hidden=hidden)
        r2.open()
        if scene == "mirror_plate":
            r2.truth.mount_target("mirror_plate", **procedures.INTRINSIC_MOUNTS[0])
            r2.turntable.move_to(cs.params["dofp"]["turntable_deg"])
        procedures.auto_expose(r2.camera, percentile=99.9, target=0.45)
        gt = r2.truth.ground_truth()
        truth = evaluate.truth_on_superpixel_grid(gt["mueller"], r2.camera.layout)
        mask = evaluate.uniform_cells(gt["mueller"], gt["lit"], r2.camera.layout)
        res = evaluate.compare_models(r2, cs, truth, mask, frames=args.frames,
                                      others={"ideal_mirror": cs_ideal})
        r2.close()
        emit(f"| {scene} | {'default' if noise else 'off'} | {res['ideal'] * 100:.2f} % | "
             f"{res['ideal_analyzer_calibrated_generator'] * 100:.2f} % | "
             f"{res['calibrated'] * 100:.2f} % | {res['improvement']:.1f}x | "
             f"{res['calibrated:ideal_mirror'] * 100:.2f} % |")
    rig.close()
    text = "\n".join(out) + "\n"
    print(text)
    res_dir = pathlib.Path(__file__).resolve().parent / "results"
    res_dir.mkdir(exist_ok=True)
    name = "calibration.md" if args.light is None else "calibration_light.md"
    (res_dir / name).write_text("# Calibration of the simulated rig\n\n" + text)


if __name__ == "__main__":
    main()
