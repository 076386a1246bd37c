"""Operator commands against emulated hardware: move, home, light, snap, devices."""

from __future__ import annotations

import _thread
import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from _genicam import VIKY, viky_camera

from polrig.cli import main
from polrig.drivers.emulators import dc2200 as dc2200_emulator
from polrig.drivers.emulators.ell14 import PULSES_PER_REV, Ell14Emulator
from polrig.drivers.emulators.grbl import GrblEmulator
from polrig.drivers.emulators.k10cr1 import STEPS_PER_DEG, K10cr1Emulator
from polrig.formats.rawio import read_raw

pytestmark = pytest.mark.timeout(30)
REPO = Path(__file__).resolve().parents[1]


def config(tmp_path, text: str) -> str:
    p = tmp_path / "rig.toml"
    p.write_text(textwrap.dedent(text))
    return str(p)


def run(capsys, *argv: str) -> tuple[int, str, str]:
    rc = main(list(argv))
    out, err = capsys.readouterr()
    return rc, out, err


def test_move_stage_ell14(tmp_path, capsys):
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=4) as emu:
        cfg = config(tmp_path, f'[stage]\ndriver = "ell14"\nport = "{emu.port}"\naddress = 0\n')
        rc, out, err = run(capsys, "move", "stage", "45", "--config", cfg)
        assert rc == 0, err
        assert abs(emu.position_deg - 45.0) <= 360.0 / PULSES_PER_REV  # one encoder pulse
        assert out.startswith("stage: at 45.0") and "ELL14, serial 11400123" in out
        rc, out, _ = run(capsys, "home", "stage", "--config", cfg)
        assert rc == 0 and "homed, at 0.0000 deg" in out
        assert emu.position_deg == pytest.approx(0.0, abs=360.0 / PULSES_PER_REV)


def test_move_stage_k10cr1(tmp_path, capsys):
    with K10cr1Emulator(link=tmp_path / "k10cr1", speed_factor=40) as emu:
        cfg = config(tmp_path, f'[stage]\ndriver = "k10cr1"\nport = "{emu.port}"\n')
        rc, out, err = run(capsys, "move", "stage", "45", "--config", cfg)
        assert rc == 1 and err.count("\n") == 1 and "not homed" in err
        assert run(capsys, "home", "stage", "--config", cfg)[0] == 0
        rc, out, err = run(capsys, "move", "stage", "45", "--config", cfg)
        assert rc == 0, err
        assert abs(emu.position_deg - 45.0) <= 1.0 / STEPS_PER_DEG  # one micro-step
        assert "K10CR1, serial 55000123" in out


def test_move_turntable_grbl(tmp_path, capsys):
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as emu:
        cfg = config(tmp_path, f'[turntable]\ndriver = "grbl"\nport = "{emu.port}"\naxis = "A"\n')
        rc, _, err = run(capsys, "move", "turntable", "45", "--config", cfg)
        assert rc == 1 and ("alarm" in err.lower() or "error 9" in err)
        # one line naming the command that clears it, with this rig file
        assert err.count("\n") == 1 and f"`polrig home turntable --config {cfg}`" in err
        assert run(capsys, "home", "turntable", "--config", cfg)[0] == 0
        rc, out, err = run(capsys, "move", "turntable", "45", "--config", cfg)
        assert rc == 0, err
        assert emu.axis_position("A") == pytest.approx(45.0, abs=1e-3)
        assert out.startswith("turntable: at 45.0000 deg")


def test_move_timeout_and_missing_port(tmp_path, capsys):
    """--timeout bounds the move: it fails after 0.3 s (plus opening the port), in one line,
    long before the motion would end (180 deg at 8.6 deg/s: 21 s)."""
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=0.02) as emu:
        cfg = config(tmp_path, f'[stage]\ndriver = "ell14"\nport = "{emu.port}"\n')
        t0 = time.monotonic()
        rc, _, err = run(capsys, "move", "stage", "180", "--timeout", "0.3", "--config", cfg)
        assert rc == 1 and "within 0.3 s; stopped" in err and err.count("\n") == 1
        assert 0.3 <= time.monotonic() - t0 < 21.0 / 3
        assert emu.move is None  # stopped before the error: it went on turning to 180 deg
    cfg = config(tmp_path, f'[stage]\ndriver = "ell14"\nport = "{tmp_path / "ttyNone"}"\n')
    rc, _, err = run(capsys, "move", "stage", "10", "--config", cfg)
    assert rc == 1 and "cannot open serial port" in err and err.count("\n") == 1


