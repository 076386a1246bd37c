"""GenICam camera driver against the GenTL producer shipped in the genicam wheel (viky.cti)."""

from __future__ import annotations

import signal
import time
from pathlib import Path

import genicam
import numpy as np
import pytest

from polrig.acquisition import hal
from polrig.drivers.genicam_camera import (
    GenicamCamera,
    gentl_paths_from_env,
    list_gentl_devices,
)
from polrig.errors import (
    ConfigError,
    DeviceDisconnected,
    DeviceFault,
    DeviceNotFound,
    DeviceTimeout,
    FormatError,
)
from polrig.sensor.layouts import get_layout

pytestmark = pytest.mark.timeout(60)
VIKY = str(Path(genicam.__file__).parent / "viky.cti")


@pytest.fixture(scope="module")
def viky():
    if not Path(VIKY).is_file():
        pytest.fail(f"viky.cti missing from the genicam wheel at {VIKY}")
    return VIKY


@pytest.fixture
def cam(viky):
    c = GenicamCamera(viky, serial="1", pixel_format="Mono8", frame_rate_hz=200.0,
                      roi=(120, 100, 0, 0))
    with c:
        yield c


def test_lists_the_three_viky_devices(viky, monkeypatch):
    devs = list_gentl_devices([viky])
    assert [d.serial for d in devs] == ["0", "1", "2"]
    assert all(d.model == "Viky" for d in devs)
    monkeypatch.setenv("GENICAM_GENTL64_PATH", str(Path(viky).parent))
    assert VIKY in gentl_paths_from_env()


def test_configure_and_stream_100_frames(cam):
    assert cam.info().serial == "1" and cam.info().model == "Viky"
    assert cam.pixel_format == "Mono8" and cam.roi == (120, 100, 0, 0)
    frames = list(cam.frames(100, timeout_s=2.0))
    assert len(frames) == 100
    ids = [f.meta.frame_id for f in frames]
    assert ids == sorted(ids) and len(set(ids)) == 100
    f = frames[-1]
    assert f.raw.shape == (100, 120) and f.raw.dtype == np.uint8
    assert f.meta.bit_depth == 8 and f.meta.layout == "imx250mzr" and f.meta.host_timestamp
    get_layout(f.meta.layout, *f.meta.offset_xy)
    # copies, not views of re-queued buffers: frames differ in identity and survive
    assert not np.shares_memory(frames[0].raw, frames[1].raw)
    assert f.raw.flags.owndata or f.raw.base is not None


def test_fetch_timeout_then_recover(cam):
    """A grab with no frame within its timeout raises DeviceTimeout once the timeout has run
    (the next frame, half a second away, would have ended a longer wait without an error),
    then the camera streams again."""
    cam.set_frame_rate_hz(2.0)
    cam.grab(timeout_s=3.0)  # one frame, the next is half a second away
    t0 = time.monotonic()
    with pytest.raises(DeviceTimeout, match=r"no frame within 0\.2 s"):
        cam.grab(timeout_s=0.2)
    assert time.monotonic() - t0 >= 0.19  # waited its timeout (less the producer's ms rounding)
    cam.set_frame_rate_hz(200.0)
    assert cam.grab(timeout_s=2.0).raw.shape == (100, 120)


def test_stopped_stream_times_out_then_restarts(cam):
    cam.grab(timeout_s=2.0)
    cam.stop()
    with pytest.raises(DeviceTimeout):
        cam.fetch(timeout_s=0.2)
    cam.start()
    assert cam.grab(timeout_s=2.0).raw.size == 120 * 100


def test_missing_features_are_named(cam):
    assert np.isnan(cam.exposure_us)
    with pytest.raises(DeviceFault, match="ExposureTime"):
        cam.set_exposure_us(1000.0)
    with pytest.raises(ConfigError, match="no TriggerMode/TriggerSoftware feature"):
        cam.set_trigger("software")
    with pytest.raises(ConfigError, match="'sometimes' is not supported"):
        cam.set_trigger("sometimes")
    with pytest.raises(DeviceFault, match="not offered"):
        cam.set_pixel_format("Mono12p")
    with pytest.raises(DeviceFault, match="Width"):
        cam.set_roi(10, 10)  # below the camera's minimum


def test_non_mosaic_format_is_a_format_error(viky):
    with GenicamCamera(viky, serial="2", pixel_format="RGBa8", frame_rate_hz=200.0,
                       roi=(100, 100, 0, 0)) as c:
        with pytest.raises(FormatError, match="RGBa8"):
            c.grab(timeout_s=2.0)
        c.set_pixel_format("Mono8")
        assert c.grab(timeout_s=2.0).raw.shape == (100, 100)


