"""Two-state hybrid captures with the diffuse term tested on the samples alone
(``polrig capture --mode hybrid --states 0,90 --models diffuse``; ``polrig reconstruct``
likewise).

Two polarizer states leave one direction of each row of the 3x3 block unobserved; the hybrid
solve (:mod:`polrig.solve.hybrid`) takes it from the single-shot network's prior. Where the
pixel is Baek et al.'s diffuse term, with their specular term where it is significant, the rig's
geometry predicts that direction instead (:mod:`polrig.solve.diffuse_geometry`), and whether the
pixel *is* that model is decided by a likelihood-ratio test on the two frames' samples alone,
with nothing of the network in the decision (:mod:`polrig.solve.diffuse_test`; on the held-out
sets +6.35..+10.13 dB over single-shot where a model holds; false acceptance where the samples
can tell, the test's Monte Carlo power at least 0.95, 0.0-0.7 % on the sets where such pixels are
more than 1 % of the scored ones and 1.4 % pooled over the Baek sets,
``benchmarks/results/continuum_models.md``). This module gives that route what a capture knows:

* the geometry (:func:`capture_geometry`): each output pixel's view direction from the
  intrinsics carried to the analyzer grid
  (:func:`polrig.app.single_shot.analyzer_grid_intrinsics`), two candidate light fields from the
  calibrated light position and the object's centre (the light seen from the surface at the
  object's distance along each pixel's ray, :func:`polrig.solve.diffuse_geometry.light_directions`,
  and the one direction from the object's centre; the test picks one per image), the polarizer
  stage's zero axis, and the network's surface normals as the completion's first guess;
* the run (:func:`solve_diffuse`): the two states' analyzer samples over the whole image (the
  index and the light are chosen per image; the completion's second pass looks at each pixel's
  neighbours), tested on the network's object pixels;
* the record (:func:`diffuse_header`, :func:`diffuse_planes`, :data:`DIFFUSE_PLANES`): the model
  map (``model.{colour}``: ``rank_one`` where accepted, ``full`` where tested and not,
  ``untested`` elsewhere) with the test's statistic and p-value and the specular albedo
  (``specular.{colour}``), always written; the header's ``model_selection`` (the test, its
  level and degrees of freedom, the counts) and ``diffuse_test`` (the index and light chosen,
  the pixels completed, where the geometry came from).

Off by default, never applied silently: the map is always written (as ``--models auto``).
Shapes: images ``(C, 3, 3, H, W)`` on the output grid, directions ``(H, W, 3)`` in the camera
frame (OpenCV: X right, Y down, Z forward; ``docs/conventions.md``).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from polrig.acquisition.plan import PlanError
from polrig.app.single_shot import analyzer_grid_intrinsics
from polrig.sensor.frame import Frame
from polrig.sensor.layouts import MosaicLayout
from polrig.solve.diffuse_geometry import DiffuseGeometry, light_directions
from polrig.solve.diffuse_test import SPECULAR_LEVEL, DiffuseTest, complete_tested_diffuse, degrees_of_freedom
from polrig.solve.model_selection import UNTESTED, ModelMaps, SelectionOptions, selection_header
from polrig.solve.radiometry import StateRadiance, analyzer_stack
from polrig.solve.reference import ReferenceResult

__all__ = ["LIGHTS", "DIFFUSE_PLANES", "GEOMETRY_NEEDED", "check_diffuse_states", "missing_geometry",
           "check_geometry", "view_directions", "network_normals", "capture_geometry", "solve_diffuse",
           "diffuse_planes", "diffuse_header"]

#: The candidate light fields, in the order :func:`capture_geometry` gives them.
LIGHTS = ("at the object's distance along each pixel's ray", "from the object's centre")
#: The geometry the route needs (:func:`polrig.app.calibrations.single_shot_geometry`'s keys).
GEOMETRY_NEEDED = ("intrinsics", "stage_zero_axis_camera", "light_position_camera_m", "object_point_camera_m")
#: What the model planes hold on this route (the header's ``planes``).
DIFFUSE_PLANES = {
    "model": "model per pixel: 6 rank_one (Baek's diffuse term, plus the specular term of "
             "specular.{colour} where that is not 0, accepted by the diffuse test and its open "
             "direction predicted from the geometry), 0 full (tested, not accepted), 255 untested "
             "(codes in model_selection.codes)",
    "model_chi2": "the diffuse test's likelihood-ratio statistic on the two states' samples alone "
                  "(the same in every colour; chi^2 with model_selection.df degrees of freedom where "
                  "the diffuse term holds, model_selection.df_specular where the specular term was "
                  "taken)",
    "model_p": "its p-value",
    "specular": "the specular albedo per pixel: the weight of Baek's specular block (its shape set by "
                "the light, the view and the refractive index; m00 = 1) that the diffuse test fitted "
                "and the completion took off before the rank-one estimate and put back after; 0 where "
                "the term is not significant, the pixel not accepted or not tested"}


def check_diffuse_states(mode: str, n_states: int | None) -> None:
    """The diffuse test's plan: the hybrid mode at exactly two polarizer states (``n_states``;
    None: not known yet, not checked); one-line :class:`PlanError` s of ``models``."""
    if mode != "hybrid":
        raise PlanError("models", f"the diffuse test completes the hybrid method at two polarizer "
                                  f"states, not the {mode} mode: use --mode hybrid --states A,B",
                        subject="diffuse", what="models")
    if n_states is not None and n_states != 2:
        raise PlanError("models", f"the diffuse test takes two polarizer states, the plan has "
                                  f"{n_states}: at three or more, use --models auto",
                        subject="diffuse", what="models")


def missing_geometry(geometry: Mapping[str, Any]) -> list[str]:
    """The keys of :data:`GEOMETRY_NEEDED` that ``geometry`` lacks (None)."""
    return [k for k in GEOMETRY_NEEDED if geometry.get(k) is None]


def check_geometry(geometry: Mapping[str, Any]) -> None:
    """A one-line :class:`PlanError` of ``models`` naming what is missing, and where to get it."""
    missing = missing_geometry(geometry)
    if missing:
        raise PlanError("models", f"the diffuse test needs the rig's geometry, and {', '.join(missing)} "
                                  f"is unknown: use a calibration set with the intrinsics, light and "
                                  f"turntable steps ('polrig calibrate all --out DIR'), or give it in "
                                  f"the rig configuration's [nominal_geometry] table",
                        subject="diffuse", what="models")


def view_directions(intrinsics: Sequence[float], shape: tuple[int, int]) -> np.ndarray:
    """Unit vectors surface -> camera ``(H, W, 3)`` of a grid of ``shape`` ``(H, W)`` with
    pinhole ``intrinsics`` ``(fx, fy, cx, cy)`` on that grid (pixel ``(u, v)`` centred at the
    integers): each pixel's ray ``((u - cx) / fx, (v - cy) / fy, 1)`` reversed."""
    fx, fy, cx, cy = (float(v) for v in intrinsics)
    v, u = np.mgrid[0:shape[0], 0:shape[1]].astype(np.float64)
    ray = np.stack([(u - cx) / fx, (v - cy) / fy, np.ones_like(u)], axis=-1)
    return -ray / np.linalg.norm(ray, axis=-1, keepdims=True)


