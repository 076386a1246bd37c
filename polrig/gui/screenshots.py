"""Render screenshots of the main GUI views offscreen into ``docs/screenshots/``.

``python -m polrig.gui.screenshots [--out docs/screenshots] [--size 512x512] [--only analysis]``
opens the window on the simulated rig (``QT_QPA_PLATFORM=offscreen`` unless a platform is set), waits
for real frames and writes:

* ``live_dolp.png``, ``live_aolp.png`` -- the live view showing DoLP and DoLP-weighted AoLP;
* ``mueller_grid.png`` -- the 3x3 Mueller grid with its colour bar: the single-shot live
  display when a model is installed, otherwise the viewer showing the reference capture's
  Mueller EXR (the same rendering);
* ``viewer_reference_mueller.png`` -- the viewer showing a reference capture's Mueller EXR;
* ``capture_progress.png`` -- the capture panel during a reference capture (progress, ETA,
  thumbnails of finished poses, scores against the simulator's truth);
* ``capture_adaptive.png`` -- the capture panel after an adaptive capture (three poses, target
  relative sigma 0.05) that was stopped at the second pose's first decision and resumed: its
  "Adaptive decisions" list, the first pose's decisions recorded by the stopped run (greyed,
  "(recorded)"), then those the resumed run made (needs the single-shot model; ``--only
  adaptive`` writes it alone);
* ``viewer_roi_stats.png`` -- the viewer showing a parameter map (linear retardance) of a
  reference capture of the stressed-film scene, an ellipse ROI with its statistics table
  (counted and masked pixels) and a line profile;
* ``viewer_virtual_polarizer.png`` -- the viewer's virtual polarizer (incident 30 deg,
  analyzer 120 deg) on the same capture;
* ``devices.png`` -- the devices panel;
* ``calibration.png`` -- the calibration panel after the intrinsics and turntable steps
  (report text and its residual plot).

The two viewer analysis screenshots come from a one-pose reference capture of their own (the
``film_plane`` scene, a stressed film with a retardance texture, on the mono sensor at
``--size``) shown in a viewer panel on its own; ``--only analysis`` writes them alone.
"""

from __future__ import annotations

import argparse
import os
import pathlib
import sys
import tempfile
import time


def _wait(app, cond, timeout_s: float, what: str) -> None:
    t = time.monotonic()
    while not cond():
        if time.monotonic() - t > timeout_s:
            raise TimeoutError(f"screenshots: timed out waiting for {what}")
        app.processEvents()
        time.sleep(0.01)


def open_in_viewer(app, viewer, session: pathlib.Path) -> None:
    """Open ``session`` in ``viewer`` and wait until its first file is shown (the viewer loads
    files on a thread of its own)."""
    if not viewer.open_session(session):
        raise RuntimeError(f"screenshots: the viewer cannot open {session}")
    _wait(app, lambda: not viewer.loading and not viewer.drawing, 600.0,
          "the viewer to load the capture")
    if viewer.data is None:
        raise RuntimeError(f"screenshots: the viewer cannot show {session}'s first file")


def analysis_views(app, viewer, shot) -> None:
    """The viewer's analysis tools on the result it shows: a parameter map with an ellipse ROI,
    its statistics and a line profile (``viewer_roi_stats.png``), then the virtual polarizer
    (``viewer_virtual_polarizer.png``)."""
    v = viewer
    h, w = v.data.mueller.shape[-2:]
    v.display.setCurrentIndex(v.display.findData("maps"))
    v.map_name.setCurrentIndex(v.map_name.findData("retardance_deg"))
    _wait(app, lambda: v.data.maps_ready() and v.view.image() is not None and not v.drawing,
          600.0, "the parameter maps (computed on a worker thread)")
    v.roi.tool.setCurrentIndex(v.roi.tool.findData("line"))
    v.view.set_shape("line", [(0.1 * w, 0.8 * h), (0.9 * w, 0.2 * h)])
    _wait(app, lambda: not v.roi.busy, 600.0, "the line profile (computed on a worker thread)")
    v.roi.profile_quantity.setCurrentText("retardance_deg")
    v.roi.tool.setCurrentIndex(v.roi.tool.findData("ellipse"))
    v.view.set_shape("ellipse", [(0.3 * w, 0.3 * h), (0.7 * w, 0.6 * h)])
    _wait(app, lambda: not v.roi.busy, 600.0, "the ROI statistics (computed on a worker thread)")
    shot(v, "viewer_roi_stats.png")
    v.display.setCurrentIndex(v.display.findData("polarizer"))
    v.incident.setValue(30)
    v.analyzer.setValue(120)
    _wait(app, lambda: not v.drawing, 600.0, "the virtual polarizer (redrawn on a worker thread)")
    shot(v, "viewer_virtual_polarizer.png")


