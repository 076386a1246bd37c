"""``polrig devices [--config FILE]``: configured devices and their status, plus what can be
discovered: serial ports by USB VID:PID (``serial.tools.list_ports``), DC2200 LED drivers on
USB (pyusb, when libusb is available) and GenTL cameras (the .cti files named in the config
or found through ``GENICAM_GENTL64_PATH``)."""

from __future__ import annotations

import argparse
import sys

from polrig.cli.commands._device_args import add_config_argument, identity
from polrig.errors import ConfigError, DeviceError
from polrig.choices import DEVICE_KINDS

#: USB VID:PID of the serial adapters the rig's devices use (vendor documentation:
#: FTDI application note AN_146 for FTDI's ids; Thorlabs assigns 0403:FAF0 to its APT
#: controllers (K10CR1); the Elliptec interface board is an FTDI FT230X (0403:6015);
#: GRBL runs on an Arduino (2341:0043 Uno, 2341:0001) or a CH340 clone (1A86:7523)).
KNOWN_SERIAL = {
    (0x0403, 0xFAF0): "Thorlabs APT controller (k10cr1)",
    (0x0403, 0x6015): "FTDI FT230X: Elliptec interface board (ell14)",
    (0x0403, 0x6001): "FTDI FT232R serial adapter",
    (0x2341, 0x0043): "Arduino Uno (grbl)",
    (0x2341, 0x0001): "Arduino Uno (grbl)",
    (0x1A86, 0x7523): "CH340 serial adapter (grbl on an Arduino clone)",
}


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("devices", help="list configured and discoverable devices",
                       description="Show each configured device (driver, settings, and what "
                                   "it reports when opened), then the devices that can be "
                                   "discovered: serial ports by USB VID:PID, DC2200 LED "
                                   "drivers, GenTL cameras. Exit code 1 if a configured "
                                   "device cannot be opened.")
    add_config_argument(p)
    p.add_argument("--no-open", action="store_true",
                   help="do not open the configured devices (list settings only)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from polrig.app.rig import load_rig_config, open_device

    config = load_rig_config(args.config)
    print(f"configured ({args.config or 'built-in simulated rig'}):")
    failures = 0
    for kind in DEVICE_KINDS:
        table = config[kind]
        settings = ", ".join(f"{k}={v}" for k, v in table.items()
                             if k != "driver" and v is not None)
        print(f"  {kind:<10} {table['driver']:<8} {settings}")
        if args.no_open:
            continue
        try:
            with open_device(args.config, kind) as dev:
                print(f"             ok: {identity(dev.info())}")
        except (DeviceError, ConfigError) as exc:  # ConfigError: a setting the device refuses
            failures += 1
            print(f"             unreachable: {exc}")
    print("serial ports:")
    for line in _serial_ports():
        print(f"  {line}")
    print("USB LED drivers (DC2200):")
    for line in _dc2200s(config["light"].get("backend") if config["light"]["driver"] ==
                         "dc2200" else None):
        print(f"  {line}")
    print("GenTL cameras:")
    for line in _gentl(config["camera"]):
        print(f"  {line}")
    if failures:
        print(f"polrig: error: {failures} configured device(s) could not be opened",
              file=sys.stderr)
        return 1
    return 0


def _serial_ports() -> list[str]:
    from serial.tools import list_ports

    out = []
    for port in sorted(list_ports.comports(), key=lambda p: p.device):
        if port.vid is None:
            continue
        known = KNOWN_SERIAL.get((port.vid, port.pid), "")
        serial_no = f" serial {port.serial_number}" if port.serial_number else ""
        out.append(f"{port.device}  {port.vid:04X}:{port.pid:04X}{serial_no}  "
                   f"{known or port.description or ''}".rstrip())
    return out or ["(no USB serial ports)"]


def _dc2200s(backend_name: str | None) -> list[str]:
    import usb.core

    from polrig.drivers.dc2200 import PRODUCT_ID, VENDOR_ID, resolve_backend

    try:
        backend = resolve_backend(backend_name)
        devs = list(usb.core.find(find_all=True, idVendor=VENDOR_ID, idProduct=PRODUCT_ID,
                                  backend=backend))
    except usb.core.NoBackendError:
        return ["(pyusb has no backend: install libusb to search USB)"]
    except (usb.core.USBError, DeviceError) as exc:
        return [f"(USB search failed: {exc})"]
    out = []
    for d in devs:
        try:
            serial_no = d.serial_number
        except (usb.core.USBError, ValueError):
            serial_no = "?"
        out.append(f"usb {d.bus}:{d.address}  {VENDOR_ID:04X}:{PRODUCT_ID:04X}  serial {serial_no}")
    return out or ["(none)"]


def _gentl(camera_table: dict) -> list[str]:
    from polrig.drivers.genicam_camera import gentl_paths_from_env, list_gentl_devices

    cti = camera_table.get("cti") if camera_table["driver"] == "genicam" else None
    files = ([cti] if isinstance(cti, str) else list(cti)) if cti else gentl_paths_from_env()
    if not files:
        return ["(no .cti named in the config and GENICAM_GENTL64_PATH is empty)"]
    out = []
    for f in files:
        try:
            devs = list_gentl_devices([f])
        except DeviceError as exc:
            out.append(f"{f}: {exc}")
            continue
        out += [f"{f}: {d.model} serial {d.serial} ({d.extra.get('vendor', '')}, id {d.port})"
                for d in devs] or [f"{f}: no devices"]
    return out
