"""Simulated devices obey polrig.acquisition.hal and share one world (polrig.sim.devices)."""

from __future__ import annotations

import numpy as np
import pytest

from polrig.acquisition import hal
from polrig.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceFault,
    DeviceTimeout,
    FormatError,
    ProtocolError,
)
from polrig.optics.mueller import estimate_linear
from polrig.sensor.layouts import get_layout
from polrig.sim import create_sim_rig
from polrig.sim.clock import SimClock
from polrig.sim.motion import Move

VIRTUAL = float("inf")


def _rig(**kw):
    opts = {"size": (64, 48), "clock_speed": VIRTUAL, "noise": False}
    opts.update(kw)
    return create_sim_rig(opts)


def _signal(frame, rig):
    m = rig.world.sensor.model
    dark = m.dark_electrons(frame.meta.exposure_us) / rig.world.sensor.gained_model(
        frame.meta.gain_db).gain_e_per_dn
    return frame.raw.astype(np.float64) - m.black_level_dn - dark


def test_devices_implement_the_hal_interfaces():
    rig = _rig()
    assert isinstance(rig.camera, hal.Camera)
    assert isinstance(rig.stage, hal.RotationStage) and not isinstance(rig.stage, hal.Turntable)
    assert isinstance(rig.turntable, hal.Turntable)
    assert isinstance(rig.light, hal.Light)
    for kind, dev in rig.devices.items():
        assert dev.is_open
        info = dev.info()
        assert info.kind == kind and info.driver == "sim"
    rig.close()
    assert not any(d.is_open for d in rig.devices.values())
    with pytest.raises(DeviceDisconnected, match="not open"):
        rig.camera.grab()
    rig.close()  # twice is fine
    with rig:
        assert rig.camera.grab().raw.shape == (48, 64)


def test_motion_takes_time_on_the_clock():
    rig = _rig()
    clock = rig.world.clock
    t0 = clock.now()
    rig.stage.move_to(90.0)
    v, a = rig.stage.speed_deg_s, rig.stage.accel_deg_s2
    assert clock.now() - t0 == pytest.approx(90.0 / v + v / a)
    assert rig.stage.position_deg() == pytest.approx(90.0)
    # without waiting: busy, between the ends, then done
    rig.turntable.move_to(30.0, wait=False)
    assert rig.turntable.is_busy()
    clock.sleep(1.0)
    p = rig.turntable.position_deg()
    assert 0.0 < p < 30.0
    rig.turntable.wait()
    assert not rig.turntable.is_busy() and rig.turntable.position_deg() == pytest.approx(30.0)
    # stop halts where it is
    rig.turntable.move_to(90.0, wait=False)
    clock.sleep(2.0)
    rig.turntable.stop()
    p = rig.turntable.position_deg()
    clock.sleep(5.0)
    assert rig.turntable.position_deg() == p and 30.0 < p < 90.0
    # a move longer than the timeout is stopped, then DeviceTimeout (as the drivers do)
    with pytest.raises(DeviceTimeout, match="; stopped"):
        rig.turntable.move_to(-300.0, timeout_s=2.0)
    assert not rig.turntable.is_busy()
    p = rig.turntable.position_deg()
    clock.sleep(5.0)
    assert rig.turntable.position_deg() == p and -300.0 < p < 90.0
    rig.turntable.home(timeout_s=100.0)
    assert rig.turntable.position_deg() == 0.0


def test_accelerated_real_time_clock():
    clock = SimClock(speed=2000.0)
    t0 = clock.now()
    clock.sleep(4.0)  # 2 ms of wall time
    assert clock.now() - t0 >= 4.0
    m = Move(0.0, 2.0, 0.0, 20.0, 100.0)  # too short to reach 20 deg/s: triangular profile
    assert m.duration_s == pytest.approx(2 * np.sqrt(2.0 / 100.0))
    assert m.position(m.duration_s / 2) == pytest.approx(1.0)
    m = Move(0.0, -10.0, 0.0, 20.0, 100.0)  # trapezoid: 10/20 s cruise-equivalent + v/a
    assert m.duration_s == pytest.approx(0.7)
    assert m.position(0.1) == pytest.approx(-0.5 * 100.0 * 0.01)
    with pytest.raises(ValueError):
        SimClock(0.0)