def adaptive_capture_view(app, w, session: pathlib.Path, shot) -> None:
    """``capture_adaptive.png``: in window ``w``, an adaptive capture into ``session`` (poses
    0, 120, 240 deg, target relative sigma 0.05) stopped once the second pose's first decision
    is made, then resumed from the panel to its end: the decisions list shows the ones the
    stopped run recorded, then the resumed run's."""
    cp = w.capture
    cp.poses.setText("0:360:120")
    cp.out.setText(str(session))
    cp.mode.setCurrentText("adaptive")
    cp.target_sigma.setValue(0.05)
    cp.states.setText("")
    w.show_panel(cp)
    cp.start()
    _wait(app, lambda: any(e.kind == "decision" and e.capture_index >= 1 for e in cp.events)
          or not cp.is_running, 900, "the second pose's first decision")
    cp.stop()
    _wait(app, lambda: not cp.is_running, 600, "the adaptive capture to stop")
    if cp.last_status != "interrupted":
        raise RuntimeError(f"screenshots: the adaptive capture ended {cp.last_status}: "
                           f"{cp.eta.text()}")
    cp.resume()
    _wait(app, lambda: cp.is_running, 60, "the resumed adaptive capture to start")
    _wait(app, lambda: not cp.is_running, 900, "the resumed adaptive capture")
    if cp.last_status != "complete":
        raise RuntimeError(f"screenshots: the resumed adaptive capture ended {cp.last_status}: "
                           f"{cp.eta.text()}")
    bar = w.pages[cp].verticalScrollBar()  # the page scrolled to its ETA, poses and decisions
    bar.setValue(bar.maximum())
    cp.decisions.scrollToTop()
    shot(w, "capture_adaptive.png")


def _shooter(app, out: pathlib.Path, written: list[pathlib.Path]):
    """``shot(widget, name)``: process pending events, grab ``widget`` into ``out/name`` (PNG)
    and append the path to ``written``."""

    def shot(widget, name: str) -> None:
        app.processEvents()
        path = out / name
        widget.grab().save(str(path))
        written.append(path)

    return shot