def test_opening_a_camera_keeps_the_processs_ctrl_c(viky):
    """harvesters installs its own SIGINT handler when it creates an image acquirer (it
    destroys the acquirer and swallows the interrupt); polrig keeps the process's, so an
    operator's Ctrl-C still stops a capture."""
    mine = lambda signum, frame: None  # noqa: E731
    previous = signal.signal(signal.SIGINT, mine)
    try:
        with GenicamCamera(viky, serial="0", pixel_format="Mono8", frame_rate_hz=200.0) as c:
            assert signal.getsignal(signal.SIGINT) is mine
            c.grab(timeout_s=2.0)
        assert signal.getsignal(signal.SIGINT) is mine
    finally:
        signal.signal(signal.SIGINT, previous)


def test_close_reopen_and_errors(viky, tmp_path):
    c = GenicamCamera(viky, serial="0", pixel_format="Mono8", frame_rate_hz=200.0)
    c.open()
    with pytest.raises(DeviceNotFound):  # one camera, one owner
        GenicamCamera(viky, serial="0").open()
    c.close()
    c.close()
    c.open()
    assert c.grab(timeout_s=2.0).raw.shape == (400, 400)
    c.close()
    with pytest.raises(DeviceNotFound, match="not found"):
        GenicamCamera(str(tmp_path / "missing.cti")).open()
    with pytest.raises(DeviceNotFound, match="serial '42'"):
        GenicamCamera(viky, serial="42").open()
    with pytest.raises(DeviceNotFound, match="index 7"):
        GenicamCamera(viky, index=7).open()


def test_vanished_device(viky):
    c = GenicamCamera(viky, serial="1", pixel_format="Mono8", frame_rate_hz=200.0)
    c.open()
    c._ia.destroy()  # the producer drops the device under the driver
    with pytest.raises(DeviceDisconnected):
        c.grab(timeout_s=1.0)
    assert not c.is_open
    c.open()
    assert c.grab(timeout_s=2.0).raw.ndim == 2
    c.close()


def test_two_cameras_of_one_producer(viky):
    """A second camera of the same producer in one process opens (it failed with 'no
    camera with serial '0'; the producer offers no devices'), and listing the producer
    while they are open shows its devices (it returned [])."""
    c1 = GenicamCamera(viky, serial="1", pixel_format="Mono8", frame_rate_hz=200.0)
    c2 = GenicamCamera(viky, serial="0", pixel_format="Mono8", frame_rate_hz=200.0)
    with c1, c2:
        assert c1.grab(timeout_s=2.0).meta.extra["serial"] == "1"
        assert c2.grab(timeout_s=2.0).meta.extra["serial"] == "0"
        assert [d.serial for d in list_gentl_devices([viky])] == ["0", "1", "2"]
        with pytest.raises(DeviceNotFound, match="serial '0' is already open"):
            GenicamCamera(viky, serial="0").open()
        c2.close()
        assert c1.grab(timeout_s=2.0).raw.ndim == 2
    assert [d.serial for d in list_gentl_devices([viky])] == ["0", "1", "2"]


def test_a_file_that_is_not_a_producer(tmp_path):
    """Not a GenTL producer: said so (it was 'no camera with serial ...; the producer offers
    no devices'). A shared library without GCInitLib is refused before the GenTL loader,
    which crashes the process on one."""
    text = tmp_path / "notes.cti"
    text.write_text("not a shared library\n")
    with pytest.raises(DeviceNotFound, match="is not a loadable GenTL producer"):
        GenicamCamera(str(text), serial="0").open()
    with pytest.raises(DeviceNotFound, match="is not a loadable GenTL producer"):
        list_gentl_devices([str(text)])
    import _ctypes
    so = _ctypes.__file__  # a shared library (an extension module), not a producer
    with pytest.raises(DeviceNotFound, match="without the GenTL entry point GCInitLib"):
        GenicamCamera(so, serial="0").open()


def test_producer_held_by_other_code_in_the_process(viky):
    """Some other code of this process initialised the producer: said so."""
    from harvesters.core import Harvester
    h = Harvester()
    h.add_file(viky)
    h.update()
    try:
        with pytest.raises(DeviceNotFound, match="in use elsewhere in this process"):
            GenicamCamera(viky, serial="0").open()
    finally:
        h.reset()
    with GenicamCamera(viky, serial="0") as c:
        assert c.info().serial == "0"


