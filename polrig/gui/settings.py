"""Settings remembered between runs (``QSettings``).

The default scope is organisation ``polrig``, application ``polrig-gui`` (the platform's usual
place: ``~/.config/polrig/polrig-gui.conf`` on Linux). :func:`make_settings` with a file path
uses an INI file instead (``polrig gui --settings FILE``; the tests use a temporary one so
that they never touch the user's settings).

A file edited by hand may hold anything: a value a widget cannot take (not a number, out of
its range, ``@Invalid()``) is skipped and named (:meth:`SettingsBinder.restore`), never a
crash; an unquoted comma list (``poses=0,90,180``, which ``QSettings`` reads as a list) is
joined back with commas. :func:`settings_problem` says when the file could not be read or
written.
"""

from __future__ import annotations

import math
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
            except (TypeError, ValueError, OverflowError):
                i = -1
        if i < 0:
            raise ValueError(f"not one of the choices: {v!r}")
        combo.setCurrentIndex(i)
    return get, put


def as_text(value: Any) -> str:
    """A stored value as a line edit's text: strings and numbers as they are, a list (an
    unquoted ``a,b,c`` in an INI file) joined with commas; ``ValueError`` for anything else
    (``@Invalid()`` reads as ``None``, binary data)."""
    if isinstance(value, str):
        return value
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        return str(value)
    if isinstance(value, (list, tuple)) and all(isinstance(v, (str, int, float))
                                                and not isinstance(v, bool) for v in value):
        return ",".join(str(v) for v in value)
    raise ValueError(f"not a text value: {value!r}")


def text_binding(edit):
    return edit.text, lambda v: edit.setText(as_text(v))


def int_binding(spin):
    def put(v):
        n = int(as_text(v).strip())
        if not spin.minimum() <= n <= spin.maximum():
            raise ValueError(f"{n} is outside [{spin.minimum()}, {spin.maximum()}]")
        spin.setValue(n)
    return spin.value, put


def float_binding(spin):
    """Getter/setter of a ``QDoubleSpinBox``: a stored value that is not a finite number in the
    box's range is refused (:class:`ValueError`: the binder skips it and says so)."""
    def put(v):
        x = float(as_text(v).strip())
        if not (math.isfinite(x) and spin.minimum() <= x <= spin.maximum()):
            raise ValueError(f"{x} is outside [{spin.minimum()}, {spin.maximum()}]")
        spin.setValue(x)
    return spin.value, put


_TRUE, _FALSE = (True, "true", "1", 1), (False, "false", "0", 0)


def bool_binding(box):
    def put(v):
        if v in _TRUE:
            box.setChecked(True)
        elif v in _FALSE:
            box.setChecked(False)
        else:
            raise ValueError(f"not true or false: {v!r}")
    return box.isChecked, put


def settings_problem(settings: QSettings, action: str = "read") -> str:
    """One line when ``settings`` could not be read (``action="read"``) or written
    (``"saved"``), else ``""``: ``QSettings`` reports it only in :meth:`QSettings.status`."""
    st = settings.status()
    if st == QSettings.Status.NoError or (action != "read"
                                          and st != QSettings.Status.AccessError):
        return ""  # a file that did not parse is rewritten whole by the save
    why = ("the file cannot be written (permissions, missing folder)"
           if st == QSettings.Status.AccessError else "the file is not a valid settings file")
    where = settings.fileName()
    if action == "read":
        return f"settings {where}: {why}; the defaults are used"
    return f"settings could not be saved to {where}: {why}"


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
        """Apply stored values; returns the keys whose values could not be applied (each
        skipped: the widget keeps its default; whatever the file holds, never an
        exception)."""
        bad = []
        for key, (_, put) in self.bindings.items():
            try:
                if self.settings.contains(key):
                    put(self.settings.value(key))
            except Exception:  # noqa: BLE001 - any value: OverflowError, lists, None...
                bad.append(key)
        return bad
