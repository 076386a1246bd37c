"""ROI tools of the viewer and the live view: draw a rectangle, ellipse or polygon ROI or a
line on the image, see the statistics table (counted and masked pixels) and the profile, export
CSV; and the AoLP colour wheel shown beside every image.

The numbers are :func:`polrig.gui.pipeline.roi_statistics` and
:func:`polrig.app.roi.line_profile` (what ``polrig stats`` computes); this module only turns
drawn shapes into :mod:`polrig.app.roi` geometry and shows the rows. They are computed on a
thread of their own (one worker, as the capture panel's thumbnails; at the full sensor's
1224x1024 superpixel grid a region's statistics take seconds): the table says "computing..."
meanwhile, a result for an earlier shape or data is dropped, and :meth:`RoiTools.shutdown`
ends the thread.
"""

from __future__ import annotations

import math
import pathlib
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor

import numpy as np
from PySide6.QtCore import Qt, Signal
from PySide6.QtGui import QColor, QPainter, QPen, QPixmap
from PySide6.QtWidgets import (
    QComboBox,
    QFileDialog,
    QHBoxLayout,
    QLabel,
    QPushButton,
    QTableWidget,
    QTableWidgetItem,
    QVBoxLayout,
    QWidget,
)

from polrig.app import preview, roi
from polrig.atomic import atomic_write_text
from polrig.gui import pipeline
from polrig.gui.qtimage import to_qimage
from polrig.gui.widgets import DRAW_TOOLS, ImageView

#: Columns of the statistics table (labels), one per :data:`polrig.app.roi.STATS_COLUMNS`.
TABLE_COLUMNS = ("quantity", "ch", "mean", "std / spread", "sem scatter", "sem sigma",
                 "counted", "masked")
#: Pen colour of each channel in the profile plot.
CHANNEL_PENS = {"Y": QColor(40, 40, 40), "R": QColor(200, 40, 40), "G": QColor(30, 150, 40),
                "B": QColor(40, 70, 210)}


def shape_from_points(tool: str, points: list[tuple[float, float]]):
    """A drawn shape (image coordinates) -> :mod:`polrig.app.roi` geometry (``rect``,
    ``ellipse``: the drag's box; ``poly``: its vertices) or, for ``line``, the segment
    ``(x0, y0, x1, y1)``."""
    if tool == "poly":
        return roi.PolygonROI(tuple((float(x), float(y)) for x, y in points))
    (x0, y0), (x1, y1) = points[0], points[-1]
    if tool == "line":
        return (x0, y0, x1, y1)
    if tool == "rect":
        return roi.RectROI(min(x0, x1), min(y0, y1), abs(x1 - x0), abs(y1 - y0))
    if tool == "ellipse":
        return roi.EllipseROI((x0 + x1) / 2, (y0 + y1) / 2, abs(x1 - x0) / 2, abs(y1 - y0) / 2)
    raise ValueError(f"unknown drawing tool {tool!r}")


def _fmt(v) -> str:
    if isinstance(v, float):
        return f"{v:.5g}" if math.isfinite(v) else str(v)
    return str(v)


class AolpWheel(QLabel):
    """The AoLP colour wheel (:func:`polrig.app.preview.aolp_wheel`), always on screen beside
    the image; it follows how the AoLP display shows DoLP (:meth:`set_mode`)."""

    def __init__(self, size: int = 120, parent=None):
        super().__init__(parent)
        self.wheel_px = int(size)
        self.mode: str | None = "value"
        self.setFixedSize(self.wheel_px, self.wheel_px)
        self.setToolTip("AoLP colour key: hue = angle of linear polarization (0 deg along the "
                        "image +u axis, counter-clockwise towards image up); distance from the "
                        "centre = DoLP 0..1, shown as value or as saturation like the display")
        self.set_mode("value")

    def set_mode(self, dolp_as: str | None) -> None:
        self.mode = dolp_as
        self.rgb = preview.aolp_wheel(self.wheel_px, dolp_as=dolp_as)
        self.setPixmap(QPixmap.fromImage(to_qimage(self.rgb)))


