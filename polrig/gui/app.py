"""``run_gui``: what ``polrig gui`` runs (QApplication, rig, main window)."""

from __future__ import annotations

import os
import sys
from typing import Any

#: Simulated sensor size of the GUI's built-in rig (width x height). Smaller than a real
#: IMX250 (2448x2048): the simulator renders every new pose, which at full size takes
#: seconds; ``polrig gui --sim-size 2448x2048`` gives the full size.
DEFAULT_SIM_SIZE = "512x512"


def sim_options(size: str = DEFAULT_SIM_SIZE, clock_speed: float = 1.0) -> dict[str, Any]:
    return {"size": size, "clock_speed": clock_speed}


def model_loader(weights: str | None = None):
    """A function loading the single-shot model (the CLI's message when none is installed)."""
    def load():
        from polrig import processing

        if weights is None:
            return processing.single_shot_model()
        from models.runtime import SingleShotModel

        return SingleShotModel.load(weights)
    return load


def run_gui(config: str | os.PathLike | None = None, *, sim_size: str = DEFAULT_SIM_SIZE,
            sim_clock_speed: float = 1.0, weights: str | None = None,
            settings_file: str | None = None, argv: list[str] | None = None) -> int:
    """Open the rig (simulated unless ``config``) and run the GUI until its window closes."""
    from PySide6.QtWidgets import QApplication

    from polrig.gui.main_window import MainWindow
    from polrig.gui.settings import make_settings
    from polrig.rig import build_rig, load_rig_config

    config_data = load_rig_config(config)  # configuration errors before any window opens
    rig = build_rig(config_data, sim_options(sim_size, sim_clock_speed))
    app = QApplication.instance() or QApplication(argv or sys.argv[:1])
    app.setApplicationName("polrig")
    window = MainWindow(rig, make_settings(settings_file), model_loader=model_loader(weights))
    window.show()
    window.start()
    return int(app.exec())