def network_normals(normal: np.ndarray | None, grid: tuple[int, int]) -> np.ndarray | None:
    """The networks' unit normals ``(3, h, w)`` (camera frame, on their own superpixel grid) on
    the output grid ``grid`` ``(H, W)``, ``(H, W, 3)``: each network pixel's normal over the output
    pixels it covers (a full-resolution demosaic's grid is an integer multiple of it); None
    without normals (the device route keeps none) or on a grid that is no multiple of theirs."""
    if normal is None:
        return None
    h, w = normal.shape[-2:]
    fy, fx = grid[0] // h, grid[1] // w
    if (h * fy, w * fx) != tuple(grid):
        return None
    return np.repeat(np.repeat(np.moveaxis(np.asarray(normal, np.float64), 0, -1), fy, axis=0), fx, axis=1)


def capture_geometry(geometry: Mapping[str, Any], frame: Frame, grid_shape: tuple[int, int],
                     network_normal: np.ndarray | None = None) -> DiffuseGeometry:
    """What the rig knows of the output grid's geometry (module docstring).

    ``geometry``: :func:`polrig.app.calibrations.single_shot_geometry`'s (every key of
    :data:`GEOMETRY_NEEDED` known; :func:`check_geometry`); ``frame``: the capture's first raw
    frame (its readout offset and size carry the intrinsics to the grid); ``grid_shape``
    ``(H, W)``; ``network_normal``: the networks' normals ``(3, h, w)`` or None, the completion's
    first guess (:func:`network_normals`)."""
    check_geometry(geometry)
    intr = analyzer_grid_intrinsics(geometry["intrinsics"], frame.meta.offset_xy, frame.raw.shape, grid_shape)
    view = view_directions(intr, grid_shape)
    light = np.asarray(geometry["light_position_camera_m"], np.float64)
    centre = np.asarray(geometry["object_point_camera_m"], np.float64)
    from_centre = light - centre
    return DiffuseGeometry(view=view,
                           light=(light_directions(light, view, float(np.linalg.norm(centre))),
                                  from_centre / np.linalg.norm(from_centre)),
                           stage_zero_axis=np.asarray(geometry["stage_zero_axis_camera"], np.float64),
                           normal_guess=network_normals(network_normal, grid_shape))


