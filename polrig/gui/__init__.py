"""PySide6 operator GUI of polrig (``polrig gui``).

Module map (imports flow downwards; :mod:`polrig.gui.pipeline`, :mod:`polrig.gui.geometry_layer`
and :mod:`polrig.gui.rigaccess` are free of Qt):

* :mod:`polrig.gui.pipeline` -- frames/EXRs -> :class:`PolarizationData` -> display images
  (reuses :mod:`polrig.sensor.stokes` and :mod:`polrig.app.preview`), cursor readout, histograms.
* :mod:`polrig.gui.rigaccess` -- one lock per device so that device calls from the worker
  threads never overlap.
* :mod:`polrig.gui.geometry_layer` -- the viewer's geometry planes (normals, albedo, roughness,
  light direction) as displays and a cursor readout.
* :mod:`polrig.gui.qtimage` -- numpy RGB <-> ``QImage``.
* :mod:`polrig.gui.settings` -- settings remembered between runs (``QSettings``).
* :mod:`polrig.gui.latency` -- the event loop's latency probe.
* :mod:`polrig.gui.widgets` -- image view with cursor tracking, histogram, message area.
* :mod:`polrig.gui.roi_panel` -- ROI tools, statistics table, profile plot, CSV export, the AoLP
  colour wheel.
* :mod:`polrig.gui.live` -- the live worker ``QThread`` (latest-frame slot).
* :mod:`polrig.gui.live_panel` -- the live view panel: display choice, camera controls, image,
  cursor readout, histogram.
* :mod:`polrig.gui.devices` -- devices panel and its worker thread.
* :mod:`polrig.gui.capture_panel` -- capture panel and its worker thread
  (:func:`polrig.app.capture.run_capture`).
* :mod:`polrig.gui.calibration_panel` -- the :mod:`polrig.calibration.procedures` step by step.
* :mod:`polrig.gui.viewer` -- saved sessions and Mueller/Stokes EXRs.
* :mod:`polrig.gui.main_window` -- the window, settings (``QSettings``), shortcuts.
* :mod:`polrig.gui.app` -- :func:`run_gui` (what ``polrig gui`` calls).
* :mod:`polrig.gui.screenshots` -- renders ``docs/screenshots/*.png`` offscreen.

The GUI has no processing of its own: capture, sessions, Stokes, previews and single-shot
inference are the core functions the CLI calls.
"""
