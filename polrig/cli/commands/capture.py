"""``polrig capture``: reference (single-shot, hybrid, adaptive) captures over turntable poses into a session.

A shell over :func:`polrig.app.capture.run_capture`, the one capture call (the GUI makes the
same): the options become a typed :class:`polrig.app.capture.CaptureRequest`, its events are
shown (a progress bar, one line per capture), and library errors, which name the plan field
they are about, are reported naming the option (:func:`options_named`). Bad input (pose spec,
states, output folder, config) is rejected before any device is opened or any file is
written; what needs the opened rig (the camera's exposure range, on ``--resume`` the same rig
as the session's) is checked before any file is written. A session being written by another
process is refused (its lock).
"""

from __future__ import annotations

import argparse
import contextlib
import pathlib
import sys
from typing import Iterator

from polrig.choices import (
    DEFAULT_PRIOR_SCALE,
    DEMOSAIC_METHODS,
    EXR_COMPRESSIONS,
    EXR_UNCERTAINTY_PRECISIONS,
    MODEL_CHOICES,
    PRIOR_SCALES,
    NETWORK_BINNINGS,
    PLANE_GROUPS,
)
from polrig.errors import ConfigError
from polrig.models.sizes import CHOICES as MODEL_SIZES

POSES_HELP = ("turntable poses in degrees: a list 0,30,60 or a range START:STOP:STEP with STOP "
              "exclusive (0:360:90 = 0, 90, 180, 270)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "capture", help="capture Mueller images over turntable poses into a session folder",
        description="Capture over turntable poses into a session folder (simulated rig unless "
                    "--config names real hardware). Every raw frame is kept; each pose gets a "
                    "Mueller EXR with uncertainty and mask planes. --poses: " + POSES_HELP + ". "
                    "Interrupted sessions (Ctrl-C, device fault, full disk) continue with "
                    "--out DIR --resume.")
    p.add_argument("--poses", help=POSES_HELP + " (required unless --resume)")
    p.add_argument("--mode", choices=("reference", "single-shot", "hybrid", "adaptive"), default=None,
                   help="reference: N polarizer states per pose (default); single-shot: the "
                        "trained network; hybrid: N >= 1 states solved with the network's estimate "
                        "of one of them (--seen-state) as a prior (polrig.solve.hybrid); adaptive: "
                        "the network's state (--states gives that one; default 0), then states chosen from the "
                        "posterior until --target-sigma holds (polrig.app.adaptive)")
    add_seen_state_option(p, "default 0")
    add_prior_scale_option(p, f"default {DEFAULT_PRIOR_SCALE}; on --resume the session's")
    add_models_option(p)
    add_adaptive_options(p)
    p.add_argument("--mirror-average", action="store_true", default=None,
                   help="single-shot, hybrid, adaptive: also run the network on each frame's left-right "
                        "mirror image "
                        "and average the two answers (a few per cent lower error, twice the network "
                        "time; models/MODEL_CARD.md, 'Mirror averaging')")
    p.add_argument("--states", help="polarizer stage angles in degrees (default 0,45,90,135; "
                                    "at least 3 non-collinear states for the reference method, "
                                    "1 or more for the hybrid method)")
    p.add_argument("--frames", type=int, default=None, help="frames averaged per state (default 1)")
    p.add_argument("--exposure", help="exposure time(s) in microseconds; several (comma "
                                      "separated) form an HDR bracket, the first is the "
                                      "reference exposure (default: the camera's current one)")
    p.add_argument("--dark-frames", type=int, default=None,
                   help="dark frames (light off) per pose and exposure (default 0: subtract "
                        "the camera's black level only)")
    p.add_argument("--demosaic", choices=DEMOSAIC_METHODS, default=None,
                   help="demosaic method for processing (default superpixel: no interpolated "
                        "values, exact propagated uncertainty)")
    p.add_argument("--resolution", choices=("superpixel", "full"), default=None,
                   help="single-shot output resolution: superpixel (the networks' grid, default) or "
                        "full (the raw frame's: the networks' answer with the measured detail of a "
                        "full-resolution demosaic, --demosaic bilinear unless newton is given; no "
                        "sigma at full resolution; models/full_resolution.py)")
    add_binning_option(p, "default 1")
    add_exr_options(p, "default: mueller,sigma,sigma_noise,mask,residual (all)",
                    "default half", "default zip")  # polrig.acquisition.plan.ExrChoice
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default=None,
                   help="where the single-shot network runs: auto (CUDA where onnxruntime offers it, "
                        "else the CPU; default), cpu or cuda (refused when unavailable); the provider "
                        "used is recorded in each result's header")
    add_model_size_option(p)
    p.add_argument("--config", help="rig configuration TOML (default: the simulated rig)")
    p.add_argument("--calibration", help="calibration set folder (default: nominal ideal "
                                         "polarizer and analyzer, calibration id 'nominal')")
    p.add_argument("--out", required=True, help="session folder (must be new or empty)")
    p.add_argument("--resume", action="store_true",
                   help="continue the session in --out where it stopped")
    add_metadata_options(p)
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def add_metadata_options(p: argparse.ArgumentParser) -> None:
    """``--sample``, ``--operator``, ``--note``, ``--md KEY=VALUE``: who, why, what
    (:class:`polrig.app.manifest.SampleMetadata`), recorded in the manifest and every result
    header; on ``--resume`` the stored ones are kept (different ones are refused)."""
    g = p.add_argument_group("metadata", "who, why, what: recorded in session.json and every result "
                                         "EXR header, shown by polrig info (--resume keeps the "
                                         "stored metadata; giving different ones is refused)")
    g.add_argument("--sample", default=None, help="what is on the turntable")
    g.add_argument("--operator", default=None, help="who captures it")
    g.add_argument("--note", default=None, help="why, free text")
    g.add_argument("--md", action="append", default=None, metavar="KEY=VALUE",
                   help="a further key (an identifier, not one of polrig's own keys) and its "
                        "value; repeat for several")


