"""Layer 10, the application: a rig, sessions, processing, capture and scale-out.

Composes every layer below: opening a rig from its configuration (``rig``), the session folder
and its typed manifest (``manifest``, ``session``, ``records``, ``sessionio``), calibration sets
as processing needs them (``calibrations``), processing captures into Mueller results (``processing``), the one
capture call (``capture``), Dask scale-out (``cluster``) and previews (``preview``). The shells
(:mod:`polrig.cli`, :mod:`polrig.gui`) only present what these modules do.
"""
