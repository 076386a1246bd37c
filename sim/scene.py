"""Scenes of the simulator: objects (shape + pose + materials), the rig (camera, light,
turntable, polarizer stage axis) and named presets.

Units: metres, world frame ``+Z`` up (:mod:`polrig.sim.geometry`). An object's pose maps its local
frame to the world at turntable angle 0; objects with ``on_turntable`` are additionally carried
by the turntable rotation. Per-region materials: ``region(p_local) -> index`` into
``materials`` (``None``: one material).

The incident Stokes frame's ``x`` axis is the polarizer stage's zero axis, ``stage_zero_axis``,
a world unit vector perpendicular to the illumination axis (light -> ``illumination_target_m``);
see ``docs/conventions.md`` ("Stokes reference frames").
"""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from polrig.choices import MATERIAL_SCENES, SCENES
from polrig.sim.geometry import (
    PinholeCamera,
    PointLight,
    TurntableGeometry,
    look_at,
    rotation_about_axis,
    unit,
)
from polrig.sim.materials import (
    Material,
    SurfaceMaterial,
    Texture,
    get_material,
    random_material,
    random_mix_material,
)
from polrig.sim.optical_data import conductor_rgb, dielectric_rgb
from polrig.sim.shapes import (
    Blob,
    Box,
    Cylinder,
    HeightField,
    Rectangle,
    Shape,
    Sphere,
    Torus,
    gaussian_bumps,
    wave_normal_map,
)

RegionFn = Callable[[np.ndarray], np.ndarray]


@dataclasses.dataclass(frozen=True)
class SceneObject:
    """One object: ``shape`` in its local frame, placed by ``rotation`` (local->world) and
    ``position_m`` at turntable angle 0."""

    name: str
    shape: Shape
    materials: tuple[Material | SurfaceMaterial, ...]
    position_m: np.ndarray = dataclasses.field(default_factory=lambda: np.zeros(3))
    rotation: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))
    region: RegionFn | None = None
    on_turntable: bool = True
    #: Sub-pixel samples per axis of ``region`` over each pixel's footprint (1: the pixel
    #: centre alone). Above 1 a pixel's diffuse albedo is the mean over ``n x n`` stratified
    #: points of the footprint on the surface's tangent plane
    #: (:func:`polrig.sim.footprint.footprint_albedo`), as a sensor pixel integrates a
    #: printed pattern; this needs every material to be a Baek :class:`Material` differing
    #: from the others in ``kd`` alone, so that the mean albedo is the pixel's exact area
    #: integral for one surface point's geometry.
    footprint_samples: int = 1

    def __post_init__(self) -> None:
        object.__setattr__(self, "position_m", np.asarray(self.position_m, float).reshape(3))
        object.__setattr__(self, "rotation", np.asarray(self.rotation, float).reshape(3, 3))
        if not self.materials:
            raise ValueError(f"object {self.name}: needs at least one material")
        n = self.footprint_samples
        if not (isinstance(n, int) and n >= 1):
            raise ValueError(f"object {self.name}: footprint_samples must be an integer >= 1, "
                             f"got {n!r}")
        if n > 1 and not _albedo_only(self.materials):
            raise ValueError(
                f"object {self.name}: footprint_samples > 1 averages the diffuse albedo, so its "
                "materials must all be Baek Materials with the same alpha, eta and ks, got "
                f"{[m.name for m in self.materials]}")

    def world_pose(self, turntable: TurntableGeometry,
                   angle_deg: float) -> tuple[np.ndarray, np.ndarray]:
        """``(R, t)`` with ``p_world = R @ p_local + t`` at turntable ``angle_deg``."""
        if not self.on_turntable:
            return self.rotation, self.position_m
        rt, tt = turntable.transform(angle_deg)
        return rt @ self.rotation, rt @ self.position_m + tt

    def material_index(self, p_local: np.ndarray) -> np.ndarray:
        if self.region is None or len(self.materials) == 1:
            return np.zeros(len(p_local), dtype=np.int64)
        return np.clip(np.asarray(self.region(p_local), dtype=np.int64), 0,
                       len(self.materials) - 1)

    def to_json(self) -> dict:
        out = {"name": self.name, "shape": self.shape.to_json(),
               "materials": [m.to_json() for m in self.materials],
               "position_m": self.position_m.tolist(), "rotation": self.rotation.tolist(),
               "regions": self.region is not None, "on_turntable": self.on_turntable}
        if self.footprint_samples > 1:  # only then: a scene recorded before it reads the same
            out["footprint_samples"] = self.footprint_samples
        return out


