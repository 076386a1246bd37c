"""Viewer of saved sessions and EXRs with the live view's displays.

A session folder lists its captures' files (Mueller EXR, truth EXR on the simulated rig, raw
frames); a Mueller or Stokes EXR opens on its own. Files are read with the core readers
(:mod:`polrig.app.session`, :mod:`polrig.formats.exr`, :mod:`polrig.formats.rawio`) and shown through
:mod:`polrig.gui.pipeline` (a raw frame is processed like a live frame).

The parameter maps (display "Parameter map") take seconds at full sensor size
(``benchmarks/results/analyze.md``), so they are computed off the GUI thread: a
:class:`MapsWorker` (a ``QThread``, as the capture, calibration and device workers are) computes
:meth:`pipeline.PolarizationData.compute_maps` and delivers the result by its ``done`` signal;
the view says "computing parameter maps..." meanwhile and the rest of the viewer stays usable.
One worker runs at a time; a result for data that is no longer shown (another file was opened)
is discarded, and the maps of the data shown then are requested in turn.

Opening a file is slow too (a full colour sensor's Mueller result, 1224x1024x3, takes seconds
to read and render, longer with its sigma planes), so :meth:`ViewerPanel.open_file` only starts
the load: the file is read, and its first image rendered, on a thread of the panel's own (one
worker, as the capture panel makes its thumbnails), and shown when it arrives; meanwhile the
view says "loading NAME...". A load superseded by a newer one (another file or entry chosen
before it ended) is dropped, never shown. The panel's ``loaded(ok)`` signal and its
:attr:`~ViewerPanel.loading` property say when the latest load has been shown (or its error
reported); the ROI statistics follow on their own thread (:class:`polrig.gui.roi_panel.RoiTools`).

Changing the display (the shown quantity, the colour, the SNR threshold, the parameter map, the
virtual polarizer's sliders, the geometry layer) redraws the image and its histogram, which takes
about a second for the 3x3 Mueller grid of a full colour sensor's result. Such a redraw runs on
the same load thread, in the same way: :meth:`ViewerPanel.refresh` only starts it ("redrawing..."
across the image meanwhile, which keeps the image it had) and the result is shown when it
arrives. Latest wins: while one redraw runs, further changes queue redraws of which only the
newest runs (the others are skipped when their turn comes), so a dragged slider costs at most
the redraw in progress and one more with the newest settings; a redraw superseded by a newer
change, another file or the panel's shutdown is never shown (while a file loads, a change only
sets the controls: the file is drawn with them once read). The ``drawn`` signal and the
:attr:`~ViewerPanel.drawing` property say when the image of the latest settings is shown (or its
error reported). Small images stay synchronous: where the image's full-resolution grid has at
most :data:`SYNC_REDRAW_MAX_PX` pixels (the small files of the tests, a 256x256 sensor's
superpixel result) the redraw is done at once on the UI thread, under 15 ms on a 2-core machine
for the 3x3 grid of a 128x128 colour result.
"""

from __future__ import annotations

import copy
import dataclasses
import pathlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from PySide6.QtCore import Qt, QThread, Signal
from PySide6.QtWidgets import (
    QCheckBox,
    QComboBox,
    QDoubleSpinBox,
    QFileDialog,
    QGridLayout,
    QGroupBox,
    QHBoxLayout,
    QLabel,
    QListWidget,
    QListWidgetItem,
    QPushButton,
    QSlider,
    QSplitter,
    QVBoxLayout,
    QWidget,
)

from polrig.app.manifest import RESERVED_METADATA_KEYS
from polrig.app.session import Session
from polrig.errors import FormatError, PolrigError
from polrig.formats.exr import MuellerRows, mueller_exr, read_exr, stokes_exr
from polrig.formats.rawio import read_raw
from polrig.gui import geometry_layer, pipeline
from polrig.gui.live_panel import DEMOSAIC_METHODS, colour_choices
from polrig.gui.qtimage import to_qimage
from polrig.gui.roi_panel import AolpWheel, RoiTools
from polrig.gui.widgets import HistogramWidget, ImageView, ReadoutLabel, min_snr_box, scrolled
from polrig.optics.parameters import ANGLE_PERIOD_DEG, MAPS


