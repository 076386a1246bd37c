"""``polrig infer RAW --layout imx250myr --state-deg 0 --out OUT.exr``: single-shot Mueller
image of one raw frame with the shipped ONNX model (onnxruntime only, no torch).

Decode (:func:`polrig.formats.rawio.read_raw`), then the one single-shot route
(:meth:`polrig.app.single_shot.SingleShot.frame`: demosaic, Stokes, PIPNet -> pBRDF -> PMMNet,
the planes) with its options (:class:`polrig.acquisition.plan.SingleShotOptions`, whose refusals
name this command's options), and the one result writer
(:func:`polrig.formats.exr.write_result_exr`: ``mask.{colour}`` reason bits as in a session).
An output (the EXR or a preview) that is an input file (the raw frame, its sidecar, ``--config``)
is refused before any work; the EXR and its three previews are written all or none
(:mod:`polrig.formats.outputs`); a ``--layout`` that contradicts the sidecar is refused as by
``polrig stokes`` (:func:`polrig.cli.commands.stokes.check_layout_option`).
"""

from __future__ import annotations

import argparse

from polrig.choices import DEMOSAIC_METHODS, NETWORK_BINNINGS
from polrig.cli.commands.capture import add_model_size_option
from polrig.cli.commands.stokes import check_layout_option
from polrig.errors import ConfigError
from polrig.formats.argcheck import (
    axis_vector,
    check_output_file,
    finite_float,
    nonnegative_float,
    positive_float,
)

#: What the numbers of a ``polrig infer`` EXR are (also written into its header).
UNITS = ("Mueller elements in ADC DN per unit incident S0 (the raw file's values times "
         "2**(ADC bits - file bits), polrig.app.processing.adc_scale: a Mono16 frame of a 12-bit "
         "ADC counts 16 file DN per ADC DN), as the noise model, a session and a simulated "
         "capture's truth")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("infer", help="single-shot Mueller EXR from one raw frame (ONNX model)",
                       description="Reconstruct the 3x3 linear Mueller image of one DoFP raw frame "
                                   "(16-bit PNG/TIFF/.npy + optional JSON sidecar) captured under a "
                                   "known polarizer state, with the single-shot network. The "
                                   "result is in ADC DN (the file's values times 2^(ADC bits - "
                                   "file bits): 1/16 for a Mono16 frame of a 12-bit ADC; the ADC "
                                   "from --config's sensor model, default 12 bits), the unit of a "
                                   "session's results and a simulated capture's truth.")
    p.add_argument("raw", help="raw frame file")
    p.add_argument("--layout", default=None, help="mosaic layout (default: the sidecar's, else imx250mzr, with a note)")
    p.add_argument("--state-deg", type=finite_float, required=True, help="polarizer stage angle of the capture (deg)")
    p.add_argument("--out", required=True, help="output EXR path")
    p.add_argument("--demosaic", choices=DEMOSAIC_METHODS, default=None,
                   help="demosaic method (default superpixel: the sensor's native sampling; bilinear "
                        "with --resolution full). bilinear/newton at the default resolution run the "
                        "networks on the full-resolution demosaic (slow: resized to 1.5 Mpx)")
    p.add_argument("--resolution", choices=("superpixel", "full"), default="superpixel",
                   help="output resolution: superpixel (the networks' grid, default) or full (the raw "
                        "frame's: the networks on the superpixel grid plus the measured detail of a "
                        "full-resolution demosaic, models/full_resolution.py)")
    p.add_argument("--network-binning", type=int, choices=NETWORK_BINNINGS, default=1,
                   help="1 (default): the networks on the analyzer grid; 2: a faster mode, the networks on "
                        "that grid binned 2x2 (a quarter of the work) and the answer lifted back with the "
                        "grid's measured detail (models/full_resolution.py; its accuracy in "
                        "models/MODEL_CARD.md, 'Speed, warm and cold'); no --sigma")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="where the networks run: auto (CUDA when onnxruntime offers it, else the CPU; "
                        "default), cpu, or cuda (refused when unavailable). The provider used is "
                        "printed and recorded in the EXR header")
    p.add_argument("--black-level", type=nonnegative_float, default=None,
                   help="black level in DN, >= 0 and below the saturation level (default: the sidecar's)")
    p.add_argument("--scale", type=positive_float, default=None,
                   help="ADC DN per normalised unit, > 0 (default: from the image)")
    p.add_argument("--calibration", default=None,
                   help="calibration set folder: its camera intrinsics and stage zero axis "
                        "are used (a set of another sensor layout, or whose calibrated area "
                        "does not cover the frame, is refused)")
    p.add_argument("--config", default=None,
                   help="rig configuration TOML: its [nominal_geometry] table (default: the "
                        "simulated rig's design geometry), used where no calibration is given")
    p.add_argument("--stage-zero-axis", type=axis_vector, default=None,
                   help="polarizer stage zero axis in the camera frame, x,y,z (overrides the "
                        "calibration / rig geometry)")
    p.add_argument("--saturation-dn", type=positive_float, default=None,
                   help="raw value (DN, black level included) at which the sensor clips (default: "
                        "full scale of the frame's bit depth, 2^bits - 1; give 4095 for 12-bit data "
                        "stored in 16-bit files without a sidecar)")
    p.add_argument("--sigma", action="store_true",
                   help="also write the model's calibrated standard deviation of every element "
                        "(sigma.M{row}{col}.{colour} planes, models/uncertainty.py; costs about a "
                        "third more time)")
    p.add_argument("--geometry", action="store_true",
                   help="also write the networks' geometry: surface normal and light direction "
                        "(geometry.normal.{X,Y,Z}, geometry.light.{X,Y,Z}, camera frame), diffuse "
                        "albedo (geometry.albedo.{colour}) and roughness (geometry.roughness); "
                        "superpixel resolution, network binning 1")
    p.add_argument("--mirror-average", action="store_true",
                   help="also run the network on the frame's left-right mirror image and average the "
                        "two answers (models/mirror.py): a few per cent lower error for twice the "
                        "network time (models/MODEL_CARD.md, 'Mirror averaging')")
    add_model_size_option(p)
    p.add_argument("--weights", default=None, help="weights folder (default: the shipped model of --model-size)")
    p.add_argument("--min-snr", type=nonnegative_float, default=None, metavar="K",
                   help="in the previews (OUT_grid.png, OUT_dolp.png, OUT_aolp.png), mask pixels "
                        "whose measured S0 is below K noise standard deviations (default 3, "
                        "polrig.app.preview.DEFAULT_MIN_SNR; 0 masks only background and clipped pixels)")
    p.set_defaults(func=run)


