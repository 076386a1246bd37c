"""Small calibration sets for the tests (no procedure runs: instant)."""

from __future__ import annotations

import pathlib

import numpy as np

from polrig.calibration.calset import CalibrationSet
from polrig.sensor.analyzer import AnalyzerModel, layout_name_at


def set_calibrated_on(folder: pathlib.Path, size=(320, 240), layout: str = "imx250myr", *,
                      legacy: bool = False, readout=None, analyzer: AnalyzerModel | None = None
                      ) -> dict[str, bytes]:
    """Write a set (intrinsics, generator, analyzer) calibrated on a camera whose sensor is
    ``size`` ``(W, H)`` of ``layout``, read out at ``readout`` ``(w, h, x, y)`` (default: the
    whole sensor). ``legacy``: as written before the ``camera`` section existed (the
    intrinsics' image size and the analyzer say which camera). ``analyzer``: the analyzer
    model of the readout (default: the ideal one). Returns the folder's files and bytes."""
    w, h = size
    rw, rh, rx, ry = readout or (w, h, 0, 0)
    cs = CalibrationSet()
    if not legacy:
        cs.params["camera"] = {"layout": layout, "readout": [rw, rh, rx, ry],
                               "sensor_size": [w, h]}
    cs.params["intrinsics"] = {"K": [[600.0, 0, rw / 2], [0, 600.0, rh / 2], [0, 0, 1]],
                               "dist": [0.0] * 5, "image_size": [rw, rh]}
    cs.params["generator"] = {"zero_offset_deg": 0.5, "extinction_ratio": 500.0,
                              "stage_zero_axis_cam": [1.0, 0.0, 0.0]}
    cs.analyzer = analyzer or AnalyzerModel.ideal(layout_name_at(layout, rx, ry), (rh, rw))
    cs.dofp_maps = {"valid": np.ones((rh, rw), bool)}
    cs.save(folder)
    return {p.name: p.read_bytes() for p in pathlib.Path(folder).iterdir()}


SHAPE = (4, 8)  # (H, W)


def small_set() -> CalibrationSet:
    """A set with every section the processing reads, 8x4 pixels, in memory (``_small_set``
    of test_calibration_units plus turntable, light and the camera it was calibrated on)."""
    cs = CalibrationSet()
    cs.params["camera"] = {"layout": "imx250myr", "readout": [8, 4, 0, 0], "sensor_size": [8, 4]}
    cs.params["intrinsics"] = {"K": [[600.0, 0, 4.0], [0, 600.0, 2.0], [0, 0, 1]],
                               "dist": [0.0] * 5, "std_fx_fy_cx_cy_px": [0.1] * 4,
                               "image_size": [8, 4]}
    cs.params["turntable"] = {"axis_cam": [0.0, -1.0, 0.0], "point_cam_m": [0.0, 0.0, 0.5],
                              "axis_std_deg": 0.05}
    cs.params["light"] = {"position_cam_m": [0.2, -0.1, 0.0], "std_m": [0.001] * 3}
    cs.params["generator"] = {"zero_offset_deg": 1.5, "zero_offset_std_deg": 0.01,
                              "extinction_ratio": 800.0, "extinction_ratio_std": 5.0,
                              "stage_zero_axis_cam": [1.0, 0.0, 0.0]}
    cs.params["dofp"] = {"layout": "imx250myr", "shape": list(SHAPE), "valid_fraction": 1.0}
    cs.analyzer = AnalyzerModel.ideal("imx250myr", SHAPE)
    cs.dofp_maps = {"valid": np.ones(SHAPE, bool),
                    "angle_std_deg": np.full(SHAPE, 0.05, np.float32)}
    return cs
