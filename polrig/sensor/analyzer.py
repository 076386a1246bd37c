"""Per-pixel analyzer model of a division-of-focal-plane (DoFP) polarization sensor.

Each sensor pixel ``p`` sits behind a micro-polarizer and reads (Powell and Gruev,
"Calibration methods for division-of-focal-plane polarimeters", Opt. Express 21(18):21039,
2013)::

    I_p = g_p / 2 * [1, D_p cos 2 t_p, D_p sin 2 t_p] . S + o_p

with ``g_p`` the gain (dimensionless, 1 for an ideal pixel), ``t_p`` the analyzer angle in
degrees, ``D_p`` the diattenuation (1 for an ideal polarizer), ``o_p`` the offset in DN and ``S``
the linear Stokes vector ``(S0, S1, S2)`` of the light arriving at that pixel in the emergent
(camera) frame. Angles and Stokes follow ``docs/conventions.md`` (``psi`` counter-clockwise as
displayed from image ``+u``; ideal analyzer ``I(t) = (S0 + S1 cos 2t + S2 sin 2t) / 2``).

The model is stored per sensor pixel (arrays of the readout's shape ``(H, W)``) together with
the name of the mosaic layout (with its ROI phase, e.g. ``"imx250mzr@1,0"``) that tells which
colour each pixel sees. :meth:`AnalyzerModel.ideal` builds the nominal model of a layout;
calibration (``calibration/``) fits a real one and saves it with :meth:`AnalyzerModel.save`.
"""

from __future__ import annotations

import dataclasses
import io
import os
import re
from typing import TYPE_CHECKING, Union

import numpy as np

from polrig.atomic import atomic_write_bytes
from polrig.errors import FormatError
from polrig.sensor.layouts import MosaicLayout, get_layout

if TYPE_CHECKING:
    from polrig.sensor.frame import Frame

LayoutLike = Union[str, MosaicLayout]

_FILE_VERSION = 1
_LAYOUT_NAME = re.compile(r"^(?P<base>[^@]+)(?:@(?P<x>-?\d+),(?P<y>-?\d+))?$")


def resolve_layout(layout: LayoutLike) -> MosaicLayout:
    """A :class:`MosaicLayout` from a layout or a name such as ``"imx250mzr"`` or
    ``"imx250mzr@1,0"`` (the ``@x,y`` suffix is the ROI offset that sets the phase, as
    :meth:`MosaicLayout.shifted` names it)."""
    if isinstance(layout, MosaicLayout):
        return layout
    m = _LAYOUT_NAME.match(str(layout).strip())
    if not m:
        raise ValueError(f"bad mosaic layout name {layout!r}")
    x, y = int(m["x"] or 0), int(m["y"] or 0)
    return get_layout(m["base"], x, y)


def _layout_base_and_offset(layout: MosaicLayout) -> tuple[str, int, int]:
    m = _LAYOUT_NAME.match(layout.name)
    if not m:  # pragma: no cover - layouts are named by polrig.sensor.layouts
        raise ValueError(f"bad mosaic layout name {layout.name!r}")
    return m["base"], int(m["x"] or 0), int(m["y"] or 0)


def layout_name_at(layout: LayoutLike, offset_x: int, offset_y: int) -> str:
    """Name of ``layout`` further shifted by a crop starting at ``(offset_x, offset_y)``,
    reduced modulo the layout period (``"imx250mzr"`` when the phase is the layout's own)."""
    lay = resolve_layout(layout)
    base, x0, y0 = _layout_base_and_offset(lay)
    ph, pw = get_layout(base).period
    x, y = (x0 + offset_x) % pw, (y0 + offset_y) % ph
    return base if (x, y) == (0, 0) else f"{base}@{x},{y}"


def frame_layout(frame: "Frame") -> MosaicLayout:
    """Mosaic layout of a :class:`polrig.sensor.frame.Frame`, its phase from the frame's ROI
    offset (:func:`layout_name_at`)."""
    ox, oy = frame.meta.offset_xy
    return resolve_layout(layout_name_at(frame.meta.layout, int(ox), int(oy)))