def _albedo_only(materials) -> bool:
    """Whether ``materials`` are Baek :class:`Material` s that differ in ``kd`` alone."""
    if not all(type(m) is Material for m in materials):
        return False
    return len({(m.alpha, m.eta, m.ks) for m in materials}) == 1


@dataclasses.dataclass(frozen=True)
class Scene:
    name: str
    objects: tuple[SceneObject, ...]
    camera: PinholeCamera
    light: PointLight
    turntable: TurntableGeometry
    stage_zero_axis: np.ndarray
    illumination_target_m: np.ndarray

    def __post_init__(self) -> None:
        k = unit(np.asarray(self.illumination_target_m, float) - self.light.position_m)
        x = np.asarray(self.stage_zero_axis, float)
        x = unit(x - np.dot(x, k) * k)
        if not np.any(x):
            raise ValueError("stage zero axis must not be parallel to the illumination axis")
        object.__setattr__(self, "stage_zero_axis", x)
        object.__setattr__(self, "illumination_target_m",
                           np.asarray(self.illumination_target_m, float).reshape(3))

    @property
    def materials(self) -> list[Material | SurfaceMaterial]:
        return [m for o in self.objects for m in o.materials]

    def with_camera(self, camera: PinholeCamera) -> "Scene":
        return dataclasses.replace(self, camera=camera)

    def to_json(self) -> dict:
        return {"name": self.name, "objects": [o.to_json() for o in self.objects],
                "camera": self.camera.to_json(),
                "light": {"position_m": self.light.position_m.tolist(),
                          "intensity_rgb": self.light.intensity_rgb.tolist()},
                "turntable": {"axis": self.turntable.axis.tolist(),
                              "point_m": self.turntable.point_m.tolist()},
                "stage_zero_axis": self.stage_zero_axis.tolist(),
                "illumination_target_m": self.illumination_target_m.tolist()}


# ---------------------------------------------------------------------------------------------
# The default rig and named scenes

#: Object centre height above the turntable in the default rig (metres).
OBJECT_Z_M = 0.06


def default_camera(width: int, height: int, *, distance_m: float = 0.5,
                   elevation_deg: float = 15.0, target_m=(0.0, 0.0, OBJECT_Z_M),
                   focal_per_px: float = 2.5) -> PinholeCamera:
    """The default camera: ``distance_m`` from the target along ``-Y`` raised by
    ``elevation_deg``; ``fx = fy = focal_per_px * min(width, height)``, principal point at the
    image centre (so the field of view does not depend on the simulated size)."""
    e = np.deg2rad(elevation_deg)
    target = np.asarray(target_m, float)
    eye = target + distance_m * np.array([0.0, -np.cos(e), np.sin(e)])
    r, t = look_at(eye, target)
    f = focal_per_px * min(width, height)
    return PinholeCamera(f, f, (width - 1) / 2.0, (height - 1) / 2.0, width, height, r, t)


def default_light(position_m=(0.18, -0.42, 0.25), intensity_rgb=(1.0, 1.0, 1.0)) -> PointLight:
    return PointLight(np.asarray(position_m, float), np.asarray(intensity_rgb, float))


def stage_zero_axis_for(light: PointLight, turntable: TurntableGeometry,
                        height_m: float = OBJECT_Z_M) -> tuple[np.ndarray, np.ndarray]:
    """The rig's definition of the polarizer stage zero axis and the illumination target.

    The target is the turntable-axis point at ``height_m`` (world ``Z`` of the object centre);
    the zero axis is the horizontal direction (perpendicular to the turntable axis, the rig's
    "up") perpendicular to the illumination axis: ``x0 = normalize(k x up)`` with ``k`` from
    the light to the target, as ``calibration/rigframes.py`` defines it for the lab rig.
    """
    up = turntable.axis
    target = turntable.point_m + up * (height_m - turntable.point_m[2]) / up[2]
    x0 = unit(np.cross(target - light.position_m, up))
    if not np.any(x0):
        raise ValueError("the light lies on the turntable axis: the stage zero axis is undefined")
    return x0, target


