"""``polrig snap --out FILE``: grab one frame, write the raw mosaic losslessly (with its JSON
sidecar) and Stokes previews next to it (``FILE_s0.png``, ``FILE_dolp.png``,
``FILE_aolp.png``), using the DoFP pipeline (:mod:`polrig.rawio`, :mod:`polrig.stokes`,
:mod:`polrig.preview`)."""

from __future__ import annotations

import argparse
import pathlib

from polrig.commands._device_args import add_config_argument, add_timeout_argument, identity
from polrig.errors import ConfigError

RAW_SUFFIXES = (".png", ".tif", ".tiff", ".npy")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("snap", help="grab one raw frame and write it with Stokes previews",
                       description="Grab one frame from the camera, write the raw mosaic "
                                   "losslessly (16-bit PNG, TIFF or .npy by the suffix of FILE, "
                                   "plus a .json sidecar of its metadata) and previews of S0, "
                                   "DoLP and AoLP (superpixel demosaic, ideal analyzers).")
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="FILE",
                   help="raw output file (.png, .tif, .tiff or .npy)")
    p.add_argument("--exposure-us", type=float, default=None, metavar="US",
                   help="set the exposure time first (microseconds)")
    add_config_argument(p)
    add_timeout_argument(p, 10.0)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.commands.stokes import _write_png  # the stokes command's PNG writer
    from polrig.preview import aolp_rgb, dolp_gray, tone_map
    from polrig.rawio import write_raw
    from polrig.rig import open_device
    from polrig.stokes import stokes_from_raw

    out: pathlib.Path = args.out
    if out.suffix.lower() not in RAW_SUFFIXES:
        raise ConfigError(f"--out must end in {', '.join(RAW_SUFFIXES)}, got {out.name}")
    if not out.parent.is_dir():
        raise ConfigError(f"--out folder {out.parent} does not exist")
    if args.exposure_us is not None and not args.exposure_us > 0:
        raise ConfigError(f"--exposure-us must be positive, got {args.exposure_us}")
    with open_device(args.config, "camera") as cam:
        if args.exposure_us is not None:
            cam.set_exposure_us(args.exposure_us)
        frame = cam.grab(timeout_s=args.timeout)
        who = identity(cam.info())
    write_raw(out, frame)
    m = frame.meta
    ox, oy = m.offset_xy
    res = stokes_from_raw(frame.raw, f"{m.layout.split('@')[0]}@{ox},{oy}", "superpixel",
                          black_level_dn=m.black_level_dn, bit_depth=m.bit_depth)
    ci = 0 if res.stokes.shape[0] == 1 else 1  # mono Y, or green of a colour sensor
    valid = res.valid[ci]
    stem = out.with_suffix("")
    names = {k: stem.with_name(f"{stem.name}_{k}.png") for k in ("s0", "dolp", "aolp")}
    _write_png(names["s0"], tone_map(res.stokes[ci, 0]))
    _write_png(names["dolp"], dolp_gray(res.dolp[ci], valid=valid))
    _write_png(names["aolp"], aolp_rgb(res.aolp_deg[ci], res.dolp[ci], valid=valid))
    h, w = frame.raw.shape
    exposure = f"{m.exposure_us:g} us" if m.exposure_us == m.exposure_us else "not reported"
    print(f"snap: frame {m.frame_id} {w}x{h} {m.pixel_format} ({m.bit_depth} bit, layout "
          f"{m.layout}, exposure {exposure}) from {who}")
    print(f"wrote {out} (+ .json sidecar), {', '.join(p.name for p in names.values())}")
    return 0