class ProfilePlot(QWidget):
    """A line plot of one profile quantity against arc length, one pen per colour."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.s = np.zeros(0)
        self.values = np.zeros((0, 0))
        self.channels: tuple[str, ...] = ()
        self.label = ""
        self.setMinimumHeight(90)

    def set_profile(self, s: np.ndarray, values: np.ndarray, channels: tuple[str, ...],
                    label: str) -> None:
        self.s, self.values, self.channels, self.label = s, values, channels, label
        self.update()

    def paintEvent(self, _event) -> None:  # noqa: N802
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(250, 250, 250))
        finite = self.values[np.isfinite(self.values)] if self.values.size else self.values
        if self.s.size < 2 or finite.size == 0:
            p.setPen(QColor(120, 120, 120))
            p.drawText(self.rect(), Qt.AlignmentFlag.AlignCenter, "draw a line for a profile")
            return
        lo, hi = float(finite.min()), float(finite.max())
        hi = hi if hi > lo else lo + 1.0
        w, h, top = self.width() - 4, self.height() - 18, 2
        smax = float(self.s[-1]) or 1.0
        p.setRenderHint(QPainter.RenderHint.Antialiasing, True)
        for ci, ch in enumerate(self.channels):
            pen = QPen(CHANNEL_PENS.get(ch, QColor(0, 0, 0)))
            pen.setWidth(2)
            p.setPen(pen)
            prev = None
            for s, v in zip(self.s, self.values[ci]):
                if not np.isfinite(v):
                    prev = None
                    continue
                pt = (2 + s / smax * w, top + (hi - v) / (hi - lo) * h)
                if prev is not None:
                    p.drawLine(int(prev[0]), int(prev[1]), int(pt[0]), int(pt[1]))
                prev = pt
        p.setPen(QColor(0, 0, 0))
        p.drawText(2, self.height() - 3, f"{self.label}: {lo:.4g} .. {hi:.4g} over {smax:.4g} px")


#: What the ROI summary says while the statistics are computed.
COMPUTING_ROI = "computing the ROI statistics..."


class RoiTools(QWidget):
    """Drawing tool choice, statistics table, profile plot and CSV export for an
    :class:`ImageView`. :meth:`set_data` gives the data and how image points map to its pixels
    (``to_data``: a list of image points -> data points; default the identity). The numbers
    are computed off the UI thread; :attr:`busy` is True until the latest request's arrive
    (``computed`` is emitted then)."""

    message = Signal(str, str)
    #: the latest request's numbers are shown (or its error reported)
    computed = Signal()
    #: from the statistics thread: request id, rows (None: no region), profile (None: no
    #: line), error text ("" when none)
    _result = Signal(int, object, object, str)

    def __init__(self, view: ImageView, parent=None):
        super().__init__(parent)
        self.view = view
        #: ROI statistics and profiles are computed here, off the UI thread; ``_job`` tells
        #: the latest request's result from those of earlier ones
        self._worker = ThreadPoolExecutor(max_workers=1, thread_name_prefix="roi-statistics")
        self._job = 0
        self._pending = False
        self._result.connect(self._show_result)
        self.data: pipeline.PolarizationData | None = None
        self.to_data: Callable[[list], list] = lambda pts: pts
        self.region: roi.ROI | None = None
        self.segment: tuple[float, float, float, float] | None = None
        self.rows: list[roi.RoiRow] = []
        self.profile: roi.Profile | None = None
        self.tool = QComboBox()
        for key, label in DRAW_TOOLS.items():
            self.tool.addItem(label, key)
        self.tool.currentIndexChanged.connect(lambda _i: view.set_tool(self.tool.currentData()))
        self.summary = QLabel("no ROI: choose a tool and draw on the image")
        self.summary.setWordWrap(True)
        self.summary.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.table = QTableWidget(0, len(TABLE_COLUMNS))
        self.table.setHorizontalHeaderLabels(TABLE_COLUMNS)
        self.table.verticalHeader().setVisible(False)
        self.table.setEditTriggers(QTableWidget.EditTrigger.NoEditTriggers)
        self.table.setMinimumHeight(140)
        self.table.verticalHeader().setDefaultSectionSize(20)
        self.table.setStyleSheet("font-size: 9pt")
        self.plot = ProfilePlot()
        self.profile_quantity = QComboBox()
        self.profile_quantity.currentIndexChanged.connect(self._show_profile)
        self.export = QPushButton("Export CSV...")
        self.export.clicked.connect(lambda: self.export_csv())
        lay = QVBoxLayout(self)
        lay.setContentsMargins(0, 0, 0, 0)
        row = QHBoxLayout()
        row.addWidget(QLabel("Tool"))
        row.addWidget(self.tool, 1)
        row.addWidget(self.export)
        lay.addLayout(row)
        lay.addWidget(self.summary)
        lay.addWidget(self.table, 2)
        row = QHBoxLayout()
        row.addWidget(QLabel("Profile of"))
        row.addWidget(self.profile_quantity, 1)
        lay.addLayout(row)
        lay.addWidget(self.plot, 1)
        view.drawn.connect(self._drawn)

    # -- input
    def set_data(self, data: pipeline.PolarizationData | None,
                 to_data: Callable[[list], list] | None = None) -> None:
        """New data (a new file, a new live frame): the drawn ROI and line are measured again."""
        self.data = data
        if to_data is not None:
            self.to_data = to_data
        self.recompute()

    def _drawn(self, tool: str, points: list) -> None:
        shape = shape_from_points(tool, self.to_data(points))
        if tool == "line":
            self.segment = shape
        else:
            self.region = shape
        self.recompute()

    def set_region(self, region: roi.ROI | None) -> None:
        """Measure ``region`` (data pixels) as if drawn."""
        self.region = region
        self.recompute()

    def set_segment(self, segment: tuple[float, float, float, float] | None) -> None:
        self.segment = segment
        self.recompute()

    # -- numbers
    def recompute(self) -> None:
        """Measure the region and the line on the data, on the statistics thread."""
        self._job += 1  # whatever is still being computed is for an earlier request
        data = self.data
        if data is None or (data.mueller is None and data.stokes is None):
            self._pending = False
            self.rows, self.profile = [], None
            self._fill()
            self.computed.emit()
            return
        if self.region is None and self.segment is None:
            self._pending = False
            self.computed.emit()
            return
        self._pending = True
        if self.region is not None:
            self.summary.setText(f"{self.region.text()}: {COMPUTING_ROI}")
        try:
            self._worker.submit(self._compute, self._job, data, self.region, self.segment)
        except RuntimeError:  # shut down: the window is closing
            self._pending = False

    def _compute(self, job: int, data: pipeline.PolarizationData, region, segment) -> None:
        """The statistics thread: one request's rows and profile, handed to the UI thread."""
        if job != self._job:  # superseded while queued
            return
        rows = profile = None
        error = ""
        try:
            if region is not None:
                rows = pipeline.roi_statistics(data, roi.roi_mask(region, pipeline.roi_shape(data)))
            if segment is not None:
                profile = pipeline.roi_profile(data, segment)
        except (ValueError, FloatingPointError) as exc:
            error = str(exc)
        except Exception as exc:  # noqa: BLE001 - a failure is a message, never a dead thread
            error = f"{type(exc).__name__}: {exc}"
        try:
            self._result.emit(job, rows, profile, error)
        except RuntimeError:  # the panel is gone
            pass

    def _show_result(self, job: int, rows, profile, error: str) -> None:
        if job != self._job:  # an earlier shape or data: dropped
            return
        self._pending = False
        if error:
            self.summary.setText(f"ROI: {error}")
            self.message.emit("error", f"ROI: {error}")
        else:
            if rows is not None:
                self.rows = rows
            if profile is not None:
                self.profile = profile
            self._fill()
        self.computed.emit()

    @property
    def busy(self) -> bool:
        """True until the numbers of the latest shape and data are shown."""
        return self._pending

    def shutdown(self) -> None:
        """End the statistics thread (a computation in progress is finished, queued ones
        dropped) before the panel goes."""
        self._job += 1
        self._pending = False
        self._worker.shutdown(wait=True, cancel_futures=True)

    def _fill(self) -> None:
        self.table.setRowCount(len(self.rows))
        for i, r in enumerate(self.rows):
            cells = (r.quantity + (" (circ.)" if r.kind != "linear" else ""), r.channel,
                     r.mean, r.std, r.sem_scatter, r.sem_sigma, r.n_counted, r.n_masked)
            for j, v in enumerate(cells):
                item = QTableWidgetItem(_fmt(v))
                if j >= 2:
                    item.setTextAlignment(Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter)
                self.table.setItem(i, j, item)
        self.table.resizeColumnsToContents()
        if self.region is not None and self.rows:
            first = self.rows[0]
            self.summary.setText(f"{self.region.text()}: {first.n_counted + first.n_masked} "
                                 f"pixels inside, {first.n_counted} counted, {first.n_masked} "
                                 f"masked ({first.quantity}); sem scatter = std/sqrt(n), sem "
                                 f"sigma from the pixels' sigma planes")
        keep = self.profile_quantity.currentText()
        names = list(self.profile.values) if self.profile is not None else []
        if [self.profile_quantity.itemText(i) for i in range(self.profile_quantity.count())] != names:
            self.profile_quantity.blockSignals(True)
            self.profile_quantity.clear()
            self.profile_quantity.addItems(names)
            if keep in names:
                self.profile_quantity.setCurrentText(keep)
            self.profile_quantity.blockSignals(False)
        self._show_profile()

    def _show_profile(self, *_a) -> None:
        p = self.profile
        name = self.profile_quantity.currentText()
        if p is None or name not in p.values:
            self.plot.set_profile(np.zeros(0), np.zeros((0, 0)), (), "")
            return
        self.plot.set_profile(p.s, p.values[name], p.channels, name)

    def table_values(self) -> list[list[str]]:
        """The table's text, row by row (what the operator sees)."""
        return [[self.table.item(i, j).text() for j in range(self.table.columnCount())]
                for i in range(self.table.rowCount())]

    # -- export
    def export_csv(self, path: str | pathlib.Path | None = None) -> list[pathlib.Path]:
        """Write the statistics (``path``) and the profile (``PATH_profile.csv``) as CSV
        (:func:`polrig.app.roi.stats_csv`, :func:`polrig.app.roi.profile_csv`); asks for the
        file without ``path``. Returns the files written."""
        if self.busy:
            self.message.emit("warning", "ROI: the statistics are still being computed: export "
                                         "once the table shows them")
            return []
        if not self.rows and self.profile is None:
            self.message.emit("warning", "ROI: nothing to export: draw an ROI or a line first")
            return []
        if path is None:
            path, _ = QFileDialog.getSaveFileName(self, "ROI statistics CSV", "roi.csv",
                                                  "CSV (*.csv)")
            if not path:
                return []
        path = pathlib.Path(path)
        header = {"source": self.data.source if self.data is not None else "",
                  "pixel_convention": "pixel (u, v) has its centre at (u + 0.5, v + 0.5)"}
        written = []
        try:
            if self.rows:
                atomic_write_text(path, roi.stats_csv(self.rows, {**header,
                                                                  "roi": self.region.text()}))
                written.append(path)
            if self.profile is not None:
                out = path.with_name(path.stem + "_profile.csv")
                seg = ",".join(f"{v:g}" for v in self.segment)
                atomic_write_text(out, roi.profile_csv(self.profile, {**header, "profile": seg,
                                                                      "spacing_px": "1"}))
                written.append(out)
        except OSError as exc:
            self.message.emit("error", f"ROI: cannot write {path}: {exc}")
            return written
        self.message.emit("info", "ROI: wrote " + ", ".join(map(str, written)))
        return written