def test_bad_config_is_usage_error_before_opening(tmp_path, capsys):
    with Ell14Emulator(link=tmp_path / "ell14") as emu:
        cfg = config(tmp_path, f'[stage]\ndriver = "ell14"\nport = "{emu.port}"\naddress = "0"\n')
        rc, _, err = run(capsys, "move", "stage", "10", "--config", cfg)
        assert rc == 2 and "[stage] address: expected an integer" in err
        assert emu.received == b""


def test_light_on_off(tmp_path, capsys):
    cfg = config(tmp_path, '[light]\ndriver = "dc2200"\nbackend = "polrig.drivers.emulators.dc2200"\n')
    rc, out, err = run(capsys, "light", "on", "--level", "0.4", "--config", cfg)
    assert rc == 0, err
    emu = dc2200_emulator.get_backend()
    assert emu.output_on and emu.brightness_percent == pytest.approx(40.0)
    assert out.startswith("light: on, level 0.400") and "DC2200, serial M00123456" in out
    rc, out, _ = run(capsys, "light", "off", "--config", cfg)
    assert rc == 0 and not emu.output_on and out.startswith("light: off")
    rc, _, err = run(capsys, "light", "on", "--level", "2", "--config", cfg)
    assert rc == 2 and "[0, 1]" in err


def test_snap_from_viky(tmp_path, capsys):
    cfg = config(tmp_path, f"""
        {viky_camera()}
        """)
    out_file = tmp_path / "frame.png"
    rc, out, err = run(capsys, "snap", "--out", str(out_file), "--config", cfg)
    assert rc == 0, err
    frame = read_raw(out_file)
    assert frame.raw.shape == (100, 128) and frame.raw.dtype == np.uint8
    side = json.loads(Path(str(out_file) + ".json").read_text())
    assert side["layout"] == "imx250mzr" and side["pixel_format"] == "Mono8"
    for name in ("frame_s0.png", "frame_dolp.png", "frame_aolp.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert "Viky, serial 0" in out
    rc, _, err = run(capsys, "snap", "--out", str(tmp_path / "x.jpg"), "--config", cfg)
    assert rc == 2 and "--out must end in" in err


def test_devices_lists_configured_and_discovered(tmp_path, capsys, monkeypatch):
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(VIKY.parent))
    with Ell14Emulator(link=tmp_path / "ell14") as emu:
        cfg = config(tmp_path, f"""
            [stage]
            driver = "ell14"
            port = "{emu.port}"
            [light]
            driver = "dc2200"
            backend = "polrig.drivers.emulators.dc2200"
            """)
        rc, out, err = run(capsys, "devices", "--config", cfg)
        assert rc == 0, err
        assert "ok: ELL14, serial 11400123" in out and "ok: DC2200, serial M00123456" in out
        assert "serial M00123456" in out.split("USB LED drivers")[1]
        assert f"{VIKY}: Viky serial 2" in out
    rc, out, err = run(capsys, "devices", "--config", cfg)  # emulator gone
    assert rc == 1 and "unreachable" in out and "could not be opened" in err


def test_devices_goes_on_past_a_device_that_refuses_a_setting(tmp_path, capsys, monkeypatch):
    """A configured setting the device cannot take (software trigger on a free-running camera)
    is reported as that device's, and the listing goes on to the others and the discovery."""
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(VIKY.parent))
    cfg = config(tmp_path, f'[camera]\ndriver = "genicam"\ncti = "{VIKY}"\nserial = "0"\ntrigger = "software"\n')
    rc, out, err = run(capsys, "devices", "--config", cfg)
    assert rc == 1 and "could not be opened" in err, err
    camera = out.split("camera")[1].split("stage")[0]
    assert "unreachable: trigger mode 'software' is not supported" in camera, out
    assert "ok: " in out.split("stage")[1] and f"{VIKY}: Viky serial 2" in out  # the others, then discovery


def test_emulator_cli_and_polrig_in_separate_processes(tmp_path):
    """A human's path: start the emulator from its CLI, point a config at the link."""
    link = tmp_path / "ell14"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    emu = subprocess.Popen([sys.executable, "-m", "polrig.drivers.emulators.ell14", "--link", str(link),
                            "--speed-factor", "4"], stdout=subprocess.PIPE, text=True, env=env)
    try:
        first = emu.stdout.readline()
        assert first.startswith("/dev/pts/") and f"(link {link})" in first
        cfg = config(tmp_path, f'[stage]\ndriver = "ell14"\nport = "{link}"\n')
        res = subprocess.run([sys.executable, "-m", "polrig", "move", "stage", "45",
                              "--config", cfg], capture_output=True, text=True, env=env,
                             timeout=20)
        assert res.returncode == 0, res.stderr
        assert res.stdout.startswith("stage: at 45.0")
    finally:
        emu.terminate()
        emu.wait(timeout=5)


