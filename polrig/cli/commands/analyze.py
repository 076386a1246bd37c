"""``polrig analyze RESULT.exr|SESSION [--out FILE|DIR]``: parameter maps of Mueller results,
each with its propagated sigma, as named EXR planes.

Maps, definitions and the propagation: :mod:`polrig.optics.parameters` and
``docs/analysis.md``. A session (a folder with ``session.json``) is read through
:class:`polrig.app.session.Session` (read only, no lock): one maps file per capture that has a
Mueller result, next to it (``mueller_maps.exr`` beside ``mueller.exr``; not recorded in the
manifest: a derived file, replaced when analyzed again) or in ``--out DIR`` as
``<capture>_maps.exr``. A maps file that would be the result it is computed from (or, of a
session, any of its results or its manifest) is refused before any work
(:func:`polrig.formats.outputs.check_not_input`). With ``--normals``, pixels outside the
result's mask (the pixels the decomposition counts) have NaN normals and are not counted.
"""

from __future__ import annotations

import argparse
import pathlib
import sys
from typing import TYPE_CHECKING, Any

from polrig.choices import SIGMA_SOURCES
from polrig.errors import ConfigError, FormatError, PolrigError
from polrig.formats.argcheck import (check_output_file, check_output_folder, finite_float,
                                     nonnegative_float, positive_float)

if TYPE_CHECKING:
    import numpy as np


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "analyze", help="parameter maps (diattenuation, retardance, ...) of Mueller results",
        description="Compute parameter maps of a Mueller result EXR or of every capture of a "
                    "session: m00; linear diattenuation and polarizance with their axes; the "
                    "signed singular values of the lower 2x2 block (invariants of independent "
                    "frame rotations); the MMT parameters b, t1, A, x; the 3x3 polar "
                    "decomposition (linear retardance, its axis modulo 90 deg, depolarization, "
                    "rotation), which assumes isotropic linear depolarization (docs/analysis.md) "
                    "and flags per pixel where that assumption decides the answer. Each map "
                    "has its standard deviation, propagated to first order from the result's "
                    "sigma planes. Output: an EXR with planes NAME.{R,G,B|Y}, sigma.NAME.{...}, "
                    "decomposition_flags.{...} and the result's mask.{...}.")
    p.add_argument("source", type=pathlib.Path, metavar="RESULT_OR_SESSION",
                   help="a Mueller result EXR, or a session folder (holds session.json)")
    p.add_argument("--out", type=pathlib.Path, default=None, metavar="FILE_OR_DIR",
                   help="output EXR for one result (default: RESULT_maps.exr beside it); for a "
                        "session a folder that receives CAPTURE_maps.exr per capture (default: "
                        "each capture's mueller_maps.exr beside its result)")
    p.add_argument("--sigma", choices=SIGMA_SOURCES, default="sigma",
                   help="per-element standard deviations to propagate: sigma (noise and "
                        "calibration uncertainty, default), sigma_noise (sensor noise alone) "
                        "or none (maps only)")
    p.add_argument("--k", type=nonnegative_float, default=3.0, metavar="K",
                   help="decomposition_flags bit 2 (linearly anisotropic: retardance or "
                        "anisotropic depolarization, the block cannot tell) where the "
                        "anisotropy exceeds K of its sigmas (default 3: 1.1%% of isotropic "
                        "pixels by chance)")
    g = p.add_argument_group(
        "shape from polarization",
        "surface normals from the linear polarizance (the DoLP and AoLP unpolarized light "
        "leaves): zenith from the DoLP for --ior, azimuth from the AoLP, in the camera frame; "
        "every candidate the ambiguities allow is written (diffuse: azimuth or azimuth + 180 "
        "deg; specular: also below or above Brewster's angle). polrig.optics.shape_from_polarization")
    g.add_argument("--normals", action="store_true",
                   help="also write the normal planes sfp_normal{K}.{X,Y,Z}.{ch}, "
                        "sfp_zenith_deg{Z}.{ch}, sfp_azimuth_deg.{ch}")
    g.add_argument("--ior", type=positive_float, default=None, metavar="N",
                   help="refractive index of the surface (> 1; required with --normals), e.g. 1.5")
    g.add_argument("--reflection", choices=("diffuse", "specular"), default="diffuse",
                   help="reflection model (default diffuse: a matte dielectric)")
    g.add_argument("--intrinsics", type=intrinsics, default=None, metavar="FX,FY,CX,CY",
                   help="pinhole intrinsics of the result's pixel grid (pixels) for per-pixel "
                        "viewing directions (default: orthographic view along the optical axis)")
    p.set_defaults(func=run)


