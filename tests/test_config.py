"""Rig TOML validation: clear one-line errors naming the key, before anything is opened."""

from __future__ import annotations

import textwrap
from pathlib import Path

import pytest

from polrig.app.rig import DRIVERS, load_rig_config, open_rig
from polrig.drivers.emulators.ell14 import Ell14Emulator
from polrig.errors import ConfigError
from polrig.formats.config import validate_config

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


@pytest.mark.parametrize("toml, pattern", [
    ("[sim]\nhidden = {stage_zero_offset_deg = [1, 2]}",
     r"/rig\.toml: \[sim\] hidden\.stage_zero_offset_deg: expected a number, got \[1, 2\]$"),
    ('[sim]\nseed = "x"', r"/rig\.toml: \[sim\] seed: expected an integer >= 0, got 'x'$"),
    ("[sim]\nseed = -1", r"/rig\.toml: \[sim\] seed: expected an integer >= 0"),
    ('[sim]\nhidden = "abc"', r"/rig\.toml: \[sim\] hidden: expected a table"),
    ('[sim]\nhidden = {extinction_ratio = "x"}',
     r"/rig\.toml: \[sim\] hidden\.extinction_ratio: expected a number, got 'x'$"),
    ("[sim]\nhidden = {extinction_ratio = 0.5}", r"\[sim\] hidden\.extinction_ratio: must be > 1"),
    ("[sim]\nhidden = {turntable_axis = [0, 0, 0]}", r"\[sim\] hidden\.turntable_axis: must not be zero"),
    ("[sim]\nhidden = {colour_qe = [1, 1]}", r"\[sim\] hidden\.colour_qe: expected a list of 3 numbers"),
    ("[sim]\nhidden = {analyzer = {gain_sigma = 'a'}}", r"\[sim\] hidden\.analyzer\.gain_sigma: expected a number"),
    ("[sim]\nhidden = {analyzer = {gain = 1}}", r"\[sim\] hidden\.analyzer\.gain: unknown key"),
    ("[sim]\nhidden = {secret = 1}", r"\[sim\] hidden\.secret: unknown hidden parameter"),
    ("[sim]\nsensor_model = {full_well_e = 'x'}", r"\[sim\] sensor_model\.full_well_e: expected a number"),
    ('[sim]\nsize = "abc"', r"\[sim\] size must be 'WxH'"),
    ('[sim]\nscene = "teapot"', r"\[sim\] scene: unknown scene 'teapot'"),
    ('[sim]\ndistribution = "phong"', r"\[sim\] distribution: must be one of ggx, beckmann"),
    ("[sim]\nindirect_samples = -2", r"\[sim\] indirect_samples: expected an integer in 0\.\.4096, got -2$"),
    ("[sim]\nnoise = 1", r"\[sim\] noise: expected true or false, got 1"),
    ("[sim]\nexposure_us = -5", r"\[sim\] exposure_us: must be > 0"),
    ("[sim]\nexposure_us = nan", r"\[sim\] exposure_us: must be a finite number"),
    ("[sim]\nspeed = 3", r"\[sim\] speed: unknown simulated-rig option"),
    ('[sensor_model]\nfull_well_e = "x"', r"/rig\.toml: \[sensor_model\] full_well_e: expected a number, got 'x'$"),
    ("[sensor_model]\nbit_depth = 12.5", r"\[sensor_model\] bit_depth: expected an integer"),
    ("[sensor_model]\nbit_depth = 40", r"\[sensor_model\] bit_depth: must be an integer in 1\.\.16"),
    ("[sensor_model]\nread_noise_e = nan", r"\[sensor_model\] read_noise_e: must be >= 0 and finite"),
])
def test_sim_and_sensor_model_tables_name_table_and_key(tmp_path, toml, pattern):
    """The [sim] table goes through the simulated rig's own option parser at validation time
    (bad values used to surface as TypeErrors in build_world, or as one-liners naming neither
    table nor key, once devices were already being opened)."""
    with pytest.raises(ConfigError, match=pattern) as ei:
        load_rig_config(write(tmp_path, toml))
    assert "\n" not in str(ei.value) and str(ei.value).startswith(str(tmp_path / "rig.toml"))


def test_good_sim_table_is_kept_as_written(tmp_path):
    cfg = load_rig_config(write(tmp_path, """
        [sim]
        size = "64x48"
        seed = 3
        clock_speed = inf
        hidden = {extinction_ratio = 1e12, ideal_analyzer = true, turntable_axis = [0, 0, 1]}
        sensor_model = {full_well_e = 9000}
        [sensor_model]
        full_well_e = 9000
        """))
    assert cfg["sim"]["size"] == "64x48" and cfg["sim"]["hidden"]["ideal_analyzer"] is True
    assert cfg["sensor_model"] == {"full_well_e": 9000.0}
    with open_rig(write(tmp_path, '[sim]\nsize = "64x48"\nclock_speed = inf\n')) as rig:
        assert rig.camera.grab().raw.shape == (48, 64)


def test_devices_checks_the_sim_table_before_printing_anything(tmp_path, capsys):
    from polrig.cli import main

    path = write(tmp_path, "[sim]\nhidden = {stage_zero_offset_deg = [1, 2]}\n")
    assert main(["devices", "--config", str(path)]) == 2
    out, err = capsys.readouterr()
    assert out == ""
    assert err == (f"polrig: error: {path}: [sim] hidden.stage_zero_offset_deg: expected a "
                   f"number, got [1, 2]\n")


@pytest.mark.parametrize("table, pattern", [
    ('[stage]\ndriver = "ell14"\nport = "/dev/x"\nzero_offset_deg = nan',
     r"\[stage\] zero_offset_deg: nan must be a finite angle$"),
    ('[stage]\ndriver = "k10cr1"\nport = "/dev/x"\nzero_offset_deg = inf',
     r"\[stage\] zero_offset_deg: inf must be a finite angle$"),
    ('[turntable]\ndriver = "grbl"\nport = "/dev/x"\naxes = "XYZ"',
     r"\[turntable\] axis: 'A' is not one of the controller's axes 'XYZ'"),
    ('[turntable]\ndriver = "grbl"\nport = "/dev/x"\naxes = "XXYA"', r"\[turntable\] axes: 'XXYA' is not a list of distinct"),
    ('[turntable]\ndriver = "grbl"\nport = "/dev/x"\naxes = ""', r"\[turntable\] axes: '' is not a list"),
    ('[light]\ndriver = "dc2200"\nbackend = ""', r"\[light\] backend: '' is not a module name"),
    ('[light]\ndriver = "dc2200"\nbackend = "usb backend"', r"\[light\] backend: 'usb backend' is not a module name"),
])
def test_values_a_device_cannot_take_are_named_before_it_opens(tmp_path, table, pattern):
    """Values that would fail only once the port is open (a NaN zero offset, an axis the
    controller does not report, an empty backend name) are refused by the configuration's check,
    naming the table and key."""
    with pytest.raises(ConfigError, match=pattern):
        load_rig_config(write(tmp_path, table))
    assert load_rig_config(write(tmp_path, '[turntable]\ndriver = "grbl"\nport = "/dev/x"\naxes = "xyza"\naxis = "a"'))


def test_a_backend_module_that_is_no_pyusb_backend_is_one_line():
    from polrig.drivers.dc2200 import resolve_backend
    from polrig.errors import DeviceNotFound

    with pytest.raises(DeviceNotFound, match=r"'json' is no pyusb backend module"):
        resolve_backend("json")
