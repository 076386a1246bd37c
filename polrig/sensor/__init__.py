"""Layer 2, sensor: the DoFP camera's data from raw mosaic to Stokes.

Mosaic layouts, pixel formats, the :class:`~polrig.sensor.frame.Frame` types, demosaicking,
the per-pixel analyzer model, Stokes estimation and the sensor noise model. Imports the optics
layer and nothing above it.
"""
