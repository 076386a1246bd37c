"""Acceptance: ``polrig capture --poses 0,90 --mode reference --config
drivers/emulators/rig-emulated.toml`` completes against the emulated rig: the GenTL producer
shipped in the genicam wheel (Viky: Mono8, free run only, no exposure control), the ELL14 and
GRBL emulators on the pseudo-terminals the file names, and the DC2200 USB-TMC emulator.

The camera declares free run only (no TriggerMode), so the capture runs in free run and
discards the declared settle frames after every motion; its Mono8 frames (8-bit codes of
the 12-bit ADC the default noise model describes) go through the whole chain: raw frames
and sidecars written, the reference solve in ADC DN, a Mueller EXR per pose. The Viky test
pattern is a white frame (code 255, the top of the 8-bit format) with a black square moving
with the frame number: white samples are clipped and must be masked as saturated, which
the 12-bit saturation threshold alone (4095 - 5 sigma) would not do at 255 * 16 = 4080 DN.

GRBL starts locked in its Alarm state (homing enabled) and the capture never homes it on its
own (issue 33 item 5): the operator runs ``polrig home turntable --config ...`` first, as the
rig file says. A limit switch that fires during a capture (something in the way of the
turntable) stops it with one line naming that command; after the operator clears the way and
runs it, ``polrig capture --resume`` completes.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
from pathlib import Path

import genicam
import numpy as np
import pytest

from polrig.app.processing import adc_scale, state_radiance
from polrig.cli import main
from polrig.drivers.emulators.ell14 import Ell14Emulator
from polrig.drivers.emulators.grbl import GrblEmulator
from polrig.formats.exr import read_mueller_exr
from polrig.formats.rawio import read_raw
from polrig.sensor.noise import SensorModel
from polrig.solve.reference import SATURATED

pytestmark = pytest.mark.timeout(120)
ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "drivers" / "emulators" / "rig-emulated.toml"
#: the rig file names fixed ports; concurrent runs on this machine take turns
LOCK = Path("/tmp/polrig-emulated-rig.lock")


@contextlib.contextmanager
def emulated_rig_ports():
    """The ELL14 and GRBL emulators at the ports rig-emulated.toml names."""
    import tomllib

    cfg = tomllib.loads(CONFIG.read_text())
    with open(LOCK, "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        with Ell14Emulator(link=cfg["stage"]["port"], speed_factor=4) as ell, \
                GrblEmulator(link=cfg["turntable"]["port"], speed_factor=20) as grbl:
            yield ell, grbl


def home_turntable(capsys) -> None:
    """The operator's command: ``polrig home turntable --config rig-emulated.toml``."""
    assert main(["home", "turntable", "--config", str(CONFIG)]) == 0
    assert "turntable: homed" in capsys.readouterr().out


