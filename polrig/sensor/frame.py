"""One raw frame as the camera delivered it: the mosaic and its metadata.

A :class:`Frame` is the first step of polrig's data flow (device bytes -> raw frame -> analyzer
images -> Stokes -> Mueller). Cameras (:mod:`polrig.acquisition.hal`) produce it; raw files
(:mod:`polrig.formats.rawio`) store it with its :class:`FrameMeta` as a JSON sidecar.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from polrig.errors import FormatError


@dataclasses.dataclass(frozen=True)
class FrameMeta:
    """Metadata of one raw frame, as the camera reported it.

    ``layout`` names a :mod:`polrig.sensor.layouts` mosaic layout and ``offset_xy`` the ROI offset
    (pixels) that sets its phase. ``bit_depth`` is the number of significant bits of the
    raw values (8, 10, 12, 16). ``timestamp_s`` is the device clock (or host clock when the
    device has none, flagged by ``host_timestamp``).
    """

    frame_id: int
    timestamp_s: float
    exposure_us: float
    gain_db: float
    pixel_format: str
    layout: str
    bit_depth: int
    offset_xy: tuple[int, int] = (0, 0)
    black_level_dn: float = 0.0
    host_timestamp: bool = False
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict[str, Any]:
        d = dataclasses.asdict(self)
        d["offset_xy"] = list(self.offset_xy)
        return d

    @classmethod
    def from_json(cls, d: dict[str, Any], *, source: Any = None) -> "FrameMeta":
        """The metadata of a JSON object (a raw frame's sidecar), every field type-checked.

        Raises :class:`polrig.errors.FormatError` with one line naming ``source`` (the file
        it came from, if given) and the key: missing or unknown keys, wrong types (``null``,
        strings for numbers, booleans for integers), ``bit_depth`` outside 1..16, a negative,
        non-finite or saturating ``black_level_dn``, a negative ``offset_xy``. Timestamps,
        exposure and gain may be NaN (a camera that does not report them).
        """
        where = f"{source}: " if source is not None else ""

        def bad(key: str, problem: str) -> FormatError:
            return FormatError(f"{where}{key}: {problem}")

        if not isinstance(d, dict):
            raise FormatError(f"{where}frame metadata must be a JSON object, got {_show(d)}")
        names = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(set(d) - set(names))
        if unknown:
            raise bad(unknown[0], f"unknown frame metadata key; known: {', '.join(names)}")
        required = [f.name for f in dataclasses.fields(cls)
                    if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING]
        missing = [k for k in required if k not in d]
        if missing:
            raise bad(missing[0], "missing from the frame metadata")
        out: dict[str, Any] = {}
        for key in ("frame_id", "bit_depth"):
            v = d[key]
            if not (isinstance(v, int) and not isinstance(v, bool)):
                raise bad(key, f"expected an integer, got {_show(v)}")
            out[key] = v
        if not 1 <= out["bit_depth"] <= 16:
            raise bad("bit_depth", f"must be 1..16 bits (raw frames are 8 or 16-bit "
                                   f"integers), got {out['bit_depth']}")
        for key in ("timestamp_s", "exposure_us", "gain_db", "black_level_dn"):
            if key not in d:
                continue
            v = d[key]
            if not (isinstance(v, (int, float)) and not isinstance(v, bool)):
                raise bad(key, f"expected a number, got {_show(v)}")
            out[key] = float(v)
        black = out.get("black_level_dn", 0.0)
        top = 2 ** out["bit_depth"] - 1
        if not (math.isfinite(black) and 0 <= black < top):
            raise bad("black_level_dn", f"must be a finite number in [0, {top}) for "
                                        f"{out['bit_depth']}-bit data, got {black!r}")
        for key in ("pixel_format", "layout"):
            if not isinstance(d[key], str):
                raise bad(key, f"expected a string, got {_show(d[key])}")
            out[key] = d[key]
        if "offset_xy" in d:
            v = d["offset_xy"]
            if not (isinstance(v, (list, tuple)) and len(v) == 2
                    and all(isinstance(x, int) and not isinstance(x, bool) and x >= 0 for x in v)):
                raise bad("offset_xy", f"expected two integers >= 0 [x, y], got {_show(v)}")
            out["offset_xy"] = (int(v[0]), int(v[1]))
        if "host_timestamp" in d:
            if not isinstance(d["host_timestamp"], bool):
                raise bad("host_timestamp", f"expected true or false, got {_show(d['host_timestamp'])}")
            out["host_timestamp"] = d["host_timestamp"]
        if "extra" in d:
            if not isinstance(d["extra"], dict):
                raise bad("extra", f"expected a JSON object, got {_show(d['extra'])}")
            out["extra"] = d["extra"]
        return cls(**out)


def _show(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


@dataclasses.dataclass(frozen=True)
class Frame:
    """A raw mosaic (``uint16`` or ``uint8``, shape ``(H, W)``, one value per sensor pixel)."""

    raw: np.ndarray
    meta: FrameMeta