def load_exr(path: str | pathlib.Path) -> pipeline.PolarizationData:
    """A Mueller or a Stokes EXR as :class:`pipeline.PolarizationData` (kind from its
    channels), with the file's masks (``valid``, ``saturated``, ``mask``, SNR planes:
    :func:`polrig.app.preview.exr_masks`) and its geometry planes (the single-shot networks'
    ``geometry.*``, or the ``sfp_*`` normals of a ``polrig analyze --normals`` maps EXR, which
    then holds only them: :func:`polrig.gui.geometry_layer.geometry_from_planes`);
    :class:`polrig.errors.FormatError` for anything else."""

    path = pathlib.Path(path)
    whole = read_exr(path)
    planes = whole.planes
    geometry = geometry_layer.geometry_from_planes(planes, whole.metadata)
    if any(k.startswith("M00.") for k in planes):
        img = mueller_exr(whole)  # the file is read once
        data = pipeline.PolarizationData.from_mueller(img.mueller, str(path), img.extra)
    elif any(k.startswith("S0.") for k in planes):
        img = stokes_exr(whole)
        data = pipeline.PolarizationData.from_stokes(img.stokes, str(path), img.extra)
    elif geometry is not None:
        data = pipeline.PolarizationData(source=str(path))
    else:
        raise FormatError(f"{path}: neither a Mueller (M00.*) nor a Stokes (S0.*) EXR, nor "
                          "geometry planes (geometry.*, sfp_normal*)")
    data.geometry = geometry
    return data


def load_raw(path: str | pathlib.Path, method: str = "superpixel") -> pipeline.PolarizationData:
    """A raw frame (with its sidecar) processed like a live frame."""

    return pipeline.process_frame(read_raw(path, layout="imx250myr"), method, source=str(path))


def session_entries(root: str | pathlib.Path) -> list[tuple[str, str, pathlib.Path]]:
    """``(label, kind, path)`` of the viewable files of a session: per capture its Mueller
    EXR(s) (``exr``) and raw frames (``raw``), in plan order."""

    s = Session.open(root)
    out = []
    for cap in s.captures:
        head = f"{cap['name']} ({cap['status']})"
        files = cap["files"]
        for role in ("mueller", "truth_mueller"):
            rec = files.get(role)
            if rec is not None:
                out.append((f"{head}: {role}.exr", "exr", s.root / rec["path"]))
        for name, rev in cap["revisions"].items():
            rec = rev["files"].get("mueller")
            if rec is not None:
                out.append((f"{head}: {name} mueller.exr", "exr", s.root / rec["path"]))
        for rec in files.get("raw", []):
            out.append((f"{head}: raw {pathlib.PurePosixPath(rec['path']).name}", "raw",
                        s.root / rec["path"]))
    return out


def metadata_text(entries: dict) -> str:
    """Sample metadata (``sample``, ``operator``, ``note``, user keys) as one line per given key."""
    return "\n".join(f"{k}: {v}" for k, v in entries.items() if isinstance(v, str) and v)


def session_metadata(root: str | pathlib.Path) -> dict[str, str]:
    """A session's sample metadata (:class:`polrig.app.manifest.SampleMetadata`), flat."""
    return Session.open(root).manifest["metadata"].header()


def result_metadata(path: str | pathlib.Path) -> dict[str, str]:
    """The sample metadata a result EXR's header holds (``{}`` for a file without, or not a
    Mueller result): ``sample``, ``operator``, ``note`` and the keys that are not polrig's."""
    try:
        with MuellerRows(path) as rows:
            header = rows.metadata
    except (PolrigError, OSError, ValueError):
        return {}
    named = {k: header[k] for k in ("sample", "operator", "note") if k in header}
    return {**named, **{k: v for k, v in sorted(header.items())
                        if k not in RESERVED_METADATA_KEYS and isinstance(v, str)}}


def initial_display(data: pipeline.PolarizationData, keep: str | None) -> str:
    """The display a newly opened file shows: the one shown before where the file has it,
    else the Mueller grid, else the file's first."""
    available = data.available()
    if keep in available:
        return keep
    return "mueller" if "mueller" in available else available[0]


