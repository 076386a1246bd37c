"""polrig: drive a DoFP polarimetric imaging rig and turn its captures into Mueller matrices.

Conventions (angles, Stokes frames, Mueller layout) are written once in
``docs/conventions.md``; :mod:`polrig.optics.conventions` holds the version string.
"""

__version__ = "0.1.0"
