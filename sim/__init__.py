"""Simulated polarimetric rig: scenes, renderer, generator, DoFP sensor, devices, truth.

Entry point: :func:`polrig.sim.devices.create_sim_rig` (what :func:`polrig.app.rig.open_rig` uses when no
rig configuration is given). Module map and file formats: ``docs/sim.md``. ``sim`` imports
``polrig`` core only (``docs/architecture.md``). The names below are loaded lazily so that
importing a light submodule (``polrig.sim.scene``) does not load the devices.
"""

from __future__ import annotations

__all__ = ["SimCamera", "SimLight", "SimRig", "SimStage", "SimTurntable", "create_sim_rig"]


def __getattr__(name: str):
    if name in __all__:
        from polrig.sim import (
            devices,  # on first use: a light submodule does not load the devices
        )

        return getattr(devices, name)
    raise AttributeError(f"module 'polrig.sim' has no attribute {name!r}")