def initial_geometry(data: pipeline.PolarizationData, keep: str | None) -> str | None:
    """The geometry layer choice a newly opened file shows (kept where it can be)."""
    keys = [key for key, _ in data.geometry.choices()] if data.geometry is not None else []
    return keep if keep in keys else (keys[0] if keys else None)


@dataclasses.dataclass
class Rendered:
    """An image rendered off the UI thread: ``key`` ``(display, colour, options, min_snr)``
    it was rendered for, the image and its histogram ``(counts, edges, label)``."""

    data: pipeline.PolarizationData
    key: tuple
    image: object
    histogram: tuple


@dataclasses.dataclass
class Loaded:
    """A file read (and its first image rendered) by the load thread."""

    data: pipeline.PolarizationData
    #: the result's sample metadata (:func:`result_metadata`; None for a raw frame)
    metadata: dict | None
    rendered: Rendered | None


#: Largest full-resolution image grid (pixels, ``H x W`` of :func:`pipeline.display_shape`) the
#: viewer redraws at once on the UI thread; larger ones are redrawn on the panel's load thread.
#: Measured (2 shared cores) with the image, its histogram and its QImage: the 3x3 Mueller grid
#: of a 128x128 colour result 14 ms, the virtual polarizer 4 ms; a 256x256 one's grid 60 ms,
#: a full colour sensor's (1224x1024) 1.1-1.5 s.
SYNC_REDRAW_MAX_PX = 128 * 128


def redraws_at_once(data: pipeline.PolarizationData, display: str) -> bool:
    """True where ``display`` of ``data`` is small enough to redraw on the UI thread
    (:data:`SYNC_REDRAW_MAX_PX`)."""
    h, w = pipeline.display_shape(data, display)
    return h * w <= SYNC_REDRAW_MAX_PX


def render_view(data: pipeline.PolarizationData, display: str, colour: int,
                options: pipeline.ViewOptions, min_snr: float,
                wanted: Callable[[], bool] = lambda: True) -> Rendered | None:
    """The image (with the saturation overlay) and histogram the viewer shows for these
    settings; ``data.min_snr`` must be ``min_snr``. None when ``wanted()`` says False once the
    image is rendered (superseded: its histogram is not computed). Raises ValueError where the
    data cannot show ``display``."""
    rgb = pipeline.render(data, display, colour, saturation_overlay=True, options=options)
    if not wanted():
        return None
    hist = pipeline.histogram(data, display, colour, options=options)
    return Rendered(data, (display, colour, options, min_snr), to_qimage(rgb), hist)


def load_and_render(path: pathlib.Path, kind: str, method: str, keep_display: str | None,
                    keep_geometry: str | None, options: pipeline.ViewOptions,
                    min_snr: float, wanted: Callable[[], bool] = lambda: True) -> Loaded:
    """Read ``path`` (``kind`` ``exr`` or ``raw``, a raw frame demosaiced by ``method``) and
    render the image the viewer will show first (the controls as given), as
    :meth:`ViewerPanel.set_data` then :meth:`ViewerPanel.refresh` would; not rendered when
    ``wanted()`` says False once the file is read (superseded). Runs on the load thread;
    raises what the readers raise."""
    data = load_exr(path) if kind == "exr" else load_raw(path, method)
    metadata = result_metadata(path) if kind == "exr" else None
    if not wanted():
        return Loaded(data, metadata, None)
    display = initial_display(data, keep_display)
    colour = colour_choices(data.n_colours)[0][1]
    options = dataclasses.replace(
        options, geometry=initial_geometry(data, keep_geometry) or geometry_layer.NETWORK_NORMAL)
    rendered = None
    if display != "maps" or data.maps_ready():  # maps come from a MapsWorker
        data.min_snr = min_snr
        try:
            rendered = render_view(data, display, colour, options, min_snr, wanted)
        except ValueError:  # refresh() says why, on the UI thread
            pass
    return Loaded(data, metadata, rendered)


def _angle_slider() -> QSlider:
    """A horizontal slider of an angle in whole degrees, 0..180 (180 is 0 again)."""
    sl = QSlider(Qt.Orientation.Horizontal)
    sl.setRange(0, 180)
    sl.setSingleStep(1)
    sl.setPageStep(15)
    sl.setTickInterval(45)
    sl.setTickPosition(QSlider.TickPosition.TicksBelow)
    return sl