def _rig(name: str, objects: list[SceneObject], width: int, height: int,
         light: PointLight | None = None, camera: PinholeCamera | None = None,
         stage_zero_axis: np.ndarray | None = None,
         turntable: TurntableGeometry | None = None) -> Scene:
    """A scene in the default rig; the stage zero axis defaults to :func:`stage_zero_axis_for`."""
    light = light or default_light()
    camera = camera or default_camera(width, height)
    turntable = turntable or TurntableGeometry()
    zero, target = stage_zero_axis_for(light, turntable)
    if stage_zero_axis is not None:
        zero = stage_zero_axis
    return Scene(name, tuple(objects), camera, light, turntable, zero, target)


def checker_regions(n_az: int = 6, n_el: int = 3) -> RegionFn:
    """Region index 0/1 in a checkerboard over azimuth/elevation of the local point."""
    def region(p: np.ndarray) -> np.ndarray:
        az = np.arctan2(p[:, 1], p[:, 0]) + np.pi
        el = np.arctan2(p[:, 2], np.hypot(p[:, 0], p[:, 1])) + np.pi / 2
        return ((np.floor(az / (2 * np.pi) * n_az) + np.floor(el / np.pi * n_el)) % 2).astype(int)
    return region


def halves_region(axis: int = 0) -> RegionFn:
    """Region 1 where the local coordinate ``axis`` is positive, else 0."""
    return lambda p: (p[:, axis] > 0).astype(int)


def _floor(material: str = "diffuse_grey") -> SceneObject:
    return SceneObject("floor", Rectangle(0.25, 0.25), (get_material(material),),
                       position_m=np.zeros(3), on_turntable=False)


def _tilt(deg_x: float, deg_z: float) -> np.ndarray:
    return rotation_about_axis([0, 0, 1], deg_z) @ rotation_about_axis([1, 0, 0], deg_x)


def _scene_objects(name: str) -> list[SceneObject]:
    c = np.array([0.0, 0.0, OBJECT_Z_M])
    m = get_material
    if name == "sphere":
        return [SceneObject("sphere", Sphere(0.05), (m("plastic_red"),), c)]
    if name == "diffuse_sphere":
        return [SceneObject("sphere", Sphere(0.05), (m("diffuse"),), c)]
    if name == "mirror_sphere":
        return [SceneObject("sphere", Sphere(0.05), (m("mirror"),), c)]
    if name == "rough_sphere":
        return [SceneObject("sphere", Sphere(0.05), (m("rough"),), c)]
    if name == "checker_sphere":
        return [SceneObject("sphere", Sphere(0.05), (m("plastic_blue"), m("ceramic")), c,
                            region=checker_regions())]
    if name == "plane":
        return [SceneObject("plane", Rectangle(0.06, 0.06), (m("ceramic"), m("rough")), c,
                            rotation=_tilt(70.0, 20.0), region=halves_region(0))]
    if name == "box":
        return [SceneObject("box", Box((0.045, 0.03, 0.035)), (m("plastic_green"),),
                            c + [0.015, 0.0, -0.02], rotation=_tilt(0.0, 30.0)), _floor()]
    if name == "cylinder":
        return [SceneObject("cylinder", Cylinder(0.035, 0.05), (m("plastic_white"),),
                            c + [0.0, 0.0, -0.005], rotation=_tilt(0.0, 0.0))]
    if name == "multi":
        return [
            SceneObject("sphere", Sphere(0.03), (m("plastic_red"),), [-0.03, -0.02, 0.03]),
            SceneObject("box", Box((0.025, 0.025, 0.04)), (m("rough"),), [0.035, 0.03, 0.04],
                        rotation=_tilt(0.0, 25.0)),
            SceneObject("cylinder", Cylinder(0.015, 0.035), (m("mirror"), m("diffuse")),
                        [0.03, -0.035, 0.035], region=halves_region(2)),
            _floor(),
        ]
    if name == "heightfield":
        h, g = gaussian_bumps([[-0.02, 0.01], [0.025, -0.015], [0.0, 0.03], [0.01, -0.035]],
                              [0.012, 0.015, 0.01, 0.008], [0.015, 0.02, -0.008, 0.01])
        return [SceneObject("terrain", HeightField(0.06, 0.06, -0.009, 0.021, h, g),
                            (m("ceramic"),), [0.0, 0.0, 0.02])]
    if name == "blob":
        return [SceneObject("blob", Blob(0.045, ((1.0, 0.2, 0.3), (-0.4, 1.0, 0.2), (0.1, -0.3, 1.0),
                                                 (-0.8, -0.6, -0.2), (0.3, 0.5, -1.0)),
                                         (0.5, 0.4, 0.35, 0.6, 0.45), (0.35, -0.25, 0.3, 0.2, -0.3)),
                            (m("ceramic"),), c, rotation=_tilt(20.0, 30.0))]
    if name == "torus":
        return [SceneObject("torus", Torus(0.04, 0.015), (m("plastic_white"),), c,
                            rotation=_tilt(45.0, 20.0))]
    if name == "normalmap":
        return [SceneObject("panel", Rectangle(0.06, 0.06, normal_map=wave_normal_map()),
                            (m("plastic_white"),), c, rotation=_tilt(70.0, 0.0))]
    if name in MATERIAL_SCENES:
        return _material_scene_objects(name, c)
    raise ValueError(f"unknown scene {name!r}; known: {', '.join(SCENES)}")


