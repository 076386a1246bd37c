"""``polrig stats RESULT_OR_SESSION --roi SHAPE [--profile x0,y0,x1,y1] [--csv OUT]``: ROI
statistics and line profiles of Mueller results and Stokes EXRs, headless (the numbers of the
GUI's ROI tools).

Statistics, conventions and the two standard errors: :mod:`polrig.app.roi`. A session is read
through :class:`polrig.app.session.Session` (read only, no lock): every capture with a Mueller
result, in one CSV table whose first column ``capture`` names each row's capture (the profile
CSV alike; each capture's source, image size and sigma in a ``# capture NAME:`` comment line
above it). The CSV and its profile are written together or not at all
(:class:`polrig.formats.outputs.OutputSet`); neither may be an input. A Stokes EXR (``polrig stokes --out``)
gives the Stokes quantities (S0, DoLP, AoLP) with the masks the Viewer applies
(:func:`polrig.app.preview.stokes_exr_masks`) and the standard errors from its ``snr`` planes.
"""

from __future__ import annotations

import argparse
import math
import pathlib

from polrig.choices import SIGMA_SOURCES
from polrig.errors import ConfigError
from polrig.formats.argcheck import check_output_file, positive_float


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "stats", help="ROI statistics and line profiles of Mueller results and Stokes EXRs",
        description="Statistics over a region of a Mueller result EXR, of a Stokes EXR (polrig "
                    "stokes), or of every capture of a session: mean and standard deviation of S0, DoLP and the circular mean and "
                    "spread of AoLP (of the light unpolarized illumination leaves: m00, PL, "
                    "PL_axis_deg), of every m_ij/m00 and of the parameter maps of polrig "
                    "analyze (of a Stokes EXR: S0, DoLP, AoLP), each with two standard errors of the mean (from the pixels' "
                    "scatter and from their sigma planes) and the pixels counted and masked "
                    "(the result's mask, NaN). A pixel belongs to the ROI when its centre "
                    "(u + 0.5, v + 0.5) does. --profile samples quantities along a segment "
                    "(bilinear, every --spacing pixels).")
    p.add_argument("source", type=pathlib.Path, metavar="RESULT_OR_SESSION",
                   help="a Mueller result EXR, a Stokes EXR, or a session folder (holds "
                        "session.json)")
    p.add_argument("--roi", default=None, metavar="SHAPE",
                   help="rect:x,y,w,h | ellipse:cx,cy,rx,ry | poly:x1,y1,x2,y2,... in image "
                        "pixels (default: the whole image)")
    p.add_argument("--profile", default=None, metavar="x0,y0,x1,y1",
                   help="also a line profile along this segment (image pixels)")
    p.add_argument("--spacing", type=positive_float, default=1.0, metavar="PX",
                   help="profile sample spacing in pixels of arc length (default 1)")
    p.add_argument("--sigma", choices=SIGMA_SOURCES, default="sigma",
                   help="per-element standard deviations to propagate (default sigma: noise "
                        "and calibration; sigma_noise: sensor noise alone; none)")
    p.add_argument("--csv", type=pathlib.Path, default=None, metavar="OUT.csv",
                   help="write the statistics as CSV (the profile, if any, to OUT_profile.csv); "
                        "without it a table is printed")
    p.set_defaults(func=run)


def _sources(src: pathlib.Path) -> list[tuple[str, pathlib.Path]]:
    if src.is_dir():
        from polrig.app.session import Session

        session = Session.open(src)  # a reader: no lock
        out = [(cap["name"], session.root / cap["files"]["mueller"]["path"])
               for cap in session.captures if cap.get("files", {}).get("mueller")]
        if not out:
            raise ConfigError(f"{src}: no capture has a Mueller result yet")
        return out
    if src.suffix.lower() != ".exr":
        raise ConfigError(f"{src}: give a Mueller result or Stokes .exr, or a session folder")
    return [("", src)]


