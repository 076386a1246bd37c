"""Layer 1, optics: Stokes and Mueller algebra, the rig's Stokes bases, Fresnel and the pBRDF.

Pure functions of arrays; imports nothing of polrig but :mod:`polrig.errors`. Conventions
(angles, frames, Mueller layout) are in ``docs/conventions.md``.
"""