def solve_diffuse(result: ReferenceResult, s_in: np.ndarray, states: Sequence[StateRadiance],
                  layout: MosaicLayout, method: str, analyzer, geometry: DiffuseGeometry, *,
                  prior: Mapping[str, Any], mask: np.ndarray, alpha: float = 0.05
                  ) -> tuple[ReferenceResult, DiffuseTest, np.ndarray]:
    """The two-state hybrid ``result`` with the diffuse term where the test accepts it.

    ``s_in`` ``(2, 3)``, ``states`` the two states' radiances, ``layout``, ``method`` and
    ``analyzer`` (the capture's, cropped to its readout, or None) as the hybrid solve had them;
    ``prior``: the hybrid solve's keywords (``prior_mean``, ``prior_sigma``, ``seen_state``,
    ``prior_correlation``); ``mask`` ``(H, W)``: the pixels to test (the network's object).
    Returns the result, its ``models`` the maps of this route (module docstring), the test and
    the completed colour-pixels ``(C, H, W)``."""
    samples = [analyzer_stack(st, layout, method, analyzer) for st in states]
    measured, variance, valid = (np.stack([s[i] for s in samples]) for i in range(3))
    rows = samples[0][3]
    out, test, completed = complete_tested_diffuse(
        result, s_in, measured, variance, valid, geometry,
        prior=(prior["prior_mean"], prior["prior_sigma"]), seen_state=int(prior["seen_state"]),
        prior_correlation=prior.get("prior_correlation"), alpha=alpha, mask=mask, analyzer_rows=rows,
        specular=True)
    maps = out.models
    code = np.where(test.tested[None], maps.code, np.uint8(UNTESTED)).astype(np.uint8)
    stat = np.broadcast_to(test.statistic.astype(np.float32), code.shape).copy()
    pval = np.broadcast_to(test.p_value.astype(np.float32), code.shape).copy()
    options = SelectionOptions(alpha=float(alpha), models=("rank_one",))
    return dataclasses.replace(out, models=ModelMaps(code, stat, pval, options)), test, completed


def diffuse_planes(test: DiffuseTest, colours: Sequence[str]) -> dict[str, np.ndarray]:
    """The route's planes besides the model map: ``specular.{colour}`` (:data:`DIFFUSE_PLANES`),
    float32, at the accepted pixels (0 elsewhere)."""
    albedo = np.zeros(test.albedo.shape) if test.specular_albedo is None else test.specular_albedo
    albedo = np.where(test.accepted[None], albedo, 0.0).astype(np.float32)
    return {f"specular.{col}": albedo[ci] for ci, col in enumerate(colours)}


def diffuse_header(test: DiffuseTest, completed: np.ndarray, maps: ModelMaps,
                   sources: Mapping[str, str]) -> dict[str, Any]:
    """The result header's ``model_selection`` (the test, its level, degrees of freedom, codes
    and counts) and ``diffuse_test`` (the refractive index and the light chosen for the image,
    pixels tested, accepted and completed, where the geometry came from) entries."""
    selection = selection_header(maps)["model_selection"]
    selection.update(test="the diffuse term (Baek et al. 2018, rank one, at the rig's geometry), with "
                          "Baek's specular term where it explains significantly more (chi^2(C), level "
                          f"{SPECULAR_LEVEL}), against the full 3x3 block on the two states' samples "
                          "alone, likelihood ratio, chi^2(5 C - 2), with the specular term chi^2(4 C - 2) "
                          "(polrig.solve.diffuse_test); the open direction of the accepted pixels "
                          "predicted from the geometry (polrig.solve.diffuse_geometry)",
                     df=int(test.df), df_specular=int(degrees_of_freedom(test.albedo.shape[0], True)))
    specular = 0 if test.specular_albedo is None else int(np.count_nonzero(
        (test.specular_albedo > 0) & test.accepted[None]))
    return {"model_selection": selection, "diffuse_test": {
        "refractive_index": test.eta, "light": None if test.light is None else LIGHTS[test.light],
        "pixels_tested": int(test.tested.sum()), "pixels_accepted": int(test.accepted.sum()),
        "colour_pixels_completed": int(np.count_nonzero(completed)),
        "colour_pixels_specular": specular,
        "geometry_sources": {k: str(sources.get(k, "")) for k in GEOMETRY_NEEDED}}}
