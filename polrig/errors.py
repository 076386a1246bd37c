"""Typed errors. Every error a user can cause or a device can raise is one of these.

Device errors carry the device's own code and text where the device reports one, so an
operator sees what the manual calls it.
"""

from __future__ import annotations


class PolrigError(Exception):
    """Base class of every error polrig raises on purpose."""


class ConfigError(PolrigError, ValueError):
    """A rig configuration or command-line value is invalid; the message names the key."""


class FormatError(PolrigError, ValueError):
    """A file or a buffer is not in the format expected (pixel format, EXR, raw frame)."""


class DeviceError(PolrigError):
    """Base class of hardware errors."""

    def __init__(self, message: str, *, device: str | None = None):
        self.device = device
        super().__init__(f"{device}: {message}" if device else message)


class DeviceNotFound(DeviceError):
    """The device (or its port, producer, serial number) cannot be found or opened."""


class DeviceTimeout(DeviceError):
    """The device did not answer or finish within the stated timeout."""


class DeviceFault(DeviceError):
    """The device reported an error of its own; ``code`` and ``text`` are the device's.
    ``requires_operator``: a safety fault (:class:`DeviceAlarm`) rather than one the fault
    policy may retry."""

    requires_operator = False

    def __init__(self, message: str, *, device: str | None = None,
                 code: int | str | None = None, text: str | None = None):
        self.code = code
        self.text = text
        detail = f" (device error {code}: {text})" if code is not None else ""
        super().__init__(message + detail, device=device)


class DeviceAlarm(DeviceFault):
    """A safety fault: the device stopped itself (a limit switch fired, a soft limit, a
    controller locked in its alarm state) and must not be driven on without the operator. A
    limit switch that fired means something may be in the way. The acquisition engine never
    retries it and never re-homes the axis on its own (:mod:`polrig.acquisition.engine`): it
    stops and reports. ``axis`` is the rig's device (``"turntable"``), ``command`` the
    command line the operator runs once the cause is cleared (``polrig home turntable``:
    :meth:`command_for` adds the rig file); ``code``/``text`` are the device's alarm."""

    requires_operator = True

    def __init__(self, message: str, *, device: str | None = None,
                 code: int | str | None = None, text: str | None = None,
                 axis: str = "turntable", command: str | None = None):
        self.axis = axis
        self.command = command or f"polrig home {axis}"
        self.reason = message
        super().__init__(f"{message}; clear the cause, then run `{self.command}`",
                         device=device, code=code, text=text)

    def command_for(self, config: object | None = None) -> str:
        """:attr:`command`, with ``--config CONFIG`` when the rig came from a file."""
        return f"{self.command} --config {config}" if config else self.command

    def operator_message(self, config: object | None = None) -> str:
        """One line for the operator: what stopped, the device's alarm, and the command (with
        the rig file ``config``) that clears it."""
        detail = f" (device error {self.code}: {self.text})" if self.code is not None else ""
        where = f"{self.device}: " if self.device else ""
        return (f"{where}{self.reason}{detail}; clear the cause, then run "
                f"`{self.command_for(config)}`")


class ProtocolError(DeviceError):
    """The device answered with bytes that do not follow its protocol (garbled, partial)."""


class DeviceDisconnected(DeviceError):
    """The transport to the device went away (cable pulled, port closed)."""


#: Exit status of a command line that stopped on bad input (arguments, config, files).
EXIT_USAGE = 2
#: Exit status of a command line that failed while running (device, disk, processing).
EXIT_FAILURE = 1


def exit_code_for(exc: BaseException) -> int | None:
    """The exit status a command line reports for ``exc`` (README, "CLI"): :data:`EXIT_USAGE`
    for bad input (``ConfigError``, ``FormatError``, a missing or existing file, a
    ``ValueError``), :data:`EXIT_FAILURE` for other polrig and OS errors, ``None`` for anything
    else (a bug: let it propagate). One rule for ``polrig`` and the ``python -m polrig.models.*``
    tools."""
    if isinstance(exc, (ConfigError, FormatError, FileNotFoundError, FileExistsError, ValueError)):
        return EXIT_USAGE
    if isinstance(exc, (PolrigError, OSError)):
        return EXIT_FAILURE
    return None