def intrinsics(text: str) -> tuple[float, float, float, float]:
    """An argparse type: ``FX,FY,CX,CY``, finite, focal lengths > 0."""
    parts = text.split(",")
    if len(parts) != 4:
        raise argparse.ArgumentTypeError(f"expected FX,FY,CX,CY, got {text!r}")
    fx, fy = positive_float(parts[0]), positive_float(parts[1])
    return (fx, fy, finite_float(parts[2]), finite_float(parts[3]))


def _sfp(args: argparse.Namespace) -> dict | None:
    """The shape-from-polarization request of the options, checked (``None``: not asked)."""
    if not args.normals:
        if args.ior is not None or args.intrinsics is not None:
            raise ConfigError("--ior and --intrinsics need --normals")
        return None
    if args.ior is None:
        raise ConfigError("--normals needs --ior N, the surface's refractive index (e.g. 1.5)")
    if not args.ior > 1:
        raise ConfigError(f"--ior must be > 1, got {args.ior:g}")
    return {"ior": args.ior, "reflection": args.reflection, "intrinsics": args.intrinsics}


def run(args: argparse.Namespace) -> int:
    from polrig.formats.outputs import check_not_input

    src: pathlib.Path = args.source
    if src.is_dir():
        return _run_session(args, src)
    if src.suffix.lower() != ".exr":
        raise ConfigError(f"{src}: give a Mueller result .exr or a session folder")
    out = args.out if args.out is not None else src.with_name(src.stem + "_maps.exr")
    if out.suffix.lower() != ".exr":
        raise ConfigError(f"--out must name an .exr file, got {out}")
    check_output_file(out)
    check_not_input([("--out", out)], [src])
    print(analyze_file(src, out, args.sigma, args.k, _sfp(args)))
    return 0


def _run_session(args: argparse.Namespace, root: pathlib.Path) -> int:
    from polrig.app.session import Session
    from polrig.formats.outputs import check_not_input

    if args.out is not None:
        check_output_folder(args.out)
    sfp = _sfp(args)
    session = Session.open(root)  # a reader: no lock
    jobs = []
    for cap in session.captures:
        rec = cap.get("files", {}).get("mueller")
        if not rec:
            continue
        result = session.root / rec["path"]
        if args.out is not None:
            out = args.out / f"{cap['name']}_maps.exr"
        else:
            out = result.with_name(result.stem + "_maps.exr")
        jobs.append((cap["name"], result, out))
    if not jobs:
        raise ConfigError(f"{root}: no capture has a Mueller result yet")
    inputs = [session.root / "session.json"] + [result for _, result, _ in jobs]
    check_not_input([("--out" if args.out is not None else "maps file", out)
                     for _, _, out in jobs], inputs)
    if args.out is not None:
        args.out.mkdir(parents=True, exist_ok=True)
    failed = []
    for name, result, out in jobs:  # a damaged result fails alone; the others are analysed
        try:
            print(f"{name}: {analyze_file(result, out, args.sigma, args.k, sfp)}")
        except FormatError as exc:
            failed.append(name)
            print(f"{name}: failed ({exc})")
    if failed:  # as reconstruct with damaged captures: a failure while running (exit 1)
        raise PolrigError(f"{root}: {len(failed)} of {len(jobs)} capture(s) could not be analysed "
                          f"({', '.join(failed)}); the others' maps are written")
    return 0


