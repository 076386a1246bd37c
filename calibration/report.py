"""Calibration report: ``report.md`` with every result, its uncertainty and (simulated rig) its
error against the hidden truth, plus PNG plots (residuals, per-pixel maps).

Per-pixel maps are written with OpenCV; residual plots with matplotlib (a dependency of
polrig, Agg backend: no display needed).
"""

from __future__ import annotations

import json
import pathlib
from typing import Any

import cv2
import numpy as np

from polrig.calibration.calset import CalibrationSet, _jsonable
from polrig.sensor.analyzer import AnalyzerModel


def map_png(path: pathlib.Path, values: np.ndarray, lo: float, hi: float) -> None:
    """A per-pixel map as a colour PNG (viridis, ``lo``..``hi``), nearest-upscaled to >= 256
    pixels wide."""
    v = np.clip((np.nan_to_num(values, nan=lo) - lo) / max(hi - lo, 1e-12), 0, 1)
    img = cv2.applyColorMap((v * 255).astype(np.uint8), cv2.COLORMAP_VIRIDIS)
    scale = max(1, int(np.ceil(256 / img.shape[1])))
    if scale > 1:
        img = cv2.resize(img, None, fx=scale, fy=scale, interpolation=cv2.INTER_NEAREST)
    cv2.imwrite(str(path), img)


def _plots(out: pathlib.Path, extras: dict[str, Any]) -> list[str]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    lines = []
    jr = extras.get("turntable")
    if jr is not None and len(jr.residuals_px):
        fig, ax = plt.subplots(figsize=(4, 4))
        ax.scatter(jr.residuals_px[:, 0], jr.residuals_px[:, 1], s=2)
        ax.set_xlabel("u residual (px)")
        ax.set_ylabel("v residual (px)")
        ax.set_title(f"board corner residuals, RMS {jr.rms_px:.3f} px")
        ax.set_aspect("equal")
        fig.tight_layout()
        fig.savefig(out / "geometry_residuals.png", dpi=100)
        plt.close(fig)
        lines.append("![board corner reprojection residuals](geometry_residuals.png)")
    lf = extras.get("light")
    if lf is not None:
        fig, ax = plt.subplots(figsize=(5, 3))
        ax.bar(np.arange(len(lf.ray_distances_m)), lf.ray_distances_m * 1000)
        ax.set_xlabel("sphere view")
        ax.set_ylabel("ray miss distance (mm)")
        fig.tight_layout()
        fig.savefig(out / "light_rays.png", dpi=100)
        plt.close(fig)
        lines.append("![distance of the fitted light from each reflected ray](light_rays.png)")
    off = extras.get("stokes")
    if off is not None:
        fig, ax = plt.subplots(figsize=(5, 3))
        ax.hist(off.per_pixel_deg, bins=60)
        ax.set_xlabel("per-pixel zero offset (deg)")
        fig.tight_layout()
        fig.savefig(out / "offset_histogram.png", dpi=100)
        plt.close(fig)
        lines.append("![per-pixel generator zero offsets](offset_histogram.png)")
    return lines