def metadata_option(args: argparse.Namespace):
    """The :class:`polrig.app.manifest.SampleMetadata` the options give, ``None`` where none is
    given (a new session: empty; ``--resume``: the stored one). One-line :class:`ConfigError`."""
    from polrig.app.manifest import MetadataError, SampleMetadata

    given = [getattr(args, k, None) for k in ("sample", "operator", "note", "md")]
    if all(v is None for v in given):
        return None
    try:
        return SampleMetadata(sample=args.sample or "", operator=args.operator or "",
                              note=args.note or "", user=SampleMetadata.parse_user(args.md or ()))
    except MetadataError as exc:
        first = str(exc).split()[0]
        flag = "--" + first if first in ("sample", "operator", "note") else "--md"
        raise ConfigError(f"{flag}: {exc}") from None


def add_models_option(p: argparse.ArgumentParser) -> None:
    """``--models full|auto|diffuse``: lower-order models per pixel (``capture`` and ``reconstruct``;
    :mod:`polrig.solve.model_selection`, :mod:`polrig.app.diffuse_route`)."""
    p.add_argument("--models", choices=MODEL_CHOICES, default=None,
                   help="full (default): the 3x3 block at every pixel; auto (reference and hybrid "
                        "modes): per pixel the lower-order model (depolarizer, diattenuator, "
                        "retarder, Fresnel-type, rank one...) that a likelihood-ratio test at "
                        "level 0.05 accepts, estimated under it; diffuse (hybrid mode, two states): "
                        "per pixel the diffuse term, with the specular term where significant, tested "
                        "on the two states' samples alone (level 0.05) and, where accepted, the "
                        "direction they leave open predicted from the "
                        "rig's geometry (calibrated light and turntable, or [nominal_geometry]); the "
                        "model map (model.{colour}, codes in the header) and its statistic are "
                        "always written; capture --resume goes on with the session's")


def add_prior_scale_option(p: argparse.ArgumentParser, default: str) -> None:
    """``--prior-scale innovations|geometry|calibrated``: the hybrid prior's scale
    (:mod:`polrig.solve.prior_scale`, :mod:`polrig.solve.open_scale`; ``capture`` and ``reconstruct``)."""
    p.add_argument("--prior-scale", choices=PRIOR_SCALES, default=None,
                   help="hybrid and adaptive: innovations scales the network's calibrated sigma per "
                        "capture by how far the states after the seen one find its estimate off "
                        "(recorded with each result as sigma_scale; factor 1 at one state); geometry "
                        "does that and, at two states, scales the prior along the direction they leave "
                        "open by how far the diffuse term fitted to the rig's geometry finds it off "
                        "(needs the calibrated light and intrinsics; recorded as "
                        "sigma_scale.open_direction); calibrated keeps the sigma as calibrated "
                        f"({default})")


