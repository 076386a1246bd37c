"""Every driver call on a device that was never opened raises the project's not-open error
(DeviceDisconnected: "... not open ..."), never an untyped Python error (Ell14Stage.move_to
raised ZeroDivisionError) and never a wait on a port that is not there: every timeout a call
could wait on is set to :data:`WAIT_S`, longer than the test's own timeout, so a wait fails the
test (no wall-clock assertion, which a loaded machine can break)."""

from __future__ import annotations

import pytest

from polrig.drivers.dc2200 import Dc2200Light
from polrig.drivers.ell14 import Ell14Stage
from polrig.drivers.emulators.dc2200 import Dc2200Emulator
from polrig.drivers.genicam_camera import GenicamCamera
from polrig.drivers.grbl import GrblTurntable
from polrig.drivers.k10cr1 import K10cr1Stage
from polrig.errors import DeviceDisconnected

pytestmark = pytest.mark.timeout(20)
#: Every reply, grab and fetch timeout of the devices below (s): past the test's timeout.
WAIT_S = 60.0

AXIS_CALLS = ["info()", "position_deg()", "move_to(5.0)", "move_to(5.0, wait=False)", "home()",
              "is_busy()", "stop()", "capabilities", "move_time_s(0.0, 90.0)",
              "calculate_timeout(90.0)"]
CASES = (
    [("ell14", lambda p: Ell14Stage(p, reply_timeout_s=WAIT_S), c) for c in AXIS_CALLS + ["status_code()"]]
    + [("k10cr1", lambda p: K10cr1Stage(p, reply_timeout_s=WAIT_S), c) for c in AXIS_CALLS + ["status_bits()"]]
    + [("grbl", lambda p: GrblTurntable(p, reply_timeout_s=WAIT_S), c) for c in AXIS_CALLS + ["status()", "unlock()"]]
    + [("dc2200", lambda p: Dc2200Light(backend=Dc2200Emulator(), timeout_s=WAIT_S), c)
       for c in ["info()", "set_on(True)", "set_level(0.5)", "status()"]]
    + [("genicam", lambda p: GenicamCamera(p), c)
       for c in ["info()", "grab(WAIT_S)", "fetch(WAIT_S)", "roi", "pixel_format", "start()",
                 "set_exposure_us(100.0)", "set_trigger('free')", "capabilities"]]
)


@pytest.mark.parametrize("name, make, call", CASES, ids=[f"{n}.{c}" for n, _, c in CASES])
def test_calls_before_open(tmp_path, name, make, call):
    device = make(str(tmp_path / "never-opened"))
    with pytest.raises(DeviceDisconnected, match="not open"):
        eval(f"device.{call}")  # noqa: S307 - the call names above
