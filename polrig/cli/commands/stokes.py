"""``polrig stokes``: a raw DoFP mosaic -> Stokes EXR plus DoLP and AoLP PNG previews.

An output (the EXR or a preview) that is an input file (the raw frame, its sidecar,
``--analyzer``, ``--config``) is refused before any work, and the EXR and its six previews are
written all or none (:mod:`polrig.formats.outputs`): a failed write leaves the files of an
earlier run as they were. A ``--layout`` that contradicts the sidecar is refused
(:func:`check_layout_option`, shared with ``polrig infer``)."""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import TYPE_CHECKING

from polrig.choices import DEMOSAIC_METHODS, LAYOUT_NAMES, MIN_SNR
from polrig.errors import ConfigError, FormatError
from polrig.formats.argcheck import check_output_file, int_range, nonnegative_float

if TYPE_CHECKING:
    import numpy as np

    from polrig.sensor.analyzer import AnalyzerModel

#: What the extra planes of a ``polrig stokes`` EXR mean (also written into its header).
STOKES_EXR_PLANES = {"valid": "1 = valid in every colour (finite, S0 > 0, no saturated sample in the demosaic support)",
                     "saturated": "1 = a saturated raw sample in the demosaic support of some colour",
                     "snr.{ch}": "S0 over its noise standard deviation (sensor noise model); "
                                 "DoLP/AoLP of a pixel below --min-snr are background noise",
                     "dolp.{ch}": "degree of linear polarization, 0 where invalid",
                     "aolp_deg.{ch}": "angle of linear polarization in degrees [0, 180) (docs/conventions.md), 0 where invalid"}
#: The unit of a ``polrig stokes`` EXR (also written into its header).
STOKES_UNITS = ("S0..S2 in ADC DN (the raw file's values minus the black level, times "
                "2**(ADC bits - file bits), polrig.app.processing.adc_scale)")


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "stokes", help="turn a raw DoFP mosaic into a Stokes EXR with DoLP/AoLP previews",
        description="Read a raw DoFP mosaic (16/8-bit PNG, TIFF or .npy; its .json sidecar, if "
                    "present, supplies layout, ROI offset, bit depth and black level), "
                    "demosaic it, compute linear Stokes images and write OUT.exr "
                    "(channels S0..S2 per colour, plus mask and DoLP/AoLP planes) and "
                    "OUT_dolp.png, OUT_aolp.png (AoLP as hue, DoLP as value or saturation, with "
                    "the hue bar and the colour wheel), OUT_imin.png and OUT_imax.png (the "
                    "intensity across and along the AoLP: Imin is the glare-reduced image, both "
                    "on S0's scale) and OUT_s1.png, OUT_s2.png (signed S1, S2 on a blue-white-red "
                    "map with its bar). "
                    "Stokes values are in ADC DN (a Mono16 file of a 12-bit ADC is divided by "
                    "16). Pixels whose S0 is below --min-snr noise standard deviations are "
                    "masked (black) in the previews and counted.")
    p.add_argument("raw", type=pathlib.Path, metavar="RAW", help="raw mosaic file")
    p.add_argument("--layout", choices=sorted(LAYOUT_NAMES), default=None,
                   help="mosaic layout (default: from the sidecar, else imx250mzr, with a "
                        "note); one that contradicts the sidecar's is refused")
    p.add_argument("--demosaic", choices=DEMOSAIC_METHODS, default="bilinear",
                   help="demosaicing method (default: bilinear)")
    p.add_argument("--black-level", type=nonnegative_float, default=None, metavar="N",
                   help="black level in DN to subtract, >= 0 and below the full scale "
                        "(default: from the sidecar, else 0)")
    p.add_argument("--roi-offset", default=None, metavar="X,Y",
                   help="sensor ROI offset of the frame, sets the mosaic phase (default: from "
                        "the sidecar, else 0,0)")
    p.add_argument("--bit-depth", type=int_range(1, 16), default=None, metavar="BITS",
                   help="significant bits of the raw values, 1..16 (at most 8 for 8-bit "
                        "files; no value above 2**BITS-1, the saturation level) (default: from "
                        "the sidecar, else the file's dtype)")
    p.add_argument("--analyzer", type=pathlib.Path, default=None, metavar="NPZ",
                   help="calibrated per-pixel analyzer model (.npz) of this readout")
    p.add_argument("--min-snr", type=nonnegative_float, default=MIN_SNR, metavar="K",
                   help=f"mask DoLP/AoLP where S0 is below K noise standard deviations of the "
                        f"sensor noise model (default {MIN_SNR:g}; 0 masks only clipped pixels "
                        f"and those without signal, S0 below 0)")
    p.add_argument("--config", type=pathlib.Path, default=None, metavar="RIG.toml",
                   help="rig configuration whose sensor model (ADC bits, gain, read noise) "
                        "gives the unit and the noise (default: the IMX250 model, 12 bits)")
    p.add_argument("--aolp-dolp", choices=("value", "saturation"), default="value",
                   help="how OUT_aolp.png shows DoLP: as the colour's value (dark = weakly "
                        "polarized, default) or its saturation (white = weakly polarized)")
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="OUT.exr",
                   help="output Stokes EXR")
    p.set_defaults(func=run)


