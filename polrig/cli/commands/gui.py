"""``polrig gui [--config FILE]``: the operator GUI (PySide6), see :mod:`polrig.gui`."""

from __future__ import annotations

import argparse

from polrig.choices import GUI_SIM_SIZE
from polrig.cli.commands._device_args import add_config_argument
from polrig.cli.commands.capture import add_model_size_option


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("gui", help="operator GUI: live view, devices, capture, calibration, viewer",
                       description="Open the operator GUI on the rig (simulated unless --config "
                                   "names real hardware).")
    add_config_argument(p)
    p.add_argument("--sim-size", default=GUI_SIM_SIZE, metavar="WxH",
                   help=f"sensor size of the simulated rig (default {GUI_SIM_SIZE}; the "
                        f"real IMX250 is 2448x2048, which renders slowly)")
    p.add_argument("--sim-clock-speed", type=float, default=1.0, metavar="X",
                   help="simulated seconds per real second (default 1: real time)")
    p.add_argument("--weights", default=None, metavar="DIR",
                   help="single-shot model folder (default: the shipped models/weights)")
    p.add_argument("--device", choices=("auto", "cpu", "cuda"), default="auto",
                   help="where the live view's single-shot network runs: auto (CUDA where "
                        "onnxruntime offers it, else the CPU; default), cpu or cuda (refused when "
                        "unavailable, before the window opens)")
    add_model_size_option(p)
    p.add_argument("--settings", default=None, metavar="FILE",
                   help="INI file for the remembered settings (default: the user's "
                        "polrig/polrig-gui settings)")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    if args.config is not None and not args.config.is_file():
        raise FileNotFoundError(f"--config {args.config}: no such file")
    from polrig.sim.options import parse_size

    w, h = parse_size(args.sim_size)  # bad sizes: a one-line ConfigError before Qt starts
    if args.device == "cuda":  # refused before Qt starts (polrig.models.devices.DeviceUnavailable, exit 2)
        import onnxruntime as ort

        from polrig.models.devices import choose_providers

        choose_providers(args.device, ort.get_available_providers())
    if args.weights is None and args.model_size not in (None, "auto"):  # a size not shipped: one line, before Qt starts
        from polrig.models.sizes import choose_size

        choose_size(args.model_size, on_cuda=False)
    from polrig.gui.app import run_gui

    return run_gui(args.config, sim_size=f"{w}x{h}", sim_clock_speed=args.sim_clock_speed,
                   weights=args.weights, device=args.device, settings_file=args.settings,
                   model_size=args.model_size or "auto")
