"""ChArUco calibration board: definition, printable image, detection, intrinsics, pose.

Board coordinates (metres): origin at the board's top-left outer corner as printed, ``x`` along
the squares' columns (image ``+u`` of the printed image), ``y`` along the rows (down the
printed image), ``z = x cross y`` pointing into the board (away from a viewer of the printed
side). This is OpenCV's ``CharucoBoard.getChessboardCorners`` frame. Camera frame and pixel
coordinates follow ``docs/conventions.md`` (OpenCV's: pixel centres at integer coordinates).

Uses OpenCV's ``aruco`` module (``cv2.aruco.CharucoBoard``, ``CharucoDetector``, OpenCV >= 4.7)
and ``cv2.calibrateCameraExtended`` (Zhang, "A flexible new technique for camera calibration",
IEEE TPAMI 22(11), 2000; OpenCV documentation "Camera Calibration and 3D Reconstruction",
tutorial "Detection of ChArUco Boards").
"""

from __future__ import annotations

import dataclasses
import os
import struct
import zlib

import cv2
import numpy as np

from polrig.calibration.errors import BoardNotFound
from polrig.errors import ConfigError
from polrig.sensor.analyzer import resolve_layout

_DICTIONARIES = {name[5:]: getattr(cv2.aruco, name) for name in dir(cv2.aruco)
                 if name.startswith("DICT_")}


@dataclasses.dataclass(frozen=True)
class BoardSpec:
    """A ChArUco board: ``squares_x`` columns by ``squares_y`` rows of squares of side
    ``square_m``, ArUco markers of side ``marker_m`` from the dictionary ``dictionary``
    (an OpenCV name such as ``"4X4_50"``)."""

    squares_x: int = 7
    squares_y: int = 5
    square_m: float = 0.03
    marker_m: float = 0.022
    dictionary: str = "4X4_50"

    def __post_init__(self) -> None:
        if self.squares_x < 3 or self.squares_y < 3:
            raise ConfigError(f"ChArUco board needs at least 3x3 squares, got "
                              f"{self.squares_x}x{self.squares_y}")
        if not (0 < self.marker_m < self.square_m):
            raise ConfigError(f"ChArUco marker_m ({self.marker_m}) must be in (0, square_m="
                              f"{self.square_m})")
        if self.dictionary.upper() not in _DICTIONARIES:
            raise ConfigError(f"unknown ArUco dictionary {self.dictionary!r}; e.g. 4X4_50, "
                              f"5X5_100, 6X6_250")
        n_markers = (self.squares_x * self.squares_y) // 2
        size = int(self.dictionary.upper().split("_")[-1]) if self.dictionary[0].isdigit() else 10**9
        if n_markers > size:
            raise ConfigError(f"board needs {n_markers} markers but dictionary "
                              f"{self.dictionary} has {size}; choose a larger dictionary")

    @property
    def size_m(self) -> tuple[float, float]:
        """Board width and height in metres."""
        return self.squares_x * self.square_m, self.squares_y * self.square_m

    def cv_board(self) -> "cv2.aruco.CharucoBoard":
        d = cv2.aruco.getPredefinedDictionary(_DICTIONARIES[self.dictionary.upper()])
        return cv2.aruco.CharucoBoard((self.squares_x, self.squares_y), self.square_m,
                                      self.marker_m, d)

    def corners_m(self) -> np.ndarray:
        """Inner chessboard corners in board coordinates ``(N, 3)``, indexed by corner id."""
        return np.asarray(self.cv_board().getChessboardCorners(), dtype=np.float64)

    def image(self, pixels_per_square: int = 100) -> np.ndarray:
        """The board as a uint8 image, exactly ``squares * pixels_per_square`` pixels wide and
        high with no margin: image pixel ``(row, col)`` covers board ``x`` in
        ``[col, col+1) * square_m / pixels_per_square`` (same for ``y``/``row``)."""
        w, h = self.squares_x * pixels_per_square, self.squares_y * pixels_per_square
        return self.cv_board().generateImage((w, h), marginSize=0, borderBits=1)

    def to_json(self) -> dict:
        return dataclasses.asdict(self)