def _parse_offset(text: str) -> tuple[int, int]:
    try:
        x, y = (int(v) for v in text.split(","))
    except ValueError:
        raise ConfigError(f"--roi-offset must be X,Y (two integers), got {text!r}") from None
    if x < 0 or y < 0:
        raise ConfigError(f"--roi-offset must not be negative, got {text!r}")
    return x, y


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from polrig.app.preview import DARK, SATURATED, display_valid, mask_summary, s0_snr
    from polrig.formats.exr import colour_planes, write_stokes_exr
    from polrig.formats.outputs import OutputSet, check_not_input
    from polrig.formats.rawio import (
        DEFAULT_LAYOUT,
        assumed_layout_note,
        check_bit_depth,
        read_raw,
        sidecar_path,
    )
    from polrig.sensor.layouts import LAYOUTS
    from polrig.sensor.stokes import stokes_from_raw

    out = args.out
    if out.suffix.lower() != ".exr":
        raise ConfigError(f"--out must name an .exr file, got {out}")
    check_output_file(out)
    stem = out.with_suffix("")
    pngs = {k: stem.with_name(f"{stem.name}_{k}.png")
            for k in ("dolp", "aolp", "imin", "imax", "s1", "s2")}
    for preview in pngs.values():
        check_output_file(preview, "--out preview")
    check_not_input([("--out", out)] + [("--out preview", p) for p in pngs.values()],
                    [args.raw, sidecar_path(args.raw), args.analyzer, args.config])
    frame = read_raw(args.raw)
    meta = frame.meta
    check_layout_option(args.raw, args.layout, meta.layout)
    layout_name = args.layout or meta.layout or DEFAULT_LAYOUT
    if layout_name.split("@")[0].lower() not in LAYOUTS:
        raise ConfigError(f"unknown layout {layout_name!r} (sidecar of {args.raw})")
    ox, oy = _parse_offset(args.roi_offset) if args.roi_offset else tuple(meta.offset_xy)
    black = meta.black_level_dn if args.black_level is None else args.black_level
    if args.bit_depth is not None:
        check_bit_depth(frame.raw, args.bit_depth, str(args.raw), label="--bit-depth",
                        exact_dtype=False)
    bits = args.bit_depth or meta.bit_depth  # read_raw checked the sidecar's against the data
    if not black < 2 ** bits - 1:
        source = "--black-level" if args.black_level is not None else "the sidecar's black level"
        raise ConfigError(f"{source} {black:g} DN is not below the full scale {2 ** bits - 1} "
                          f"DN of {bits}-bit data")
    layout = f"{layout_name.split('@')[0].lower()}@{ox},{oy}"
    analyzer = _load_analyzer(args.analyzer) if args.analyzer else None
    from polrig.app.rig import load_rig_config
    from polrig.cli.commands._units import adc_factor

    model, to_adc = adc_factor(load_rig_config(args.config), bits)
    res = stokes_from_raw(frame.raw, layout, args.demosaic, black_level_dn=black,
                          analyzer=analyzer, bit_depth=bits)
    stokes = res.stokes * np.float32(to_adc)  # file DN -> ADC DN (DoLP, AoLP unchanged)
    snr = s0_snr(stokes[:, 0], model, meta.exposure_us)
    # saturated, or no signal at all (S0 <= 0 or not finite: dark)
    flags = (np.where(res.saturated, SATURATED, 0)
             | np.where(~res.valid & ~res.saturated, DARK, 0)).astype(np.uint8)
    extra = {"valid": res.valid.all(axis=0), "saturated": res.saturated.any(axis=0)}
    extra.update(colour_planes("snr", np.nan_to_num(snr, nan=0.0)))
    extra.update(colour_planes("dolp", res.dolp))
    extra.update(colour_planes("aolp_deg", res.aolp_deg))
    masked = mask_summary(flags, snr, args.min_snr)
    metadata = {"capture": {"source": str(args.raw), "frame": meta.to_json()},
                "planes": STOKES_EXR_PLANES, "units": STOKES_UNITS,
                "processing": {"layout": res.layout, "demosaic": args.demosaic,
                               "black_level_dn": black, "bit_depth": bits,
                               "adc_dn_per_file_dn": to_adc,
                               "analyzer": str(args.analyzer) if args.analyzer else "ideal",
                               "dolp_overshoot": res.dolp_overshoot,
                               "min_snr": args.min_snr,
                               "masked_pixels": int((~res.valid).sum())}}
    with OutputSet() as outputs:  # the EXR and its previews: all or none
        write_stokes_exr(outputs.temporary(out), stokes, extra=extra, metadata=metadata)
        _write_previews(outputs, pngs, res, stokes, flags, snr, args)
    shown = display_valid(flags, snr, args.min_snr)
    with np.errstate(all="ignore"):
        over = int((shown & (np.hypot(stokes[:, 1], stokes[:, 2]) > stokes[:, 0])).sum())
    clipped = (f"; DoLP above 1 (noise) in {over} shown pixel-colour(s), drawn as 1"
               if over else "")
    print(f"wrote {out} ({res.stokes.shape[-1]}x{res.stokes.shape[-2]}, {res.stokes.shape[0]} "
          f"colour plane(s), "
          f"{args.demosaic}, ADC DN), {', '.join(p.name for p in pngs.values())}; "
          f"{masked}{clipped}")
    note = assumed_layout_note(args.raw, args.layout)  # after the work: a failure stays one line
    if note:
        print(f"polrig stokes: note: {note}", file=sys.stderr)
    return 0