@pytest.mark.parametrize("timeout", [0, -1.0, float("nan"), float("inf")])
def test_non_positive_frame_timeouts_are_refused(cam, timeout):
    """harvesters waits forever for fetch(timeout <= 0): the driver refuses them (grab(0)
    blocked). A call that waited instead would run into the module's 60 s test timeout."""
    for call in (cam.grab, cam.fetch, lambda t: list(cam.frames(1, t))):
        with pytest.raises(ValueError, match="positive, finite number of seconds"):
            call(timeout)
    assert cam.grab(timeout_s=2.0).raw.shape == (100, 120)


# -- capabilities, as the Viky producer's node map declares them -------------------------
def test_capabilities_of_a_camera_without_trigger_or_exposure_features(cam):
    """Viky has no TriggerMode/TriggerSoftware and no ExposureTime[Abs]: free run only, no
    exposure control (a plan's exposure is refused), the readout is one frame period at its
    AcquisitionFrameRate (it has no SensorReadoutTime or ResultingFrameRate)."""
    nm = cam._ia.remote_device.node_map
    assert not any(nm.has_node(n) for n in ("TriggerMode", "TriggerSoftware", "ExposureTime",
                                            "ExposureTimeAbs", "SensorReadoutTime",
                                            "ResultingFrameRate"))
    caps = cam.capabilities
    assert isinstance(caps, hal.CameraCapabilities)
    assert caps.trigger_modes == ("free",) and caps.preferred_trigger == "free"
    assert caps.exposure_range_us == (0.0, 0.0)
    with pytest.raises(ConfigError, match=r"outside the camera's range \[0, 0\]"):
        caps.check_exposure(1000.0)
    assert nm.get_node("AcquisitionFrameRate").value == pytest.approx(200.0)
    assert caps.readout_us == pytest.approx(1e6 / 200.0)
    assert caps.settle_frames == 2
    # nor SensorWidth/SensorHeight or WidthMax/HeightMax: the sensor size is not declared
    assert not any(nm.has_node(n) for n in ("SensorWidth", "SensorHeight", "WidthMax",
                                            "HeightMax"))
    assert caps.sensor_size is None
    cam.set_trigger("free")  # free run works without TriggerMode
    assert cam.trigger == "free" and cam.grab(timeout_s=2.0).raw.shape == (100, 120)


def test_capabilities_follow_the_settings(cam):
    """The readout is re-read after a setting changes (here the frame rate), and the grab
    timeout of the HAL follows it."""
    cam.set_frame_rate_hz(20.0)
    assert cam.capabilities.readout_us == pytest.approx(50_000.0)
    assert hal.grab_timeout_s(cam, 1.0) == pytest.approx(1.0 + 0.05)  # no exposure: NaN
    cam.set_frame_rate_hz(200.0)
    assert cam.capabilities.readout_us == pytest.approx(5_000.0)


def test_a_configured_software_trigger_is_refused_on_open(viky):
    """A rig configuration asking a free-run-only camera for software trigger fails on
    open with one line (and leaves the camera closed)."""
    c = GenicamCamera(viky, serial="0", pixel_format="Mono8", trigger="software")
    with pytest.raises(ConfigError, match="'software' is not supported"):
        c.open()
    assert not c.is_open
    with GenicamCamera(viky, serial="0", pixel_format="Mono8") as again:
        assert again.capabilities.trigger_modes == ("free",)


# -- capabilities from GenApi node maps of cameras Viky does not imitate -------------------
# Camera descriptions (GenApi XML, schema 1.1) evaluated by the real GenApi of the genicam
# wheel; values are constants (no register port needed), feature names per SFNC.
_XML_HEAD = (
    '<?xml version="1.0" encoding="utf-8"?>'
    '<RegisterDescription ModelName="Test" VendorName="polrig" ToolTip="" StandardNameSpace='
    '"None" SchemaMajorVersion="1" SchemaMinorVersion="1" SchemaSubMinorVersion="0" '
    'MajorVersion="1" MinorVersion="0" SubMinorVersion="0" ProductGuid="11111111-2222-3333-'
    '4444-555555555555" VersionGuid="11111111-2222-3333-4444-555555555556" xmlns="http://www.'
    'genicam.org/GenApi/Version_1_1" xmlns:xsi="http://www.w3.org/2001/XMLSchema-instance" '
    'xsi:schemaLocation="http://www.genicam.org/GenApi/Version_1_1 http://www.genicam.org/'
    'GenApi/GenApiSchema_Version_1_1.xsd">')


