"""Simulated polarimetric rig: scenes, renderer, generator, DoFP sensor, devices, truth.

Entry point: :func:`sim.devices.create_sim_rig` (what :func:`polrig.rig.open_rig` uses when no
rig configuration is given). Module map: ``docs/sim.md``. ``sim`` imports ``polrig`` core only
(``docs/architecture.md``).
"""

from sim.devices import SimCamera, SimLight, SimRig, SimStage, SimTurntable, create_sim_rig

__all__ = ["SimCamera", "SimLight", "SimRig", "SimStage", "SimTurntable", "create_sim_rig"]
