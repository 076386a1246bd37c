"""Layer 5, acquisition: device interfaces, capture plans as data, and the one engine.

The hardware abstraction layer (``hal``: cameras, stages, turntables, lights and their declared
capabilities), plans of device steps (``plan``) and the executor with the one fault policy
(``engine``). Drivers (:mod:`polrig.drivers`) and the simulated rig (:mod:`polrig.sim`) implement
``hal``; nothing here knows which kind it drives.
"""
