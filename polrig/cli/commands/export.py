"""``polrig export SESSION_OR_RESULT --format ome-zarr|ome-tiff -o OUT``: a session or a result
EXR as OME-Zarr (OME-NGFF 0.4 by default, ``--ngff 0.5``) or OME-TIFF, for napari and Fiji.

The layout, the channel names and the metadata: :mod:`polrig.app.export` and
:mod:`polrig.formats.ome`.
"""

from __future__ import annotations

import argparse
import pathlib

from polrig.choices import OME_UNITS
from polrig.errors import ConfigError
from polrig.formats.argcheck import check_output_file, positive_float


def pixel_size(text: str) -> tuple[float, float]:
    """An argparse type: ``S`` or ``SY,SX``, positive finite numbers."""
    parts = text.split(",")
    if len(parts) not in (1, 2):
        raise argparse.ArgumentTypeError(f"expected SIZE or SIZE_Y,SIZE_X, got {text!r}")
    values = tuple(positive_float(p) for p in parts)
    return (values[0], values[-1])


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "export", help="a session or a result as OME-Zarr or OME-TIFF (napari, Fiji)",
        description="Write a session (a folder with session.json: its captures as the T axis) "
                    "or one Mueller result EXR as OME-Zarr (OME-NGFF 0.4 on Zarr v2 by default) "
                    "or OME-TIFF: one image per quantity (mueller, sigma, sigma_noise, mask, "
                    "residual, those the source holds), each with a channel axis named "
                    "M{i}{j}.{colour} (mask.{colour}, ...), and the sample metadata, plan and "
                    "rig as attributes. Needs the export extra: pip install 'polrig[export]'.")
    p.add_argument("source", type=pathlib.Path, metavar="SESSION_OR_RESULT",
                   help="a session folder or a Mueller result EXR")
    p.add_argument("--format", choices=("ome-zarr", "ome-tiff"), default="ome-zarr",
                   help="output format (default ome-zarr)")
    p.add_argument("-o", "--out", type=pathlib.Path, required=True, metavar="OUT",
                   help="output: a .zarr folder (replaced if it is a Zarr store) or an .ome.tif file")
    p.add_argument("--ngff", choices=("0.4", "0.5"), default="0.4",
                   help="OME-Zarr only: OME-NGFF version, 0.4 on Zarr v2 (default: what Fiji's and "
                        "QuPath's readers read) or 0.5 on Zarr v3")
    p.add_argument("--pixel-size", type=pixel_size, default=None, metavar="S|SY,SX",
                   help="the output pixel's size in the object, in --unit (default: not known, "
                        "unit-less pixels)")
    p.add_argument("--calibration", type=pathlib.Path, default=None, metavar="DIR",
                   help="the calibration set the source was captured with: the pixel size at the "
                        "turntable axis from its intrinsics and turntable steps, in micrometres "
                        "(instead of --pixel-size)")
    p.add_argument("--unit", choices=tuple(OME_UNITS), default="micrometer",
                   help="unit of --pixel-size (default micrometer)")
    p.add_argument("--revision", default=None, metavar="NAME",
                   help="a session's reconstruct revision (rev1, ...) instead of the capture's results")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.app.export import export

    src: pathlib.Path = args.source
    if not src.exists():
        raise ConfigError(f"{src}: no such session folder or result file")
    if not src.is_dir() and src.suffix.lower() != ".exr":
        raise ConfigError(f"{src}: give a session folder or a Mueller result .exr")
    if args.format == "ome-tiff":
        check_output_file(args.out)
    else:
        check_output_file(args.out.with_name(args.out.name + ".probe"))  # its folder exists
    try:
        out = export(src, args.out, args.format, pixel_size=args.pixel_size, unit=args.unit,
                     revision=args.revision, version=args.ngff, calibration=args.calibration)
    except (ValueError, FileExistsError, KeyError) as exc:
        raise ConfigError(str(exc).strip("'\"")) from None
    print(f"wrote {out} ({args.format}"
          f"{f', OME-NGFF {args.ngff}' if args.format == 'ome-zarr' else ''}"
          f"{'' if args.pixel_size or args.calibration else ', unit-less pixels'})")
    return 0