def add_seen_state_option(p: argparse.ArgumentParser, default: str) -> None:
    """``--seen-state K``: the hybrid method's seen state, an index into ``--states``
    (:attr:`polrig.acquisition.plan.CapturePlan.seen_state`; ``capture`` and ``reconstruct``)."""
    p.add_argument("--seen-state", type=int, default=None, metavar="K",
                   help=f"hybrid: index into the polarizer states of the one whose frame the network "
                        f"sees; its estimate and calibrated sigma are the prior ({default})")


def add_adaptive_options(p: argparse.ArgumentParser) -> None:
    """``--target-sigma``, ``--target-share``, ``--max-states``, ``--min-states``: the adaptive mode's stopping rule
    (:func:`polrig.acquisition.plan.check_adaptive_target`)."""
    p.add_argument("--target-sigma", type=float, default=None, metavar="X",
                   help="adaptive: stop a pose once each object pixel's posterior sigma, RMS over the "
                        "nine elements relative to its m00 (the block normalised to m00 = 1; worst "
                        "colour), is at most X, e.g. 0.01 (required with --mode adaptive)")
    p.add_argument("--target-share", type=float, default=None, metavar="F",
                   help="adaptive: the share of object pixels that must meet --target-sigma "
                        "(default 0.95)")
    p.add_argument("--max-states", type=int, default=None, metavar="N",
                   help="adaptive: the most polarizer states per pose, the first included (default "
                        "4, at most 8)")
    p.add_argument("--min-states", type=int, default=None, metavar="N",
                   help="adaptive: the fewest polarizer states per pose before the target may stop "
                        "it (default 2: the network's sigma is checked by a state it did not see; "
                        "1 lets a pose stop on the network's frame alone)")


def add_binning_option(p: argparse.ArgumentParser, default: str) -> None:
    """``--network-binning {1,2}``: the single-shot networks on the analyzer grid or on that
    grid binned 2x2 (:attr:`polrig.acquisition.plan.CapturePlan.network_binning`; ``capture`` and
    ``reconstruct`` share it)."""
    p.add_argument("--network-binning", type=int, choices=NETWORK_BINNINGS, default=None,
                   help="single-shot: 1 runs the networks on the analyzer grid; 2 on that grid binned "
                        "2x2, the answer lifted back with the grid's measured detail: about half the "
                        "frame time at full sensor size for -0.56..+0.03 dB on held-out sets "
                        "(models/MODEL_CARD.md, 'Speed, warm and cold'); the output grid is the same, "
                        f"but there is no sigma (NaN planes) ({default})")


def add_model_size_option(p: argparse.ArgumentParser) -> None:
    """``--model-size {auto,small,large}``: which shipped single-shot model runs
    (:mod:`polrig.models.sizes`; ``infer``, ``capture``, ``reconstruct`` and ``gui`` share it)."""
    p.add_argument("--model-size", choices=MODEL_SIZES, default=None,  # None: auto, left out of a manifest's command line
                   help="single-shot model: small (the CPU networks, for CPUs and the live view), "
                        "large (wider networks trained on a GPU; refused while not shipped) or auto "
                        "(default: large where the networks run on CUDA and it is shipped, else small); "
                        "the size, training hardware and minutes are recorded with each result")