#: The option that sets each :class:`polrig.acquisition.plan.SingleShotOptions` field and each
#: other field a library error names (:func:`polrig.cli.commands.capture.options_named`).
FLAGS = {"resolution": "--resolution", "demosaic": "--demosaic", "network_binning": "--network-binning",
         "mirror_average": "--mirror-average", "sigma": "--sigma", "calibration": "--calibration",
         "geometry": "--geometry"}
#: The plane groups of a ``polrig infer`` EXR (:func:`polrig.formats.exr.result_planes`): the
#: reason-bit mask always, the sigma with ``--sigma`` (``sigma_noise`` and ``residual`` are not
#: modelled for the single-shot method).
PLANES, SIGMA_PLANES = ("mueller", "mask"), ("mueller", "sigma", "mask")


def run(args: argparse.Namespace) -> int:
    import pathlib
    import sys

    import numpy as np

    from polrig.acquisition.plan import SingleShotOptions
    from polrig.app import calibrations
    from polrig.app.preview import (
        DEFAULT_MIN_SNR,
        RESULT_PREVIEW_SUFFIXES,
        mask_summary,
        write_result_previews,
    )
    from polrig.app.rig import load_rig_config
    from polrig.app.single_shot import SingleShot
    from polrig.cli.commands._units import adc_factor
    from polrig.cli.commands.capture import options_named
    from polrig.formats.exr import write_result_exr
    from polrig.formats.outputs import OutputSet, check_not_input
    from polrig.formats.rawio import DEFAULT_LAYOUT, assumed_layout_note, read_raw, sidecar_path
    from polrig.models.uncertainty import BEYOND_WARN_FRACTION
    from polrig.solve.reference import SATURATED, reason_names

    with options_named(FLAGS):  # the option rules (SingleShotOptions), before any file is read
        options = SingleShotOptions(args.resolution, args.demosaic, args.network_binning,
                                    args.mirror_average, args.sigma, args.geometry)
    out = pathlib.Path(args.out)
    if out.suffix.lower() != ".exr":
        raise ValueError(f"--out must be an .exr file, got {out}")
    check_output_file(out)
    previews = [out.with_name(f"{out.stem}{sfx}") for sfx in RESULT_PREVIEW_SUFFIXES]
    for preview_path in previews:
        check_output_file(preview_path, "--out preview")
    check_not_input([("--out", out)] + [("--out preview", p) for p in previews],
                    [args.raw, sidecar_path(args.raw), args.config])
    frame = read_raw(args.raw, layout=args.layout or DEFAULT_LAYOUT)
    check_layout_option(args.raw, args.layout, frame.meta.layout)  # a sidecar's layout stands
    layout = frame.meta.layout
    black = frame.meta.black_level_dn if args.black_level is None else args.black_level
    saturation = (2.0 ** frame.meta.bit_depth - 1) if args.saturation_dn is None else args.saturation_dn
    if not black < saturation:
        source = "--black-level" if args.black_level is not None else "the sidecar's black level"
        raise ConfigError(f"{source} {black:g} DN is not below the saturation level {saturation:g} DN")
    with options_named(FLAGS):
        calibration = calibrations.load_calibration(args.calibration)
        # a set from another sensor (layout) or one that does not cover this frame: refused
        h, w = frame.raw.shape[-2:]
        calibrations.check_calibration_fits(calibration, layout=layout,
                                            readout=(w, h, *frame.meta.offset_xy),
                                            what=f"{args.raw}", phase=False)
    config = load_rig_config(args.config)
    # the same geometry capture processing uses: calibration set, else the rig's nominal one
    geometry = calibrations.single_shot_geometry(calibration, config)
    route = SingleShot.open(args.device, args.weights, size=args.model_size or "auto")
    # the result is in the unit of the noise model, the truth of a simulated capture and a
    # session: ADC DN (a Mono16 frame of a 12-bit ADC holds its codes times 16)
    sensor, to_adc = adc_factor(config, frame.meta.bit_depth)
    with options_named(FLAGS):  # --sigma without a calibration of the graph: before the work
        result = route.frame(frame, args.state_deg, options, geometry=geometry, sensor=sensor,
                             black_level_dn=black, saturation_dn=saturation, scale=args.scale,
                             stage_zero_axis=args.stage_zero_axis)
    planes = (SIGMA_PLANES if options.sigma else PLANES) + (("geometry",) if options.geometry else ())
    min_snr = DEFAULT_MIN_SNR if args.min_snr is None else args.min_snr
    flags = result.preview_flags()
    with OutputSet() as outputs:  # the EXR and its previews: all or none
        write_result_exr(outputs.temporary(out), result, planes=planes, compression="none",
                         extra=result.extra_planes(planes),
                         metadata={"method": "single-shot",
                                   "model": f"PIPNet+pBRDF+PMMNet ({route.model.weights_dir}/{route.model.graph})",
                                   **route.model_header(),
                                   "scale_dn": result.scale, "alpha": result.alpha,
                                   "source": str(args.raw), "state_deg": args.state_deg,
                                   "layout": str(layout), "demosaic": options.demosaic,
                                   "saturation_dn": saturation, "units": UNITS,
                                   "adc_dn_per_file_dn": to_adc,
                                   "mask_bits": {str(b): n for b, n in reason_names().items()},
                                   **result.header(planes)})
        # previews: the measured S0 against its noise sigma decides what is signal
        write_result_previews(result.mueller, out.parent, flags=flags, snr=result.snr,
                              stem=outputs.temporary_stem(out.parent, out.stem, RESULT_PREVIEW_SUFFIXES),
                              min_snr=min_snr)
    mueller = result.mueller
    print(f"wrote {out}: {mueller.shape[-1]}x{mueller.shape[-2]}, {mueller.shape[0]} colour(s), "
          f"network {1e3 * result.timings_s['network']:.1f} ms; {mask_summary(flags, result.snr, min_snr)}; "
          f"previews {', '.join(p.name for p in previews)}")
    opts = ", ".join(f"{k}={v}" for k, v in result.provider_options.items())
    print(f"networks ran on {route.provider}" + (f" ({opts})" if opts else ""))
    n_clipped, n_object = int(np.sum(result.saturated)), int(np.sum(result.object))
    if n_clipped:
        print(f"polrig infer: warning: {n_clipped} of {n_object} object pixels have raw samples at or above "
              f"{saturation:g} DN (clipped); their Mueller estimate comes from clipped data (EXR planes "
              f"'mask', bit {SATURATED}: saturated); lower the exposure", file=sys.stderr)
    beyond = result.beyond_fraction
    if beyond is not None and beyond > BEYOND_WARN_FRACTION:
        print(f"polrig infer: warning: {100 * beyond:.0f} % of the object's pixels lie beyond the misfit range "
              f"the sigma was calibrated on (1 % by construction; e.g. a metal or a retarding film, which the "
              f"networks never saw): their sigma may be too small (EXR plane 'beyond_calibration'; "
              f"models/MODEL_CARD.md, 'Mismatched materials and interreflections')", file=sys.stderr)
    note = assumed_layout_note(args.raw, args.layout)  # after the work: a failure stays one line
    if note:
        print(f"polrig infer: note: {note}", file=sys.stderr)
    return 0
