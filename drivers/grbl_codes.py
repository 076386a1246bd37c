"""GRBL 1.1 error and alarm texts.

Sources: grbl/grbl ``doc/csv/error_codes_en_US.csv`` and ``doc/csv/alarm_codes_en_US.csv``
(the "message" column, with the description in parentheses where the message alone is
ambiguous, e.g. the two "Setting disabled" and "Probe fail" codes); ``doc/markdown/
interface.md``. Codes 18 and 19 are not used by GRBL 1.1.
"""

ERRORS = {
    1: "Expected command letter",
    2: "Bad number format",
    3: "Invalid statement",
    4: "Value < 0",
    5: "Setting disabled (homing is not enabled in the settings)",
    6: "Value < 3 usec (minimum step pulse time)",
    7: "EEPROM read fail. Using defaults",
    8: "Not idle",
    9: "G-code lock (alarm or jog state)",
    10: "Homing not enabled (soft limits need homing)",
    11: "Line overflow",
    12: "Step rate > 30kHz",
    13: "Check Door",
    14: "Line length exceeded",
    15: "Travel exceeded",
    16: "Invalid jog command",
    17: "Setting disabled (Laser mode requires PWM output)",
    20: "Unsupported command",
    21: "Modal group violation",
    22: "Undefined feed rate",
    23: "Invalid gcode ID:23 (command value not integer)",
    24: "Invalid gcode ID:24 (more than one g-code command that requires axis words)",
    25: "Invalid gcode ID:25 (repeated g-code word)",
    26: "Invalid gcode ID:26 (no axis words found in block)",
    27: "Invalid gcode ID:27 (line number invalid)",
    28: "Invalid gcode ID:28 (missing a required value word)",
    29: "Invalid gcode ID:29 (G59.x work coordinate systems not supported)",
    30: "Invalid gcode ID:30 (G53 only allowed with G0 and G1)",
    31: "Invalid gcode ID:31 (axis words found in block when no command uses them)",
    32: "Invalid gcode ID:32 (G2/G3 arcs need at least one in-plane axis word)",
    33: "Invalid gcode ID:33 (motion command target invalid)",
    34: "Invalid gcode ID:34 (arc radius value invalid)",
    35: "Invalid gcode ID:35 (G2/G3 arcs need at least one in-plane offset word)",
    36: "Invalid gcode ID:36 (unused value words found)",
    37: "Invalid gcode ID:37 (G43.1 dynamic tool length offset not assigned to configured "
        "tool length axis)",
    38: "Invalid gcode ID:38 (tool number greater than max supported value)",
}
ALARMS = {
    1: "Hard limit triggered (machine position likely lost: re-home)",
    2: "Soft limit (motion target exceeds machine travel; machine position retained)",
    3: "Reset while in motion (position lost)",
    4: "Probe fail (probe not in the expected initial state)",
    5: "Probe fail (probe did not contact the workpiece)",
    6: "Homing fail: reset during homing", 7: "Homing fail: door opened during homing",
    8: "Homing fail: pull-off failed to clear limit switch",
    9: "Homing fail: could not find limit switch",
}
#: Checked against grbl/grbl ``doc/csv/alarm_codes_en_US.csv`` (commit 5e3048f): 1 hard limit,
#: 2 soft limit, 3 abort during cycle (reset while in motion), 4-5 probe fail, 6-9 homing fail
#: (reset, door, pull-off, switch not found); ``report.c`` prints MESSAGE_CRITICAL_EVENT and
#: MESSAGE_ALARM_LOCK as below (GRBL 1.1 puts them in ``[MSG:...]``).
#: What each alarm means for the rig, in the operator's words (the message of the
#: :class:`polrig.errors.DeviceAlarm` the driver raises). Every GRBL alarm locks the
#: controller (G-code answered ``error:9``) until ``$H`` homes it or ``$X`` unlocks it
#: (interface.md, "Alarm messages"; ``[MSG:'$H'|'$X' to unlock]``); after a hard limit, a
#: reset in motion or a failed homing the position is lost and homing is the safe route
#: (alarm_codes_en_US.csv: "Re-homing is highly recommended").
ALARM_MEANINGS = {
    1: "hard limit: a limit switch fired, something may be in the way; the motion stopped "
       "at once and the position is lost",
    2: "soft limit: a move's target was beyond the machine travel; nothing moved",
    3: "reset during a motion: the position is lost",
    4: "probe failed: the probe was not in its expected state",
    5: "probe failed: no contact within the programmed travel",
    6: "homing failed: the homing cycle was reset",
    7: "homing failed: the safety door was opened during homing",
    8: "homing failed: the pull-off did not clear the limit switch",
    9: "homing failed: no limit switch found within the search distance",
}
#: The ``$N`` alarm names of GRBL 1.0 and earlier ("Alarm Message in v1.0-" column).
ALARM_NAMES = {1: "Hard limit", 2: "Soft limit", 3: "Abort during cycle", 4: "Probe fail",
               5: "Probe fail", 6: "Homing fail", 7: "Homing fail", 8: "Homing fail",
               9: "Homing fail"}
#: ``report.c`` MESSAGE_ALARM_LOCK: printed after the banner when the controller comes up
#: (power-up with homing enabled, a reset out of an alarm) locked in the Alarm state.
LOCK_MESSAGE = "[MSG:'$H'|'$X' to unlock]"
#: Alarms after which GRBL 1.1 halts until a soft reset: protocol.c
#: ``protocol_exec_rt_system`` reports the alarm, prints ``[MSG:Reset to continue]`` and
#: blocks everything, status reports included, until the user issues a reset (0x18) -
#: "Currently hard and soft limits flag this".
CRITICAL_ALARMS = frozenset({1, 2})
#: ``report.c`` MESSAGE_CRITICAL_EVENT, printed after a critical alarm.
CRITICAL_MESSAGE = "[MSG:Reset to continue]"
#: Sub-states of the ``?`` report (``doc/markdown/interface.md``, "Real-time Status
#: Reports"): Hold and Door suspend a motion, which resumes with cycle start (``~``).
SUBSTATES = {
    "Hold:0": "feed hold complete, ready to resume",
    "Hold:1": "feed hold in progress",
    "Door:0": "safety door closed, ready to resume",
    "Door:1": "safety door ajar, machine stopped; cannot resume until it is closed",
    "Door:2": "safety door opened, parking in progress",
    "Door:3": "safety door closed, resuming",
}
