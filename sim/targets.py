"""Calibration targets of the simulated rig, as :class:`polrig.sim.scene.SceneObject` s.

* ``charuco``: a ChArUco board (8 x 6 squares of 25 mm, 18 mm ``4X4_50`` markers: the default
  board of ``polrig.calibration.runner.Options``, printed with OpenCV's own board image) on a fixture
  at the turntable centre: a two-sided
  :class:`polrig.sim.shapes.Rectangle` whose per-region materials (matte black / matte white
  dielectric, Baek diffuse only) follow the board image;
* ``mirror_plate``: a polished aluminium plate in the same fixture (:data:`MIRROR_ALUMINIUM`:
  a real conductor with the complex index of :data:`polrig.sim.optical_data.CONDUCTORS` per colour,
  so with the diattenuation and retardance of its Fresnel reflection; a non-depolarizing GGX
  lobe of roughness 0.3 spreads the reflected light of the polarizer over the whole image),
  the polarized flat field of the DoFP calibration. Aluminium because it is the usual bare
  front-surface mirror metal, and the calibration's default
  (:data:`polrig.calibration.mirror.DEFAULT_MIRROR_METAL`, tested equal);
* ``white_plate``: a matte white plate in the same fixture (flat field, unpolarizing);
* ``chrome_sphere``: a chrome ball of known radius off the turntable axis, in front of a matte
  white backdrop (so that its silhouette is a dark disc), for the light position; chrome is
  the real conductor ``Cr`` (:data:`CHROME`, normal-incidence reflectance 0.64, 0.67 and
  0.70 for R, G and B, partly polarizing at oblique incidence), not an ideal mirror.

Both metals render through :class:`polrig.sim.materials.SurfaceMaterial` (:mod:`polrig.sim.surface_bsdf`).

The fixture's pose (tilt back from vertical, yaw on the turntable) is shared by the plates and
the board so that a board pose measured at a turntable angle is the plate pose there, as with a
kinematic mount in the lab. :func:`mount` swaps the target of a running simulated rig (the
guided procedures call it where an operator would swap targets by hand); the rig's camera,
light, stage, sensor and hidden parameters stay the same.

Hook added here (the simulator's scene model has no notion of swapping objects): :func:`mount`
replaces ``world.scene`` and empties the world's render caches.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from polrig.sim.geometry import rotation_about_axis
from polrig.sim.materials import Material, SurfaceMaterial
from polrig.sim.optical_data import conductor_rgb
from polrig.sim.scene import OBJECT_Z_M, Scene, SceneObject
from polrig.sim.shapes import Rectangle, Sphere
from polrig.sim.world import SimWorld

TARGETS = ("charuco", "mirror_plate", "white_plate", "chrome_sphere")

BOARD_BLACK = Material("board_black", (0.03, 0.03, 0.03), 0.5, 1.5, ks=0.0)
BOARD_WHITE = Material("board_white", (0.85, 0.85, 0.85), 0.5, 1.5, ks=0.0)
#: The DoFP plate: polished (GGX roughness 0.3) bare aluminium.
MIRROR_ALUMINIUM = SurfaceMaterial("mirror_aluminium", conductor_rgb("aluminium"), 0.3)
#: The light-calibration ball: polished chrome (GGX roughness 0.04).
CHROME = SurfaceMaterial("chrome", conductor_rgb("chrome"), 0.04)
WHITE = Material("matte_white", (0.8, 0.8, 0.8), 0.5, 1.5, ks=0.0)
#: Sub-pixel samples per axis of the printed board's pattern over each pixel
#: (:attr:`polrig.sim.scene.SceneObject.footprint_samples`): a pixel sees its area's mean albedo,
#: as a sensor pixel does, so its square edges move continuously with the board's pose.
BOARD_FOOTPRINT_SAMPLES = 4

#: Default geometry of the targets (metres, degrees).
DEFAULTS: dict[str, Any] = {
    "fixture_centre_m": (0.0, 0.0, OBJECT_Z_M),
    "tilt_deg": 25.0,
    "yaw_deg": 0.0,
    "roll_deg": 0.0,
    "squares_x": 8, "squares_y": 6, "square_m": 0.025, "marker_m": 0.018,
    "dictionary": "4X4_50",
    "plate_half_m": 0.2,
    "sphere_radius_m": 0.03,
    "sphere_offset_m": (0.075, 0.0, 0.0),
    "sphere_height_m": 0.05,
    "backdrop_y_m": 0.6,
}


def fixture_rotation(tilt_deg: float, yaw_deg: float, roll_deg: float = 0.0) -> np.ndarray:
    """Local -> world rotation of the fixture at turntable angle 0: the plate's local ``+z``
    (its front) faces the camera side (``-Y``), tilted back (towards ``+Z``) by ``tilt_deg``
    and turned about the vertical by ``yaw_deg``; local ``+y`` is the plate's up edge, turned
    in the plate's plane by ``roll_deg`` (counter-clockwise seen from the front)."""
    r0 = np.column_stack([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
    return (rotation_about_axis([0, 0, 1], yaw_deg) @ rotation_about_axis([1, 0, 0], -tilt_deg)
            @ r0 @ rotation_about_axis([0, 0, 1], roll_deg))


def board_image(squares_x: int, squares_y: int, square_m: float, marker_m: float,
                dictionary: str, pixels_per_square: int = 64) -> np.ndarray:
    """The printed ChArUco board (uint8, white 255, no margin) as OpenCV draws it
    (``cv2.aruco.CharucoBoard.generateImage``): exactly ``squares * pixels_per_square`` pixels
    on each side, so that image pixel ``(row, col)`` covers board ``x`` in
    ``[col, col + 1) * square_m / pixels_per_square`` (and ``y`` likewise, down the print).
    The calibration side (:class:`polrig.calibration.charuco.BoardSpec`) describes the same board."""
    import cv2

    d = cv2.aruco.getPredefinedDictionary(getattr(cv2.aruco, f"DICT_{dictionary.upper()}"))
    board = cv2.aruco.CharucoBoard((int(squares_x), int(squares_y)), float(square_m),
                                   float(marker_m), d)
    return board.generateImage((int(squares_x) * pixels_per_square,
                                int(squares_y) * pixels_per_square), marginSize=0, borderBits=1)


def board_region(img: np.ndarray, square_m: float, half_x_m: float, half_y_m: float,
                 pixels_per_square: int = 64):
    """Region function (0 black, 1 white) of a board image on a rectangle: local ``x`` to
    the right, ``y`` up the printed image, so board coordinates (OpenCV's, ``y`` down the
    print) are ``(x + half_x, half_y - y)``."""
    h, w = img.shape
    scale = pixels_per_square / square_m

    def region(p: np.ndarray) -> np.ndarray:
        col = np.clip(np.floor((p[:, 0] + half_x_m) * scale).astype(np.int64), 0, w - 1)
        row = np.clip(np.floor((half_y_m - p[:, 1]) * scale).astype(np.int64), 0, h - 1)
        return (img[row, col] > 127).astype(np.int64)

    return region


def target_objects(name: str, **kw) -> list[SceneObject]:
    """The scene objects of calibration target ``name`` (:data:`TARGETS`); keyword arguments
    override :data:`DEFAULTS`."""
    unknown = set(kw) - set(DEFAULTS)
    if unknown:
        raise ValueError(f"unknown target option(s) {sorted(unknown)}; known: {sorted(DEFAULTS)}")
    o = {**DEFAULTS, **kw}
    centre = np.asarray(o["fixture_centre_m"], float)
    rot = fixture_rotation(float(o["tilt_deg"]), float(o["yaw_deg"]), float(o["roll_deg"]))
    if name == "charuco":
        sq = float(o["square_m"])
        img = board_image(o["squares_x"], o["squares_y"], sq, o["marker_m"], o["dictionary"])
        hx, hy = 0.5 * int(o["squares_x"]) * sq, 0.5 * int(o["squares_y"]) * sq
        return [SceneObject("charuco", Rectangle(hx, hy), (BOARD_BLACK, BOARD_WHITE), centre,
                            rotation=rot, region=board_region(img, sq, hx, hy),
                            footprint_samples=BOARD_FOOTPRINT_SAMPLES)]
    if name in ("mirror_plate", "white_plate"):
        half = float(o["plate_half_m"])
        mat = MIRROR_ALUMINIUM if name == "mirror_plate" else WHITE
        return [SceneObject(name, Rectangle(half, half), (mat,), centre, rotation=rot)]
    if name == "chrome_sphere":
        r = float(o["sphere_radius_m"])
        pos = np.asarray(o["sphere_offset_m"], float) + [0.0, 0.0, float(o["sphere_height_m"])]
        backdrop_rot = np.column_stack([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]])
        return [SceneObject("chrome_sphere", Sphere(r), (CHROME,), pos),
                SceneObject("backdrop", Rectangle(1.0, 1.0), (WHITE,),
                            [0.0, float(o["backdrop_y_m"]), OBJECT_Z_M],
                            rotation=backdrop_rot, on_turntable=False)]
    raise ValueError(f"unknown calibration target {name!r}; known: {', '.join(TARGETS)}")


def target_scene(base: Scene, name: str, **kw) -> Scene:
    """``base`` (camera, light, turntable, stage axis kept) with its objects replaced by the
    calibration target ``name``."""
    return dataclasses.replace(base, name=f"target:{name}", objects=tuple(target_objects(name, **kw)))


def mount(world: SimWorld, name: str, **kw) -> None:
    """Swap the target in a simulated ``world``: its scene gets the target's objects and its
    render caches are emptied. Camera, light, stage, turntable position and all hidden
    parameters are kept. A rig's callers reach it through the rig's declared truth,
    :meth:`polrig.acquisition.hal.RigTruth.mount_target`."""
    world.set_scene(target_scene(world.scene, name, **kw))