def write_board_png(spec: BoardSpec, path: str | os.PathLike, dpi: float = 300.0,
                    margin_m: float = 0.01) -> tuple[int, int]:
    """Write the printable board as a PNG whose ``pHYs`` chunk states ``dpi``, so that printing
    at 100 % scale gives squares of exactly ``spec.square_m``. A white margin of ``margin_m``
    surrounds the board. Returns the image size ``(width, height)`` in pixels.
    """
    if not (50 <= dpi <= 2400):
        raise ValueError(f"dpi must be within [50, 2400], got {dpi}")
    px_per_m = dpi / 0.0254
    pps = spec.square_m * px_per_m
    if abs(pps - round(pps)) > 1e-6 * pps:
        # keep squares an integer number of pixels so every square prints the same size
        pps = round(pps)
    pps = int(round(pps))
    board = spec.image(pps)
    m = int(round(margin_m * px_per_m))
    img = cv2.copyMakeBorder(board, m, m, m, m, cv2.BORDER_CONSTANT, value=255)
    ok, buf = cv2.imencode(".png", img)
    if not ok:  # pragma: no cover - OpenCV always encodes uint8
        raise OSError("PNG encoding failed")
    data = bytes(buf)
    ppm = int(round(px_per_m))
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body) & 0xFFFFFFFF)
    ihdr_end = 8 + 4 + 4 + 13 + 4  # signature + IHDR length/type/data/crc
    data = data[:ihdr_end] + chunk + data[ihdr_end:]
    with open(path, "wb") as f:
        f.write(data)
    return img.shape[1], img.shape[0]


@dataclasses.dataclass(frozen=True)
class CharucoDetection:
    """Detected ChArUco corners of one image: ``ids`` ``(N,)`` and ``corners_px`` ``(N, 2)``
    (``u, v``, pixel centres at integers), with the matching board points ``object_m``
    ``(N, 3)``."""

    ids: np.ndarray
    corners_px: np.ndarray
    object_m: np.ndarray

    @property
    def count(self) -> int:
        return int(self.ids.size)


def to_detection_image(image: np.ndarray) -> np.ndarray:
    """A uint8 grey image for detection from any finite 2-D intensity image (DN), stretched
    between its 1st and 99th percentiles; non-finite pixels become 0."""
    a = np.asarray(image, dtype=np.float64)
    if a.ndim != 2:
        raise ValueError(f"board detection needs a 2-D grey image, got shape {a.shape}")
    a = np.where(np.isfinite(a), a, 0.0)
    lo, hi = np.percentile(a, [1, 99])
    if hi - lo <= 0:
        return np.zeros(a.shape, np.uint8)
    return np.clip((a - lo) * (255.0 / (hi - lo)), 0, 255).astype(np.uint8)


def detect(spec: BoardSpec, image: np.ndarray, min_corners: int = 6) -> CharucoDetection:
    """Detect the board's ChArUco corners in a grey image (any dtype, see
    :func:`to_detection_image`); raises :class:`BoardNotFound` with fewer than
    ``min_corners`` corners (at least 4 are needed for a pose, 6 for calibration)."""
    grey = to_detection_image(image) if np.asarray(image).dtype != np.uint8 else np.asarray(image)
    board = spec.cv_board()
    detector = cv2.aruco.CharucoDetector(board)
    corners, ids, _marker_corners, marker_ids = detector.detectBoard(grey)
    n = 0 if ids is None else int(np.asarray(ids).size)
    if n < min_corners:
        nm = 0 if marker_ids is None else int(np.asarray(marker_ids).size)
        raise BoardNotFound(
            f"ChArUco board not found: {n} corners and {nm} markers detected, need "
            f"{min_corners} corners; bring the {spec.squares_x}x{spec.squares_y} board "
            f"({spec.dictionary}) fully into view, raise exposure or light level, or refocus")
    ids = np.asarray(ids, dtype=np.int64).reshape(-1)
    corners = np.asarray(corners, dtype=np.float64).reshape(-1, 2)
    return CharucoDetection(ids, corners, spec.corners_m()[ids])


@dataclasses.dataclass(frozen=True)
class IntrinsicsResult:
    """Pinhole intrinsics with distortion, fitted from several board views.

    ``K`` 3x3 (pixels), ``dist`` OpenCV distortion coefficients (k1, k2, p1, p2, k3),
    ``std_fx_fy_cx_cy`` one-sigma uncertainties in pixels (from the Jacobian at the
    optimum, OpenCV's ``stdDeviationsIntrinsics``), ``rms_px`` the RMS reprojection error,
    ``per_view_rms_px`` per image, and the board poses (board -> camera) ``rvecs``/``tvecs``.
    """

    K: np.ndarray
    dist: np.ndarray
    image_size: tuple[int, int]
    rms_px: float
    std_fx_fy_cx_cy: np.ndarray
    per_view_rms_px: np.ndarray
    rvecs: np.ndarray
    tvecs: np.ndarray
    residuals_px: np.ndarray  # (M, 2) all reprojection residuals

    @property
    def fx(self) -> float:
        return float(self.K[0, 0])

    @property
    def fy(self) -> float:
        return float(self.K[1, 1])

    def to_json(self) -> dict:
        return {"K": self.K.tolist(), "dist": self.dist.tolist(),
                "image_size": list(self.image_size), "rms_px": self.rms_px,
                "std_fx_fy_cx_cy_px": self.std_fx_fy_cx_cy.tolist(),
                "per_view_rms_px": self.per_view_rms_px.tolist()}


