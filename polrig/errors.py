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
    """The device reported an error of its own; ``code`` and ``text`` are the device's."""

    def __init__(self, message: str, *, device: str | None = None,
                 code: int | str | None = None, text: str | None = None):
        self.code = code
        self.text = text
        detail = f" (device error {code}: {text})" if code is not None else ""
        super().__init__(message + detail, device=device)


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