def _write_previews(outputs, pngs: dict[str, pathlib.Path], res, stokes: np.ndarray,
                    flags: np.ndarray, snr: np.ndarray, args: argparse.Namespace) -> None:
    """Write the previews ``pngs`` (by key: dolp, aolp, imin, imax, s1, s2) to their
    temporaries in ``outputs`` (:class:`polrig.formats.outputs.OutputSet`). They show one
    colour plane: Y for mono, G (the best-sampled Bayer colour) for colour."""
    import numpy as np

    from polrig.app.preview import (
        aolp_key,
        aolp_rgb,
        colorbar,
        display_valid,
        diverging,
        dolp_gray,
        dolp_legend,
        tone_map,
        with_legend,
    )
    from polrig.sensor.stokes import min_max_intensity

    c = res.stokes.shape[0]
    ci = 0 if c == 1 else 1  # green: the best-sampled colour of a Bayer sensor
    valid = display_valid(flags[ci], snr[ci], args.min_snr)
    _write_png(outputs.temporary(pngs["dolp"]), with_legend(dolp_gray(res.dolp[ci], valid=valid),
                                                            dolp_legend(res.dolp.shape[-2])))
    h = res.dolp.shape[-2]
    _write_png(outputs.temporary(pngs["aolp"]),
               with_legend(aolp_rgb(res.aolp_deg[ci], res.dolp[ci], dolp_as=args.aolp_dolp,
                                    valid=valid),
                           aolp_key(h, dolp_as=args.aolp_dolp)))
    imin, imax = min_max_intensity(stokes, res.valid)
    white = float(np.percentile(stokes[ci, 0][res.valid[ci]], 99.5)) if res.valid[ci].any() else 1.0
    for key, plane in (("imin", imin[ci]), ("imax", imax[ci])):
        _write_png(outputs.temporary(pngs[key]), tone_map(plane, white=white, valid=res.valid[ci]))
    with np.errstate(all="ignore"):
        lin = np.hypot(stokes[ci, 1], stokes[ci, 2])[res.valid[ci]]
    vmax = float(np.percentile(lin, 99.5)) if lin.size and lin.max() > 0 else 1.0
    for key, plane in (("s1", stokes[ci, 1]), ("s2", stokes[ci, 2])):
        _write_png(outputs.temporary(pngs[key]),
                   with_legend(diverging(plane, vmax=vmax, valid=res.valid[ci]),
                               colorbar(h, vmax=vmax)))


def check_layout_option(raw: str | pathlib.Path, option: str | None, sidecar_layout: str) -> None:
    """:class:`ConfigError` when ``--layout`` (``option``) contradicts the sidecar of the raw
    file ``raw`` (its layout ``sidecar_layout``): the layout names differ, or ``option``
    gives an ROI offset (``name@x,y``) that differs. Nothing without ``option`` or without a
    sidecar. ``polrig stokes`` and ``polrig infer`` refuse alike."""
    from polrig.formats.rawio import sidecar_path

    if not option or not sidecar_path(raw).is_file():
        return
    given, said = (t.replace(" ", "").lower() for t in (option, sidecar_layout))
    if "@" not in given:
        said = said.split("@")[0]
    if given != said:
        raise ConfigError(f"--layout {option} contradicts the sidecar of {raw}, which says "
                          f"{sidecar_layout}; drop --layout (or fix the sidecar)")


def _load_analyzer(path: pathlib.Path) -> AnalyzerModel:
    """The ``--analyzer`` model; a file that is not an .npz archive is one line in polrig's
    words (numpy's own message for a text file is advice about unpickling it)."""
    from polrig.sensor.analyzer import AnalyzerModel

    try:
        with open(path, "rb") as f:
            head = f.read(4)
    except IsADirectoryError:
        raise ConfigError(f"--analyzer {path} is a directory; give the .npz file") from None
    if head != b"PK\x03\x04":  # every .npz is a zip archive
        raise FormatError(f"--analyzer {path}: not a polrig analyzer model (an .npz file "
                          f"written by polrig calibrate)")
    return AnalyzerModel.load(path)


def _write_png(path: pathlib.Path, rgb: np.ndarray) -> None:
    from polrig.app.preview import png_bytes
    from polrig.atomic import atomic_write_bytes

    atomic_write_bytes(path, png_bytes(rgb))