def _analysis_only(app, out: pathlib.Path, tmp: pathlib.Path, size: str) -> list[pathlib.Path]:
    from polrig.app.capture import CaptureRequest, run_capture
    from polrig.gui.viewer import ViewerPanel

    cfg = tmp / "rig.toml"
    cfg.write_text(f'[sim]\nsize = "{size}"\nsensor = "imx250mzr"\nclock_speed = inf\nseed = 3\n'
                   'scene = "film_plane"\nnoise = true\n')
    session = tmp / "analysis_session"  # its own folder: the full run's capture is in tmp / "session"
    result = run_capture(CaptureRequest(out=session, poses_deg=(0.0,), mode="reference",
                                        config=cfg), command_line=["screenshots"])
    if result.status != "complete":
        raise RuntimeError(f"screenshots: the capture ended {result.status}: {result.reason}")
    v = ViewerPanel()
    v.resize(1560, 900)
    v.show()
    open_in_viewer(app, v, session)
    written: list[pathlib.Path] = []
    shot = _shooter(app, out, written)

    analysis_views(app, v, shot)
    v.shutdown()
    v.close()
    return written


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m polrig.gui.screenshots", description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", default="docs/screenshots", help="output folder")
    ap.add_argument("--size", default="512x512", help="simulated sensor size WxH")
    ap.add_argument("--no-calibration", action="store_true",
                    help="skip calibration.png (two calibration steps, about a minute)")
    ap.add_argument("--only", choices=("all", "analysis", "adaptive"), default="all",
                    help="analysis: only the viewer's ROI statistics and virtual polarizer "
                         "screenshots, from a quick capture of their own; adaptive: only "
                         "capture_adaptive.png")
    args = ap.parse_args(argv)
    os.environ.setdefault("QT_QPA_PLATFORM", "offscreen")
    from PySide6.QtWidgets import QApplication

    from polrig.app.rig import build_rig, load_rig_config
    from polrig.gui import pipeline
    from polrig.gui.app import model_loader
    from polrig.gui.main_window import MainWindow
    from polrig.gui.settings import make_settings

    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    app = QApplication.instance() or QApplication(sys.argv[:1])
    tmp = pathlib.Path(tempfile.mkdtemp(prefix="polrig-shots-"))
    if args.only == "analysis":
        for p in _analysis_only(app, out, tmp, args.size):
            print(f"wrote {p}")
        return 0
    rig = build_rig(load_rig_config(None), {"size": args.size, "clock_speed": 200.0})
    w = MainWindow(rig, make_settings(tmp / "gui.ini"), model_loader=model_loader(),
                   live_max_fps=15.0)
    w.resize(1400, 900)
    w.show()
    w.start()
    written: list[pathlib.Path] = []
    shot = _shooter(app, out, written)
    if args.only == "adaptive":
        _wait(app, lambda: all(d.is_open for d in rig.devices.values()), 120, "the devices")
        adaptive_capture_view(app, w, tmp / "adaptive_session", shot)
        w.close()
        _wait(app, lambda: not w.isVisible(), 60, "the window to close")
        for p in written:
            print(f"wrote {p}")
        return 0

    w.show_panel(w.live)
    # the exposure box shows the camera's value (from the device poll), as the status line does
    _wait(app, lambda: w.live.last is not None
          and abs(w.live.exposure.value() - w.live.last.exposure_us) < 0.5, 120,
          "the camera's exposure in the live panel")
    for display, name in (("dolp", "live_dolp.png"), ("aolp_dolp", "live_aolp.png")):
        w.live.set_display(display)
        _wait(app, lambda: w.live.last is not None and w.live.last.display == display
              and w.live.frames_shown > 3, 120, f"live {display}")
        w.live._hovered(w.live.last.image.width() // 2, w.live.last.image.height() // 2)
        shot(w, name)
    w.live.set_display("mueller")
    _wait(app, lambda: w.live.last.display == "mueller" or "unavailable" in w.live.last.note,
          300, "the Mueller display")
    live_mueller = w.live.last.display == "mueller"
    if live_mueller:
        shot(w, "mueller_grid.png")
    w.live.set_display("aolp_dolp")

    cp = w.capture
    cp.poses.setText("0:360:60")
    cp.out.setText(str(tmp / "session"))
    w.show_panel(cp)
    cp.start()
    _wait(app, lambda: cp.thumbnails_shown >= 2 or not cp.is_running, 600, "two finished poses")
    _wait(app, lambda: any(e.kind == "frame" and e.step > cp.progress.maximum() // 3 + 2
                           for e in cp.events) or not cp.is_running, 600, "capture progress")
    bar = w.pages[cp].verticalScrollBar()  # the page scrolled to its progress, ETA and poses
    bar.setValue(bar.maximum())
    shot(w, "capture_progress.png")
    cp.stop()
    _wait(app, lambda: not cp.is_running, 600, "the capture to stop")
    if live_mueller:  # the adaptive mode needs the single-shot model, as the live grid does
        adaptive_capture_view(app, w, tmp / "adaptive_session", shot)
    else:
        print("capture_adaptive.png not written: no single-shot model installed")
    open_in_viewer(app, w.viewer, tmp / "session")
    w.show_panel(w.viewer)
    v = w.viewer
    h, wd = v.data.mueller.shape[-2:]  # cursor on the object in the m11 tile
    b = pipeline.GRID_BORDER_PX
    v._hovered(2 * b + wd + wd // 2 - wd // 10, 2 * b + h + h // 2 - h // 10)
    shot(w, "viewer_reference_mueller.png")
    if not live_mueller:
        shot(w, "mueller_grid.png")
    w.show_panel(w.devices)
    w.devices.move("stage", 22.5)
    _wait(app, lambda: abs(w.devices.last_status.get("stage", {}).get("position_deg", 0) - 22.5)
          < 1e-6 and not any("busy_with" in v for v in w.devices.last_status.values()),
          60, "fresh device status")
    shot(w, "devices.png")
    written += _analysis_only(app, out, tmp, args.size)
    if not args.no_calibration:
        cal = w.calibration
        cal.folder.setText(str(tmp / "calibration"))
        w.show_panel(cal)
        for step in ("intrinsics", "turntable"):
            cal.run_step(step)
            _wait(app, lambda: not cal.is_running, 900, f"calibration step {step}")
        shot(w, "calibration.png")
    w.close()
    _wait(app, lambda: not w.isVisible(), 60, "the window to close")
    for p in written:
        print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
