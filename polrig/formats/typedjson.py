"""JSON documents read by their declared types: one reader, no hand-written validators.

A document's shape is declared once, as Python types: ``TypedDict`` s for JSON objects (their
``Required``/``NotRequired`` keys), frozen dataclasses for values the code uses as objects
(every field must be present: a document states every value, so a default that changes later
never changes what an old document means), ``list[T]``, ``tuple[T, ...]``, ``dict[str, T]``,
``Literal[...]``, ``T | None``, ``bool``, ``int``, ``float``, ``str`` and ``Any``.
``Annotated[T, Check(...)]`` adds a constraint the type cannot say (a path inside a folder, a
SHA-256 digest, an index >= 0); ``Annotated[T, Label(...)]`` says how errors name what is
inside a value (``"capture 3 (c003_pose090.0): "``).

:func:`load` checks parsed JSON against such a type and returns it converted (dataclasses built,
``tuple`` fields as tuples); the first problem is one :class:`Invalid` whose message names the
record and the key (``"capture 1 (c001_pose090.0): raw file record 2: missing 'sha256'"``).
:func:`encode` is the ``default`` of :func:`json.dumps` for the dataclasses in a document.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
import typing
from typing import Annotated, Any, Callable, Literal, Union

__all__ = ["FINITE", "NON_NEGATIVE", "Check", "Invalid", "Label", "encode", "extra_keys", "load"]


class Invalid(ValueError):
    """A value that does not have its declared type. The message is one line, relative to the
    document (the labels of the records around the value first)."""


@dataclasses.dataclass(frozen=True)
class Check:
    """A constraint beyond the type: ``ok(value)`` must hold (it is called once the value has
    its type); ``what`` says what the value must be (``"an index >= 0"``), ``plural`` the same
    for a list of them (``"indices >= 0"``)."""

    ok: Callable[[Any], bool]
    what: str
    plural: str | None = None


@dataclasses.dataclass(frozen=True)
class Label:
    """How errors name what lies inside a value. ``prefix`` (a record: ``"plan: "``, ``""`` for
    none) and/or ``entry(key, value)`` (a list or an object of records: the prefix of its entry
    ``key``, e.g. ``lambda i, v: f"raw file record {i}: "``). Without a label a nested record is
    named ``"<key>: "`` and an entry ``"<key> <index>: "``."""

    prefix: str | None = None
    entry: Callable[[Any, Any], str] | None = None


FINITE = Check(lambda v: math.isfinite(v), "a finite number", "finite numbers")
NON_NEGATIVE = Check(lambda v: v >= 0, "an integer >= 0", "integers >= 0")

_EXTRA = "__extra_keys__"


def extra_keys(cls):
    """Mark a ``TypedDict`` whose objects may hold keys it does not declare (kept as they are):
    a record another module fills (a score, an event's details)."""
    setattr(cls, _EXTRA, True)
    return cls


def encode(obj: Any) -> Any:
    """``json.dumps(doc, default=encode)``: a dataclass as the object of its fields (in their
    order; tuples are written as lists by ``json``)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: getattr(obj, f.name) for f in dataclasses.fields(obj)}
    raise TypeError(f"{type(obj).__name__} is not JSON serializable")


def load(tp: Any, value: Any, *, context: str = "") -> Any:
    """``value`` (parsed JSON) checked against ``tp`` and converted; :class:`Invalid` naming the
    first problem (its message starts with ``context``)."""
    return _load(tp, value, context, "the document", context)


# -- the reader ---------------------------------------------------------------------------------
def _fail(outer: str, name: str, what: str, value: Any) -> Invalid:
    subject = f"{outer}{name} " if name else outer  # an entry: named by its label
    return Invalid(f"{subject}must be {what}, got {_short(value)}")


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 60 else text[:57] + "..."


def _load(tp: Any, value: Any, outer: str, name: str, inner: str) -> Any:
    """``outer + name`` names the value in a message about the value itself; ``inner`` prefixes
    a message about something inside it."""
    base, checks, label = _unwrap(tp)
    origin = typing.get_origin(base)
    if base is Any:
        return value
    if origin in (Union, types.UnionType):
        return _load_union(base, value, checks, outer, name, inner, label)
    if typing.is_typeddict(base):
        if not isinstance(value, dict):
            raise _fail(outer, name, "an object", value)
        return _load_typeddict(base, value, inner)
    if dataclasses.is_dataclass(base):
        if not isinstance(value, dict):
            raise _fail(outer, name, "an object", value)
        return _load_dataclass(base, value, inner)
    if origin in (list, tuple):
        return _load_list(base, value, outer, name, inner, label)
    if origin is dict:
        return _load_mapping(base, value, outer, name, inner, label)
    if not _is_scalar(base, value) or not all(c.ok(value) for c in checks):
        raise _fail(outer, name, _phrase(tp), value)
    return value


def _unwrap(tp: Any) -> tuple[Any, list[Check], Label | None]:
    checks: list[Check] = []
    label = None
    while typing.get_origin(tp) is Annotated:
        for meta in tp.__metadata__:
            if isinstance(meta, Check):
                checks.append(meta)
            elif isinstance(meta, Label):
                label = meta
        tp = tp.__origin__
    return tp, checks, label


def _is_scalar(tp: Any, value: Any) -> bool:
    if tp is type(None) or tp is None:
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if tp is str:
        return isinstance(value, str)
    if typing.get_origin(tp) is Literal:
        return any(type(value) is type(a) and value == a for a in typing.get_args(tp))
    raise TypeError(f"typedjson: unsupported type {tp!r}")


def _load_union(tp, value, checks, outer, name, inner, label) -> Any:
    options = typing.get_args(tp)
    if value is None and type(None) in options:
        return None
    rest = [o for o in options if o is not type(None)]
    if len(rest) == 1:  # T | None with a value: T's own message (naming what is inside)
        try:
            return _load(rest[0], value, outer, name, inner)
        except Invalid:
            if _is_record(rest[0]) and isinstance(value, dict):
                raise
            raise _fail(outer, name, _phrase(tp), value) from None
    for option in rest:
        try:
            return _load(option, value, outer, name, inner)
        except Invalid:
            continue
    raise _fail(outer, name, _phrase(tp), value)


def _is_record(tp: Any) -> bool:
    base = _unwrap(tp)[0]
    return typing.is_typeddict(base) or dataclasses.is_dataclass(base) or \
        typing.get_origin(base) in (list, tuple, dict)


def _entry_prefix(label: Label | None, key: Any, value: Any, default: str) -> str:
    if label is not None and label.entry is not None:
        return label.entry(key, value)
    return default


def _inner(tp: Any, ctx: str, key: str) -> str:
    """The context of what lies inside field ``key`` of type ``tp``: a record's is
    ``"<key>: "`` after ``ctx`` (or its label's prefix); a list's or an object's entries name
    themselves (their label's ``entry``, else ``"<key> <index>: "``) after ``ctx``."""
    base, _, label = _unwrap(tp)
    if label is not None and label.prefix is not None:
        return ctx + label.prefix
    if typing.get_origin(base) in (Union, types.UnionType):
        base = next((o for o in typing.get_args(base) if o is not type(None)), base)
        base = _unwrap(base)[0]
    if typing.get_origin(base) in (list, tuple, dict):
        return ctx
    return ctx + f"{key}: "


@functools.cache
def _hints(cls: type) -> dict[str, Any]:
    return typing.get_type_hints(cls, include_extras=True)


def _load_typeddict(cls: type, value: dict, ctx: str) -> dict:
    hints = _hints(cls)
    required = cls.__required_keys__
    out = {}
    for key, ft in hints.items():
        ft_plain = ft
        while typing.get_origin(ft_plain) in (typing.Required, typing.NotRequired):
            ft_plain = typing.get_args(ft_plain)[0]
        if key not in value:
            if key in required:
                raise Invalid(f"{ctx}missing {key!r}")
            continue
        out[key] = _load(ft_plain, value[key], ctx, repr(key), _inner(ft_plain, ctx, key))
    extra = [k for k in value if k not in hints]
    if extra:
        if not getattr(cls, _EXTRA, False):
            raise Invalid(f"{ctx}unknown key {extra[0]!r}")
        out.update((k, value[k]) for k in extra)
    return out


def _load_dataclass(cls: type, value: dict, ctx: str) -> Any:
    hints = _hints(cls)
    kw = {}
    for f in dataclasses.fields(cls):
        if not f.init:
            continue
        if f.name not in value:
            raise Invalid(f"{ctx}missing {f.name!r}")
        ft = hints[f.name]
        kw[f.name] = _load(ft, value[f.name], ctx, repr(f.name), _inner(ft, ctx, f.name))
    extra = [k for k in value if k not in kw]
    if extra:
        raise Invalid(f"{ctx}unknown key {extra[0]!r}")
    try:
        return cls(**kw)
    except (ValueError, TypeError) as exc:  # the class's own checks (a PlanError...)
        raise Invalid(f"{ctx}{exc}") from None


def _load_list(tp, value, outer, name, inner, label) -> Any:
    args = typing.get_args(tp)
    if typing.get_origin(tp) is tuple and not (len(args) == 2 and args[1] is Ellipsis):
        raise TypeError(f"typedjson: only tuple[T, ...] is supported, got {tp!r}")
    item = args[0]
    if not isinstance(value, list):
        raise _fail(outer, name, _phrase(tp), value)
    if _is_record(item):
        key = name.strip("'")
        out = []
        for i, v in enumerate(value):
            prefix = inner + _entry_prefix(label, i, v, f"{key} {i}: ")
            out.append(_load(item, v, prefix, "", prefix))
    else:  # a list of plain values: the list is named as a whole
        try:
            out = [_load(item, v, "", "", "") for v in value]
        except Invalid:
            raise _fail(outer, name, _phrase(tp), value) from None
    return tuple(out) if typing.get_origin(tp) is tuple else out


def _load_mapping(tp, value, outer, name, inner, label) -> dict:
    key_type, item = typing.get_args(tp)
    if key_type is not str:
        raise TypeError(f"typedjson: object keys are strings, got {tp!r}")
    if not isinstance(value, dict):
        raise _fail(outer, name, "an object", value)
    if not _is_record(item):
        try:
            return {k: _load(item, v, "", "", "") for k, v in value.items()}
        except Invalid:
            raise _fail(outer, name, _phrase(tp), value) from None
    key = name.strip("'")
    out = {}
    for k, v in value.items():
        prefix = inner + _entry_prefix(label, k, v, f"{key} {k!r}: ")
        out[k] = _load(item, v, prefix, "", prefix)
    return out


# -- what a type is called in a message ---------------------------------------------------------
_PLURAL = {"a number": "numbers", "an integer": "integers", "a string": "strings",
           "true or false": "booleans", "an object": "objects", "null": "nulls"}


def _phrase(tp: Any, plural: bool = False) -> str:
    base, checks, _ = _unwrap(tp)
    if checks:
        c = checks[-1]
        return (c.plural or f"values that are {c.what}") if plural else c.what
    origin = typing.get_origin(base)
    if origin in (Union, types.UnionType):
        parts = [_phrase(o, plural) for o in typing.get_args(base) if o is not type(None)]
        text = " or ".join(parts)
        return text + (" or null" if type(None) in typing.get_args(base) else "")
    if origin in (list, tuple):
        text = "a list of " + _phrase(typing.get_args(base)[0], plural=True)
        return f"lists of {text[len('a list of '):]}" if plural else text
    if origin is Literal:
        return "one of " + ", ".join(str(a) for a in typing.get_args(base))
    singular = {bool: "true or false", int: "an integer", float: "a number", str: "a string",
                type(None): "null", None: "null"}.get(base, "an object")
    return _PLURAL.get(singular, singular) if plural else singular
