"""``polrig export SESSION_OR_RESULT --format ome-zarr|ome-tiff -o OUT``: a session or a result
EXR as OME-Zarr (OME-NGFF 0.4 by default, ``--ngff 0.5``) or OME-TIFF, for napari and Fiji.

The layout, the channel names and the metadata: :mod:`polrig.app.export` and
:mod:`polrig.formats.ome`. Refused in one line (exit 2) before anything is read: an output that
is the source (or, for OME-Zarr, a folder holding it), an output name without the format's
ending (``.zarr``; ``.ome.tif`` or ``.ome.tiff``), ``--ngff`` with ``--format ome-tiff``. A
failed write (a full disk) is one line naming the output (exit 1).
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
                   help="output: a .zarr folder (replaced if it is a Zarr store) or an .ome.tif "
                        "(.ome.tiff) file; another name is refused")
    p.add_argument("--ngff", choices=("0.4", "0.5"), default=None,
                   help="OME-Zarr only (refused with ome-tiff): OME-NGFF version, 0.4 on Zarr v2 "
                        "(default: what Fiji's and QuPath's readers read) or 0.5 on Zarr v3")
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


#: The output name endings of each format (lower case).
OUT_ENDINGS = {"ome-zarr": (".zarr",), "ome-tiff": (".ome.tif", ".ome.tiff")}


def run(args: argparse.Namespace) -> int:
    from polrig.app.export import export
    from polrig.formats.outputs import check_not_input

    src: pathlib.Path = args.source
    out: pathlib.Path = args.out
    if not src.exists():
        raise ConfigError(f"{src}: no such session folder or result file")
    if not src.is_dir() and src.suffix.lower() != ".exr":
        raise ConfigError(f"{src}: give a session folder or a Mueller result .exr")
    if args.ngff is not None and args.format != "ome-zarr":
        raise ConfigError(f"--ngff {args.ngff} applies to --format ome-zarr only, not "
                          f"{args.format}")
    endings = OUT_ENDINGS[args.format]
    check_not_input([("-o", out)], [src, args.calibration],
                    replaces_folder=args.format == "ome-zarr")
    if not out.name.lower().endswith(endings):
        raise ConfigError(f"-o {out}: an {args.format} output's name must end in "
                          f"{' or '.join(endings)}")
    if args.format == "ome-tiff":
        check_output_file(out)
    else:
        check_output_file(out.with_name(out.name + ".probe"))  # its folder exists
    version = args.ngff or "0.4"
    try:
        written = export(src, out, args.format, pixel_size=args.pixel_size, unit=args.unit,
                         revision=args.revision, version=version, calibration=args.calibration)
    except KeyError as exc:  # str() of a KeyError is the repr of its message
        raise ConfigError(str(exc.args[0]) if exc.args else str(exc)) from None
    except (ValueError, FileExistsError) as exc:
        raise ConfigError(str(exc)) from None
    print(f"wrote {written} ({args.format}"
          f"{f', OME-NGFF {version}' if args.format == 'ome-zarr' else ''}"
          f"{'' if args.pixel_size or args.calibration else ', unit-less pixels'})")
    return 0
