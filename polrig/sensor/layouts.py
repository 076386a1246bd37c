"""DoFP mosaic layouts as data.

A layout is a small periodic cell (2x2 for a mono polarization sensor, 4x4 for a colour
one) giving, for each sensor pixel, the analyzer angle in degrees (convention:
``docs/conventions.md``, counter-clockwise as displayed from image ``+u``) and the colour
channel index (0 for mono; 0, 1, 2 = R, G, B for colour). A region of interest starting at
``(offset_x, offset_y)`` sees the same cell rolled by that offset: :meth:`MosaicLayout.shifted`.

Sources: Sony IMX250MZR/MYR flyer and JAI GO-5100MP manual ("polarizers angled at 90 and 45
degrees are provided alternately on the first line, 135 and 0 on the second"); the
IMX250MYR places an RGGB Bayer pattern over 2x2 polarizer blocks.
"""

from __future__ import annotations

import dataclasses

import numpy as np

ANALYZER_ANGLES_DEG = (0, 45, 90, 135)


@dataclasses.dataclass(frozen=True)
class MosaicLayout:
    """A periodic DoFP mosaic.

    ``angle_deg[r, c]`` and ``colour[r, c]`` describe the cell whose top-left pixel is sensor
    pixel (0, 0) of the current readout. ``channels`` names the colour planes.
    """

    name: str
    angle_deg: np.ndarray  # (ph, pw) int
    colour: np.ndarray  # (ph, pw) int
    channels: tuple[str, ...]

    def __post_init__(self) -> None:
        a, c = np.asarray(self.angle_deg), np.asarray(self.colour)
        if a.shape != c.shape or a.ndim != 2:
            raise ValueError("angle_deg and colour must be 2-D arrays of one shape")
        for ch in range(len(self.channels)):
            for ang in ANALYZER_ANGLES_DEG:
                if not np.any((a == ang) & (c == ch)):
                    raise ValueError(f"layout {self.name}: no pixel for colour {ch}, angle {ang}")
        object.__setattr__(self, "angle_deg", a.astype(np.int64))
        object.__setattr__(self, "colour", c.astype(np.int64))

    @property
    def period(self) -> tuple[int, int]:
        return self.angle_deg.shape  # type: ignore[return-value]

    @property
    def n_colours(self) -> int:
        return len(self.channels)

    @property
    def is_colour(self) -> bool:
        return self.n_colours > 1

    def shifted(self, offset_x: int, offset_y: int) -> "MosaicLayout":
        """The layout seen by a readout whose first pixel is sensor pixel (offset_y, offset_x)."""
        ph, pw = self.period
        dy, dx = offset_y % ph, offset_x % pw
        if dx == 0 and dy == 0:
            return self
        roll = lambda m: np.roll(m, shift=(-dy, -dx), axis=(0, 1))  # noqa: E731
        return MosaicLayout(f"{self.name}@{offset_x},{offset_y}", roll(self.angle_deg),
                            roll(self.colour), self.channels)

    def masks(self, shape: tuple[int, int]) -> dict[tuple[int, int], np.ndarray]:
        """Boolean masks of every (colour index, angle) pixel class over an image of ``shape``."""
        ph, pw = self.period
        h, w = shape
        reps = (-(-h // ph), -(-w // pw))
        a = np.tile(self.angle_deg, reps)[:h, :w]
        c = np.tile(self.colour, reps)[:h, :w]
        return {(ch, ang): (a == ang) & (c == ch)
                for ch in range(self.n_colours) for ang in ANALYZER_ANGLES_DEG}

    def angle_map(self, shape: tuple[int, int]) -> np.ndarray:
        ph, pw = self.period
        reps = (-(-shape[0] // ph), -(-shape[1] // pw))
        return np.tile(self.angle_deg, reps)[: shape[0], : shape[1]]

    def colour_map(self, shape: tuple[int, int]) -> np.ndarray:
        ph, pw = self.period
        reps = (-(-shape[0] // ph), -(-shape[1] // pw))
        return np.tile(self.colour, reps)[: shape[0], : shape[1]]


_SONY_CELL = np.array([[90, 45], [135, 0]])

IMX250MZR = MosaicLayout("imx250mzr", _SONY_CELL, np.zeros((2, 2), int), ("Y",))

# 4x4: each 2x2 polarizer block carries one Bayer colour, blocks arranged R G / G B.
_BAYER_BLOCKS = np.array([[0, 1], [1, 2]])
IMX250MYR = MosaicLayout(
    "imx250myr",
    np.tile(_SONY_CELL, (2, 2)),
    np.kron(_BAYER_BLOCKS, np.ones((2, 2), int)),
    ("R", "G", "B"),
)

LAYOUTS: dict[str, MosaicLayout] = {l.name: l for l in (IMX250MZR, IMX250MYR)}


def get_layout(name: str, offset_x: int = 0, offset_y: int = 0) -> MosaicLayout:
    """Look up a layout by name (case-insensitive) and shift it to a ROI offset."""
    key = name.lower().split("@")[0]
    if key not in LAYOUTS:
        raise ValueError(f"unknown mosaic layout {name!r}; known: {', '.join(sorted(LAYOUTS))}")
    return LAYOUTS[key].shifted(offset_x, offset_y)