def analyze_file(src: pathlib.Path, out: pathlib.Path, sigma_source: str = "sigma",
                 k: float = 3.0, sfp: dict | None = None) -> str:
    """Write the maps EXR of one Mueller result (with the shape-from-polarization normals of
    ``sfp``, ``{"ior", "reflection", "intrinsics"}``, where given); return the summary line."""
    import numpy as np

    from polrig.formats.exr import channel_suffixes, colour_planes, read_mueller_exr, write_exr
    from polrig.optics import parameters as pa

    res = read_mueller_exr(src)
    c = res.mueller.shape[0]
    sfx = channel_suffixes(c)
    sigma, note = _element_sigma(res.extra, sfx, sigma_source)
    maps = pa.image_maps(res.mueller, sigma, k=k)
    planes: dict[str, np.ndarray] = {}
    for name in pa.MAPS:
        planes.update(colour_planes(name, maps.values[name]))
    for name in maps.sigma:
        planes.update(colour_planes(f"sigma.{name}", maps.sigma[name]))
    planes.update(colour_planes("decomposition_flags", maps.flags))
    for s in sfx:
        if f"mask.{s}" in res.extra:
            planes[f"mask.{s}"] = res.extra[f"mask.{s}"]
    described = {f"{n}.{{ch}}": d for n, d in pa.MAPS.items()}
    if maps.sigma:
        described["sigma.{name}.{ch}"] = ("standard deviation of map {name} (" + pa.SIGMA_METHOD
                                          + f"; from the result's {sigma_source}.M{{rc}} planes)")
    described["decomposition_flags.{ch}"] = "bits: " + "; ".join(
        f"{b} = {t}" for b, t in pa.DECOMPOSITION_FLAGS.items()) + "; 0 = decomposed, isotropic block"
    if any(k.startswith("mask.") for k in planes):
        described["mask.{ch}"] = "the result's mask plane, copied (reason bits, 0 = valid)"
    # valid: the result's mask 0 (every pixel without mask planes), for the counts and normals
    valid = np.ones(maps.flags.shape, bool)
    masks = [res.extra.get(f"mask.{s}") for s in sfx]
    if all(m is not None for m in masks):
        valid = np.stack(masks) == 0
    normals_line = ""
    if sfp is not None:
        normals_line = _normal_planes(res.mueller, sfp, planes, described, valid)
    metadata: dict[str, Any] = {
        "source": str(src), "planes": described,
        "decomposition_assumption": pa.DECOMPOSITION_ASSUMPTION,
        "decomposition_flag_bits": {str(b): t for b, t in pa.DECOMPOSITION_FLAGS.items()},
        "assumed_k": k,
        "sigma_source": sigma_source if maps.sigma else None,
        "sigma_method": pa.SIGMA_METHOD if maps.sigma else None,
        "source_units": res.metadata.get("units"),
    }
    for key in ("capture", "pose_deg", "exposure_us", "mode", "calibration_id", "revision"):
        if key in res.metadata:
            metadata[key] = res.metadata[key]
    if sfp is not None:
        metadata["shape_from_polarization"] = {
            "ior": sfp["ior"], "reflection": sfp["reflection"],
            "intrinsics": list(sfp["intrinsics"]) if sfp["intrinsics"] else None,
            "view": "per pixel, pinhole" if sfp["intrinsics"] else "orthographic (0, 0, -1)",
            "frame": "camera (OpenCV: X right, Y down, Z forward); normals point to the camera",
            "reference": "Atkinson and Hancock, IEEE TIP 15(6):1653, 2006 (rho_d, rho_s)"}
    write_exr(out, planes, kind="parameter_maps", metadata=metadata)
    flags = maps.flags
    n = int(valid.sum())
    assumed = int(np.count_nonzero(((flags & pa.DECOMP_ASSUMED) != 0) & valid))
    undefined = int(np.count_nonzero(((flags & pa.DECOMP_UNDEFINED) != 0) & valid))
    h, w = res.mueller.shape[-2:]
    line = (f"wrote {out} ({w}x{h}, {c} colour plane(s), {len(pa.MAPS)} maps"
            f"{' with sigma' if maps.sigma else ''}); decomposition of {n} valid pixel-colour(s): "
            f"{undefined} undefined, {assumed} linearly anisotropic (retardance or anisotropic "
            f"depolarization, shown under the isotropic-depolarization assumption){normals_line}")
    if note:
        print(f"polrig analyze: note: {src}: {note}", file=sys.stderr)
    return line


