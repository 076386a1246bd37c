"""Rig TOML validation: clear one-line errors naming the key, before anything is opened."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from drivers.emulators.ell14 import Ell14Emulator
from polrig.config import validate_config
from polrig.errors import ConfigError
from polrig.rig import DRIVERS, load_rig_config, open_rig

pytestmark = pytest.mark.timeout(20)

FULL = """
[camera]
driver = "genicam"
cti = "/opt/producer.cti"
serial = "223400123"
layout = "imx250mzr"
roi = [2448, 2048, 0, 0]
exposure_us = 5000
[stage]
driver = "ell14"
port = "/dev/ttyUSB0"
address = 0
[turntable]
driver = "grbl"
port = "/dev/ttyACM0"
axis = "A"
[light]
driver = "dc2200"
"""


def write(tmp_path, text: str):
    p = tmp_path / "rig.toml"
    p.write_text(textwrap.dedent(text))
    return p


def test_full_config_with_defaults(tmp_path):
    cfg = load_rig_config(write(tmp_path, FULL))
    assert cfg.driver("camera") == "genicam" and cfg["camera"]["exposure_us"] == 5000.0
    assert isinstance(cfg["camera"]["exposure_us"], float)
    assert cfg["stage"] == {"driver": "ell14", "port": "/dev/ttyUSB0", "address": 0,
                            "zero_offset_deg": 0.0, "reply_timeout_s": 1.0}
    assert cfg["turntable"]["degrees_per_unit"] == 1.0
    assert cfg["light"]["serial"] is None
    assert cfg.source.name == "rig.toml"


def test_missing_tables_are_simulated():
    cfg = validate_config({"stage": {"driver": "k10cr1", "port": "/dev/ttyUSB1"}}, DRIVERS)
    assert [cfg.driver(k) for k in ("camera", "stage", "turntable", "light")] == \
        ["sim", "k10cr1", "sim", "sim"]


@pytest.mark.parametrize("data, pattern", [
    ({"stage": {"driver": "ell41", "port": "/dev/x"}},
     r"^\[stage\] driver: unknown driver 'ell41' \(did you mean 'ell14'\?\); known for stage"),
    ({"stage": {"driver": "grbl", "port": "/dev/x"}},
     r"^\[stage\] driver: 'grbl' drives a turntable, not the stage"),
    ({"stage": {"port": "/dev/x"}}, r"^\[stage\] driver: missing"),
    ({"stage": {"driver": 14}}, r"^\[stage\] driver: expected a string, got 14"),
    ({"stage": {"driver": "ell14"}}, r"^\[stage\] port: missing \(driver 'ell14' needs it"),
    ({"stage": {"driver": "ell14", "port": "/dev/x", "address": "0"}},
     r"^\[stage\] address: expected an integer, got '0'"),
    ({"stage": {"driver": "ell14", "port": "/dev/x", "address": True}},
     r"^\[stage\] address: expected an integer, got True"),
    ({"stage": {"driver": "ell14", "port": "/dev/x", "address": 16}},
     r"^\[stage\] address: 16 is not a multidrop address"),
    ({"stage": {"driver": "ell14", "port": 0}}, r"^\[stage\] port: expected a string, got 0"),
    ({"stage": {"driver": "ell14", "port": "/dev/x", "speed": 3}},
     r"^\[stage\] speed: unknown key for driver 'ell14'; known: address, port"),
    ({"camera": {"driver": "genicam", "roi": [1, 2, 3]}},
     r"^\[camera\] roi: expected a list of 4 integers"),
    ({"camera": {"driver": "genicam", "layout": "imx999"}},
     r"^\[camera\] layout: 'imx999' is not one of imx250myr, imx250mzr"),
    ({"camera": {"driver": "genicam", "cti": 5}},
     r"^\[camera\] cti: expected a string or a list of strings"),
    ({"camera": {"driver": "genicam", "exposure_us": -5}}, r"^\[camera\] exposure_us: -5.0"),
    ({"turntable": {"driver": "grbl", "port": "/dev/x", "axis": "Q"}},
     r"^\[turntable\] axis: 'Q' is not an axis letter"),
    ({"lamp": {"driver": "dc2200"}}, r"^\[lamp\]: unknown table.*known: camera, light"),
    ({"stage": "ell14"}, r"^stage: expected a table \[stage\]"),
    ({"sensor_model": {"full_wel_e": 3}}, r"^\[sensor_model\] full_wel_e: unknown key"),
])
def test_bad_configs_name_the_key(data, pattern):
    with pytest.raises(ConfigError, match=pattern) as ei:
        validate_config(data, DRIVERS)
    assert "\n" not in str(ei.value)


def test_file_errors(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_rig_config(tmp_path / "none.toml")
    with pytest.raises(ConfigError, match=r"rig.toml: not valid TOML"):
        load_rig_config(write(tmp_path, "[stage\ndriver = 1"))
    with pytest.raises(ConfigError, match=r"rig.toml: \[stage\] port: missing"):
        load_rig_config(write(tmp_path, '[stage]\ndriver = "k10cr1"\n'))


def test_rejected_before_any_device_is_opened(tmp_path):
    """A bad [light] table stops open_rig before the (valid) stage is touched."""
    with Ell14Emulator() as emu:
        path = write(tmp_path, f"""
            [stage]
            driver = "ell14"
            port = "{emu.port}"
            [light]
            driver = "dc2200"
            timeout_s = "fast"
            """)
        with pytest.raises(ConfigError, match=r"\[light\] timeout_s: expected a number"):
            open_rig(path)
        assert emu.received == b""


def test_shipped_example_config_is_valid():
    example = Path(__file__).resolve().parents[1] / "drivers" / "emulators" / "rig-emulated.toml"
    cfg = load_rig_config(example)
    assert [cfg.driver(k) for k in ("camera", "stage", "turntable", "light")] == \
        ["genicam", "ell14", "grbl", "dc2200"]