class MapsWorker(QThread):
    """Computes the parameter maps of one :class:`pipeline.PolarizationData` off the GUI thread.
    Signals: ``done(data, MapSet)``, ``failed(data, text)``; ``data`` is the object the maps
    belong to, so that the receiver can tell a stale result."""

    done = Signal(object, object)
    failed = Signal(object, str)

    def __init__(self, data: pipeline.PolarizationData, parent=None):
        super().__init__(parent)
        self.data = data

    def run(self) -> None:
        try:
            maps = self.data.compute_maps()
        except Exception as exc:  # noqa: BLE001 - a failure is a message, never a dead thread
            self.failed.emit(self.data, f"{type(exc).__name__}: {exc}")
            return
        self.done.emit(self.data, maps)


#: What the view shows while the parameter maps are computed.
COMPUTING_MAPS = "computing parameter maps..."
#: What the view says across the image while a redraw runs.
REDRAWING = "redrawing..."


class ViewerPanel(QWidget):
    """Open a session or an EXR, pick an entry, choose the display."""

    message = Signal(str, str)
    #: the latest load has ended: shown (True) or its error reported (False)
    loaded = Signal(bool)
    #: from the load thread: load id, path, kind, :class:`Loaded` or the error text
    _load_ended = Signal(int, object, str, object)
    #: the image of the latest display settings is shown (or its error reported)
    drawn = Signal()
    #: from the load thread: redraw id, :class:`Rendered` or the error text
    _draw_ended = Signal(int, object)

    def __init__(self, parent=None):
        super().__init__(parent)
        #: files are read and first rendered, and large images redrawn, here, off the UI
        #: thread; ``_load_id`` and ``_draw_id`` tell the latest load and redraw from those
        #: they superseded
        self._loader = ThreadPoolExecutor(max_workers=1, thread_name_prefix="viewer-load")
        self._load_id = 0
        self._loading = False
        self._draw_id = 0
        self._drawing = False
        self._load_text = ""
        self._rendered: Rendered | None = None
        self._load_ended.connect(self._load_finished)
        self._draw_ended.connect(self._draw_finished)
        self.data: pipeline.PolarizationData | None = None
        #: the worker computing parameter maps, if one runs
        self.maps_worker: MapsWorker | None = None
        self.path: pathlib.Path | None = None
        open_session = QPushButton("Open session...")
        open_exr = QPushButton("Open EXR...")
        open_session.clicked.connect(self._ask_session)
        open_exr.clicked.connect(self._ask_exr)
        self.entries = QListWidget()
        self.entries.currentItemChanged.connect(self._entry_chosen)
        self.display = QComboBox()
        self.colour = QComboBox()
        self.method = QComboBox()
        self.method.addItems(DEMOSAIC_METHODS)
        self.display.currentIndexChanged.connect(self.refresh)
        self.colour.currentIndexChanged.connect(self.refresh)
        self.method.currentIndexChanged.connect(self._reload)
        self.view = ImageView(placeholder="open a session folder or a Mueller/Stokes EXR")
        self.view.hovered.connect(self._hovered)
        self.readout = ReadoutLabel("")
        #: the sample metadata of the session or file shown (who, why, what)
        self.metadata = QLabel("")
        self.metadata.setWordWrap(True)
        self.metadata.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.min_snr = min_snr_box()
        self.min_snr.valueChanged.connect(self.refresh)
        self.histogram = HistogramWidget()
        # the parameter-maps layer: which map, or its sigma
        self.map_name = QComboBox()
        for name, text in MAPS.items():
            self.map_name.addItem(name, name)
            self.map_name.setItemData(self.map_name.count() - 1, text, Qt.ItemDataRole.ToolTipRole)
        self.map_name.setCurrentIndex(self.map_name.findData("retardance_deg"))
        self.map_sigma = QCheckBox("show its sigma")
        self.map_name.currentIndexChanged.connect(self.refresh)
        self.map_sigma.toggled.connect(self.refresh)
        # the virtual polarizer: incident linear state (or unpolarized) and analyzer angle
        self.incident = _angle_slider()
        self.analyzer = _angle_slider()
        self.unpolarized = QCheckBox("unpolarized")
        self.no_analyzer = QCheckBox("no analyzer")
        self.incident_label, self.analyzer_label = QLabel(), QLabel()
        for w in (self.incident, self.analyzer):
            w.valueChanged.connect(self.refresh)
        for w in (self.unpolarized, self.no_analyzer):
            w.toggled.connect(self.refresh)
        # the geometry layer: the networks' normal or albedo, or a shape-from-polarization candidate
        self.geometry_choice = QComboBox()
        self.geometry_choice.currentIndexChanged.connect(self.refresh)
        self.wheel = AolpWheel(110)
        self.roi = RoiTools(self.view)
        self.roi.message.connect(self.message)

        maps_box = QGroupBox("Parameter map (display \"Parameter map\")")
        g = QHBoxLayout(maps_box)
        g.addWidget(self.map_name, 1)
        g.addWidget(self.map_sigma)
        pol_box = QGroupBox("Virtual polarizer (display \"Virtual polarizer\")")
        g = QGridLayout(pol_box)
        g.addWidget(QLabel("incident"), 0, 0)
        g.addWidget(self.incident, 0, 1)
        g.addWidget(self.incident_label, 0, 2)
        g.addWidget(self.unpolarized, 0, 3)
        g.addWidget(QLabel("analyzer"), 1, 0)
        g.addWidget(self.analyzer, 1, 1)
        g.addWidget(self.analyzer_label, 1, 2)
        g.addWidget(self.no_analyzer, 1, 3)

        left = QVBoxLayout()
        row = QHBoxLayout()
        row.addWidget(open_session)
        row.addWidget(open_exr)
        left.addLayout(row)
        left.addWidget(self.metadata)
        left.addWidget(self.entries, 1)
        for label, w in (("Display", self.display), ("Colour", self.colour),
                         ("Demosaic (raw frames)", self.method),
                         ("Mask below signal-to-noise", self.min_snr)):
            left.addWidget(QLabel(label))
            left.addWidget(w)
        left.addWidget(maps_box)
        left.addWidget(pol_box)
        geo_box = QGroupBox("Geometry (display \"Geometry\")")
        QHBoxLayout(geo_box).addWidget(self.geometry_choice, 1)
        left.addWidget(geo_box)
        row = QHBoxLayout()
        row.addWidget(self.histogram, 1)
        row.addWidget(self.wheel)
        left.addLayout(row)
        left.addWidget(self.readout.area, 1)
        lw = QWidget()
        lw.setLayout(left)
        lw.setMinimumWidth(430)
        left_area = scrolled(lw)  # the controls and the ROI tools scroll, the image scales
        left_area.setMinimumWidth(450)
        left_area.setMaximumWidth(540)
        self.roi.setMinimumWidth(500)
        split = QSplitter()
        split.addWidget(left_area)
        split.addWidget(self.view)
        split.addWidget(scrolled(self.roi))
        split.setStretchFactor(1, 3)
        split.setStretchFactor(2, 1)
        split.setSizes([430, 420, 600])  # the table's eight columns fit beside the image
        QHBoxLayout(self).addWidget(split)
        self._angle_labels()

    # -- opening
    def _ask_session(self) -> None:
        path = QFileDialog.getExistingDirectory(self, "Session folder")
        if path:
            self.open_session(path)

    def _ask_exr(self) -> None:
        path, _ = QFileDialog.getOpenFileName(self, "EXR file", "", "OpenEXR (*.exr)")
        if path:
            self.open_file(path)

    def open_session(self, root: str | pathlib.Path) -> bool:
        """List a session's files (its manifest, read here) and start loading the first
        (:meth:`open_file`); False when the session cannot be read."""
        try:
            entries = session_entries(root)
            metadata = session_metadata(root)
        except (PolrigError, OSError, ValueError) as exc:
            self.message.emit("error", f"viewer: {exc}")
            return False
        self.metadata.setText(metadata_text(metadata))
        self.entries.clear()
        for label, kind, path in entries:
            item = QListWidgetItem(label)
            item.setData(Qt.ItemDataRole.UserRole, (kind, str(path)))
            self.entries.addItem(item)
        self.message.emit("info", f"viewer: {root}: {len(entries)} files")
        if entries:
            self.entries.setCurrentRow(0)
        return True

    def open_file(self, path: str | pathlib.Path, kind: str = "exr") -> bool:
        """Start loading ``path`` (``kind`` ``exr`` or ``raw``) on the load thread; it is shown
        when read (``loaded(True)``), a file that cannot be read is a one-line error
        (``loaded(False)``). A load still running is superseded: its file is never shown.
        Returns whether the load started (False once the panel has shut down)."""
        path = pathlib.Path(path)
        self._load_id += 1  # an earlier load still running is superseded
        job = self._load_id
        o = self.options()
        try:
            self._loader.submit(self._load, job, path, kind, self.method.currentText(),
                                self.display.currentData(), self.geometry_choice.currentData(),
                                o, self.min_snr.value())
        except RuntimeError:  # shut down: the window is closing
            self._loading = False
            return False
        self._loading = True
        self._load_text = f"loading {path.name}..."
        self._banner()
        if self.view.image() is None:
            self.view.set_placeholder(self._load_text)
        return True

    def _load(self, job: int, path: pathlib.Path, kind: str, *args) -> None:
        """The load thread: read and render one file, hand it to the UI thread."""
        if job != self._load_id:  # superseded while queued
            return
        try:
            outcome: Loaded | str = load_and_render(path, kind, *args,
                                                    wanted=lambda: job == self._load_id)
        except Exception as exc:  # noqa: BLE001 - a damaged file is a message, never a crash
            outcome = (str(exc) if isinstance(exc, (PolrigError, OSError, ValueError))
                       else f"{type(exc).__name__}: {exc}")
        try:
            self._load_ended.emit(job, path, kind, outcome)
        except RuntimeError:  # the panel is gone
            pass

    def _load_finished(self, job: int, path: pathlib.Path, kind: str, outcome) -> None:
        if job != self._load_id:  # a newer load was started meanwhile: dropped
            return
        self._loading = False
        self._banner()
        if isinstance(outcome, str):
            self.clear(f"cannot show {path.name}: {outcome}")
            self.message.emit("error", f"viewer: {outcome}")
            self.loaded.emit(False)
            return
        self.path = path
        self._kind = kind
        if outcome.metadata is not None:
            found = outcome.metadata
            if found or not self.entries.count():  # a session's own stays when its file has none
                self.metadata.setText(metadata_text(found))
        self._rendered = outcome.rendered
        try:
            self.set_data(outcome.data)
        finally:
            self._rendered = None
        self.loaded.emit(True)

    @property
    def loading(self) -> bool:
        """True from :meth:`open_file` until its file is shown or its error reported."""
        return self._loading

    def _entry_chosen(self, item, _prev=None) -> None:
        if item is not None:
            kind, path = item.data(Qt.ItemDataRole.UserRole)
            self.open_file(path, kind)

    def _reload(self) -> None:
        if self.path is not None and getattr(self, "_kind", "") == "raw":
            self.open_file(self.path, "raw")

    # -- showing
    def clear(self, placeholder: str = "") -> None:
        """Show nothing (after a file that cannot be read): no image, histogram or readout
        of an earlier file stays on screen."""
        self._draw_id += 1  # a redraw of the data cleared is never shown
        self._end_redraw()
        self.data = None
        self.path = None
        self.view.set_image(None)
        if placeholder:
            self.view.set_placeholder(placeholder)
        self.histogram.set_data(np.zeros(0), np.zeros(1), "")
        self.readout.setText("")
        self.roi.set_data(None)

    def set_data(self, data: pipeline.PolarizationData) -> None:
        self.data = data
        want = initial_display(data, self.display.currentData())
        self.display.blockSignals(True)
        self.colour.blockSignals(True)
        self.display.clear()
        for key in data.available():
            self.display.addItem(pipeline.DISPLAYS[key], key)
        self.display.setCurrentIndex(self.display.findData(want))
        self.colour.clear()
        for label, value in colour_choices(data.n_colours):
            self.colour.addItem(label, value)
        self.display.blockSignals(False)
        self.colour.blockSignals(False)
        self._geometry_choices(data)
        self.refresh()
        self.roi.set_data(data)

    def _geometry_choices(self, data: pipeline.PolarizationData) -> None:
        """Offer what the data's geometry can show (kept across files where it can)."""
        want = initial_geometry(data, self.geometry_choice.currentData())
        self.geometry_choice.blockSignals(True)
        self.geometry_choice.clear()
        for key, label in data.geometry.choices() if data.geometry is not None else []:
            self.geometry_choice.addItem(label, key)
        self.geometry_choice.setCurrentIndex(max(self.geometry_choice.findData(want), 0))
        self.geometry_choice.setEnabled(data.geometry is not None)
        self.geometry_choice.blockSignals(False)

    def options(self) -> pipeline.ViewOptions:
        """The parameter map and the virtual polarizer's angles the controls say."""
        return pipeline.ViewOptions(
            map_name=self.map_name.currentData(), map_sigma=self.map_sigma.isChecked(),
            incident_deg=None if self.unpolarized.isChecked() else float(self.incident.value()),
            analyzer_deg=None if self.no_analyzer.isChecked() else float(self.analyzer.value()),
            geometry=self.geometry_choice.currentData() or geometry_layer.NETWORK_NORMAL)

    def _angle_labels(self) -> None:
        o = self.options()
        self.incident_label.setText("unpolarized" if o.incident_deg is None
                                    else f"{o.incident_deg:5.0f} deg")
        self.analyzer_label.setText("none" if o.analyzer_deg is None
                                    else f"{o.analyzer_deg:5.0f} deg")
        self.incident.setEnabled(o.incident_deg is not None)
        self.analyzer.setEnabled(o.analyzer_deg is not None)

    def _wheel_mode(self, display: str) -> str | None:
        if display in pipeline.AOLP_DOLP_AS:
            return pipeline.AOLP_DOLP_AS[display]
        if display == "maps" and self.map_name.currentData() in ANGLE_PERIOD_DEG:
            return None
        return "value"

    # -- the parameter maps, off the GUI thread
    @property
    def maps_busy(self) -> bool:
        """True while a :class:`MapsWorker` runs."""
        return self.maps_worker is not None

    def _request_maps(self) -> None:
        """Start a worker for the maps of the data shown, unless one runs (when it ends,
        :meth:`_maps_done` asks again for the data shown then)."""
        if self.maps_worker is not None or self.data is None or self.data.maps_ready():
            return
        w = MapsWorker(self.data, self)
        w.done.connect(self._maps_done)
        w.failed.connect(self._maps_failed)
        self.maps_worker = w
        w.start()

    def _worker_ended(self) -> None:
        w, self.maps_worker = self.maps_worker, None
        if w is not None:
            w.wait()  # its run() has returned: the signal was its last act
            w.deleteLater()

    def _maps_done(self, data: pipeline.PolarizationData, maps) -> None:
        self._worker_ended()
        if data is not self.data:  # another file is shown now: discard, ask for its maps
            if self.data is not None and self.display.currentData() == "maps":
                self._request_maps()
            return
        data.set_maps(maps)
        if self.display.currentData() == "maps":
            self.refresh()

    def _maps_failed(self, data: pipeline.PolarizationData, text: str) -> None:
        self._worker_ended()
        if data is self.data:
            self.view.set_placeholder(f"parameter maps failed: {text}")
            self.message.emit("error", f"viewer: parameter maps: {text}")
        elif self.data is not None and self.display.currentData() == "maps":
            self._request_maps()

    def shutdown(self, wait_ms: int = 60000) -> bool:
        """End the load and ROI threads (a file being read or an image being redrawn is
        finished, not shown) and wait for a running maps worker (numpy cannot be
        interrupted); True when none runs."""
        self._load_id += 1  # a load in progress skips its rendering and is dropped
        self._loading = False
        self._draw_id += 1  # so is a redraw
        self._drawing = False
        self._loader.shutdown(wait=True, cancel_futures=True)
        self.roi.shutdown()
        w = self.maps_worker
        return w is None or w.wait(wait_ms)

    def refresh(self, *_a) -> None:
        """Show the data with the display settings the controls say: at once where the image
        is small (:func:`redraws_at_once`), else redrawn on the load thread (:attr:`drawing`
        until it is shown; a redraw still running or queued is superseded)."""
        self._angle_labels()
        if self.data is None or self.display.currentData() is None:
            return
        display, colour = self.display.currentData(), self.colour.currentData()
        self.data.min_snr = self.min_snr.value()
        options = self.options()
        data = self.data
        self.roi.to_data = lambda pts: pipeline.display_to_data(data, display, pts)
        self._draw_id += 1  # an earlier redraw still running or queued is superseded
        job = self._draw_id
        if display == "maps" and not data.maps_ready():
            self._end_redraw()
            self.view.set_image(None)
            self.view.set_placeholder(COMPUTING_MAPS)
            self.histogram.set_data(np.zeros(0), np.zeros(1), COMPUTING_MAPS)
            self.wheel.set_mode(self._wheel_mode(display))
            self._request_maps()
            return
        key = (display, colour, options, data.min_snr)
        done = self._rendered  # rendered with the file on the load thread
        if done is not None and done.data is data and done.key == key:
            self._draw_finished(job, done)
            return
        if redraws_at_once(data, display):
            self._draw_finished(job, self._redraw(job, data, key))
            return
        if self._loading:  # the file being loaded comes next, drawn with the settings then
            self._end_redraw()
            return
        # the thread renders a copy holding this threshold (the UI thread sets data.min_snr);
        # the copy shares the data's arrays and its cache of derived images
        snapshot = copy.copy(data)
        snapshot.min_snr = data.min_snr
        try:
            self._loader.submit(self._draw, job, snapshot, key)
        except RuntimeError:  # shut down: the window is closing
            self._drawing = False
            return
        self._drawing = True
        self._banner()

    def _redraw(self, job: int, data: pipeline.PolarizationData,
                key: tuple) -> Rendered | str | None:
        """One redraw: its :class:`Rendered`, its error text, or None (superseded meanwhile)."""
        try:
            return render_view(data, *key, wanted=lambda: job == self._draw_id)
        except ValueError as exc:
            return str(exc)
        except Exception as exc:  # noqa: BLE001 - a failure is a message, never a dead thread
            return f"{type(exc).__name__}: {exc}"

    def _draw(self, job: int, data: pipeline.PolarizationData, key: tuple) -> None:
        """The load thread: redraw the image for the settings ``key``, hand it to the UI
        thread; skipped when a newer change superseded it while queued."""
        if job != self._draw_id:  # superseded while queued
            return
        outcome = self._redraw(job, data, key)
        try:
            self._draw_ended.emit(job, outcome)
        except RuntimeError:  # the panel is gone
            pass

    def _draw_finished(self, job: int, outcome) -> None:
        if job != self._draw_id or outcome is None:  # a newer change or file came: dropped
            return
        self._end_redraw()
        if isinstance(outcome, str):
            self.message.emit("error", f"viewer: {outcome}")
        else:
            self.histogram.set_data(*outcome.histogram)
            self.view.set_image(outcome.image)
            self.wheel.set_mode(self._wheel_mode(outcome.key[0]))
        self.drawn.emit()

    def _end_redraw(self) -> None:
        """No redraw pending any more: its banner goes (a load's stays)."""
        if self._drawing:
            self._drawing = False
            self._banner()

    def _banner(self) -> None:
        """Say across the image what is pending: a load, else a redraw, else nothing."""
        self.view.set_banner(self._load_text if self._loading
                             else REDRAWING if self._drawing else "")

    @property
    def drawing(self) -> bool:
        """True from a change of the display settings until the image of the latest is shown
        (or its error reported); always False for a small image, redrawn at once."""
        return self._drawing

    def _hovered(self, x: int, y: int) -> None:
        if self.data is not None and x >= 0:
            self.data.min_snr = self.min_snr.value()
            display = self.display.currentData()
            if display == "maps" and not self.data.maps_ready():
                layer = COMPUTING_MAPS
            else:
                layer = pipeline.layer_readout(self.data, display, self.options(), x, y)
            text = pipeline.readout(self.data, display, x, y)
            self.readout.setText(f"{layer}\n{text}" if layer else text)