@pytest.mark.parametrize("argv", [["move", "stage", "10", "--timeout", "-1"],
                                  ["move", "stage", "10", "--timeout", "nan"],
                                  ["move", "turntable", "10", "--timeout", "0"],
                                  ["home", "stage", "--timeout", "inf"],
                                  ["snap", "--out", "x.png", "--timeout", "-3"],
                                  ["snap", "--out", "x.png", "--exposure-us", "nan"]])
def test_absurd_timeouts_and_exposures_are_usage_errors(tmp_path, capsys, monkeypatch, argv):
    """``--timeout -1`` used to fail after opening the device ("did not end within -1 s"),
    ``--timeout nan`` to pass; now both stop in argument parsing (exit 2) naming the option."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    last = capsys.readouterr().err.strip().splitlines()[-1]
    assert f"error: argument {argv[-2]}: " in last
    assert list(tmp_path.iterdir()) == []


def test_snap_waits_for_a_long_exposure(tmp_path, capsys, monkeypatch):
    """The frame is awaited for its exposure and readout and then ``--timeout`` (a margin), so
    the camera's longest exposure does not time out; one out of range is refused in one line."""
    monkeypatch.chdir(tmp_path)
    rc, out, err = run(capsys, "snap", "--out", "long.png", "--exposure-us", "9995000")
    assert rc == 0 and "exposure 9.995e+06 us" in out, err
    rc, out, err = run(capsys, "snap", "--out", "over.png", "--exposure-us", "2e7")
    assert rc == 2 and err.strip().endswith("is outside the camera's range [10, 1e+07] us"), err
    assert not (tmp_path / "over.png").exists()


def test_snap_never_replaces_a_raw_frame(tmp_path, capsys):
    """A second snap onto the same name, or onto a name whose previews an earlier snap wrote,
    is refused before the camera is touched (exit 2); ``--overwrite`` replaces on purpose."""
    cfg = config(tmp_path, '[sim]\nsize = "32x32"\nclock_speed = inf\n')
    first = tmp_path / "sn.png"
    rc, _, err = run(capsys, "snap", "--out", str(first), "--config", cfg)
    assert rc == 0, err
    before = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    assert sorted(before) == ["rig.toml", "sn.png", "sn.png.json", "sn_aolp.png", "sn_dolp.png",
                              "sn_s0.png"]
    rc, out, err = run(capsys, "snap", "--out", str(first), "--config", cfg)
    assert rc == 2 and out == "" and err.count("\n") == 1
    assert f"{first} already exists" in err and "--overwrite" in err
    rc, out, err = run(capsys, "snap", "--out", str(tmp_path / "sn.npy"), "--config", cfg)
    assert rc == 2 and f"{tmp_path / 'sn_s0.png'} already exists" in err
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == before
    rc, out, err = run(capsys, "snap", "--out", str(first), "--overwrite", "--config", cfg)
    assert rc == 0, err
    (tmp_path / "folder.png").mkdir()
    rc, _, err = run(capsys, "snap", "--out", str(tmp_path / "folder.png"), "--config", cfg)
    assert rc == 2 and f"--out {tmp_path / 'folder.png'} is a directory" in err


@pytest.mark.parametrize("axis,angle", [("stage", "1e9"), ("stage", "-361"),
                                        ("turntable", "36001")])
def test_move_beyond_the_capture_limits_is_refused_before_moving(tmp_path, capsys, axis, angle):
    """``polrig move stage 1e9`` used to be accepted, move for 60 s and then time out; now it
    gets the limits ``polrig capture`` applies to --states / --poses (exit 2, one line)."""
    cfg = config(tmp_path, '[sim]\nsize = "32x32"\nclock_speed = inf\n')
    rc, out, err = run(capsys, "move", axis, angle, "--config", cfg)
    assert rc == 2 and out == ""
    assert err.startswith(f"polrig: error: DEG {float(angle):g}: a {axis} angle must be within +-")
    assert len(err.strip().splitlines()) == 1