def load_result(path: pathlib.Path, sigma_source: str = "sigma"):
    """``(mueller, sigma or None, valid)`` of a result EXR: ``valid`` ``(C, H, W)`` is the
    ``mask`` planes' 0 (all True without them)."""
    from polrig.formats.exr import read_mueller_exr

    return _result_arrays(read_mueller_exr(path), sigma_source)


def _result_arrays(res, sigma_source: str):
    """:func:`load_result` of a Mueller EXR already read (:class:`polrig.formats.exr.MuellerExr`)."""
    import numpy as np

    from polrig.formats.exr import channel_suffixes, element_stack

    c = res.mueller.shape[0]
    sigma = None if sigma_source == "none" else element_stack(sigma_source, res.extra, c)
    masks = [res.extra.get(f"mask.{s}") for s in channel_suffixes(c)]
    valid = (np.stack(masks) == 0 if all(m is not None for m in masks)
             else np.ones((c,) + res.mueller.shape[-2:], bool))
    return res.mueller, sigma, valid


def load_source(path: pathlib.Path, sigma_source: str = "sigma") -> dict:
    """The keyword arguments of :func:`polrig.app.roi.roi_statistics` and
    :func:`polrig.app.roi.profile_of` for a Mueller result EXR (``mueller``, ``sigma``,
    ``valid``: :func:`load_result`) or a Stokes EXR (``stokes``, ``valid``, ``snr``:
    :func:`polrig.app.preview.stokes_exr_masks`); :class:`polrig.errors.FormatError` for any
    other EXR."""
    from polrig.errors import FormatError
    from polrig.formats.exr import mueller_exr, read_exr, stokes_exr

    whole = read_exr(path)  # read once: its channels say which kind it is
    if any(k.startswith("M00.") for k in whole.planes):
        mueller, sigma, valid = _result_arrays(mueller_exr(whole), sigma_source)
        return {"mueller": mueller, "sigma": sigma, "valid": valid}
    if any(k.startswith("S0.") for k in whole.planes):
        from polrig.app.preview import stokes_exr_masks

        img = stokes_exr(whole)
        stokes, valid, _flags, snr = stokes_exr_masks(img.stokes, img.extra)
        return {"stokes": stokes, "valid": valid, "snr": snr}
    raise FormatError(f"{path}: neither a Mueller result (M00.*) nor a Stokes EXR (S0.*)")


def run(args: argparse.Namespace) -> int:
    from polrig.app import roi

    shape = roi.parse_roi(args.roi) if args.roi else None
    segment = roi.parse_segment(args.profile) if args.profile else None
    profile_out = None
    if args.csv is not None:
        if args.csv.suffix.lower() != ".csv":
            raise ConfigError(f"--csv must name a .csv file, got {args.csv}")
        check_output_file(args.csv, "--csv")
        if segment is not None:
            profile_out = args.csv.with_name(args.csv.stem + "_profile.csv")
            check_output_file(profile_out, "--csv profile")
    sources = _sources(args.source)
    if args.csv is not None:
        from polrig.formats.outputs import check_not_input

        outputs = [("--csv", args.csv)] + ([("--csv profile", profile_out)] if profile_out else [])
        inputs = [path for _, path in sources]
        if args.source.is_dir():
            inputs.append(args.source / "session.json")
        check_not_input(outputs, inputs)
    stats_parts, profile_parts = [], []
    for label, path in sources:
        data = load_source(path, args.sigma)
        h, w = (data["mueller"] if "mueller" in data else data["stokes"]).shape[-2:]
        region = shape or roi.RectROI(0, 0, w, h)
        inside = roi.roi_mask(region, (h, w))
        if not inside.any():  # statistics of no pixel would be NaN without a word
            raise ConfigError(f"--roi {region.text()}: no pixel centre of the {w}x{h} image of {path} lies in it "
                              f"(pixel (u, v) has its centre at (u + 0.5, v + 0.5))")
        rows = roi.roi_statistics(inside, **data)
        header = {"source": str(path), "roi": region.text(), "image": f"{w}x{h}",
                  "sigma": _sigma_text(data, args.sigma),
                  "pixel_convention": "pixel (u, v) has its centre at (u + 0.5, v + 0.5)"}
        if label:
            header["capture"] = label
        stats_parts.append((header, rows))
        if segment is not None:
            prof = roi.profile_of(segment, spacing=args.spacing, **data)
            if not any(0 <= x <= w and 0 <= y <= h for x, y in zip(prof.x.tolist(), prof.y.tolist())):
                raise ConfigError(f"--profile {','.join(f'{v:g}' for v in segment)}: the line does not cross "
                                  f"the {w}x{h} image of {path}")
            profile_parts.append((header, prof))
    if args.csv is None:
        for header, rows in stats_parts:
            print(_table(header, rows))
        for header, prof in profile_parts:
            print(f"profile {args.profile} ({prof.s.size} samples every {args.spacing:g} px) of "
                  f"{header.get('capture') or header['source']}: use --csv for the values")
        return 0
    from polrig.formats.outputs import OutputSet

    profile_header = {"profile": args.profile, "spacing_px": f"{args.spacing:g}"}
    with OutputSet() as files:  # the statistics and the profile: all or none
        _write_csv(files.temporary(args.csv), args.source, stats_parts, roi.stats_csv, {})
        if profile_out is not None:
            _write_csv(files.temporary(profile_out), args.source, profile_parts, roi.profile_csv,
                       profile_header)
    written = [str(p) for p in files.finals]
    n = sum(len(rows) for _, rows in stats_parts)
    print(f"wrote {', '.join(written)} ({n} rows, {len(stats_parts)} result(s))")
    return 0


