"""Small widgets shared by the panels: image view with cursor tracking, histogram, messages."""

from __future__ import annotations

import time

import numpy as np
from PySide6.QtCore import QPoint, QRect, Qt, Signal
from PySide6.QtGui import QColor, QImage, QPainter, QPen
from PySide6.QtWidgets import (
    QComboBox,
    QDoubleSpinBox,
    QFrame,
    QLabel,
    QPlainTextEdit,
    QScrollArea,
    QSizePolicy,
    QWidget,
)

from polrig.app.preview import DEFAULT_MIN_SNR


def network_binning_box(what: str) -> QComboBox:
    """The single-shot network binning control (the item data: 1 or 2, as
    :data:`polrig.acquisition.plan.NETWORK_BINNINGS` and :data:`polrig.models.full_resolution.BINNINGS`): the
    networks on the analyzer grid, or on that grid binned 2x2 (the faster mode). ``what``
    starts the tool tip: what the choice applies to."""
    box = QComboBox()
    box.addItem("1 (the analyzer grid)", 1)
    box.addItem("2 (binned 2x2: faster)", 2)
    box.setToolTip(f"{what}: the networks on the analyzer grid, or on that grid binned 2x2 and lifted "
                   "back with its measured detail (about half the frame time at full sensor size, a "
                   "few tenths of a dB less accurate, the same output grid, no sigma; the model "
                   "card's \"Speed, warm and cold\")")
    return box


def min_snr_box() -> QDoubleSpinBox:
    """The "mask below signal-to-noise" control: DoLP, AoLP and ``m_ij / m00`` are masked
    where ``S0`` (``m00``) is below this many noise standard deviations (0: off)."""
    box = QDoubleSpinBox()
    box.setRange(0.0, 1000.0)
    box.setDecimals(1)
    box.setSingleStep(0.5)
    box.setValue(DEFAULT_MIN_SNR)
    box.setSuffix(" sigma")
    box.setKeyboardTracking(False)
    box.setToolTip("mask DoLP, AoLP and the normalised Mueller elements where S0 (m00) is "
                   "below this many noise standard deviations; 0 masks only what the data "
                   "marks (saturated, invalid, background)")
    return box


class ReadoutLabel(QLabel):
    """The cursor readout: monospace, selectable, inside a scroll area (:attr:`area`, the
    widget to put in a layout) so that no line is ever cut off at any window size."""

    def __init__(self, text: str = "", parent=None):
        super().__init__(text, parent)
        self.setTextInteractionFlags(Qt.TextInteractionFlag.TextSelectableByMouse)
        self.setAlignment(Qt.AlignmentFlag.AlignTop | Qt.AlignmentFlag.AlignLeft)
        self.setStyleSheet("font-family: monospace; font-size: 9pt")
        self.setWordWrap(False)
        self.area = QScrollArea()
        self.area.setWidgetResizable(True)
        self.area.setFrameShape(QFrame.Shape.NoFrame)
        self.area.setWidget(self)
        self.area.setMinimumHeight(120)


#: Drawing tools of :class:`ImageView` (key -> label).
DRAW_TOOLS = {"": "None (cursor readout)", "rect": "Rectangle ROI", "ellipse": "Ellipse ROI",
              "poly": "Polygon ROI (click vertices, double-click closes)",
              "line": "Line profile"}


