"""``polrig.formats.typedjson``: JSON read by its declared types, errors naming the record."""

# no ``from __future__ import annotations``: the TypedDicts below need evaluated annotations

import dataclasses
import json
from typing import Annotated, Any, Literal, NotRequired, TypedDict

import pytest

from polrig.formats.typedjson import (
    FINITE,
    Check,
    Invalid,
    Label,
    encode,
    extra_keys,
    load,
)

Even = Annotated[int, Check(lambda v: v % 2 == 0, "an even integer", "even integers")]


class Leaf(TypedDict):
    name: str
    size: Even
    note: NotRequired[str | None]


@extra_keys
class Open(TypedDict):
    time: str


@dataclasses.dataclass(frozen=True)
class Point:
    x: float
    tags: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.x < 0:
            raise ValueError(f"x must be >= 0, got {self.x}")


def _name(v: Any) -> str:
    return v.get("name", "?") if isinstance(v, dict) else "?"


class Root(TypedDict):
    kind: Literal["a", "b"]
    ratio: Annotated[float, FINITE] | None
    leaves: Annotated[list[Leaf], Label(entry=lambda i, v: f"leaf {i} ({_name(v)}): ")]
    by_name: dict[str, Leaf]
    point: Point
    inner: Annotated[Leaf, Label("")]
    values: list[float]
    events: list[Open]
    extra: Any


GOOD = {"kind": "a", "ratio": 0.5, "leaves": [{"name": "l0", "size": 2}],
        "by_name": {"k": {"name": "k", "size": 4, "note": None}},
        "point": {"x": 1, "tags": ["t"]}, "inner": {"name": "i", "size": 0},
        "values": [1, 2.5], "events": [{"time": "now", "what": "kept"}], "extra": {"any": [1]}}


def test_a_good_document_is_read_and_converted():
    doc = load(Root, json.loads(json.dumps(GOOD)))
    assert doc["point"] == Point(1, ("t",)) and doc["leaves"][0] == {"name": "l0", "size": 2}
    assert doc["events"] == [{"time": "now", "what": "kept"}]  # an open record keeps its keys
    assert json.loads(json.dumps(doc, default=encode)) == {**GOOD, "point": {"x": 1,
                                                                             "tags": ["t"]}}
    with pytest.raises(TypeError):
        encode(object())


@pytest.mark.parametrize("change, message", [
    (lambda d: d.pop("kind"), "missing 'kind'"),
    (lambda d: d.update(kind="c"), "'kind' must be one of a, b, got 'c'"),
    (lambda d: d.update(ratio=float("inf")), "'ratio' must be a finite number or null, got inf"),
    (lambda d: d.update(ratio=True), "'ratio' must be a finite number or null, got True"),
    (lambda d: d["leaves"][0].pop("size"), "leaf 0 (l0): missing 'size'"),
    (lambda d: d["leaves"][0].update(size=3), "leaf 0 (l0): 'size' must be an even integer, got 3"),
    (lambda d: d["leaves"][0].update(colour="red"), "leaf 0 (l0): unknown key 'colour'"),
    (lambda d: d.update(leaves=[7]), "leaf 0 (?): must be an object, got 7"),
    (lambda d: d.update(leaves={}), "'leaves' must be a list of objects, got {}"),
    (lambda d: d["by_name"]["k"].update(note=5), "by_name 'k': 'note' must be a string or null"),
    (lambda d: d["point"].pop("tags"), "point: missing 'tags'"),  # every field stated
    (lambda d: d["point"].update(x=-1), "point: x must be >= 0, got -1"),
    (lambda d: d["point"].update(y=0), "point: unknown key 'y'"),
    (lambda d: d["inner"].update(size="2"), "'size' must be an even integer, got '2'"),
    (lambda d: d.update(values=[1, "x"]), "'values' must be a list of numbers, got [1, 'x']"),
    (lambda d: d["events"][0].pop("time"), "events 0: missing 'time'"),
])
def test_each_problem_is_one_line_naming_the_record(change, message):
    doc = json.loads(json.dumps(GOOD))
    change(doc)
    with pytest.raises(Invalid) as info:
        load(Root, doc, context="doc: ")
    text = str(info.value)
    assert text.startswith("doc: ") and message in text and "\n" not in text, text