def surface_presets() -> dict[str, SurfaceMaterial]:
    """Named :class:`SurfaceMaterial` presets of the material scenes (issue 23)."""
    cond = conductor_rgb
    return {m.name: m for m in (
        SurfaceMaterial("gold", cond("gold"), 0.12),
        SurfaceMaterial("chrome", cond("chrome"), 0.03),
        SurfaceMaterial("silver", cond("silver"), 0.08),
        SurfaceMaterial("aluminium", cond("aluminium"), 0.2),
        SurfaceMaterial("brushed_copper", cond("copper"), 0.12, 0.5, distribution="beckmann"),
        SurfaceMaterial("polycarbonate_red", dielectric_rgb("polycarbonate"), 0.1, kd=(0.6, 0.08, 0.05)),
        SurfaceMaterial("stressed_pmma", dielectric_rgb("pmma"), 0.15, kd=(0.3, 0.5, 0.6),
                        retardance_rad=1.8, tangent_axis=(1.0, 0.0, 0.0),
                        retardance_texture=Texture(0.2, 1.0, 0.03, (0, 0, 1), kind="rings"),
                        fast_axis_texture=Texture(-40.0, 40.0, 0.04, (1, 0, 0))),
        SurfaceMaterial("painted", dielectric_rgb("bk7"), 0.25, kd=(0.5, 0.45, 0.2),
                        distribution="beckmann", polarized_fraction=0.6,
                        kd_texture=Texture(0.3, 1.0, 0.025, (1, 0.3, 0)),
                        alpha_texture=Texture(0.2, 2.0, 0.03, (0, 1, 0.5)),
                        eta_texture=Texture(-0.1, 0.25, 0.035, (0.2, 0, 1))),
    )}