class ImageView(QWidget):
    """Shows a ``QImage`` scaled to fit (aspect kept, nearest-neighbour when enlarged).

    ``hovered(x, y)`` gives the image pixel under the cursor (``-1, -1`` outside the image).
    With a drawing :attr:`tool` (a key of :data:`DRAW_TOOLS`), a drag draws a rectangle, an
    ellipse (the drag's box) or a line, clicks place polygon vertices (a double click closes
    it); ``drawn(tool, points)`` then gives the shape's points in image coordinates (floats,
    pixel ``(u, v)`` covers ``[u, u + 1) x [v, v + 1)``): the two corners of the box, the two
    ends of the line, or the vertices. The last shape stays drawn over the image.
    """

    hovered = Signal(int, int)
    drawn = Signal(str, list)

    def __init__(self, parent=None, placeholder: str = "no image"):
        super().__init__(parent)
        self._image: QImage | None = None
        self.placeholder = placeholder
        self.setMouseTracking(True)
        self.setMinimumSize(160, 120)
        self.setSizePolicy(QSizePolicy.Policy.Expanding, QSizePolicy.Policy.Expanding)
        self.images_shown = 0
        self.banner = ""
        self.tool = ""
        #: ``(tool, [(x, y), ...])`` of the shape drawn (image coordinates), or None
        self.shape: tuple[str, list] | None = None
        self._drawing = False

    def set_banner(self, text: str) -> None:
        """A line drawn across the top of the image (e.g. "PAUSED: capture running"); ""
        removes it."""
        self.banner = text
        self.update()

    def set_image(self, image: QImage | None) -> None:
        self._image = image
        if image is not None:
            self.images_shown += 1
        self.update()

    def image(self) -> QImage | None:
        return self._image

    def set_placeholder(self, text: str) -> None:
        self.placeholder = text
        self.update()

    def _target(self) -> QRect:
        img = self._image
        w, h = self.width(), self.height()
        s = min(w / img.width(), h / img.height())
        tw, th = max(1, int(img.width() * s)), max(1, int(img.height() * s))
        return QRect((w - tw) // 2, (h - th) // 2, tw, th)

    def paintEvent(self, _event) -> None:  # noqa: N802 - Qt naming
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(30, 30, 30))
        if self._image is None or self._image.isNull():
            p.setPen(QColor(200, 200, 200))
            p.drawText(self.rect(), Qt.AlignmentFlag.AlignCenter | Qt.TextFlag.TextWordWrap,
                       self.placeholder)
            return
        t = self._target()
        p.setRenderHint(QPainter.RenderHint.SmoothPixmapTransform,
                        t.width() < self._image.width())
        p.drawImage(t, self._image)
        if self.shape is not None:
            self._paint_shape(p)
        if self.banner:
            bar = QRect(0, 0, self.width(), 28)
            p.fillRect(bar, QColor(200, 120, 0, 220))
            p.setPen(QColor(0, 0, 0))
            f = p.font()
            f.setBold(True)
            p.setFont(f)
            p.drawText(bar, Qt.AlignmentFlag.AlignCenter, self.banner)

    def set_tool(self, tool: str) -> None:
        """Choose a drawing tool (a key of :data:`DRAW_TOOLS`; "" for none)."""
        if tool not in DRAW_TOOLS:
            raise ValueError(f"unknown drawing tool {tool!r}")
        self.tool = tool
        self._drawing = False
        self.setCursor(Qt.CursorShape.CrossCursor if tool else Qt.CursorShape.ArrowCursor)

    def set_shape(self, tool: str, points: list) -> None:
        """Show a shape (image coordinates) and emit :attr:`drawn`, as if drawn by the mouse."""
        self.shape = (tool, [(float(x), float(y)) for x, y in points])
        self._drawing = False
        self.update()
        self.drawn.emit(tool, list(self.shape[1]))

    def image_point(self, pos) -> tuple[float, float] | None:
        """Widget position -> image coordinates (floats, clamped to the image), or None
        without an image."""
        if self._image is None or self._image.isNull():
            return None
        t = self._target()
        x = (pos.x() - t.x()) * self._image.width() / t.width()
        y = (pos.y() - t.y()) * self._image.height() / t.height()
        return (min(max(x, 0.0), float(self._image.width())),
                min(max(y, 0.0), float(self._image.height())))

    def _widget_point(self, x: float, y: float):
        from PySide6.QtCore import QPointF

        t = self._target()
        return QPointF(t.x() + x * t.width() / self._image.width(),
                       t.y() + y * t.height() / self._image.height())

    def mousePressEvent(self, event) -> None:  # noqa: N802
        p = self.image_point(event.position())
        if not self.tool or p is None or event.button() != Qt.MouseButton.LeftButton:
            return
        if self.tool == "poly":
            if self._drawing and self.shape is not None:
                self.shape[1].append(p)
            else:
                self.shape, self._drawing = ("poly", [p]), True
        else:
            self.shape, self._drawing = (self.tool, [p, p]), True
        self.update()

    def mouseDoubleClickEvent(self, event) -> None:  # noqa: N802
        if self.tool == "poly" and self._drawing and self.shape is not None:
            pts = self.shape[1]
            while len(pts) > 1 and pts[-1] == pts[-2]:  # the double click's own press
                pts.pop()
            if len(pts) >= 3:
                self.set_shape("poly", pts)
            self._drawing = False

    def mouseReleaseEvent(self, event) -> None:  # noqa: N802
        if self._drawing and self.shape is not None and self.tool in ("rect", "ellipse", "line"):
            p = self.image_point(event.position())
            if p is not None:
                self.shape[1][1] = p
            a, b = self.shape[1]
            if a != b:
                self.set_shape(self.tool, [a, b])
            self._drawing = False

    def _paint_shape(self, p: QPainter) -> None:
        from PySide6.QtCore import QRectF
        from PySide6.QtGui import QPolygonF

        tool, pts = self.shape
        p.setRenderHint(QPainter.RenderHint.Antialiasing, True)
        pen = QPen(QColor(255, 255, 0))
        pen.setWidth(2)
        p.setPen(pen)
        p.setBrush(Qt.BrushStyle.NoBrush)
        wp = [self._widget_point(x, y) for x, y in pts]
        if tool in ("rect", "ellipse") and len(wp) == 2:
            r = QRectF(wp[0], wp[1]).normalized()
            (p.drawRect if tool == "rect" else p.drawEllipse)(r)
        elif tool == "line" and len(wp) == 2:
            p.drawLine(wp[0], wp[1])
        elif tool == "poly" and wp:
            poly = QPolygonF(wp)
            (p.drawPolyline if self._drawing else p.drawPolygon)(poly)

    def map_to_image(self, pos: QPoint) -> tuple[int, int]:
        if self._image is None:
            return -1, -1
        t = self._target()
        x = int((pos.x() - t.x()) * self._image.width() / t.width())
        y = int((pos.y() - t.y()) * self._image.height() / t.height())
        if 0 <= x < self._image.width() and 0 <= y < self._image.height():
            return x, y
        return -1, -1

    def mouseMoveEvent(self, event) -> None:  # noqa: N802
        if self._drawing and self.shape is not None and self.tool in ("rect", "ellipse", "line"):
            p = self.image_point(event.position())
            if p is not None:
                self.shape[1][1] = p
                self.update()
        x, y = self.map_to_image(event.position().toPoint())
        self.hovered.emit(x, y)


