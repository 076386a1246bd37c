"""``polrig polarizer RESULT.exr --in DEG|unpolarized --analyzer DEG|none --out FILE``: the
image a Mueller result predicts behind a virtual polarizer and analyzer.

``I = a(analyzer)^T M s_in(in)`` (:mod:`polrig.optics.virtual_polarizer`): for ``--in`` one of
the capture's polarizer states and ``--analyzer`` one of the DoFP angles 0/45/90/135 it is what
those analyzer pixels of the raw frame read (in ADC DN, black level removed), the most direct
check of a result against a photograph. Output: a float EXR (``I.{R,G,B|Y}``, with the
result's sigma ``sigma.I.{...}`` and ``mask.{...}``) or a 16-bit PNG (``round(I * --scale)``
clipped to 0..65535, NaN as 0).
"""

from __future__ import annotations

import argparse
import math
import pathlib
from typing import TYPE_CHECKING

from polrig.errors import ConfigError
from polrig.formats.argcheck import check_output_file, positive_float

if TYPE_CHECKING:
    import numpy as np

SUFFIXES = (".exr", ".png")


def angle_or(word: str):
    """An argparse type: a finite angle in degrees, or ``word`` (returned as None)."""
    def parse(text: str) -> float | None:
        if text.strip().lower() == word:
            return None
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an angle in degrees or {word!r}, "
                                             f"got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite angle, got {text!r}")
        return value
    return parse


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "polarizer", help="the image a Mueller result predicts behind a virtual polarizer",
        description="Compute I = a(analyzer)^T M s_in from a Mueller result: the image for "
                    "incident linear polarization at --in degrees (the rig's polarizer, incident "
                    "frame; 'unpolarized' for unpolarized light of the same S0) seen through an "
                    "ideal analyzer at --analyzer degrees (emergent frame, from image right "
                    "towards image up; 'none' for the total intensity S0). At a capture's state "
                    "and a DoFP analyzer angle it is what those pixels of the raw frame read.")
    p.add_argument("result", type=pathlib.Path, metavar="RESULT", help="Mueller result EXR")
    p.add_argument("--in", dest="incident", type=angle_or("unpolarized"), required=True,
                   metavar="DEG|unpolarized", help="incident polarizer angle in degrees, or unpolarized")
    p.add_argument("--analyzer", type=angle_or("none"), required=True, metavar="DEG|none",
                   help="analyzer angle in degrees, or none (total intensity)")
    p.add_argument("--out", type=pathlib.Path, required=True, metavar="FILE",
                   help="output image: .exr (float32, with sigma) or .png (16-bit)")
    p.add_argument("--scale", type=positive_float, default=1.0, metavar="K",
                   help="PNG only: DN multiplied by K before rounding to 16 bits (default 1)")
    p.add_argument("--sigma", choices=("sigma", "sigma_noise", "none"), default="sigma",
                   help="EXR only: per-element sigma planes of the result to propagate "
                        "(default sigma; none: no sigma plane)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from polrig.formats.exr import channel_suffixes, colour_planes, read_mueller_exr, write_exr
    from polrig.optics.virtual_polarizer import virtual_polarizer_image

    out: pathlib.Path = args.out
    suffix = out.suffix.lower()
    if suffix not in SUFFIXES:
        raise ConfigError(f"--out must name an .exr or .png file, got {out}")
    check_output_file(out)
    res = read_mueller_exr(args.result)
    c = res.mueller.shape[0]
    sfx = channel_suffixes(c)
    sigma = None
    if suffix == ".exr" and args.sigma != "none":
        names = [f"{args.sigma}.M{r}{q}.{s}" for s in sfx for r in range(3) for q in range(3)]
        if all(n in res.extra for n in names):
            sigma = np.stack([np.stack([np.stack([res.extra[f"{args.sigma}.M{r}{q}.{s}"]
                                                  for q in range(3)]) for r in range(3)])
                              for s in sfx])
    image, image_sigma = virtual_polarizer_image(res.mueller, args.incident, args.analyzer, sigma)
    what = (f"incident {'unpolarized' if args.incident is None else f'{args.incident:g} deg'}, "
            f"analyzer {'none' if args.analyzer is None else f'{args.analyzer:g} deg'}")
    h, w = image.shape[-2:]
    if suffix == ".exr":
        planes = colour_planes("I", image)
        if image_sigma is not None:
            planes.update(colour_planes("sigma.I", image_sigma))
        for s in sfx:
            if f"mask.{s}" in res.extra:
                planes[f"mask.{s}"] = res.extra[f"mask.{s}"]
        metadata = {"source": str(args.result),
                    "incident_deg": args.incident, "analyzer_deg": args.analyzer,
                    "formula": "I = a(analyzer)^T M s_in(incident), docs/analysis.md",
                    "units": "DN: the result's M (DN per unit incident S0) applied to an "
                             "incident state of S0 = 1/2, as a capture's polarizer state, and "
                             "read as a DoFP analyzer pixel reads (docs/analysis.md)",
                    "planes": {"I.{ch}": "virtual polarizer image",
                               "sigma.I.{ch}": f"its standard deviation (from {args.sigma})",
                               "mask.{ch}": "the result's mask plane, copied"}}
        for key in ("capture", "pose_deg", "exposure_us"):
            if key in res.metadata:
                metadata[key] = res.metadata[key]
        write_exr(out, planes, kind="virtual_polarizer", metadata=metadata)
        print(f"wrote {out} ({w}x{h}, {c} colour plane(s), {what}"
              f"{', with sigma' if image_sigma is not None else ''})")
        return 0
    scaled = np.nan_to_num(image.astype(np.float64) * args.scale, nan=0.0)
    clipped = int(np.count_nonzero((scaled < 0) | (scaled > 65535)))
    _write_png16(out, np.clip(np.rint(scaled), 0, 65535).astype(np.uint16))
    note = f"; {clipped} pixel-colour(s) clipped to 0..65535" if clipped else ""
    print(f"wrote {out} ({w}x{h} 16-bit, {c} colour plane(s), {what}, DN x {args.scale:g}{note})")
    return 0


def _write_png16(path: pathlib.Path, planes: np.ndarray) -> None:
    """``(C, H, W)`` uint16 as a grey (C = 1) or RGB (C = 3) 16-bit PNG, atomically."""
    import cv2
    import numpy as np

    from polrig.atomic import atomic_write_bytes

    img = planes[0] if planes.shape[0] == 1 else cv2.cvtColor(
        np.ascontiguousarray(np.moveaxis(planes, 0, -1)), cv2.COLOR_RGB2BGR)
    ok, enc = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:  # pragma: no cover - OpenCV encodes every uint16 grey/RGB image
        raise OSError(f"{path}: could not encode a 16-bit PNG")
    atomic_write_bytes(path, enc.tobytes())