def calibrate_intrinsics(detections: list[CharucoDetection], image_size: tuple[int, int],
                         distortion: str = "k1k2") -> IntrinsicsResult:
    """Zhang calibration from board detections in images of ``image_size = (width, height)``.

    ``distortion``: ``"none"`` (pinhole only), ``"k1"`` (radial k1), ``"k1k2"`` (radial k1,
    k2; default) or ``"full"`` (k1, k2, p1, p2, k3). Raises :class:`BoardNotFound` (a
    ``ValueError``) naming what to add when there are fewer than 3 usable views (OpenCV's minimum
    for a stable solution with a planar target).
    """
    views = [d for d in detections if d.count >= 6]
    if len(views) < 3:
        raise BoardNotFound(f"intrinsic calibration needs at least 3 board views with 6+ corners, "
                         f"got {len(views)}; capture the board at more (tilted) poses")
    obj = [d.object_m.astype(np.float32) for d in views]
    img = [d.corners_px.astype(np.float32) for d in views]
    flags = {"none": cv2.CALIB_FIX_K1 | cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3
             | cv2.CALIB_ZERO_TANGENT_DIST,
             "k1": cv2.CALIB_FIX_K2 | cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
             "k1k2": cv2.CALIB_FIX_K3 | cv2.CALIB_ZERO_TANGENT_DIST,
             "full": 0}.get(distortion)
    if flags is None:
        raise ValueError(f"distortion must be 'none', 'k1', 'k1k2' or 'full', got {distortion!r}")
    w, h = image_size
    k0 = np.array([[max(w, h), 0, (w - 1) / 2], [0, max(w, h), (h - 1) / 2], [0, 0, 1]], float)
    rms, K, dist, rvecs, tvecs, std_in, _std_ex, per_view = cv2.calibrateCameraExtended(
        obj, img, (w, h), k0, np.zeros(5), flags=flags,
        criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12))
    res = []
    for o, i, rv, tv in zip(obj, img, rvecs, tvecs):
        p, _ = cv2.projectPoints(o, rv, tv, K, dist)
        res.append(i.reshape(-1, 2) - p.reshape(-1, 2))
    return IntrinsicsResult(np.asarray(K, float), np.asarray(dist, float).reshape(-1),
                            (int(w), int(h)), float(rms), np.asarray(std_in, float).reshape(-1)[:4],
                            np.asarray(per_view, float).reshape(-1),
                            np.asarray(rvecs, float).reshape(-1, 3),
                            np.asarray(tvecs, float).reshape(-1, 3), np.concatenate(res))


def board_pose(detection: CharucoDetection, K: np.ndarray,
               dist: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, float]:
    """Pose of the board (board -> camera: ``p_cam = R @ p_board + t``, metres) from one
    detection with known intrinsics, and its RMS reprojection error in pixels.

    Raises :class:`BoardNotFound` when fewer than 6 corners are available or the corners are
    collinear (the pose is then not determined)."""
    if detection.count < 6:
        raise BoardNotFound(f"board pose needs 6+ ChArUco corners, got {detection.count}; "
                            "bring more of the board into view")
    dist = np.zeros(5) if dist is None else np.asarray(dist, float)
    obj = detection.object_m.astype(np.float64)
    img = detection.corners_px.astype(np.float64)
    if np.linalg.matrix_rank(obj[:, :2] - obj[:, :2].mean(0), tol=1e-9) < 2:
        raise BoardNotFound("detected ChArUco corners are collinear; show more rows of the board")
    ok, rvec, tvec = cv2.solvePnP(obj, img, K, dist, flags=cv2.SOLVEPNP_ITERATIVE)
    if not ok:
        raise BoardNotFound("board pose could not be solved from the detected corners")
    rvec, tvec = cv2.solvePnPRefineLM(obj, img, K, dist, rvec, tvec)
    p, _ = cv2.projectPoints(obj, rvec, tvec, K, dist)
    rms = float(np.sqrt(np.mean(np.sum((p.reshape(-1, 2) - img) ** 2, axis=1))))
    R, _ = cv2.Rodrigues(rvec)
    return R, tvec.reshape(3), rms


