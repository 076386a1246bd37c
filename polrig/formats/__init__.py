"""Layer 3, formats: what polrig reads and writes, and the user's input checks.

Raw frames with JSON sidecars (``rawio``), Mueller/Stokes OpenEXR (``exr``), the rig TOML
(``config``) and command-line argument types (``argcheck``). Imports the sensor and optics
layers and nothing above them.
"""
