"""What a session records about the rig, and checks against it: the devices' identities,
the camera's frame geometry, the sensor noise model, the hardware timing (:func:`rig_record`, the manifest's
``rig`` entry); whether a plan fits the camera (:func:`check_rig_for_plan`) and whether a
session may continue on a rig (:func:`check_resume_rig`, :func:`rig_differences`).

``rig``: a :class:`polrig.app.rig.Rig` (its four HAL devices, ``truth`` on the simulated rig,
``config``); a session: :class:`polrig.app.session.Session`.
"""

from __future__ import annotations

import dataclasses
import json
import math
from typing import Any

import numpy as np

from polrig.acquisition.engine import settle_frames
from polrig.acquisition.plan import CapturePlan, PlanError
from polrig.app.manifest import CameraFrames, RigRecord, TimingRecord
from polrig.app.session import Session
from polrig.errors import ConfigError
from polrig.formats.rawio import read_raw
from polrig.sensor.analyzer import resolve_layout
from polrig.sensor.noise import SensorModel
from polrig.solve.design import DECISION_S


def frame_geometry(rig) -> tuple[int, int, int, tuple[int, int]]:
    """``(width, height, n_colours, layout period)`` of the rig camera's raw frames."""
    width, height = rig.camera.roi[:2]
    lay = resolve_layout(rig.camera.layout)
    return int(width), int(height), lay.n_colours, tuple(lay.period)


def camera_frames(rig) -> CameraFrames:
    """What the rig's camera frames look like (the manifest's ``rig.camera_frames``): size,
    ROI offset (the mosaic phase), layout and colour count. Frames that differ in any of
    these cannot be processed or compared together."""
    width, height, ox, oy = (int(v) for v in rig.camera.roi)
    layout = str(rig.camera.layout)
    return {"width": width, "height": height, "offset_xy": [ox, oy], "layout": layout,
            "colours": int(resolve_layout(layout).n_colours)}


def rig_record(rig) -> RigRecord:
    """The manifest's ``rig`` entry (:class:`polrig.app.manifest.RigRecord`):
    :func:`describe_rig`, the camera's frame geometry (:func:`camera_frames`) and the noise
    model used for the uncertainty."""
    info = describe_rig(rig)
    return {"simulated": info["simulated"], "config": info.get("config"),
            "devices": info["devices"], "sim_parameters": info.get("sim_parameters"),
            "camera_frames": camera_frames(rig),
            "sensor_model": jsonable(dataclasses.asdict(sensor_model_of(rig))),
            "timing": timing_record(rig)}


def timing_record(rig) -> TimingRecord:
    """The manifest's ``rig.timing`` (:class:`polrig.app.manifest.TimingRecord`): the polarizer
    stage's declared motion and the camera's readout and settle frames, as
    :func:`polrig.acquisition.engine.hardware_model` takes them, and the time a decision is
    taken to cost (:data:`polrig.solve.design.DECISION_S`). An adaptive capture weighs its
    candidate states' cost with it (:func:`polrig.app.adaptive.timing_model`), from the session
    alone, so a replay or a resume chooses alike."""
    stage = rig.stage.capabilities
    accel = float(stage.accel_deg_s2)
    caps = rig.camera.capabilities
    return {"stage_speed_deg_s": float(stage.speed_deg_s),
            "stage_accel_deg_s2": accel if math.isfinite(accel) else None,
            "readout_us": float(caps.readout_us), "settle_frames": settle_frames(caps),
            "decision_s": DECISION_S}


def check_rig_for_plan(rig, plan: CapturePlan) -> None:
    """Refuse (:class:`polrig.acquisition.plan.PlanError` of ``exposures_us``, one line) a plan this
    rig's camera cannot acquire, before any session file is written: an exposure outside the
    camera's declared range (:meth:`polrig.acquisition.hal.CameraCapabilities.check_exposure`)."""
    caps = rig.camera.capabilities
    lo, hi = caps.exposure_range_us
    for e in plan.exposures_us:
        try:
            caps.check_exposure(e)
        except ConfigError:
            raise PlanError("exposures_us", f"outside the camera's range [{lo:g}, {hi:g}] us",
                            subject=f"{e:g} us", what="exposure") from None