def test_reference_capture_on_the_emulated_rig(tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("GENICAM_GENTL64_PATH", os.path.dirname(genicam.__file__))
    out = tmp_path / "session"
    with emulated_rig_ports() as (ell, grbl):
        home_turntable(capsys)
        code = main(["capture", "--poses", "0,90", "--mode", "reference",
                     "--config", str(CONFIG), "--out", str(out)])
        said = capsys.readouterr()
        assert code == 0, said.err
        assert grbl.axis_position("A") == pytest.approx(90.0, abs=1e-3)
    assert f"session complete: 2 captures in {out}" in said.out

    manifest = json.loads((out / "session.json").read_text())
    assert manifest["status"] == "complete"
    caps = manifest["captures"]
    assert [c["pose_deg"] for c in caps] == [0.0, 90.0]
    assert all(c["status"] == "complete" and c["attempts"] == 1 for c in caps)
    assert manifest["rig"]["camera_frames"]["layout"] == "imx250mzr"

    for cap in caps:
        folder = out / cap["name"]
        raws = sorted((folder / "raw").glob("*.png"))
        assert len(raws) == 4  # states 0, 45, 90, 135, one frame each
        frames = [read_raw(p) for p in raws]
        ids = []
        for p, f in zip(raws, frames):
            side = json.loads(p.with_name(p.name + ".json").read_text())
            assert side["pixel_format"] == "Mono8" and side["bit_depth"] == 8
            assert f.raw.dtype == np.uint8 and f.raw.shape == (400, 400)
            ids.append(side["frame_id"])
        # free run: after each stage move, the 2 declared settle frames were discarded
        ids = sorted(ids)  # acquisition order (serpentine: odd poses visit the states backwards)
        assert all(b - a >= 3 for a, b in zip(ids, ids[1:])), ids

        m = read_mueller_exr(folder / "mueller.exr")
        assert m.metadata["capture"] == cap["name"] and m.metadata["mode"] == "reference"
        assert m.mueller.shape == (1, 3, 3, 200, 200)  # mono, superpixel: half resolution
        mask = np.asarray(m.extra["mask.Y"]).astype(np.int64)
        # every superpixel whose 2x2 samples are clipped (code 255) in all four states is
        # masked as saturated; none without a clipped sample is
        blocks = np.stack([f.raw.reshape(200, 2, 200, 2) == 255 for f in frames])
        all_clipped = blocks.all(axis=(0, 2, 4))
        any_clipped = blocks.any(axis=(0, 2, 4))
        assert all_clipped.mean() > 0.9  # the white test pattern
        assert (mask[all_clipped] & SATURATED).all()
        assert not (mask[~any_clipped] & SATURATED).any()


def test_a_limit_switch_stops_the_capture_until_the_operator_homes(tmp_path, monkeypatch,
                                                                  capsys):
    """Something in the way of the turntable between pose 0 and pose 90: the limit switch
    fires (ALARM:1) on the way to 90; the capture stops with one line naming the home command
    and the resume, the session interrupted, capture 0 intact; no $H from the capture, nor
    from a resume tried before the operator homed (it stops again at once); the operator
    clears the way and homes it, and the resume completes."""
    monkeypatch.setenv("GENICAM_GENTL64_PATH", os.path.dirname(genicam.__file__))
    out = tmp_path / "session"
    home_cmd = f"polrig home turntable --config {CONFIG}"
    with emulated_rig_ports() as (ell, grbl):
        home_turntable(capsys)
        grbl.obstacle = ("A", 45.0)
        sent = len(grbl.received)
        code = main(["capture", "--poses", "0,90", "--mode", "reference", "--no-progress",
                     "--config", str(CONFIG), "--out", str(out)])
        said = capsys.readouterr()
        assert code == 1, said.err
        stop = [ln for ln in said.err.splitlines() if ln.startswith("polrig: error:")]
        assert len(stop) == 1, said.err  # one line says it all
        assert f"`{home_cmd}`" in stop[0] and "ALARM:1" in stop[0]
        assert "something may be in the way" in stop[0]
        assert stop[0].endswith(f"polrig capture --out {out} --resume --config {CONFIG}")
        assert b"$H" not in grbl.received[sent:]
        assert grbl.axis_position("A") == pytest.approx(45.0) and grbl.critical
        manifest = json.loads((out / "session.json").read_text())
        assert manifest["status"] == "interrupted"
        assert home_cmd in manifest["status_reason"]
        assert [c["status"] for c in manifest["captures"]] == ["complete", "failed"]

        # resumed before the operator homed: stopped again at once, still no $H
        sent = len(grbl.received)
        assert main(["capture", "--out", str(out), "--resume", "--config", str(CONFIG),
                     "--no-progress"]) == 1
        assert home_cmd in capsys.readouterr().err
        assert b"$H" not in grbl.received[sent:]

        grbl.obstacle = None  # the operator clears the way,
        home_turntable(capsys)  # homes the turntable,
        sent = len(grbl.received)
        code = main(["capture", "--out", str(out), "--resume", "--config", str(CONFIG)])
        said = capsys.readouterr()
        assert code == 0, said.err
        assert b"$H" not in grbl.received[sent:]
        assert grbl.axis_position("A") == pytest.approx(90.0, abs=1e-3)
    assert f"session complete: 2 captures in {out}" in said.out
    manifest = json.loads((out / "session.json").read_text())
    assert manifest["status"] == "complete"
    assert all(c["status"] == "complete" for c in manifest["captures"])
    assert (out / manifest["captures"][1]["name"] / "mueller.exr").is_file()


# -- Mono8 of a 12-bit ADC through the radiometry: clipping and rounding ------------------
@pytest.mark.parametrize("signal_dn", [300.0, 1000.0])
def test_mono8_noise_is_predicted_with_its_rounding(signal_dn):
    """Flat fields from the 12-bit noise model, delivered as Mono8 (the ADC's top 8 bits, as
    a camera's Mono8 output of a 12-bit sensor): the variance the radiometry predicts
    matches the variance of the samples, rounding to 16-DN codes included (without it the
    prediction is 17 % low at 300 DN)."""
    model = SensorModel()
    rng = np.random.default_rng(7)
    raw12 = model.sample_raw(np.full((200, 200), signal_dn * model.gain_e_per_dn), rng, 1000.0)
    mono8 = (raw12 >> 4).astype(np.uint8)
    step = adc_scale(model, 8)
    assert step == 16.0
    state = state_radiance([[mono8.astype(np.float64) * step]], [1000.0], model,
                           code_step_dn=step)
    measured = float(np.var(state.signal_dn))
    predicted = float(np.mean(state.variance_dn2))
    assert predicted == pytest.approx(measured, rel=0.05)
    assert not state.excluded.any()


def test_mono8_top_code_is_saturated():
    """Code 255 of Mono8 is 4080 DN, below the 12-bit saturation threshold (4095 - 5 read
    noise sigmas - 1): such samples are clipped all the same and excluded."""
    model = SensorModel()
    assert 255 * 16 < model.saturation_dn
    frame = np.array([[255, 254], [0, 128]], dtype=np.float64) * 16
    state = state_radiance([[frame]], [1000.0], model, code_step_dn=16.0)
    assert state.excluded.tolist() == [[True, False], [False, False]]