class HistogramWidget(QWidget):
    """Bar histogram of counts over bin edges, with the quantity's label and range."""

    def __init__(self, parent=None):
        super().__init__(parent)
        self.counts = np.zeros(0)
        self.edges = np.zeros(1)
        self.label = ""
        self.setMinimumHeight(80)

    def set_data(self, counts: np.ndarray, edges: np.ndarray, label: str) -> None:
        self.counts, self.edges, self.label = np.asarray(counts), np.asarray(edges), label
        self.update()

    def paintEvent(self, _event) -> None:  # noqa: N802
        p = QPainter(self)
        p.fillRect(self.rect(), QColor(250, 250, 250))
        n = len(self.counts)
        h = self.height() - 16
        if n and self.counts.max() > 0:
            top = float(self.counts.max())
            bw = self.width() / n
            p.setPen(Qt.PenStyle.NoPen)
            p.setBrush(QColor(70, 110, 170))
            for i, c in enumerate(self.counts):
                bh = int(h * c / top)
                p.drawRect(int(i * bw), h - bh, max(1, int(bw) - 1), bh)
        p.setPen(QPen(QColor(0, 0, 0)))
        if len(self.edges) > 1:
            p.drawText(2, self.height() - 3, f"{self.edges[0]:.3g}")
            text = f"{self.label}  {self.edges[-1]:.4g}"
            p.drawText(QRect(0, h, self.width() - 2, 16),
                       Qt.AlignmentFlag.AlignRight | Qt.AlignmentFlag.AlignVCenter, text)


class MessageArea(QPlainTextEdit):
    """Dialog-free log of messages (device faults, capture events), newest at the bottom."""

    LEVELS = {"info": "", "warning": "WARNING ", "error": "ERROR "}

    def __init__(self, parent=None):
        super().__init__(parent)
        self.setReadOnly(True)
        self.setMaximumBlockCount(500)
        self.setMinimumHeight(60)
        self.messages: list[tuple[str, str]] = []

    def add(self, level: str, text: str) -> None:
        self.messages.append((level, text))
        if len(self.messages) > 1000:
            del self.messages[:500]
        stamp = time.strftime("%H:%M:%S")
        self.appendPlainText(f"{stamp} {self.LEVELS.get(level, '')}{text}")


def scrolled(widget: QWidget) -> QScrollArea:
    """``widget`` in a frameless scroll area that resizes it to the room there is: a column or
    panel taller (or wider) than that room scrolls instead of forcing the window beyond the
    screen (the main window's pages; the live and viewer panels' control columns, beside an image
    that scales)."""
    area = QScrollArea()
    area.setWidget(widget)
    area.setWidgetResizable(True)
    area.setFrameShape(QFrame.Shape.NoFrame)
    return area
