"""The replay camera (polrig.sim.replay): recorded frames served with the simulated camera's timing."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.acquisition import hal
from polrig.errors import ConfigError
from polrig.sim import create_sim_rig
from polrig.sim.replay import ReplayCamera

STATES = (0.0, 45.0, 90.0, 135.0)


def _rig_and_replay():
    rig = create_sim_rig({"size": (64, 48), "clock_speed": float("inf"), "seed": 3})
    cam = ReplayCamera(rig.world, rig.faults, exposure_us=5000.0, readout_us=2000.0)
    cam.open()
    cam.record(STATES)
    return rig, cam


def test_replay_serves_the_recorded_frame_of_the_stage_state_at_any_pose():
    rig, cam = _rig_and_replay()
    assert isinstance(cam, hal.Camera)
    for j, angle in enumerate(STATES):
        rig.stage.move_to(angle)
        first = cam.grab().raw
        rig.turntable.move_to(30.0 * (j + 1))
        again = cam.grab().raw
        np.testing.assert_array_equal(first, again)
        np.testing.assert_array_equal(first, cam._recorded[angle])
    # the frames of different states differ (the recording is not one frame four times)
    assert not np.array_equal(cam._recorded[0.0], cam._recorded[90.0])
    # a state 180 deg away is the same polarizer state
    rig.stage.move_to(180.0 + 44.0)
    np.testing.assert_array_equal(cam.grab().raw, cam._recorded[45.0])


def test_replay_frames_take_exposure_plus_readout_on_the_clock():
    rig, cam = _rig_and_replay()
    t0 = rig.world.clock.now()
    frame = cam.grab()
    assert rig.world.clock.now() - t0 == pytest.approx((5000.0 + 2000.0) * 1e-6)
    assert frame.meta.exposure_us == 5000.0


def test_replay_refuses_settings_it_did_not_record_and_an_empty_recording():
    rig, cam = _rig_and_replay()
    cam.set_exposure_us(6000.0)
    with pytest.raises(ConfigError, match="recorded with exposure"):
        cam.grab()
    empty = ReplayCamera(rig.world, rig.faults)
    empty.open()
    with pytest.raises(ConfigError, match="nothing recorded"):
        empty.grab()
