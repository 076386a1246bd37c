"""Simulated polarimetric rig: scenes, renderer, generator, DoFP sensor, devices, truth.

Entry point: :func:`sim.devices.create_sim_rig` (what :func:`polrig.rig.open_rig` uses when no
rig configuration is given). Module map and file formats: ``docs/sim.md``. ``sim`` imports
``polrig`` core only (``docs/architecture.md``). The names below are loaded lazily so that
importing a light submodule (``sim.scene``) does not load the devices.
"""

from __future__ import annotations

__all__ = ["SimCamera", "SimLight", "SimRig", "SimStage", "SimTurntable", "create_sim_rig"]


def __getattr__(name: str):
    if name in __all__:
        from sim import devices

        return getattr(devices, name)
    raise AttributeError(f"module 'sim' has no attribute {name!r}")