def write_report(directory: str | pathlib.Path, cs: CalibrationSet,
                 extras: dict[str, Any] | None = None,
                 errors: dict[str, Any] | None = None) -> pathlib.Path:
    """Write ``report.md`` and the PNGs into ``directory``; returns the report path."""
    out = pathlib.Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    extras = extras or {}
    md = [f"# Rig calibration report\n", f"Calibration set id: `{cs.id}`\n",
          "Units and frames: camera frame (OpenCV), metres, degrees "
          "(`docs/conventions.md`, `docs/calibration.md`). Uncertainties are 1 sigma.\n"]
    p = cs.params
    if "intrinsics" in p:
        i = p["intrinsics"]
        K = np.asarray(i["K"])
        s = i.get("std_fx_fy_cx_cy_px", [np.nan] * 4)
        md += ["## Camera intrinsics\n", f"method: {i.get('method', '')}\n",
               "| parameter | value | 1 sigma |", "|---|---|---|",
               f"| fx (px) | {K[0, 0]:.3f} | {s[0]:.3f} |", f"| fy (px) | {K[1, 1]:.3f} | {s[1]:.3f} |",
               f"| cx (px) | {K[0, 2]:.3f} | {s[2]:.3f} |", f"| cy (px) | {K[1, 2]:.3f} | {s[3]:.3f} |",
               f"| distortion | {np.round(i['dist'], 5).tolist()} | |",
               f"| reprojection RMS (px) | {i.get('rms_px', float('nan')):.3f} | |", ""]
    if "turntable" in p:
        t = p["turntable"]
        md += ["## Turntable axis\n", f"- axis (camera frame): {np.round(t['axis_cam'], 6).tolist()} "
               f"± {t['axis_std_deg']:.3f} deg",
               f"- point on the axis (m): {np.round(t['point_cam_m'], 5).tolist()} "
               f"± {np.round(t['point_std_m'], 5).tolist()}", ""]
    if "light" in p:
        L = p["light"]
        md += ["## Light position\n", f"- position (camera frame, m): "
               f"{np.round(L['position_cam_m'], 5).tolist()} ± {np.round(L['std_m'], 5).tolist()}",
               f"- reflected rays: {len(L['ray_distances_m'])}, miss distances (mm): "
               f"{np.round(np.asarray(L['ray_distances_m']) * 1000, 2).tolist()}"]
        a = L.get("acceptance")
        if isinstance(a, dict):
            md.append(f"- acceptance ({100 * a['limit_rel']:g} % of the "
                      f"{a['distance_m']:.3f} m from the light to the sphere positions): "
                      f"{'assured' if a['assured'] else '**not assured**'} by the uncertainty "
                      f"(2 sigma along its least certain direction: "
                      f"{1000 * a['two_sigma_m']:.1f} mm, {100 * a['two_sigma_rel']:.2f} %)")
        if "sphere_metal" in L:
            md.append(f"- mirror ball: {L['sphere_metal']['name']} (its colour divides the "
                      f"highlight's colour classes)")
        md.append("")
    if "generator" in p:
        g = p["generator"]
        md += ["## Generator (incident Stokes states)\n",
               f"- zero offset: {g['zero_offset_deg']:.4f} ± {g['zero_offset_std_deg']:.4f} deg "
               f"(stage zero axis, camera frame: {np.round(g['stage_zero_axis_cam'], 6).tolist()})",
               f"- extinction ratio: {g['extinction_ratio']:.1f} ± "
               f"{g.get('extinction_ratio_std', float('nan')):.1f} "
               f"({g.get('extinction_ratio_reference', 'not yet calibrated: run dofp')})", ""]
    if cs.analyzer is not None:
        a = cs.analyzer
        nominal = AnalyzerModel.ideal(a.layout, a.shape)
        v = cs.dofp_maps.get("valid", np.ones(a.shape, bool)).astype(bool)
        dang = a.angle_deg - nominal.angle_deg
        map_png(out / "dofp_angle_error.png", dang, -1.5, 1.5)
        map_png(out / "dofp_gain.png", a.gain, 0.97, 1.03)
        map_png(out / "dofp_diattenuation.png", a.diattenuation, 0.97, 1.0)
        if "angle_std_deg" in cs.dofp_maps:
            map_png(out / "dofp_angle_std.png", cs.dofp_maps["angle_std_deg"], 0, 0.3)
        d = p.get("dofp", {})
        md += ["## DoFP analyzer\n",
               f"- layout {a.layout}, {a.shape[1]}x{a.shape[0]} pixels, valid fraction "
               f"{d.get('valid_fraction', float('nan')):.4f}",
               f"- orientation minus nominal: mean {dang[v].mean():.3f} deg, std {dang[v].std():.3f} deg; "
               f"median 1-sigma {d.get('angle_std_deg_median', float('nan')):.3f} deg",
               f"- gain: std {a.gain[v].std():.4f}; diattenuation: mean {a.diattenuation[v].mean():.4f}, "
               f"std {a.diattenuation[v].std():.4f}",
               *([f"- plate modelled as {d['mirror']['name']} (diattenuation and retardance of "
                  f"its Fresnel reflection) at {d.get('mirror_incidence_deg', float('nan')):.1f} "
                  f"deg incidence"] if "mirror" in d else []),
               "", "Maps (viridis): orientation minus nominal (-1.5..1.5 deg) ![](dofp_angle_error.png), "
               "gain (0.97..1.03) ![](dofp_gain.png), diattenuation (0.97..1) "
               "![](dofp_diattenuation.png), orientation 1 sigma (0..0.3 deg) ![](dofp_angle_std.png)", ""]
    plots = _plots(out, extras)
    if plots:
        md += ["## Residual plots\n"] + plots + [""]
    if errors:
        md += ["## Errors against the simulated rig's hidden truth\n", "```json",
               json.dumps(_jsonable(errors), indent=2), "```", ""]
    path = out / "report.md"
    path.write_text("\n".join(md))
    return path