def add_exr_options(p: argparse.ArgumentParser, planes_default: str, unc_default: str,
                    comp_default: str) -> None:
    """``--exr-planes``, ``--exr-uncertainty``, ``--exr-compression``: the result EXR's format
    (:class:`polrig.acquisition.plan.ExrChoice`; ``capture`` and ``reconstruct`` share them)."""
    p.add_argument("--exr-planes", metavar="LIST", default=None,
                   help="plane groups of each result EXR, comma separated, from "
                        f"{','.join(PLANE_GROUPS)} (mueller always written; geometry: the "
                        f"single-shot networks' normal, albedo, roughness and light direction, "
                        f"on request only; {planes_default})")
    p.add_argument("--exr-uncertainty", choices=EXR_UNCERTAINTY_PRECISIONS, default=None,
                   help="precision of the sigma, sigma_noise, residual and mask planes: float "
                        f"(float32) or half (float16, half the bytes; {unc_default})")
    p.add_argument("--exr-compression", choices=EXR_COMPRESSIONS, default=None,
                   help="EXR compression: zip (lossless, smaller), piz (wavelet, lossless) or "
                        f"none (fastest write, largest file; {comp_default})")


def exr_planes_option(text: str | None) -> tuple[str, ...] | None:
    """``--exr-planes a,b`` as a tuple of plane groups (``None`` where not given)."""
    if text is None:
        return None
    return tuple(t.strip() for t in text.split(",") if t.strip())


#: The option that sets each :class:`polrig.app.capture.CaptureRequest` field (library errors
#: name the field, :class:`polrig.acquisition.plan.PlanError`; the command line names its option).
FLAGS = {"poses_deg": "--poses", "mode": "--mode", "states_deg": "--states",
         "frames_per_state": "--frames", "exposures_us": "--exposure",
         "dark_frames": "--dark-frames", "demosaic": "--demosaic",
         "mirror_average": "--mirror-average", "resolution": "--resolution",
         "network_binning": "--network-binning", "seen_state": "--seen-state", "models": "--models",
         "prior_scale": "--prior-scale",
         "target_sigma": "--target-sigma", "target_share": "--target-share",
         "max_states": "--max-states", "min_states": "--min-states",
         "exr_planes": "--exr-planes", "exr_uncertainty": "--exr-uncertainty",
         "exr_compression": "--exr-compression",
         "calibration": "--calibration", "out": "--out",
         "metadata": "--sample/--operator/--note/--md"}
#: What the command line adds to an error about a field.
HINTS = {"out": "--resume"}


@contextlib.contextmanager
def options_named(flags: dict[str, str] = FLAGS) -> Iterator[None]:
    """Re-raise a :class:`polrig.acquisition.plan.PlanError` as a one-line :class:`ConfigError` naming
    the option of its field: ``--states 0,5,10: the states ...``."""
    from polrig.acquisition.plan import PlanError

    try:
        yield
    except PlanError as exc:
        flag = flags.get(exc.field)
        if flag is None:
            raise
        text = (f"{flag} {exc.subject}: {exc.detail}" if exc.subject is not None
                else f"{flag}: {exc.detail}")
        if exc.field in HINTS:
            text += f" ({HINTS[exc.field]})"
        raise ConfigError(text) from None


def build_request(args: argparse.Namespace):
    """The :class:`polrig.app.capture.CaptureRequest` the options ask for (``None`` where an
    option is not given)."""
    from polrig.acquisition.plan import parse_float_list, parse_pose_spec
    from polrig.app.capture import CaptureRequest

    if not args.resume and not args.poses:
        raise ConfigError("--poses is required (e.g. --poses 0:360:90)")
    with options_named():
        return CaptureRequest(
            out=pathlib.Path(args.out),
            poses_deg=parse_pose_spec(args.poses) if args.poses else None,
            mode=args.mode,
            states_deg=(parse_float_list(args.states, "--states", field="states_deg")
                        if args.states else None),
            frames_per_state=args.frames,
            exposures_us=(parse_float_list(args.exposure, "--exposure", positive=True,
                                           field="exposures_us") if args.exposure else None),
            dark_frames=args.dark_frames,
            demosaic=args.demosaic,
            mirror_average=args.mirror_average,
            resolution=args.resolution,
            network_binning=args.network_binning,
            seen_state=args.seen_state,
            target_sigma=args.target_sigma,
            target_share=args.target_share,
            max_states=args.max_states,
            min_states=args.min_states,
            exr_planes=exr_planes_option(args.exr_planes),
            exr_uncertainty=args.exr_uncertainty,
            exr_compression=args.exr_compression,
            device=args.device or "auto",
            model_size=args.model_size or "auto",
            models=args.models,
            prior_scale=args.prior_scale,
            config=pathlib.Path(args.config) if args.config else None,
            calibration=pathlib.Path(args.calibration) if args.calibration else None,
            resume=bool(args.resume),
            metadata=metadata_option(args))


