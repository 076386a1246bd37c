"""``polrig stokes``: a raw DoFP mosaic -> Stokes EXR plus DoLP and AoLP PNG previews."""

from __future__ import annotations

import argparse
import pathlib
import sys

import cv2
import numpy as np

from polrig.analyzer import AnalyzerModel
from polrig.argcheck import check_output_file, int_range, nonnegative_float
from polrig.demosaic import METHODS
from polrig.errors import ConfigError
from polrig.exr import colour_planes, write_stokes_exr
from polrig.layouts import LAYOUTS
from polrig.preview import aolp_rgb, dolp_gray
from polrig.rawio import (DEFAULT_LAYOUT, assumed_layout_note, atomic_write_bytes,
                          check_bit_depth, read_raw)


#: What the extra planes of a ``polrig stokes`` EXR mean (also written into its header).
STOKES_EXR_PLANES = {"valid": "1 = valid in every colour (finite, S0 > 0, no saturated sample in the demosaic support)",
                     "dolp.{ch}": "degree of linear polarization, 0 where invalid",
                     "aolp_deg.{ch}": "angle of linear polarization in degrees [0, 180) (docs/conventions.md), 0 where invalid"}


def register(subparsers) -> None:
    p = subparsers.add_parser(
        "stokes", help="turn a raw DoFP mosaic into a Stokes EXR with DoLP/AoLP previews",
        description="Read a raw DoFP mosaic (16/8-bit PNG, TIFF or .npy; its .json sidecar, if "
                    "present, supplies layout, ROI offset, bit depth and black level), "
                    "demosaic it, compute linear Stokes images and write OUT.exr "
                    "(channels S0..S2 per colour, plus mask and DoLP/AoLP planes) and "
                    "OUT_dolp.png, OUT_aolp.png (AoLP as hue, DoLP as value).")
    p.add_argument("raw", type=pathlib.Path, metavar="RAW", help="raw mosaic file")
    p.add_argument("--layout", choices=sorted(LAYOUTS), default=None,
                   help="mosaic layout (default: from the sidecar, else imx250mzr, with a note)")
    p.add_argument("--demosaic", choices=METHODS, default="bilinear",
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
    from polrig.stokes import stokes_from_raw

    out = args.out
    if out.suffix.lower() != ".exr":
        raise ConfigError(f"--out must name an .exr file, got {out}")
    check_output_file(out)
    stem = out.with_suffix("")
    dolp_png = stem.with_name(stem.name + "_dolp.png")
    aolp_png = stem.with_name(stem.name + "_aolp.png")
    for preview in (dolp_png, aolp_png):
        check_output_file(preview, "--out preview")
    frame = read_raw(args.raw)
    meta = frame.meta
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
    analyzer = AnalyzerModel.load(args.analyzer) if args.analyzer else None
    res = stokes_from_raw(frame.raw, layout, args.demosaic, black_level_dn=black,
                          analyzer=analyzer, bit_depth=bits)
    extra = {"valid": res.valid.all(axis=0)}
    extra.update(colour_planes("dolp", res.dolp))
    extra.update(colour_planes("aolp_deg", res.aolp_deg))
    metadata = {"capture": {"source": str(args.raw), "frame": meta.to_json()},
                "planes": STOKES_EXR_PLANES,
                "processing": {"layout": res.layout, "demosaic": args.demosaic,
                               "black_level_dn": black, "bit_depth": bits,
                               "analyzer": str(args.analyzer) if args.analyzer else "ideal",
                               "dolp_overshoot": res.dolp_overshoot,
                               "masked_pixels": int((~res.valid).sum())}}
    write_stokes_exr(out, res.stokes, extra=extra, metadata=metadata)
    # previews show one colour plane: Y for mono, G (the best-sampled Bayer colour) for colour
    c = res.stokes.shape[0]
    ci = 0 if c == 1 else 1  # green: the best-sampled colour of a Bayer sensor
    valid = res.valid[ci]
    _write_png(dolp_png, dolp_gray(res.dolp[ci], valid=valid))
    _write_png(aolp_png, aolp_rgb(res.aolp_deg[ci], res.dolp[ci], valid=valid))
    print(f"wrote {out} ({res.stokes.shape[-1]}x{res.stokes.shape[-2]}, {c} colour plane(s), "
          f"{args.demosaic}), {dolp_png.name}, {aolp_png.name}; masked "
          f"{int((~res.valid).sum())} pixel(s), DoLP clipped at {res.dolp_overshoot}")
    note = assumed_layout_note(args.raw, args.layout)  # after the work: a failure stays one line
    if note:
        print(f"polrig stokes: note: {note}", file=sys.stderr)
    return 0


def _write_png(path: pathlib.Path, rgb: np.ndarray) -> None:
    ok, enc = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    if not ok:  # pragma: no cover
        raise OSError(f"could not encode {path}")
    atomic_write_bytes(path, enc.tobytes())
