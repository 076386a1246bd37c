"""``polrig snap --out FILE``: grab one frame, write the raw mosaic losslessly (with its JSON
sidecar) and Stokes previews next to it (``FILE_s0.png``, ``FILE_dolp.png``,
``FILE_aolp.png``), using the DoFP pipeline (:mod:`polrig.formats.rawio`, :mod:`polrig.sensor.stokes`,
:mod:`polrig.app.preview`)."""

from __future__ import annotations

import argparse
import pathlib

from polrig.cli.commands._device_args import (
    add_config_argument,
    identity,
    refuse_existing,
)
from polrig.errors import ConfigError
from polrig.formats.argcheck import check_output_file, positive_float

RAW_SUFFIXES = (".png", ".tif", ".tiff", ".npy")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("snap", help="grab one raw frame and write it with Stokes previews",
                       description="Grab one frame from the camera, write the raw mosaic "
                                   "losslessly (16-bit PNG, TIFF or .npy by the suffix of FILE, "
                                   "plus a .json sidecar of its metadata) and previews of S0, "
                                   "DoLP and AoLP (superpixel demosaic, ideal analyzers).")
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="FILE",
                   help="raw output file (.png, .tif, .tiff or .npy)")
    p.add_argument("--exposure-us", type=positive_float, default=None, metavar="US",
                   help="set the exposure time first (microseconds)")
    p.add_argument("--overwrite", action="store_true",
                   help="replace an existing FILE, its sidecar and previews (default: refuse, "
                        "so that no raw frame is lost)")
    add_config_argument(p)
    p.add_argument("--timeout", type=positive_float, default=None, metavar="S",
                   help="wait S seconds for the frame beyond its exposure and readout (> 0; default: "
                        "the margin every capture's grab has, 10)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.acquisition.hal import DEFAULT_TIMEOUT_S, grab_timeout_s
    from polrig.app.preview import aolp_rgb, dolp_gray, tone_map
    from polrig.app.rig import open_device
    from polrig.cli.commands.stokes import _write_png  # the stokes command's PNG writer
    from polrig.formats.rawio import sidecar_path, write_raw
    from polrig.sensor.stokes import stokes_from_raw

    out: pathlib.Path = args.out
    if out.suffix.lower() not in RAW_SUFFIXES:
        raise ConfigError(f"--out must end in {', '.join(RAW_SUFFIXES)}, got {out.name}")
    check_output_file(out)
    stem = out.with_suffix("")
    names = {k: stem.with_name(f"{stem.name}_{k}.png") for k in ("s0", "dolp", "aolp")}
    if not args.overwrite:  # before the camera is touched
        refuse_existing([out, sidecar_path(out)], what="a raw frame or its sidecar")
        refuse_existing(names.values(), what="a preview of an earlier snap")
    for p in (sidecar_path(out), *names.values()):
        check_output_file(p)
    with open_device(args.config, "camera") as cam:
        if args.exposure_us is not None:
            cam.capabilities.check_exposure(args.exposure_us)  # one line naming the range (exit 2)
            cam.set_exposure_us(args.exposure_us)
        margin = DEFAULT_TIMEOUT_S if args.timeout is None else args.timeout
        frame = cam.grab(timeout_s=grab_timeout_s(cam, margin))  # a long exposure never times out
        who = identity(cam.info())
    write_raw(out, frame)
    m = frame.meta
    ox, oy = m.offset_xy
    res = stokes_from_raw(frame.raw, f"{m.layout.split('@')[0]}@{ox},{oy}", "superpixel",
                          black_level_dn=m.black_level_dn, bit_depth=m.bit_depth)
    ci = 0 if res.stokes.shape[0] == 1 else 1  # mono Y, or green of a colour sensor
    valid = res.valid[ci]
    _write_png(names["s0"], tone_map(res.stokes[ci, 0]))
    _write_png(names["dolp"], dolp_gray(res.dolp[ci], valid=valid))
    _write_png(names["aolp"], aolp_rgb(res.aolp_deg[ci], res.dolp[ci], valid=valid))
    h, w = frame.raw.shape
    exposure = f"{m.exposure_us:g} us" if m.exposure_us == m.exposure_us else "not reported"
    print(f"snap: frame {m.frame_id} {w}x{h} {m.pixel_format} ({m.bit_depth} bit, layout "
          f"{m.layout}, exposure {exposure}) from {who}")
    print(f"wrote {out} (+ .json sidecar), {', '.join(p.name for p in names.values())}")
    return 0
