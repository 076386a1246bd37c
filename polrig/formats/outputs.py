"""The output files of one command: refused where one is an input, written as a set.

* :func:`check_not_input`: before any work, a :class:`polrig.errors.ConfigError` (one line
  naming both paths, exit 2) when an output path is an input file of the same command, compared
  through :func:`os.path.realpath` (symbolic links resolved) and, where both exist,
  :func:`os.path.samefile` (hard links, case-insensitive file systems). ``polrig stokes RAW --out
  X.exr`` would otherwise replace a raw frame named ``X_s1.png`` by a preview.
* :class:`OutputSet`: the files of one command appear together or not at all. Each is written
  under a hidden temporary name in its own folder (:func:`polrig.atomic.temporary_sibling`);
  only when every temporary exists are they renamed onto the final names, in order. Any failure
  before that removes the temporaries and leaves every existing file untouched; a rename that
  fails (a file that may not be replaced) puts the files already renamed back as they were
  (each replaced file is kept as a hard link, or moved aside where the file system has none,
  until the set is complete); a folder is never replaced. A failed write names the user's
  file, never a temporary one.
"""

from __future__ import annotations

import errno
import os
import pathlib
import uuid
from collections.abc import Iterable, Sequence
from types import TracebackType

from polrig.atomic import fsync_folder, temporary_sibling, write_error
from polrig.errors import ConfigError

PathLike = str | os.PathLike

__all__ = ["check_not_input", "OutputSet"]


def _same_file(a: PathLike, b: PathLike) -> bool:
    if os.path.realpath(a) == os.path.realpath(b):
        return True
    try:
        return os.path.samefile(a, b)
    except OSError:  # one of them does not exist (yet)
        return False


def _inside(path: PathLike, folder: PathLike) -> bool:
    """Whether ``path`` lies inside ``folder`` (links resolved)."""
    p, f = pathlib.Path(os.path.realpath(path)), pathlib.Path(os.path.realpath(folder))
    return f in p.parents


def check_not_input(outputs: Iterable[tuple[str, PathLike]],
                    inputs: Iterable[PathLike | None], *, replaces_folder: bool = False) -> None:
    """:class:`ConfigError` ``"{flag} {output} is the input {input}; ..."`` when an output path
    (``(flag, path)`` pairs, e.g. ``("--out preview", "x_s1.png")``) is the same file as one of
    ``inputs`` (``None`` entries skipped). With ``replaces_folder`` (an output folder that is
    replaced whole) also when an input lies inside an output. Reads nothing; call before any
    work."""
    inputs = [pathlib.Path(p) for p in inputs if p is not None]
    for flag, out in outputs:
        for inp in inputs:
            if _same_file(out, inp):
                raise ConfigError(f"{flag} {out} is the input {inp}; writing it would destroy "
                                  f"the input: choose another output name")
            if replaces_folder and _inside(inp, out):
                raise ConfigError(f"{flag} {out} holds the input {inp}; replacing it would "
                                  f"destroy the input: choose another output name")


class OutputSet:
    """A set of output files written all or none (module docstring).

    Use as a context manager: write each file to :meth:`temporary` ``(final)`` (or a group of
    files sharing a stem to :meth:`temporary_stem`) inside the ``with`` block; leaving it
    normally renames every temporary onto its final name (:meth:`commit`), leaving it by an
    exception removes them (:meth:`discard`) and re-raises, an :class:`OSError` that names a
    temporary file reworded to name the final one (same class and ``errno``)."""

    def __init__(self) -> None:
        self._temps: dict[pathlib.Path, pathlib.Path] = {}  # final -> temporary

    @property
    def finals(self) -> list[pathlib.Path]:
        """The final paths, in the order they are renamed into place."""
        return list(self._temps)

    def temporary(self, final: PathLike) -> pathlib.Path:
        """The temporary path to write ``final`` to (a hidden sibling, same suffix)."""
        final = pathlib.Path(final)
        if final not in self._temps:
            self._temps[final] = temporary_sibling(final)
        return self._temps[final]

    def temporary_stem(self, folder: PathLike, stem: str, suffixes: Sequence[str]) -> str:
        """For a writer that names its files ``{stem}{suffix}`` in ``folder``: the stem to give
        it instead, registering ``folder/{stem}{suffix}`` for every suffix."""
        folder = pathlib.Path(folder)
        tmp_stem = f".{stem}.{uuid.uuid4().hex[:12]}.tmp"
        for sfx in suffixes:
            self._temps[folder / f"{stem}{sfx}"] = folder / f"{tmp_stem}{sfx}"
        return tmp_stem

    def __enter__(self) -> OutputSet:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 tb: TracebackType | None) -> bool:
        if exc is None:
            self.commit()
            return False
        self.discard()
        if isinstance(exc, OSError):
            named = self._named(exc)
            if named is not exc:
                raise named from None
        return False

    def discard(self) -> None:
        """Remove every temporary file (those not written are skipped)."""
        for tmp in self._temps.values():
            try:
                os.unlink(tmp)
            except OSError:
                pass

    def commit(self) -> None:
        """Rename every temporary onto its final name, in order; a failure restores the files
        renamed before it, removes the temporaries and raises one line naming the final file
        (:func:`polrig.atomic.write_error`)."""
        for final, tmp in self._temps.items():
            if not tmp.is_file():
                self.discard()
                raise RuntimeError(f"{final} was not written (internal error: no {tmp.name})")
        placed: list[tuple[pathlib.Path, pathlib.Path | None]] = []
        final = None
        try:
            for final, tmp in self._temps.items():
                backup = None
                if os.path.isdir(final) and not os.path.islink(final):
                    raise IsADirectoryError(errno.EISDIR, os.strerror(errno.EISDIR), str(final))
                if os.path.lexists(final):
                    backup = temporary_sibling(final)
                    try:  # keep the old file under a second name while the set is incomplete
                        os.link(final, backup, follow_symlinks=False)
                    except (OSError, NotImplementedError):  # no hard links here: move it aside
                        os.replace(final, backup)  # fails for a file that may not be replaced
                try:
                    os.replace(tmp, final)
                except OSError:
                    if backup is not None:
                        if os.path.lexists(final):
                            os.unlink(backup)
                        else:
                            os.replace(backup, final)
                    raise
                placed.append((final, backup))
        except OSError as exc:
            for done, backup in reversed(placed):
                try:
                    if backup is None:
                        os.unlink(done)
                    else:
                        os.replace(backup, done)
                except OSError:
                    pass
            self.discard()
            raise write_error(final, exc) from None
        for _, backup in placed:
            if backup is not None:
                try:
                    os.unlink(backup)
                except OSError:
                    pass
        for folder in {f.parent for f in self._temps}:
            fsync_folder(folder)

    def _named(self, exc: OSError) -> OSError:
        """``exc`` with every temporary name replaced by its final one (``exc`` itself when it
        names none)."""
        text = str(exc)
        for final, tmp in self._temps.items():
            text = text.replace(str(tmp), str(final)).replace(tmp.name, final.name)
        if text == str(exc):
            return exc
        try:
            new = type(exc)(text)
        except TypeError:  # an OSError subclass with a constructor of its own
            new = OSError(text)
        new.errno = exc.errno
        return new