def _normal_planes(mueller: np.ndarray, sfp: dict, planes: dict[str, np.ndarray],
                   described: dict[str, str], valid: np.ndarray) -> str:
    """Add the shape-from-polarization planes of ``mueller`` ``(C, 3, 3, H, W)`` to ``planes``
    and their descriptions to ``described``; return the summary's addition. Pixel-colours
    outside ``valid`` ``(C, H, W)`` (the result's mask, as for the decomposition's counts) get
    NaN normals, zeniths and azimuths and are not counted."""
    import numpy as np

    from polrig.formats.exr import colour_planes
    from polrig.optics import shape_from_polarization as sp

    h, w = mueller.shape[-2:]
    view = sp.view_directions(sfp["intrinsics"], (h, w)) if sfp["intrinsics"] else None
    got = sp.normals_from_mueller(mueller, sfp["ior"], sfp["reflection"], view)
    masked = lambda a: np.where(valid, a, np.nan).astype(np.float32)  # noqa: E731
    for kk, normal in enumerate(got.normals):
        for axis, plane in zip("XYZ", normal):
            planes.update(colour_planes(f"sfp_normal{kk}.{axis}", masked(plane)))
    zeniths = [masked(z) for z in got.zenith_deg]
    for z, zenith in enumerate(zeniths):
        planes.update(colour_planes(f"sfp_zenith_deg{z}", zenith))
    planes.update(colour_planes("sfp_azimuth_deg", masked(got.azimuth_deg)))
    n = f"n = {sfp['ior']:g}"
    if got.reflection == "diffuse":
        described["sfp_normal{k}.{X,Y,Z}.{ch}"] = (
            f"unit normal, camera frame, diffuse reflection, {n}: k = 0 azimuth = AoLP, k = 1 "
            "azimuth + 180 deg (the pi ambiguity); NaN where the DoLP exceeds the grazing value")
        described["sfp_zenith_deg0.{ch}"] = f"zenith from the diffuse DoLP, {n} (unique)"
    else:
        described["sfp_normal{k}.{X,Y,Z}.{ch}"] = (
            f"unit normal, camera frame, specular reflection, {n}: k = 0, 1 zenith below "
            "Brewster's angle with azimuth = AoLP + 90 deg, + 270 deg; k = 2, 3 above it")
        described["sfp_zenith_deg{z}.{ch}"] = f"the two zeniths of the specular DoLP, {n}: 0 below, 1 above Brewster's angle"
    described["sfp_azimuth_deg.{ch}"] = "image azimuth of sfp_normal0, [0, 180) deg from image right towards up"
    for key in [k for k in described if k.startswith("sfp_")]:
        described[key] += "; NaN where the result's mask is set"
    found = int(np.count_nonzero(np.isfinite(zeniths[0])))
    return (f"; {got.reflection} shape-from-polarization normals ({n}, {len(got.normals)} "
            f"candidates) at {found} pixel-colour(s)")


def _element_sigma(extra: dict[str, np.ndarray], sfx: tuple[str, ...], source: str
                   ) -> tuple[np.ndarray | None, str | None]:
    """``(C, 3, 3, H, W)`` per-element sigma from the ``{source}.M{rc}.{ch}`` planes, or None
    (with a note when the file lacks them)."""
    import numpy as np

    from polrig.formats.exr import element_stack

    if source == "none":
        return None, None
    sig = element_stack(source, extra, len(sfx))
    if sig is None:
        return None, f"no {source}.M{{rc}} planes: maps written without sigma"
    if not np.isfinite(sig).any():
        return sig, f"the {source} planes hold no finite value: sigma maps are NaN or infinite"
    return sig, None
