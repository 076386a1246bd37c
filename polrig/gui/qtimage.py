"""numpy uint8 RGB ``(H, W, 3)`` <-> ``QImage`` (copied, so the array may be reused)."""

from __future__ import annotations

import numpy as np
from PySide6.QtGui import QImage


def to_qimage(rgb: np.ndarray) -> QImage:
    """A ``QImage.Format_RGB888`` copy of a uint8 RGB array (safe in any thread)."""
    a = np.ascontiguousarray(rgb, dtype=np.uint8)
    if a.ndim != 3 or a.shape[2] != 3:
        raise ValueError(f"expected (H, W, 3) uint8 RGB, got {a.shape}")
    h, w = a.shape[:2]
    return QImage(a.data, w, h, 3 * w, QImage.Format.Format_RGB888).copy()


def from_qimage(img: QImage) -> np.ndarray:
    """uint8 RGB ``(H, W, 3)`` of a ``QImage`` (for tests and screenshots checks)."""
    img = img.convertToFormat(QImage.Format.Format_RGB888)
    h, w = img.height(), img.width()
    buf = np.frombuffer(img.constBits(), np.uint8, count=img.bytesPerLine() * h)
    return buf.reshape(h, img.bytesPerLine())[:, :3 * w].reshape(h, w, 3).copy()