#: A pixel's mosaic cell counts as flat when the cell means within half a cell of it stay within
#: this share of its own (:func:`class_scales`): then every pixel its cell mean averages lies
#: in one uniform patch.
FLAT_CELL_SPREAD = 0.1
#: ... and as bright when its cell mean is at least this share of the frame's 99th percentile.
BRIGHT_CELL_SHARE = 0.25


def _cell_mean(a: np.ndarray, period: tuple[int, int]) -> np.ndarray:
    """Mean ``(H, W)`` of ``a`` over one mosaic cell centred on every pixel: a separable box of
    ``p + 1`` taps with half weights at both ends for an even period ``p`` (so every pixel class
    of the cell weighs alike and a ``p``-periodic pattern averages out exactly)."""
    def taps(p: int) -> np.ndarray:
        k = np.ones(p + 1 if p % 2 == 0 else p)
        if p % 2 == 0:
            k[0] = k[-1] = 0.5
        return k / p
    ph, pw = period
    return cv2.sepFilter2D(a, -1, taps(pw), taps(ph), borderType=cv2.BORDER_REFLECT)


def class_scales(raw: np.ndarray, layout, black_level_dn: float = 0.0) -> np.ndarray:
    """Relative level of every mosaic pixel ``(H, W)`` of a frame of a grey-ish scene.

    Each (colour, analyzer) pixel class's level is the median ratio of its pixels to their own
    mosaic cell's mean (:func:`_cell_mean`), over the pixels whose cell is bright (at least
    :data:`BRIGHT_CELL_SHARE` of the frame's 99th percentile) and flat (the cell means around
    it within :data:`FLAT_CELL_SPREAD`: no edge inside), times the median cell mean there, so
    that the classes divide to about 1 on the bright parts. A ratio to the pixel's own
    neighbourhood does not depend on what share of the frame is bright: a board filling most
    of the frame, half of it black, gives the same levels as a white wall. Where no pixel is
    bright and flat (a frame of fine texture alone), the bright pixels are used without the
    flatness test.
    """

    lay = resolve_layout(layout)
    a = np.asarray(raw, dtype=np.float64) - float(black_level_dn)
    a = np.where(np.isfinite(a), a, 0.0)
    ph, pw = lay.period
    cell = _cell_mean(a, (ph, pw))
    top = float(np.percentile(cell, 99))
    out = np.ones_like(a)
    if not top > 0:
        return out
    bright = cell >= BRIGHT_CELL_SHARE * top
    win = np.ones((ph + 1, pw + 1), np.uint8)
    spread = cv2.dilate(cell, win) - cv2.erode(cell, win)
    use = bright & (spread <= FLAT_CELL_SPREAD * cell)
    if np.count_nonzero(use) < 16 * ph * pw:  # fewer than 16 pixels of each class
        use = bright
    ratio = np.divide(a, cell, out=np.zeros_like(a), where=cell > 0)
    level = float(np.median(cell[use]))
    for m in lay.masks(a.shape).values():
        sel = m & use
        r = float(np.median(ratio[sel])) if np.count_nonzero(sel) > 8 else 1.0
        out[m] = r * level if r > 0 else level
    return out


def intensity_image(raw: np.ndarray, layout, black_level_dn: float = 0.0,
                    scales: np.ndarray | None = None) -> np.ndarray:
    """A grey float image of a raw DoFP mosaic for geometric detection (board corners, sphere
    silhouettes): black level removed, every (colour, analyzer angle) pixel class divided by
    its level (:func:`class_scales` of this frame unless ``scales`` from another frame of the
    same scene are given), then a centred ``[1, 2, 1] / 4`` smoothing that suppresses what
    remains of the mosaic without shifting edges. ``layout``: a
    :class:`polrig.sensor.layouts.MosaicLayout` or a name such as ``"imx250myr@0,1"``.
    """
    a = np.asarray(raw, dtype=np.float64) - float(black_level_dn)
    a = np.where(np.isfinite(a), a, 0.0)
    if scales is None:
        scales = class_scales(a, layout)
    k = np.array([0.25, 0.5, 0.25])
    return cv2.sepFilter2D(a / scales, -1, k, k, borderType=cv2.BORDER_REFLECT)