def _float(name, value, lo=0.0, hi=1e9):
    return (f'<Float Name="{name}" NameSpace="Standard"><Value>{value}</Value><Min>{lo}</Min>'
            f'<Max>{hi}</Max></Float>')


def _int(name, value):
    return (f'<Integer Name="{name}" NameSpace="Standard"><Value>{value}</Value><Min>0</Min>'
            f'<Max>100000</Max></Integer>')


_TRIGGER_MODE = ('<Enumeration Name="TriggerMode" NameSpace="Standard"><EnumEntry Name="Off">'
                 '<Value>0</Value></EnumEntry><EnumEntry Name="On"><Value>1</Value></EnumEntry>'
                 '<Value>0</Value></Enumeration>')
_TRIGGER_SOFTWARE = ('<Command Name="TriggerSoftware" NameSpace="Standard"><Value>0</Value>'
                     '<CommandValue>1</CommandValue></Command>')


def node_map(*nodes: str):
    from genicam.genapi import NodeMap

    names = [n.split('Name="')[1].split('"')[0] for n in nodes]
    root = ('<Category Name="Root" NameSpace="Standard">'
            + "".join(f"<pFeature>{n}</pFeature>" for n in names) + "</Category>")
    nm = NodeMap()
    nm.load_xml_from_string(_XML_HEAD + root + "".join(nodes) + "</RegisterDescription>")
    return nm


def test_capabilities_of_an_sfnc_camera():
    """TriggerMode + TriggerSoftware: both modes, software preferred; the ExposureTime range;
    SensorReadoutTime wins over the frame period."""
    from polrig.drivers.genicam_camera import capabilities_from_node_map

    nm = node_map(_TRIGGER_MODE, _TRIGGER_SOFTWARE, _float("ExposureTime", 10000, 20, 3e7),
                  _float("SensorReadoutTime", 8000), _float("AcquisitionFrameRate", 20),
                  _int("SensorWidth", 2448), _int("SensorHeight", 2048),
                  _int("WidthMax", 1224), _int("HeightMax", 1024))
    caps = capabilities_from_node_map(nm)
    assert caps.trigger_modes == ("software", "free") and caps.preferred_trigger == "software"
    assert caps.exposure_range_us == (20.0, 3e7) and caps.readout_us == 8000.0
    # the sensor's own size (SFNC SensorWidth/SensorHeight) wins over WidthMax/HeightMax
    assert caps.sensor_size == (2448, 2048)
    caps.check_exposure(20.0)
    with pytest.raises(ConfigError, match=r"\[20, 3e\+07\]"):
        caps.check_exposure(19.0)


def test_capabilities_of_an_older_gige_camera():
    """ExposureTimeAbs (pre-SFNC 2.0); a TriggerMode without TriggerSoftware is no software
    trigger; the readout is one period at the ResultingFrameRate (the rate it runs at),
    not the AcquisitionFrameRate asked for."""
    from polrig.drivers.genicam_camera import (
        capabilities_from_node_map,
        exposure_feature,
    )

    nm = node_map(_TRIGGER_MODE, _float("ExposureTimeAbs", 5000, 35, 1e6),
                  _float("AcquisitionFrameRate", 30), _float("ResultingFrameRate", 22.5),
                  _int("WidthMax", 2448), _int("HeightMax", 2048), _int("SensorWidth", 2448))
    caps = capabilities_from_node_map(nm)
    assert exposure_feature(nm) == "ExposureTimeAbs"
    assert caps.trigger_modes == ("free",) and caps.exposure_range_us == (35.0, 1e6)
    assert caps.readout_us == pytest.approx(1e6 / 22.5)
    # no SensorHeight (half a pair is no size): the largest image, WidthMax x HeightMax
    assert caps.sensor_size == (2448, 2048)


def test_capabilities_of_a_camera_that_says_nothing():
    from polrig.drivers.genicam_camera import (
        capabilities_from_node_map,
        exposure_feature,
    )

    nm = node_map(_float("Gain", 0.0))
    caps = capabilities_from_node_map(nm)
    assert exposure_feature(nm) is None
    assert caps.trigger_modes == ("free",) and caps.exposure_range_us == (0.0, 0.0)
    assert caps.readout_us == 0.0 and caps.settle_frames == 2
    assert caps.sensor_size is None
