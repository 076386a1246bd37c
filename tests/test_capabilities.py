"""Capabilities are declared, never probed (issue 30).

* The camera declares its sensor size
  (:attr:`polrig.acquisition.hal.CameraCapabilities.sensor_size`): the simulated camera its
  sensor's, a GenICam camera its ``SensorWidth``/``SensorHeight`` or ``WidthMax``/``HeightMax``
  (tests/test_driver_genicam.py); calibration reads it there.
* A rig's simulator truth is an optional, typed capability (``Rig.truth: RigTruth | None``),
  and so is the simulated devices' fault injection (``Rig.faults: FaultInjection | None``).
* No module of the distribution asks an object whether it has one of these attributes
  (``getattr``/``hasattr`` with their names) or reaches for the simulated rig behind a rig.
"""

from __future__ import annotations

import ast
import dataclasses
import math
import typing

import numpy as np
import pytest
from test_architecture import _files

from polrig.acquisition import hal
from polrig.acquisition.engine import GuardedRig
from polrig.app.rig import Rig, open_rig
from polrig.calibration.calset import SensorGeometry

SIM = {"size": (48, 32), "clock_speed": math.inf, "seed": 1}


# -- the camera's sensor size -------------------------------------------------------------------
def test_a_sensor_size_is_two_whole_pixel_counts():
    assert hal.CameraCapabilities().sensor_size is None
    caps = hal.CameraCapabilities(sensor_size=(np.int64(2448), 2048.0))
    assert caps.sensor_size == (2448, 2048) and all(type(v) is int for v in caps.sensor_size)
    for bad in ((0, 10), (10,), (10, 20, 30), (10.5, 20), (True, 20), (-4, 4)):
        with pytest.raises(ValueError, match="sensor size"):
            hal.CameraCapabilities(sensor_size=bad)


def test_the_simulated_camera_declares_its_sensor_and_calibration_reads_it():
    with open_rig(None, **SIM) as rig:
        assert rig.camera.capabilities.sensor_size == (48, 32)
        rig.camera.set_roi(16, 8, 4, 2)
        assert rig.camera.capabilities.sensor_size == (48, 32)  # the sensor, not the ROI
        geo = SensorGeometry.of_rig(rig)
        assert geo.sensor_size == (48, 32) and geo.area == (16, 8, 4, 2)
        # the guarded rig of the calibration procedures declares the same
        assert SensorGeometry.of_rig(GuardedRig.around(rig)).sensor_size == (48, 32)


def test_a_camera_that_does_not_declare_its_sensor_size_has_none():
    class Undeclared:  # a camera whose capabilities say nothing of its sensor
        roi = (64, 48, 0, 0)
        layout = "imx250mzr"
        capabilities = hal.CameraCapabilities()
        sensor_size = (64, 48)  # an attribute outside the HAL is not read

    geo = SensorGeometry.of_rig(type("R", (), {"camera": Undeclared()})())
    assert geo.sensor_size is None and geo.area == (64, 48, 0, 0)


# -- the rig's optional capabilities ------------------------------------------------------------
def test_the_rigs_optional_capabilities_are_typed():
    hints = typing.get_type_hints(Rig)
    assert hints["truth"] == (hal.RigTruth | None)
    assert hints["faults"] == (hal.FaultInjection | None)
    assert typing.get_type_hints(GuardedRig)["truth"] == (hal.RigTruth | None)
    for cls in (Rig, GuardedRig):
        assert "sim" not in {f.name for f in dataclasses.fields(cls)}


def test_the_simulated_rig_declares_its_truth_and_fault_injection():
    with open_rig(None, **SIM) as rig:
        assert isinstance(rig.truth, hal.RigTruth)
        assert isinstance(rig.faults, hal.FaultInjection)
        world = rig.camera.world
        assert rig.truth.analyzer() is world.sensor.analyzer
        assert rig.truth.ground_truth()["mueller"].shape[-2:] == (32, 48)
        rig.truth.mount_target("white_plate")
        assert world.scene.name == "target:white_plate"
        rig.faults.inject_fault("light", "protocol", after_calls=0)
        with pytest.raises(Exception, match="garbled reply"):
            rig.light.set_level(0.5)
        guarded = GuardedRig.around(rig)
        assert guarded.truth is rig.truth


def test_calibrate_mounts_targets_by_the_declared_truth_else_asks(monkeypatch):
    from polrig.cli.commands.calibrate import _mount_for

    asked = []
    monkeypatch.setattr("builtins.input", lambda prompt: asked.append(prompt) or "")
    with open_rig(None, **SIM) as rig:
        mount = _mount_for(rig)
        mount("white_plate")
        assert rig.camera.world.scene.name == "target:white_plate" and not asked
        hardware_like = dataclasses.replace(rig, truth=None)  # as a real or mixed rig
        _mount_for(hardware_like)("charuco", tilt_deg=10.0)
        assert rig.camera.world.scene.name == "target:white_plate"  # nothing swapped
        assert asked == ["Mount the charuco (tilt_deg=10.0), then press Enter: "]


# -- no probes ----------------------------------------------------------------------------------
#: Attribute names that used to be probed: the simulator behind a rig and the sensor size.
PROBED = {"sim", "truth", "faults", "world", "sensor_size", "inject_fault"}


def probes(tree: ast.AST) -> list[tuple[int, str]]:
    """``getattr``/``hasattr`` of a :data:`PROBED` name, and ``x.sim`` on anything but the
    ``polrig`` package itself."""
    found = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and \
                node.func.id in ("getattr", "hasattr") and len(node.args) >= 2 and \
                isinstance(node.args[1], ast.Constant) and node.args[1].value in PROBED:
            found.append((node.lineno, f"{node.func.id}(..., {node.args[1].value!r})"))
        elif isinstance(node, ast.Attribute) and node.attr == "sim" and not (
                isinstance(node.value, ast.Name) and node.value.id == "polrig"):
            found.append((node.lineno, f"{ast.unparse(node)}"))
    return found


def test_the_probe_finder_finds_probes():
    tree = ast.parse("getattr(rig, 'sim', None)\nhasattr(cam, 'sensor_size')\nrig.sim.world\n"
                     "import polrig.sim.targets\npolrig.sim.targets.mount\n")
    assert [line for line, _ in probes(tree)] == [1, 2, 3]


def test_no_module_probes_for_capabilities():
    found = [f"{name}:{line}: {what}" for name, path in _files().items()
             for line, what in probes(ast.parse(path.read_text("utf-8"), str(path)))]
    assert not found, "capabilities probed instead of declared:\n" + "\n".join(found)