def test_stage_changes_the_incident_state_the_camera_sees():
    rig = _rig(hidden={"ideal_analyzer": True})
    frames = {}
    for a in (0.0, 45.0, 90.0, 135.0):
        rig.stage.move_to(a)
        f = rig.camera.grab()
        assert f.meta.extra["sim"]["stage_deg"] == pytest.approx(a)
        frames[a] = _signal(f, rig)
    assert np.abs(frames[0.0] - frames[90.0]).max() > 50
    # the four states through the ideal analyzers: a 16-pixel superpixel cell sees M
    # consistent with the truth (mean over a flat-ish region is not needed: per pixel
    # I_p(state) = rows_p . M_p S_in(state), so the truth predicts every frame)
    truth = rig.truth.ground_truth()["mueller"].astype(np.float64)
    rows = rig.world.sensor.analyzer.rows()
    cmap = rig.world.sensor.analyzer.colour_map()
    m_pix = np.take_along_axis(truth, cmap[None, None, None], axis=0)[0]  # (3, 3, H, W)
    for a, sig in frames.items():
        s_in = rig.world.generator.incident_stokes(a)
        pred = np.einsum("hwi,ijhw,j->hw", rows, m_pix, s_in)
        np.testing.assert_allclose(sig, pred, atol=0.51)  # rounding to integer codes


def test_turntable_rotates_the_object():
    rig = _rig(scene="box")
    m0 = rig.truth.ground_truth()["object_index"] == 0  # the box (the floor stays)
    raw0 = rig.camera.grab().raw
    rig.turntable.move_to(35.0)
    m1 = rig.truth.ground_truth()["object_index"] == 0
    raw1 = rig.camera.grab().raw
    assert (m0 != m1).sum() > 30 and m0.sum() > 100
    assert np.abs(raw0.astype(int) - raw1).max() > 100
    assert rig.truth.ground_truth()["turntable_deg"] == pytest.approx(35.0)


def test_light_level_scales_the_image_linearly():
    rig = _rig()
    rig.camera.set_exposure_us(5000.0)
    full = _signal(rig.camera.grab(), rig)
    rig.light.set_level(0.25)
    assert rig.light.status()["level"] == 0.25
    quarter = _signal(rig.camera.grab(), rig)
    bright = full > 200
    np.testing.assert_allclose(quarter[bright], 0.25 * full[bright], atol=0.75)
    rig.light.set_on(False)
    assert not rig.light.status()["on"]
    np.testing.assert_allclose(_signal(rig.camera.grab(), rig), 0.0, atol=0.5)
    with pytest.raises(ValueError):
        rig.light.set_level(1.5)
    with pytest.raises(ValueError):
        rig.light.set_level(float("nan"))
    with pytest.raises(ValueError):
        rig.stage.move_to(float("nan"))
    with pytest.raises(ConfigError):
        rig.camera.set_exposure_us(float("nan"))
    # the truth follows the light level and the exposure linearly
    rig.light.set_on(True)
    t_quarter = rig.truth.ground_truth()["mueller"]
    rig.light.set_level(1.0)
    rig.camera.set_exposure_us(10000.0)
    np.testing.assert_allclose(rig.truth.ground_truth()["mueller"], 8.0 * t_quarter, rtol=1e-5)


def test_roi_offset_shifts_the_mosaic_phase():
    rig = _rig()
    full = rig.camera.grab().raw
    rig.camera.set_roi(40, 20, 3, 6)
    f = rig.camera.grab()
    np.testing.assert_array_equal(f.raw, full[6:26, 3:43])
    assert f.meta.offset_xy == (3, 6) and f.meta.layout == "imx250myr"
    lay = get_layout(f.meta.layout, *f.meta.offset_xy)
    np.testing.assert_array_equal(lay.angle_map(f.raw.shape),
                                  get_layout("imx250myr").angle_map(full.shape)[6:26, 3:43])
    gt = rig.truth.ground_truth()
    assert gt["mueller"].shape == (3, 3, 3, 20, 40) and gt["roi"] == (40, 20, 3, 6)
    with pytest.raises(ConfigError):
        rig.camera.set_roi(64, 48, 1, 0)


