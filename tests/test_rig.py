"""open_rig: configuration picks the classes; real drivers against emulators; one sim world."""

from __future__ import annotations

import textwrap

import pytest
import serial
from _genicam import viky_camera

from polrig.acquisition import hal
from polrig.app.rig import open_rig
from polrig.drivers.ell14 import Ell14Stage
from polrig.drivers.emulators import dc2200 as dc2200_emulator
from polrig.drivers.emulators.ell14 import Ell14Emulator
from polrig.drivers.emulators.grbl import GrblEmulator
from polrig.drivers.emulators.k10cr1 import K10cr1Emulator
from polrig.drivers.grbl import GrblTurntable
from polrig.drivers.k10cr1 import K10cr1Turntable
from polrig.errors import DeviceNotFound

pytestmark = pytest.mark.timeout(30)


@pytest.fixture
def emulators(tmp_path):
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=4) as ell, \
            K10cr1Emulator(link=tmp_path / "k10cr1", speed_factor=40) as k10, \
            GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as grbl:
        yield {"ell14": ell, "k10cr1": k10, "grbl": grbl}


def write(tmp_path, text):
    p = tmp_path / "rig.toml"
    p.write_text(textwrap.dedent(text))
    return p


def test_real_rig_against_emulators(tmp_path, emulators):
    path = write(tmp_path, f"""
        {viky_camera(serial="2", roi=(100, 100), layout=None)}
        [stage]
        driver = "ell14"
        port = "{emulators['ell14'].port}"
        [turntable]
        driver = "k10cr1"
        port = "{emulators['k10cr1'].port}"
        [light]
        driver = "dc2200"
        backend = "polrig.drivers.emulators.dc2200"
        """)
    with open_rig(path) as rig:
        assert isinstance(rig.stage, Ell14Stage) and isinstance(rig.stage, hal.RotationStage)
        assert isinstance(rig.turntable, K10cr1Turntable) and isinstance(rig.turntable, hal.Turntable)
        assert rig.truth is None and rig.faults is None and rig.source == path
        text = rig.describe()
        assert "ELL14" in text and "K10CR1" in text and "DC2200" in text and "Viky" in text
        rig.stage.move_to(30.0)
        assert emulators["ell14"].position_deg == pytest.approx(30.0, abs=360 / 143360)
        rig.light.set_level(0.5)
        assert dc2200_emulator.get_backend().brightness_percent == pytest.approx(50.0)
        assert rig.camera.grab(timeout_s=2).raw.shape == (100, 100)
    for name in ("ell14", "k10cr1"):  # ports released
        with serial.Serial(emulators[name].port, exclusive=True):
            pass
    assert "closed" in rig.describe()


def test_failed_open_closes_what_was_opened(tmp_path, emulators):
    path = write(tmp_path, f"""
        [stage]
        driver = "ell14"
        port = "{emulators['ell14'].port}"
        [turntable]
        driver = "grbl"
        port = "{tmp_path / 'no-such-port'}"
        """)
    with pytest.raises(DeviceNotFound, match="no-such-port"):
        open_rig(path)
    with serial.Serial(emulators["ell14"].port, exclusive=True):
        pass  # the stage opened first was closed again


def test_grbl_turntable_from_config(tmp_path, emulators):
    path = write(tmp_path, f"""
        [turntable]
        driver = "grbl"
        port = "{emulators['grbl'].port}"
        axis = "A"
        """)
    with open_rig(path, size=(32, 24)) as rig:
        assert isinstance(rig.turntable, GrblTurntable)
        rig.turntable.home(timeout_s=5)
        rig.turntable.move_to(12.5, timeout_s=5)
        assert emulators["grbl"].axis_position("A") == pytest.approx(12.5, abs=1e-3)


def test_simulated_rig_shares_one_world():
    pytest.importorskip("polrig.sim.devices")
    with open_rig(None, size=(32, 24)) as rig:
        assert isinstance(rig.camera, hal.Camera) and isinstance(rig.light, hal.Light)
        assert isinstance(rig.turntable, hal.Turntable)
        assert rig.truth is not None and rig.source is None
        assert rig.camera.world is rig.stage.world is rig.turntable.world is rig.light.world
        assert isinstance(rig.truth, hal.RigTruth) and isinstance(rig.faults, hal.FaultInjection)
        assert rig.camera.grab().raw.shape == (24, 32)
        assert "built-in simulated rig" in rig.describe()


def test_mixed_rig_one_sim_world(tmp_path, emulators):
    pytest.importorskip("polrig.sim.devices")
    path = write(tmp_path, f"""
        [stage]
        driver = "ell14"
        port = "{emulators['ell14'].port}"
        [sim]
        size = [32, 24]
        """)
    with open_rig(path) as rig:
        assert isinstance(rig.stage, Ell14Stage)
        assert rig.camera.world is rig.light.world is rig.turntable.world
        assert rig.truth is None  # the simulated world no longer describes the real stage
        assert rig.faults is not None  # the simulated devices still fail to order
        assert rig.camera.grab().raw.shape == (24, 32)