def _material_scene_objects(name: str, c: np.ndarray) -> list[SceneObject]:
    sm = surface_presets()
    if name == "gold_sphere":
        return [SceneObject("sphere", Sphere(0.05), (sm["gold"],), c)]
    if name == "chrome_sphere":
        return [SceneObject("sphere", Sphere(0.05), (sm["chrome"],), c)]
    if name == "brushed_cylinder":
        return [SceneObject("cylinder", Cylinder(0.035, 0.05), (sm["brushed_copper"],),
                            c + [0.0, 0.0, -0.005])]
    if name == "dispersive_sphere":
        return [SceneObject("sphere", Sphere(0.05), (sm["polycarbonate_red"],), c)]
    if name == "film_plane":
        return [SceneObject("plane", Rectangle(0.06, 0.06), (sm["stressed_pmma"],), c,
                            rotation=_tilt(70.0, 20.0))]
    if name == "textured_blob":
        return [SceneObject("blob", Blob(0.045, ((1.0, 0.2, 0.3), (-0.4, 1.0, 0.2), (0.1, -0.3, 1.0)),
                                         (0.5, 0.4, 0.35), (0.3, -0.25, 0.2)),
                            (sm["painted"],), c, rotation=_tilt(20.0, 30.0))]
    if name == "metals":
        return [SceneObject(n, Sphere(0.022), (sm[n],), p) for n, p in (
            ("gold", [-0.05, 0.0, 0.03]), ("silver", [0.0, 0.0, 0.03]), ("aluminium", [0.05, 0.0, 0.03]),
            ("chrome", [-0.025, 0.04, 0.03]))] + [
            SceneObject("copper", Sphere(0.022), (SurfaceMaterial("copper", conductor_rgb("copper"), 0.1),),
                        [0.025, 0.04, 0.03]), _floor()]
    if name == "corner":  # a metal wall and a glossy floor that light each other
        wall = SceneObject("wall", Rectangle(0.06, 0.05), (sm["aluminium"],), [0.0, 0.045, 0.05],
                           rotation=_tilt(90.0, 0.0), on_turntable=False)
        return [_floor("plastic_white"), wall,
                SceneObject("sphere", Sphere(0.025), (get_material("plastic_red"),), [0.0, 0.0, 0.025])]
    if name == "plastic_metal":  # issue 33 item 2: a dielectric half and a conductor half
        return [SceneObject("sphere", Sphere(0.05), (get_material("plastic_red"), sm["aluminium"]), c,
                            region=halves_region(0))]
    if name == "crater":  # a concave dish that lights itself
        h, g = gaussian_bumps([[0.0, 0.0]], [0.02], [-0.02])
        return [SceneObject("dish", HeightField(0.045, 0.045, -0.021, 0.001, h, g), (sm["gold"],),
                            [0.0, 0.0, 0.04], rotation=_tilt(25.0, 0.0))]
    raise ValueError(name)  # pragma: no cover - MATERIAL_SCENES is exhaustive




def make_scene(name: str = "sphere", width: int = 512, height: int = 512, *,
               light_position_m=None, light_intensity_rgb=None,
               turntable: TurntableGeometry | None = None) -> Scene:
    """A named scene (:data:`SCENES`) in the default rig at a sensor of ``width x height``
    (``turntable``: the axis the objects turn about; default vertical through the origin)."""
    light = default_light()
    if light_position_m is not None or light_intensity_rgb is not None:
        light = PointLight(light.position_m if light_position_m is None else light_position_m,
                           light.intensity_rgb if light_intensity_rgb is None
                           else light_intensity_rgb)
    return _rig(name, _scene_objects(name), width, height, light=light, turntable=turntable)


#: Shape families of the random dataset scenes (``family`` id = index).
FAMILIES = ("sphere", "box", "cylinder", "multi", "heightfield", "plane", "blob", "torus")
#: Focal length of the dataset camera in units of min(width, height): the default rig's, so
#: that networks trained on datasets see the geometry of ``polrig sim render`` captures
#: (``polrig.models.runtime.DEFAULT_FOCAL_PER_PX`` relies on it).
RANDOM_FOCAL_PER_PX = 2.5

#: Families kept out of the training set by ``polrig sim dataset`` (``--holdout`` makes them).
HOLDOUT_FAMILIES = ("heightfield", "plane")