def command_line(args: argparse.Namespace, command: str = "capture") -> list[str]:
    """The command as the manifest records it, rebuilt from the parsed options (so that it
    is the same whether polrig ran as a console script or in-process)."""
    out = ["polrig", command]
    for key, value in vars(args).items():
        if key in ("func", "command", "session") or value is None or value is False:
            continue
        flag = "--" + key.replace("_", "-")
        if isinstance(value, list):  # a repeated option (--md KEY=VALUE ...): as given
            for item in value:
                out += [flag, str(item)]
            continue
        out.append(flag)
        if value is not True:
            out.append(str(value))
    if getattr(args, "session", None):
        out.append(str(args.session))
    return out


def run(args: argparse.Namespace) -> int:
    import os

    from polrig.app import capture

    request = build_request(args)
    bar = _ProgressPrinter(enabled=not args.no_progress)
    try:
        with options_named():
            # POLRIG_DEBUG: an error once the session exists is raised (a traceback), not
            # reported as a stop (the session is left interrupted and resumable either way)
            result = capture.run_capture(request, command_line=command_line(args), events=bar,
                                         reraise=bool(os.environ.get("POLRIG_DEBUG")))
    finally:
        bar.close()
    if result.status != "complete":
        print(f"polrig: error: capture stopped ({result.reason}); completed captures are "
              f"intact, continue with: polrig capture --out {request.out} --resume"
              + (f" --config {request.config}" if request.config else ""),
              file=sys.stderr)
        return 1
    print(f"session complete: {len(result.completed)} captures in {request.out}")
    return 0


class _ProgressPrinter:
    """The events of :func:`polrig.app.capture.run_capture`: a tqdm bar on stderr (frames,
    with ETA), one score line per capture and one line per adaptive decision on stdout (a
    resumed session's kept decisions first, marked "(recorded)", as the GUI lists them)."""

    def __init__(self, enabled: bool = True):
        self.enabled = enabled
        self.bar = None

    def __call__(self, ev) -> None:
        from tqdm import tqdm

        from polrig.app.capture import Progress, SessionOpened

        if isinstance(ev, SessionOpened):  # the session exists; a resumed one's decisions kept
            for kept in ev.decisions:
                self._write(f"capture {kept.capture_index + 1}/{ev.n_captures} pose {kept.pose_deg:g} deg: "
                            f"{kept.describe()} (recorded)", sys.stdout)
            return
        if not isinstance(ev, Progress):
            return
        if self.bar is None and self.enabled and ev.total:
            self.bar = tqdm(total=ev.total, unit="frame", file=sys.stderr, dynamic_ncols=True,
                            desc="capture")
        if self.bar is not None and ev.hardware_s:
            self.bar.set_postfix_str(f"pose {ev.pose_deg:g} deg, hardware time left "
                                     f"{ev.hardware_left_s:.0f} s of {ev.hardware_s:.0f} s",
                                     refresh=False)
        if ev.kind == "frame" and self.bar is not None:
            self.bar.update(ev.step - self.bar.n)
        elif ev.kind == "retry":
            self._write(f"retry: {ev.message}", sys.stderr)
        elif ev.kind == "capture-done":
            line = f"capture {ev.capture_index + 1}/{ev.n_captures} pose {ev.pose_deg:g} deg: done"
            if ev.score:
                from polrig.solve.scoring import format_score

                line += " | " + format_score(ev.score)
            self._write(line, sys.stdout)
        elif ev.kind == "decision":
            self._write(f"capture {ev.capture_index + 1}/{ev.n_captures} pose {ev.pose_deg:g} deg: "
                        f"{ev.message}", sys.stdout)
        elif ev.kind == "capture-failed":
            self._write(f"capture {ev.capture_index + 1}/{ev.n_captures} pose "
                        f"{ev.pose_deg:g} deg: {ev.message}", sys.stderr)

    def _write(self, line: str, stream) -> None:
        if self.bar is not None:
            from tqdm import tqdm

            tqdm.write(line, file=stream)
        else:
            print(line, file=stream, flush=True)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