def _frames_text(f: dict[str, Any]) -> str:
    off = f.get("offset_xy") or [0, 0]
    where = f"+{off[0]}+{off[1]}" if any(off) else ""
    n = f.get("colours")
    return (f"{f.get('width')}x{f.get('height')}{where} {f.get('layout')}"
            + (f" ({n} colour{'s' if n != 1 else ''})" if n is not None else ""))


def recorded_camera_frames(session: Session) -> CameraFrames | None:
    """:func:`camera_frames` of a session that predates ``rig.camera_frames``: from its first
    recorded raw frame, or ``None`` without one."""

    for cap in session.captures:
        for rec in cap["files"].get("raw", []):
            try:
                frame = read_raw(session.root / rec["path"])
                layout = str(frame.meta.layout)
                return {"width": int(frame.raw.shape[1]), "height": int(frame.raw.shape[0]),
                        "offset_xy": [int(v) for v in frame.meta.offset_xy], "layout": layout,
                        "colours": int(resolve_layout(layout).n_colours)}
            except Exception:  # noqa: BLE001 - a damaged frame: try the next one
                continue
    return None


#: Relative difference below which two recorded numbers of the simulated world are the same
#: value: the world is derived from its configuration in floating point, and another processor
#: (its vector instructions) or NumPy build rounds the last bits differently (a stage axis
#: recorded as 0.002745906021358964 on one machine is 0.002745906021358971 on another).
SAME_VALUE_REL = 1e-9