def test_k10cr1_turntable_not_homed_names_its_own_home_command(tmp_path, capsys):
    """It said 'stage is not homed (run `polrig home stage`)' for a K10CR1 turntable; now
    one line naming the turntable and `polrig home turntable --config RIG`."""
    with K10cr1Emulator(link=tmp_path / "k10cr1", speed_factor=40) as emu:
        cfg = config(tmp_path, f'[turntable]\ndriver = "k10cr1"\nport = "{emu.port}"\n')
        rc, _, err = run(capsys, "move", "turntable", "45", "--config", cfg)
        assert rc == 1 and err.count("\n") == 1 and "turntable is not homed" in err
        assert f"`polrig home turntable --config {cfg}`" in err and "home stage" not in err
        assert run(capsys, "home", "turntable", "--config", cfg)[0] == 0
        emu.inject("stop_mid_move")  # a limit switch fires on the way
        rc, _, err = run(capsys, "move", "turntable", "90", "--config", cfg)
        assert rc == 1 and err.count("\n") == 1 and "turntable move interrupted" in err
        assert f"`polrig home turntable --config {cfg}`" in err


@pytest.fixture
def python_sigint():
    """Python's own Ctrl-C handler, as in a fresh `polrig` process, whatever an earlier test
    of this process installed."""
    old = signal.signal(signal.SIGINT, signal.default_int_handler)
    yield
    signal.signal(signal.SIGINT, old)


def interrupt_after(seconds: float, signum: int) -> threading.Timer:
    """Ctrl-C (SIGINT) or SIGTERM to this process after ``seconds``, as the operator or a
    service manager would send it to `polrig` (main() turns SIGTERM into an interruption)."""
    def send() -> None:
        if signum == signal.SIGINT:
            _thread.interrupt_main()
        else:
            os.kill(os.getpid(), signum)
    timer = threading.Timer(seconds, send)
    timer.start()
    return timer


@pytest.mark.parametrize("signum, rc_expected", [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_an_interrupted_move_stops_the_turntable(tmp_path, capsys, python_sigint, signum,
                                                rc_expected):
    """Ctrl-C or SIGTERM during `polrig move turntable 300`: the command exits (130, 143)
    and the turntable stops there; it went on turning to 300 deg after the exit."""
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as emu:
        cfg = config(tmp_path, f'[turntable]\ndriver = "grbl"\nport = "{emu.port}"\n')
        assert run(capsys, "home", "turntable", "--config", cfg)[0] == 0
        emu.speed_factor = 1.0  # 60 deg/s: 5 s to 300 deg
        timer = interrupt_after(1.0, signum)
        rc, _, err = run(capsys, "move", "turntable", "300", "--config", cfg)
        timer.join()
        assert rc == rc_expected and err.count("\n") == 1
        assert emu.state == "Idle"
        here = emu.axis_position()
        time.sleep(0.2)
        assert emu.axis_position() == pytest.approx(here, abs=1e-6) and 0 < here < 300


def test_an_interrupted_home_stops_the_stage(tmp_path, capsys, python_sigint):
    with Ell14Emulator(link=tmp_path / "ell14", speed_factor=4) as emu:
        cfg = config(tmp_path, f'[stage]\ndriver = "ell14"\nport = "{emu.port}"\n')
        assert run(capsys, "move", "stage", "300", "--config", cfg)[0] == 0
        emu.speed_factor = 0.02  # 8.6 deg/s: 35 s home
        timer = interrupt_after(1.0, signal.SIGINT)
        rc, _, err = run(capsys, "home", "stage", "--config", cfg)
        timer.join()
        assert rc == 130 and emu.move is None and b"0st" in emu.received
        assert 0 < emu.position_deg < 300


def test_listing_the_devices_does_not_abort_a_move_under_way(tmp_path, capsys):
    """`polrig move turntable 180 --no-wait`, then `polrig devices`: opening the GRBL soft-
    reset it, which aborted the move (ALARM:3, position lost)."""
    with GrblEmulator(link=tmp_path / "grbl", speed_factor=20) as emu:
        cfg = config(tmp_path, f'[turntable]\ndriver = "grbl"\nport = "{emu.port}"\n')
        assert run(capsys, "home", "turntable", "--config", cfg)[0] == 0
        emu.speed_factor = 1.0  # 3 s to 180 deg
        rc, out, err = run(capsys, "move", "turntable", "180", "--no-wait", "--config", cfg)
        assert rc == 0 and "moving to 180 deg" in out, err
        rc, out, err = run(capsys, "devices", "--config", cfg)
        assert "ok: GRBL" in out.split("turntable")[1], out + err
        assert emu.state == "Run" and b"\x18" not in emu.received.split(b"180")[-1]
        deadline = time.monotonic() + 10
        while emu.state != "Idle" and time.monotonic() < deadline:
            time.sleep(0.05)
        assert emu.state == "Idle" and emu.axis_position() == pytest.approx(180.0, abs=1e-3)