@dataclasses.dataclass(frozen=True)
class AnalyzerModel:
    """Per-sensor-pixel analyzer parameters of a DoFP readout (see the module docstring).

    Attributes (all ``(H, W)`` float64 arrays over the readout):

    * ``gain``: dimensionless gain ``g_p`` (1 = nominal),
    * ``angle_deg``: analyzer angle ``t_p`` in degrees (``docs/conventions.md``),
    * ``diattenuation``: ``D_p`` in [0, 1] (1 = ideal polarizer),
    * ``offset_dn``: additive offset ``o_p`` in DN (on top of any black level removed).

    ``layout`` is the mosaic layout name including its ROI phase (``"imx250myr@2,0"``).
    """

    layout: str
    gain: np.ndarray
    angle_deg: np.ndarray
    diattenuation: np.ndarray
    offset_dn: np.ndarray

    def __post_init__(self) -> None:
        lay = resolve_layout(self.layout)
        object.__setattr__(self, "layout", layout_name_at(lay, 0, 0))
        arrays = {}
        for name in ("gain", "angle_deg", "diattenuation", "offset_dn"):
            a = np.array(getattr(self, name), dtype=np.float64)
            a.setflags(write=False)
            arrays[name] = a
        shapes = {a.shape for a in arrays.values()}
        if len(shapes) != 1 or arrays["gain"].ndim != 2:
            raise ValueError(f"analyzer model arrays must be 2-D and of one shape, got "
                             f"{ {k: v.shape for k, v in arrays.items()} }")
        for name, a in arrays.items():
            if not np.all(np.isfinite(a)):
                raise ValueError(f"analyzer model {name} has non-finite values")
            object.__setattr__(self, name, a)

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def ideal(cls, layout: LayoutLike, shape: tuple[int, int]) -> "AnalyzerModel":
        """The nominal model: gain 1, diattenuation 1, offset 0, the layout's angles."""
        lay = resolve_layout(layout)
        h, w = shape
        ones = np.ones((h, w))
        return cls(lay.name, ones, lay.angle_map((h, w)).astype(np.float64), ones.copy(),
                   np.zeros((h, w)))

    # -- properties -----------------------------------------------------------------------
    @property
    def shape(self) -> tuple[int, int]:
        return self.gain.shape  # type: ignore[return-value]

    @property
    def mosaic_layout(self) -> MosaicLayout:
        return resolve_layout(self.layout)

    @property
    def n_colours(self) -> int:
        return self.mosaic_layout.n_colours

    def rows(self) -> np.ndarray:
        """Analyzer row vectors ``g/2 [1, D cos 2t, D sin 2t]`` per sensor pixel, ``(H, W, 3)``.

        ``I_p = rows[p] . S + offset_dn[p]``.
        """
        t = np.deg2rad(self.angle_deg) * 2.0
        half_g = 0.5 * self.gain
        gd = half_g * self.diattenuation
        return np.stack([half_g, gd * np.cos(t), gd * np.sin(t)], axis=-1)

    def colour_map(self) -> np.ndarray:
        """Colour index (``0..C-1``) seen by each sensor pixel, ``(H, W)`` int."""
        return self.mosaic_layout.colour_map(self.shape)

    # -- forward model --------------------------------------------------------------------
    def mosaic(self, stokes: np.ndarray) -> np.ndarray:
        """Noise-free raw-plane intensity (DN, float64, ``(H, W)``) of full-resolution Stokes
        images ``stokes`` ``(C, 3, H, W)`` (C = the layout's colour count); each sensor pixel
        reads the Stokes vector of its own colour at its own position."""
        s = np.asarray(stokes, dtype=np.float64)
        h, w = self.shape
        c = self.n_colours
        if s.shape != (c, 3, h, w):
            raise ValueError(f"stokes must have shape {(c, 3, h, w)} for layout "
                             f"{self.layout}, got {s.shape}")
        if c == 1:
            sel = s[0]
        else:
            cmap = self.colour_map()
            sel = np.take_along_axis(s, cmap[None, None], axis=0)[0]
        r = self.rows()
        return (r[..., 0] * sel[0] + r[..., 1] * sel[1] + r[..., 2] * sel[2]) + self.offset_dn

    # -- geometry -------------------------------------------------------------------------
    def crop(self, x: int, y: int, w: int, h: int) -> "AnalyzerModel":
        """The model of a readout ROI ``w x h`` starting at column ``x``, row ``y`` of this one
        (the layout phase follows the offset)."""
        H, W = self.shape
        if x < 0 or y < 0 or w <= 0 or h <= 0 or x + w > W or y + h > H:
            raise ValueError(f"crop ({x}, {y}, {w}, {h}) outside the {W}x{H} analyzer model")
        sl = (slice(y, y + h), slice(x, x + w))
        return AnalyzerModel(layout_name_at(self.layout, x, y), self.gain[sl],
                             self.angle_deg[sl], self.diattenuation[sl], self.offset_dn[sl])

    # -- files ----------------------------------------------------------------------------
    def save(self, path: str | os.PathLike) -> None:
        """Write the model to a ``.npz`` file (atomically)."""
        buf = io.BytesIO()
        np.savez_compressed(buf, version=np.int64(_FILE_VERSION), layout=np.str_(self.layout),
                            gain=self.gain, angle_deg=self.angle_deg,
                            diattenuation=self.diattenuation, offset_dn=self.offset_dn)
        atomic_write_bytes(path, buf.getvalue())

    @classmethod
    def load(cls, path: str | os.PathLike) -> "AnalyzerModel":
        """Read a model written by :meth:`save`; :class:`FormatError` if it is not one."""
        try:
            with np.load(path, allow_pickle=False) as z:
                version = int(z["version"])
                if version != _FILE_VERSION:
                    raise FormatError(f"{path}: analyzer model file version {version}, "
                                      f"expected {_FILE_VERSION}")
                return cls(str(z["layout"]), z["gain"], z["angle_deg"], z["diattenuation"],
                           z["offset_dn"])
        except FormatError:
            raise
        except FileNotFoundError:
            raise
        except (KeyError, ValueError, OSError, EOFError) as exc:
            raise FormatError(f"{path}: not a polrig analyzer model file ({exc})") from None