def same_values(a: Any, b: Any) -> bool:
    """Whether two JSON values are equal, floats to within :data:`SAME_VALUE_REL` (relative,
    with an absolute floor of ``SAME_VALUE_REL * 1e-3`` for values near 0); anything else,
    keys and lengths included, exactly."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(same_values(a[k], b[k]) for k in a)
    if isinstance(a, list) and isinstance(b, list):
        return len(a) == len(b) and all(same_values(x, y) for x, y in zip(a, b))
    if isinstance(a, float) or isinstance(b, float):
        if isinstance(a, bool) or isinstance(b, bool) or not all(
                isinstance(v, (int, float)) for v in (a, b)):
            return False
        return math.isclose(a, b, rel_tol=SAME_VALUE_REL, abs_tol=SAME_VALUE_REL * 1e-3)
    return a == b


def rig_differences(stored: dict[str, Any], current: dict[str, Any],
                    stored_frames: dict[str, Any] | None = None) -> list[str]:
    """What makes frames of the rig ``current`` (a :func:`rig_record`) incomparable with those
    a session recorded on ``stored`` (its manifest's ``rig``): simulated or not, the camera
    frames' size, offset and layout, each device's driver, model and serial, the noise model,
    and the simulated world's hidden parameters (scene, seed, sensor...). Settings that do
    not change the frames (a simulated clock's speed) are not compared. One phrase per
    difference (empty: the same rig)."""
    out: list[str] = []
    if bool(stored.get("simulated")) != bool(current.get("simulated")):
        kind = lambda r: "the simulated rig" if r.get("simulated") else "hardware"  # noqa: E731
        out.append(f"captured on {kind(stored)}, this is {kind(current)}")
    sf = stored.get("camera_frames") or stored_frames
    cf = current.get("camera_frames")
    if isinstance(sf, dict) and cf is not None:
        keys = ("width", "height", "offset_xy", "layout", "colours")
        if [sf.get(k) for k in keys] != [cf.get(k) for k in keys]:
            out.append(f"camera frames {_frames_text(sf)}, this camera's {_frames_text(cf)}")
    if stored.get("sensor_model") and stored.get("sensor_model") != current.get("sensor_model"):
        keys = sorted(k for k in set(stored["sensor_model"]) | set(current["sensor_model"] or {})
                      if stored["sensor_model"].get(k) != (current["sensor_model"] or {}).get(k))
        out.append(f"sensor noise model ({', '.join(keys)})")
    sp, cp = stored.get("sim_parameters"), current.get("sim_parameters")
    if (isinstance(sp, dict) and isinstance(cp, dict) and "error" not in sp
            and "error" not in cp and not same_values(sp, cp)):
        keys = sorted(k for k in set(sp) | set(cp) if not same_values(sp.get(k), cp.get(k)))
        out.append(f"simulated world ({', '.join(keys)})")
    sd, cd = stored.get("devices") or {}, current.get("devices") or {}
    for name in ("camera", "stage", "turntable", "light"):
        a, b = sd.get(name), cd.get(name)
        if not (isinstance(a, dict) and isinstance(b, dict)) or "error" in a or "error" in b:
            continue  # a device that could not describe itself is not compared
        ident = lambda d: " ".join(str(d.get(k)) for k in ("driver", "model", "serial")  # noqa: E731
                                   if d.get(k))
        if ident(a) != ident(b):
            out.append(f"{name} {ident(a)!r}, this rig's {ident(b)!r}")
    return out


def check_resume_rig(session: Session, rig) -> None:
    """Refuse (:class:`ConfigError`, one line) to resume ``session`` on a rig whose frames
    would not be comparable with the ones it holds (:func:`rig_differences`); nothing is
    written. Call before :func:`check_resume_space` and :func:`run_session`."""
    stored = session.manifest["rig"]
    current = json.loads(json.dumps(rig_record(rig)))  # as the manifest would store it
    frames = None if stored.get("camera_frames") else recorded_camera_frames(session)
    diffs = rig_differences(stored, current, frames)
    if diffs:
        raise ConfigError(f"{session.root} was captured on a different rig: "
                          f"{'; '.join(diffs[:4])}; continue it on the rig it was started "
                          f"with (the same rig configuration)")


def describe_rig(rig) -> dict[str, Any]:
    """What the manifest records about the rig: its config and the devices' identities (and
    the simulated world's hidden parameters on the simulated rig)."""
    out: dict[str, Any] = {"simulated": rig.truth is not None}
    if rig.config is not None:
        out["config"] = jsonable(rig.config)
    devices = {}
    for name, dev in rig.devices.items():
        try:
            devices[name] = jsonable(dataclasses.asdict(dev.info()))
        except Exception as exc:  # a device that cannot describe itself is still usable
            devices[name] = {"error": str(exc)}
    out["devices"] = devices
    if rig.truth is not None:
        try:
            out["sim_parameters"] = jsonable(rig.truth.rig_parameters())
        except Exception as exc:
            out["sim_parameters"] = {"error": str(exc)}
    return out


def jsonable(obj: Any) -> Any:
    """A JSON-compatible copy of ``obj`` (arrays to lists, dataclasses to dicts, paths to str)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return jsonable(dataclasses.asdict(obj))
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist()) if obj.size <= 64 else f"<array {obj.shape} {obj.dtype}>"
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return str(obj)
    if obj is None or isinstance(obj, (bool, int, float, str)):
        return obj
    return str(obj)



def sensor_model_of(rig) -> SensorModel:
    """The noise model of the rig's camera: the simulated rig's own, else the configured one
    (the ``[sensor_model]`` table of the rig config), else the IMX250 defaults."""
    if rig.truth is not None:
        try:
            fields = rig.truth.rig_parameters()["sensor"]["sensor_model"]
            return SensorModel(**fields)
        except (KeyError, TypeError):
            pass
    sm = rig.config.get("sensor_model") if isinstance(rig.config, dict) else None
    if isinstance(sm, SensorModel):
        return sm
    if isinstance(sm, dict):
        return SensorModel(**sm)
    return SensorModel()



def session_frame_geometry(session: Session) -> tuple[str | None, tuple[int, int, int, int] | None,
                                                      tuple[int, int] | None]:
    """``(layout, readout, sensor_size)`` of a session's frames, from its manifest
    (``rig.camera_frames``, else its first raw frame; the simulated sensor's size from
    ``rig.sim_parameters``); ``None`` where it does not say."""
    rig = session.manifest["rig"]
    frames = rig["camera_frames"]
    if frames is None:  # a session older than rig.camera_frames
        frames = recorded_camera_frames(session) or {}
    layout = frames.get("layout")
    readout = None
    try:
        off = frames.get("offset_xy") or [0, 0]
        readout = (int(frames["width"]), int(frames["height"]), int(off[0]), int(off[1]))
    except (KeyError, TypeError, ValueError, IndexError):
        readout = None
    size = None
    sensor = ((rig["sim_parameters"] or {}).get("sensor") or {}) if rig["simulated"] else {}
    try:
        h, w = sensor["shape"]
        size = (int(w), int(h))
    except (KeyError, TypeError, ValueError):
        size = None
    return (str(layout) if layout else None), readout, size




def session_sensor_model(session: Session) -> SensorModel:
    """The noise model recorded in a session's manifest (IMX250 defaults if none)."""
    fields = session.manifest["rig"]["sensor_model"]
    return SensorModel(**fields) if fields else SensorModel()