def test_pixel_formats_exposure_and_gain():
    rig = _rig()
    f12 = rig.camera.grab()
    assert f12.meta.pixel_format == "Mono12p" and f12.raw.dtype == np.uint16
    rig.camera.set_pixel_format("Mono8")
    f8 = rig.camera.grab()
    assert f8.raw.dtype == np.uint8 and f8.meta.bit_depth == 8
    assert np.abs(f8.raw.astype(float) - f12.raw / 16.0).max() <= 0.5 + 1e-9
    rig.camera.set_pixel_format("BayerRGPolarized16")
    f16 = rig.camera.grab()
    assert f16.raw.dtype == np.uint16 and f16.meta.black_level_dn == 16 * f12.meta.black_level_dn
    assert np.abs(f16.raw.astype(float) - f12.raw * 16.0).max() <= 0.5
    with pytest.raises(FormatError):
        rig.camera.set_pixel_format("PolarizedAngles_0d_45d_90d_135d_Mono8")
    with pytest.raises(FormatError):
        rig.camera.set_pixel_format("NoSuchFormat")
    mono = _rig(sensor="imx250mzr")
    with pytest.raises(FormatError, match="mono"):
        mono.camera.set_pixel_format("BayerRGPolarized8")
    assert mono.camera.layout == "imx250mzr" and mono.truth.ground_truth()["mueller"].shape[0] == 1
    rig.camera.set_pixel_format("Mono12p")
    base = _signal(rig.camera.grab(), rig)
    rig.camera.set_gain_db(20.0 * np.log10(2.0))
    doubled = _signal(rig.camera.grab(), rig)
    ok = (base > 100) & (base < 1500)
    np.testing.assert_allclose(doubled[ok], 2 * base[ok], atol=1.5)
    with pytest.raises(ConfigError):
        rig.camera.set_exposure_us(-1)
    rig.camera.set_exposure_us(3_000_000)
    with pytest.raises(DeviceTimeout):
        rig.camera.grab(timeout_s=1.0)


@pytest.mark.parametrize("kind, error", [("timeout", DeviceTimeout), ("fault", DeviceFault),
                                         ("protocol", ProtocolError),
                                         ("disconnect", DeviceDisconnected)])
def test_fault_injection_raises_typed_errors(kind, error):
    rig = _rig()
    rig.inject_fault("stage", kind, after_calls=2)
    rig.stage.move_to(10.0)
    rig.stage.position_deg()
    rig.camera.grab()  # other devices are not affected
    with pytest.raises(error) as exc:
        rig.stage.move_to(20.0)
    assert "sim-stage" in str(exc.value)
    if kind == "fault":
        assert exc.value.code == 13
    if kind == "disconnect":
        assert not rig.stage.is_open
        with pytest.raises(DeviceDisconnected):
            rig.stage.position_deg()
        rig.stage.open()
    assert rig.stage.position_deg() == pytest.approx(10.0)  # one-shot, nothing moved
    rig.inject_fault("camera", kind)
    with pytest.raises(error):
        rig.camera.grab()
    with pytest.raises(ValueError):
        rig.inject_fault("laser", "timeout")
    with pytest.raises(ValueError):
        rig.inject_fault("camera", "explode")


def test_bad_options_give_config_errors():
    with pytest.raises(ConfigError, match="unknown"):
        create_sim_rig({"sceen": "sphere"})
    with pytest.raises(ConfigError, match="size"):
        create_sim_rig({"size": "12 by 4"})
    with pytest.raises(ConfigError, match="multiple"):
        create_sim_rig({"size": (30, 30)})
    with pytest.raises(ConfigError, match="hidden"):
        create_sim_rig({"hidden": {"secret": 1}})