def random_scene(rng: np.random.Generator, width: int, height: int,
                 family: int, *, material_mix: str = "baek",
                 material_rng: np.random.Generator | None = None) -> Scene:
    """A randomized scene of shape family ``FAMILIES[family]``: random size, pose, material
    (one material per scene, so one roughness per image), light position and colour. The
    camera is the default one with ``RANDOM_FOCAL_PER_PX``; the stage zero axis is the
    camera's up direction (``-Y``), so that the rig frames are fixed in the camera frame
    across samples.

    ``material_mix`` (:data:`polrig.sim.materials.MATERIAL_MIXES`, default ``"baek"``: the
    initialization's family, as before) replaces the Baek material by one drawn from the mix
    with ``material_rng`` (required for other mixes), built on the Baek material drawn from
    ``rng``; ``rng`` is consumed exactly as for ``"baek"``, so the geometry, light and pose of
    a sample are the same in every mix (paired comparisons)."""
    fam = FAMILIES[family]
    mat = random_material(rng)
    if material_mix != "baek":
        if material_rng is None:
            raise ValueError("random_scene: a material_mix other than 'baek' needs material_rng")
        mat = random_mix_material(material_rng, material_mix, mat)
    rot = _tilt(rng.uniform(-40, 40), rng.uniform(0, 360))
    c = np.array([0.0, 0.0, OBJECT_Z_M]) + rng.uniform(-0.01, 0.01, 3)
    if fam == "sphere":
        objs = [SceneObject("sphere", Sphere(rng.uniform(0.035, 0.06)), (mat,), c)]
    elif fam == "box":
        objs = [SceneObject("box", Box(tuple(rng.uniform(0.02, 0.045, 3))), (mat,), c,
                            rotation=rot)]
    elif fam == "cylinder":
        objs = [SceneObject("cylinder", Cylinder(rng.uniform(0.02, 0.04),
                                                 rng.uniform(0.025, 0.05)), (mat,), c,
                            rotation=rot)]
    elif fam == "multi":
        objs = [SceneObject("sphere", Sphere(rng.uniform(0.02, 0.035)), (mat,),
                            c + [-0.03, -0.02, -0.02]),
                SceneObject("box", Box(tuple(rng.uniform(0.015, 0.03, 3))), (mat,),
                            c + [0.03, 0.02, -0.01], rotation=rot)]
    elif fam == "heightfield":
        k = int(rng.integers(3, 7))
        h, g = gaussian_bumps(rng.uniform(-0.045, 0.045, (k, 2)), rng.uniform(0.006, 0.018, k),
                              rng.uniform(-0.012, 0.02, k))
        objs = [SceneObject("terrain", HeightField(0.06, 0.06, -0.012 * k, 0.02 * k, h, g),
                            (mat,), c - [0, 0, 0.03], rotation=_tilt(rng.uniform(-20, 20),
                                                                      rng.uniform(0, 360)))]
    elif fam == "blob":
        k = int(rng.integers(4, 11))
        objs = [SceneObject("blob", Blob(rng.uniform(0.035, 0.05),
                                         tuple(map(tuple, rng.normal(size=(k, 3)))),
                                         tuple(rng.uniform(0.25, 0.7, k)),
                                         tuple(rng.uniform(-0.35, 0.45, k))),
                            (mat,), c, rotation=rot)]
    elif fam == "torus":
        objs = [SceneObject("torus", Torus(rng.uniform(0.03, 0.045), rng.uniform(0.01, 0.02)),
                            (mat,), c, rotation=_tilt(rng.uniform(-70, 70), rng.uniform(0, 360)))]
    elif fam == "plane":
        objs = [SceneObject("plane", Rectangle(0.06, 0.06,
                                               normal_map=wave_normal_map(
                                                   64, rng.uniform(1, 6), rng.uniform(0, 0.5))),
                            (mat,), c, rotation=_tilt(rng.uniform(40, 85), rng.uniform(-30, 30)))]
    else:  # pragma: no cover - FAMILIES is exhaustive
        raise ValueError(fam)
    az = rng.uniform(-70, 70)
    el = rng.uniform(5, 60)
    dist = rng.uniform(0.3, 0.6)
    a, e = np.deg2rad(az), np.deg2rad(el)
    lp = np.array([0.0, 0.0, OBJECT_Z_M]) + dist * np.array(
        [np.sin(a) * np.cos(e), -np.cos(a) * np.cos(e), np.sin(e)])
    colour = rng.uniform(0.6, 1.0, 3)
    light = PointLight(lp, colour / colour.max())
    cam = default_camera(width, height, focal_per_px=RANDOM_FOCAL_PER_PX)
    return _rig(fam, objs, width, height, light=light, camera=cam,
                stage_zero_axis=-cam.R[1])  # camera up (-Y): fixed in the camera frame
