"""Settings remembered between runs (``QSettings``).

The default scope is organisation ``polrig``, application ``polrig-gui`` (the platform's usual
place: ``~/.config/polrig/polrig-gui.conf`` on Linux). :func:`make_settings` with a file path
uses an INI file instead (``polrig gui --settings FILE``; the tests use a temporary one so
that they never touch the user's settings).
"""

from __future__ import annotations

import os
from typing import Any, Callable

from PySide6.QtCore import QSettings

ORGANISATION = "polrig"
APPLICATION = "polrig-gui"


def make_settings(path: str | os.PathLike | None = None) -> QSettings:
    if path is not None:
        return QSettings(str(path), QSettings.Format.IniFormat)
    return QSettings(ORGANISATION, APPLICATION)


def combo_binding(combo) -> tuple[Callable[[], Any], Callable[[Any], None]]:
    """Getter/setter storing a combo box's item data (or text when it has no data)."""
    def get():
        d = combo.currentData()
        return combo.currentText() if d is None else d

    def put(v):
        i = combo.findData(v)
        if i < 0:
            i = combo.findText(str(v))
        if i < 0:
            try:  # QSettings INI files give numbers back as strings
                i = combo.findData(int(v))
            except (TypeError, ValueError):
                i = -1
        if i >= 0:
            combo.setCurrentIndex(i)
    return get, put


def text_binding(edit):
    return edit.text, lambda v: edit.setText(str(v))


def int_binding(spin):
    return spin.value, lambda v: spin.setValue(int(v))


def bool_binding(box):
    return box.isChecked, lambda v: box.setChecked(v in (True, "true", "1", 1))


class SettingsBinder:
    """Keys bound to widget getters/setters; :meth:`save` and :meth:`restore` them."""

    def __init__(self, settings: QSettings) -> None:
        self.settings = settings
        self.bindings: dict[str, tuple[Callable[[], Any], Callable[[Any], None]]] = {}

    def bind(self, key: str, binding: tuple[Callable[[], Any], Callable[[Any], None]]) -> None:
        self.bindings[key] = binding

    def save(self) -> None:
        for key, (get, _) in self.bindings.items():
            self.settings.setValue(key, get())
        self.settings.sync()

    def restore(self) -> list[str]:
        """Apply stored values; returns the keys that could not be applied."""
        bad = []
        for key, (_, put) in self.bindings.items():
            if self.settings.contains(key):
                try:
                    put(self.settings.value(key))
                except (TypeError, ValueError):
                    bad.append(key)
        return bad