def _sigma_text(data: dict, requested: str) -> str:
    """What the standard errors of ``data`` (:func:`load_source`) come from, for the header."""
    if "stokes" in data:
        return ("snr planes" if data["snr"] is not None
                else "none (a Stokes EXR without snr planes)")
    if data["sigma"] is not None:
        return requested
    return "none" if requested == "none" else f"none (no {requested}.M{{rc}} planes)"


def _write_csv(path: pathlib.Path, source: pathlib.Path, parts: list, to_csv,
               extra: dict) -> None:
    """Write ``parts`` (``(header, rows or profile)`` per result) as one CSV table with
    ``to_csv`` (:func:`polrig.app.roi.stats_csv` or :func:`~polrig.app.roi.profile_csv`): one
    result's alone under its header's comment lines, a session's by capture (a ``capture``
    column) under the session's, each capture's own in a ``# capture NAME:`` line."""
    from polrig.atomic import atomic_write_text

    if len(parts) == 1 and "capture" not in parts[0][0]:
        header, data = parts[0]
        atomic_write_text(path, to_csv(data, {**header, **extra}))
        return
    first = parts[0][0]
    header = {"source": str(source), "roi": first["roi"], "sigma": first["sigma"], **extra,
              "pixel_convention": first["pixel_convention"]}
    for key, mixed in (("roi", "each capture's whole image"), ("sigma", "per capture, below")):
        if any(h[key] != first[key] for h, _ in parts):  # e.g. captures of two sizes
            header[key] = mixed
    for h, _ in parts:
        header[f"capture {h['capture']}"] = (f"source {h['source']}, image {h['image']}, "
                                             f"sigma {h['sigma']}")
    atomic_write_text(path, to_csv({h["capture"]: d for h, d in parts}, header))


def _num(v: float) -> str:
    return f"{v:.6g}" if math.isfinite(v) else str(v)


def _table(header: dict, rows) -> str:
    title = (f"{header.get('capture') or header['source']}: {header['roi']} "
             f"(image {header['image']}, sigma {header['sigma']})")
    columns = (f"{'quantity':<22}{'ch':<3}{'mean':>12}{'std':>12}{'sem_scatter':>13}"
               f"{'sem_sigma':>12}{'counted':>9}{'masked':>8}")
    lines = [title, columns]
    for r in rows:
        lines.append(f"{r.quantity:<22}{r.channel:<3}{_num(r.mean):>12}{_num(r.std):>12}"
                     f"{_num(r.sem_scatter):>13}{_num(r.sem_sigma):>12}{r.n_counted:>9}"
                     f"{r.n_masked:>8}")
    return "\n".join(lines)
