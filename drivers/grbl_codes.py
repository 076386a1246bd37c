"""GRBL 1.1 error and alarm texts (grbl/grbl ``doc/csv/error_codes_en_US.csv`` and
``doc/csv/alarm_codes_en_US.csv``; ``doc/markdown/interface.md``)."""

ERRORS = {
    1: "Expected command letter", 2: "Bad number format", 3: "Invalid statement",
    4: "Negative value", 5: "Homing not enabled", 6: "Minimum step pulse time",
    7: "EEPROM read fail", 8: "Not idle", 9: "G-code lock (alarm or jog state)",
    10: "Homing not enabled (soft limits)", 11: "Line overflow", 15: "Travel exceeded",
    16: "Invalid jog command", 20: "Unsupported command", 22: "Undefined feed rate",
    24: "Modal group violation", 33: "Invalid target",
}
ALARMS = {
    1: "Hard limit triggered", 2: "Soft limit (motion target exceeds machine travel)",
    3: "Reset while in motion (position lost)", 4: "Probe fail", 5: "Probe fail",
    6: "Homing fail: reset during homing", 7: "Homing fail: door opened during homing",
    8: "Homing fail: pull-off failed to clear limit switch",
    9: "Homing fail: could not find limit switch",
}