@pytest.mark.parametrize("sensor", ["imx250myr", "imx250mzr"])
def test_noise_free_four_state_round_trip_recovers_the_truth(sensor):
    """Noise off: four polarizer states, per-pixel Stokes from the full-resolution analyzer
    images, least-squares Mueller (polrig.optics.mueller.estimate_linear) == truth to 1e-4."""
    rig = _rig(scene="multi", size=(96, 64), sensor=sensor)
    w = rig.world
    states = (0.0, 45.0, 90.0, 135.0)
    s_in = np.stack([w.generator.incident_stokes(a) for a in states])
    s_out = []
    for a in states:
        rig.stage.move_to(a)
        an = w.analyzer_images(w.turntable_angle_deg(), rig.stage.position_deg(),
                               rig.camera.exposure_us, rig.camera.gain_db)
        s_out.append(np.stack([an[:, 0] + an[:, 2], an[:, 0] - an[:, 2], an[:, 1] - an[:, 3]], 1))
    s = np.moveaxis(np.stack(s_out), (0, 2), (-2, -1)).astype(np.float64)  # (C, H, W, N, 3)
    m, cond = estimate_linear(s_in, s)
    est = np.moveaxis(m, (-2, -1), (1, 2))
    truth = rig.truth.ground_truth()
    t = truth["mueller"].astype(np.float64)
    lit = truth["lit"]
    scale = np.abs(t[..., lit]).max(axis=(1, 2), keepdims=True)
    rel = np.abs(est[..., lit] - t[..., lit]) / scale
    assert rel.max() < 1e-4
    assert cond < 3


def test_swapping_the_scene_drops_cached_images():
    from polrig.sim.scene import make_scene

    rig = _rig()
    before = rig.truth.ground_truth()["mask"].sum()
    rig.world.set_scene(make_scene("plane", 64, 48))
    after = rig.truth.ground_truth()["mask"].sum()
    assert before != after
    with pytest.raises(ValueError, match="sensor"):
        rig.world.set_scene(make_scene("plane", 32, 32))


def test_noise_is_keyed_by_condition_and_repeat_index():
    """A resumed session re-grabs the same frames: noise depends on (seed, pose, state,
    exposure, repeat index, earlier visits of the state since the turntable moved), not on how
    many frames were grabbed before; a resumed capture starts again from its turntable move."""
    from polrig.sim.devices import create_sim_rig

    def grab_two(detour: bool):
        rig = create_sim_rig({"size": (64, 64), "clock_speed": float("inf"), "seed": 3})
        with rig:
            if detour:  # an interrupted attempt grabbed and moved before
                rig.turntable.move_to(30)
                rig.stage.move_to(45)
                rig.camera.grab()
                rig.stage.move_to(90)
                rig.camera.grab()
            rig.turntable.move_to(30)
            rig.stage.move_to(45)
            return rig.camera.grab().raw, rig.camera.grab().raw

    a1, b1 = grab_two(False)
    a2, b2 = grab_two(True)
    assert np.array_equal(a1, a2) and np.array_equal(b1, b2)
    assert np.mean(a1 != b1) > 0.5  # repeated frames of one state have independent noise


def test_a_state_visited_twice_gets_independent_noise():
    """``--states 0,45,0``: the second visit to 0 deg is a new exposure, not a copy of the
    first (identical frames made the reference solve count one noise sample twice)."""
    from polrig.sim.devices import create_sim_rig

    def sweep():
        rig = create_sim_rig({"size": (64, 64), "clock_speed": float("inf"), "seed": 3})
        with rig:
            rig.turntable.move_to(30)
            frames = []
            for state in (0, 45, 0):
                rig.stage.move_to(state)
                frames.append(rig.camera.grab().raw)
            return frames

    first, _, second = sweep()
    assert np.mean(first != second) > 0.5
    assert all(np.array_equal(a, b) for a, b in zip(sweep(), sweep()))  # still reproducible
