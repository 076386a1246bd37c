"""Training sets of randomized simulated scenes for the single-shot networks (``models/``).

Layout of a dataset folder (the schema is documented in ``docs/sim.md``, section "Dataset"):
``manifest.json`` and shards ``shard-00000.npz``, ``shard-00001.npz``, ... of
``shard_size`` samples each. Sample ``i`` depends only on ``(seed, holdout, i)`` (its own
random generator), so shards can be made in any order, a crashed run resumes by skipping the
shards already complete, and every shard is written atomically (temporary file + rename).

Each sample is one single-shot capture: a random scene (:func:`polrig.sim.scene.random_scene`: shape
family, one material drawn from a material mix (:data:`polrig.sim.materials.MATERIAL_MIXES`, default
``"baek"``: the pBRDF family of the networks' initialization), light position and colour,
turntable pose), optionally one bounce of interreflected light (``indirect_samples``), one
random polarizer state,
the full-resolution ideal-analyzer intensities per colour (0/45/90/135 deg) at ``H x W``
with the sensor noise model (:class:`polrig.sensor.noise.SensorModel`) applied independently to every
value, black level and mean dark signal removed, divided by a per-sample ``scale``. The ground
truth Mueller image is in the same units. Vectors are in the camera frame.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import zipfile
from typing import Any, Callable, Iterator, Sequence

import numpy as np

from polrig.atomic import atomic_write_bytes, atomic_write_text
from polrig.errors import ConfigError, FormatError
from polrig.formats.argcheck import check_output_folder
from polrig.optics.conventions import CONVENTIONS_VERSION
from polrig.sensor.noise import SensorModel
from polrig.sim.generator import Generator
from polrig.sim.materials import (
    MATERIAL_KINDS,
    MATERIAL_MIXES,
    Material,
    SurfaceMaterial,
)
from polrig.sim.options import HIDDEN_DEFAULTS, SENSOR_MODEL_DEFAULTS
from polrig.sim.render import render
from polrig.sim.scene import (
    FAMILIES,
    HOLDOUT_FAMILIES,
    RANDOM_FOCAL_PER_PX,
    Scene,
    default_camera,
    random_scene,
    stage_zero_axis_for,
)
from polrig.sim.truth import npz_bytes
from polrig.sim.world import ideal_analyzer_images

DATASET_FORMAT = "polrig-sim-dataset"
DATASET_VERSION = 1
#: Exposure (microseconds) used for the dark signal of the dataset's noise model.
DATASET_EXPOSURE_US = 10000.0
#: Percentile of the analyzer values inside the mask that ``scale`` maps to 1.
SCALE_PERCENTILE = 99.5
#: Image sides must be multiples of this: the networks' size multiple (``polrig.models.runtime.SIZE_MULTIPLE``,
#: three 2x downsamplings), which trains and evaluates on whole images without padding.
SIZE_MULTIPLE = 8

#: Arrays of a shard: name -> (shape with N, H, W symbols, dtype).
SHARD_ARRAYS: dict[str, tuple[str, str]] = {
    "analyzer": ("(N, 3, 4, H, W)", "float32"),
    "scale": ("(N,)", "float32"),
    "mask": ("(N, H, W)", "uint8"),
    "normal": ("(N, 3, H, W)", "float32"),
    "kd": ("(N, 3, H, W)", "float32"),
    "alpha": ("(N,)", "float32"),
    "eta": ("(N,)", "float32"),
    "wi": ("(N, 3, H, W)", "float32"),
    "wo": ("(N, 3, H, W)", "float32"),
    "s_in": ("(N, 3)", "float32"),
    "mueller": ("(N, 3, 3, 3, H, W)", "float32"),
    "family": ("(N,)", "int16"),
    "index": ("(N,)", "int64"),
    "stage_deg": ("(N,)", "float32"),
    "lit": ("(N, H, W)", "uint8"),
    "stage_zero_axis": ("(N, 3)", "float32"),
    "material_kind": ("(N,)", "int16"),
}

#: What the analytic model's best fit is given for a material outside the Baek family (the
#: ``alpha``, ``eta`` and ``kd`` arrays of a sample; :func:`fit_parameters`), recorded in the
#: manifest.
GROUND_TRUTH_PARAMETERS = {
    "kd": "per pixel: the diffuse albedo of the base (textures applied); 0 for a conductor",
    "alpha": "isotropic equivalent: the median over the object pixels of the textured roughness, "
             "sqrt(alpha_u alpha_v) for anisotropic roughness (GGX or Beckmann alike)",
    "eta": "a real index: the base's eta (film, depolarizing, anisotropic; the median over the object "
           "pixels where an eta texture varies it), the green channel (532 nm) for a dispersive "
           "dielectric, and for a conductor the real dielectric index with the conductor's "
           "normal-incidence reflectance in green, (1 + sqrt(R0)) / (1 - sqrt(R0)), "
           "R0 = |(n - 1) / (n + 1)|^2 of the complex n at 532 nm",
}

#: How the polarizer stage zero axis of a sample is chosen (``stage_zero_axes``):
#: ``"camera-up"`` -- the camera's up direction ``-Y`` for every sample (version-1 datasets);
#: ``"random"`` -- per sample, the rig definition of :func:`polrig.sim.scene.stage_zero_axis_for`
#: (horizontal, perpendicular to the illumination axis: the default rig and the lab rig) with
#: probability :data:`RIG_AXIS_FRACTION`, else the camera up direction with probability
#: :data:`CAMERA_UP_FRACTION`, else a direction perpendicular to the illumination axis at an
#: angle uniform in [0, 180) deg, so that a network learns every incident frame.
STAGE_ZERO_AXES = ("random", "camera-up")
RIG_AXIS_FRACTION = 0.5
CAMERA_UP_FRACTION = 0.2


def families_for(holdout: bool, names: Sequence[str] | None = None) -> tuple[int, ...]:
    """Family ids (indices of :data:`polrig.sim.scene.FAMILIES`) of the training or held-out set:
    every family of that side, or the subset ``names``. A name that is unknown or belongs to
    the other side raises :class:`ConfigError`, so no held-out family can leak into a
    training set."""
    side = tuple(i for i, f in enumerate(FAMILIES) if (f in HOLDOUT_FAMILIES) == bool(holdout))
    if names is None:
        return side
    names = tuple(names)
    bad = [n for n in names if n not in FAMILIES or FAMILIES.index(n) not in side]
    if bad or not names:
        allowed = ", ".join(FAMILIES[i] for i in side)
        raise ConfigError(f"{'held-out' if holdout else 'training'} families must be a non-empty "
                          f"subset of {allowed}; got {', '.join(names) or 'none'}")
    return tuple(i for i in side if FAMILIES[i] in names)


def dataset_sensor_model() -> SensorModel:
    return SensorModel(**SENSOR_MODEL_DEFAULTS)


def sample_stage_zero_axis(scene: Scene, rng: np.random.Generator) -> np.ndarray:
    """A world-frame stage zero axis for ``scene`` drawn as :data:`STAGE_ZERO_AXES` ``"random"``
    describes (unit, perpendicular to the illumination axis)."""
    u = float(rng.uniform())
    if u < RIG_AXIS_FRACTION:
        return stage_zero_axis_for(scene.light, scene.turntable)[0]
    if u < RIG_AXIS_FRACTION + CAMERA_UP_FRACTION:
        return -scene.camera.R[1]
    k = np.asarray(scene.illumination_target_m, float) - scene.light.position_m
    k = k / np.linalg.norm(k)
    x = np.asarray(scene.stage_zero_axis, float)  # already perpendicular to k
    y = np.cross(k, x)
    t = float(rng.uniform(0.0, np.pi))
    return np.cos(t) * x + np.sin(t) * y


def check_transport(material_mix: str, indirect_samples: int) -> None:
    """:class:`ConfigError` (one line) unless ``material_mix`` names a mix of
    :data:`polrig.sim.materials.MATERIAL_MIXES` and ``indirect_samples`` is an integer >= 0."""
    if material_mix not in MATERIAL_MIXES:
        raise ConfigError(f"material mix must be one of {', '.join(MATERIAL_MIXES)}, got {material_mix!r}")
    if isinstance(indirect_samples, bool) or not isinstance(indirect_samples, (int, np.integer)) \
            or indirect_samples < 0:
        raise ConfigError(f"indirect_samples must be an integer >= 0, got {indirect_samples!r}")


def material_kind(material: Material | SurfaceMaterial) -> str:
    """The :data:`polrig.sim.materials.MATERIAL_KINDS` entry a material of a mix was drawn as
    (:func:`polrig.sim.materials.random_surface_material` makes each kind distinguishable: a
    conductor has a complex index, a film a retardance, a depolarizing layer a polarized
    fraction below 1, anisotropic roughness two roughnesses, a dispersive dielectric an index
    varying across the channels)."""
    if isinstance(material, Material):
        return "baek"
    if material.conductor:
        return "conductor"
    if material.retardance_rad > 0:
        return "film"
    if material.polarized_fraction < 1:
        return "depolarizing"
    if material.alpha_v is not None:
        return "anisotropic"
    return "dispersive"


def effective_eta(eta: complex) -> float:
    """A real dielectric index with the normal-incidence reflectance of the (complex) index
    ``eta``: ``(1 + sqrt(R0)) / (1 - sqrt(R0))``, ``R0 = |(eta - 1) / (eta + 1)|^2``; ``eta``
    itself for a real index > 1."""
    r = abs((complex(eta) - 1.0) / (complex(eta) + 1.0))
    return float((1.0 + r) / (1.0 - r))


def fit_parameters(material: SurfaceMaterial, res, mask: np.ndarray) -> tuple[float, float]:
    """``(alpha, eta)`` of a :class:`SurfaceMaterial` sample for the image-wide parameters the
    analytic model takes (:data:`GROUND_TRUTH_PARAMETERS`), from the rendered per-pixel
    nominal truth ``res`` (:class:`polrig.sim.render.RenderResult`: ``alpha`` along the tangent with
    textures, ``eta`` the green real part with textures) over ``mask``."""
    if not mask.any():
        return float(material.alpha), effective_eta(material.eta_rgb[1])
    aniso = 1.0 if material.alpha_v is None else float(np.sqrt(material.alpha_v / material.alpha))
    alpha = float(np.median(res.alpha[mask])) * aniso
    if material.conductor:
        return alpha, effective_eta(material.eta_rgb[1])
    return alpha, float(np.median(res.eta[mask]))


def indirect_seed_for(seed: int, holdout: bool, index: int) -> int:
    """Seed of a sample's interreflection Monte Carlo (:func:`polrig.sim.render.render`'s
    ``indirect_seed``), derived from ``(seed, holdout, index)`` only."""
    return int(np.random.SeedSequence([int(seed), int(bool(holdout)), int(index), 3]).generate_state(1)[0])


def make_sample(index: int, *, seed: int, width: int, height: int, holdout: bool = False,
                model: SensorModel | None = None, stage_zero_axes: str = "random",
                families: Sequence[str] | None = None, material_mix: str = "baek",
                indirect_samples: int = 0) -> dict[str, Any]:
    """One sample (arrays without the ``N`` axis), deterministic in ``(seed, holdout, index)``
    (and ``stage_zero_axes``, see :data:`STAGE_ZERO_AXES`; the axis comes from its own random
    stream, so a ``"camera-up"`` sample equals the version-1 sample of the same index) and in
    ``families`` (the shape families drawn from, :func:`families_for`; version-1 sets used
    ``sphere, box, cylinder, multi``).

    ``material_mix`` (:data:`polrig.sim.materials.MATERIAL_MIXES`): the default ``"baek"`` gives the
    samples as before, bit for bit; another mix replaces the material by one drawn from the mix
    on its own random stream ``(seed, holdout, index, 2)``, built on the Baek material the
    sample would have had, with the same geometry, light, pose, polarizer state and exposure
    draw (paired sets). ``indirect_samples > 0`` adds one bounce of interreflected light
    (:mod:`polrig.sim.interreflection`, that many Monte Carlo samples per pixel, seed
    :func:`indirect_seed_for`) to the images and the truth alike. ``alpha`` and ``eta`` of a
    material outside the Baek family are the image-wide values of
    :data:`GROUND_TRUTH_PARAMETERS` (:func:`fit_parameters`); ``material_kind`` is the index
    of its kind in :data:`polrig.sim.materials.MATERIAL_KINDS`."""
    if stage_zero_axes not in STAGE_ZERO_AXES:
        raise ConfigError(f"stage_zero_axes must be one of {STAGE_ZERO_AXES}, got {stage_zero_axes!r}")
    check_transport(material_mix, indirect_samples)
    model = model or dataset_sensor_model()
    rng = np.random.default_rng([int(seed), int(bool(holdout)), int(index)])
    fams = families_for(holdout, families)
    family = int(fams[rng.integers(len(fams))])
    mat_rng = (None if material_mix == "baek"
               else np.random.default_rng([int(seed), int(bool(holdout)), int(index), 2]))
    scene = random_scene(rng, width, height, family, material_mix=material_mix, material_rng=mat_rng)
    if stage_zero_axes == "random":
        axis_rng = np.random.default_rng([int(seed), int(bool(holdout)), int(index), 1])
        scene = dataclasses.replace(scene, stage_zero_axis=sample_stage_zero_axis(scene, axis_rng))
    return capture_sample(scene, rng, model=model, index=index, family=family,
                          indirect_samples=indirect_samples,
                          indirect_seed=indirect_seed_for(seed, holdout, index) if indirect_samples else 0)


def capture_sample(scene: Scene, rng: np.random.Generator, *, model: SensorModel | None = None,
                   index: int = 0, family: int = -1, turntable_deg: float | None = None,
                   indirect_samples: int = 0, indirect_seed: int = 0) -> dict[str, Any]:
    """One sample of ``scene`` (the arrays of :data:`SHARD_ARRAYS` without the ``N`` axis, as
    :func:`make_sample` describes them): rendered at the turntable angle ``turntable_deg``
    (degrees; ``None``: drawn from ``rng``, uniform in [0, 360)), then from ``rng`` the polarizer
    state, the exposure and the sensor noise. ``alpha``, ``eta`` and ``material_kind`` are those
    of the scene's first material (a random scene's one material; a named scene
    (:func:`polrig.sim.scene.make_scene`) may have more). ``family``: the index in
    :data:`polrig.sim.scene.FAMILIES`, -1 for none."""
    model = model or dataset_sensor_model()
    material = scene.materials[0]  # the sample's one material (every object has it)
    pose = float(rng.uniform(0.0, 360.0)) if turntable_deg is None else float(turntable_deg)
    res = render(scene, pose, indirect_samples=int(indirect_samples), indirect_seed=int(indirect_seed))
    stage_deg = float(rng.uniform(0.0, 180.0))
    gen = Generator(0.0, float(np.exp(rng.uniform(np.log(200.0), np.log(3000.0)))))
    s_in = gen.incident_stokes(stage_deg)
    colour = scene.light.intensity_rgb * np.asarray(HIDDEN_DEFAULTS["colour_qe"])
    m_rad = res.radiance_mueller().astype(np.float64) * colour[:, None, None, None, None]
    an_rad = ideal_analyzer_images(np.einsum("cijhw,j->cihw", m_rad, s_in))
    mask = res.mask
    vals = an_rad[:, :, mask]
    ref = float(np.percentile(vals, SCALE_PERCENTILE)) if vals.size else 0.0
    target = float(rng.uniform(0.25, 0.85)) * model.clip_dn  # random exposure
    k = target / ref if ref > 0 else 1.0
    dark_dn = float(model.dark_electrons(DATASET_EXPOSURE_US) / model.gain_e_per_dn)
    raw = model.sample_raw(np.clip(an_rad * k, 0, None) * model.gain_e_per_dn, rng,
                           DATASET_EXPOSURE_US)
    analyzer = raw.astype(np.float64) - model.black_level_dn - dark_dn
    vals = analyzer[:, :, mask]
    scale = max(float(np.percentile(vals, SCALE_PERCENTILE)) if vals.size else 1.0, 1.0)
    lit = res.lit
    if isinstance(material, SurfaceMaterial):
        alpha, eta = fit_parameters(material, res, mask)
    else:
        alpha = float(res.alpha[mask][0]) if mask.any() else float(scene.materials[0].alpha)
        eta = float(res.eta[mask][0]) if mask.any() else float(scene.materials[0].eta)
    return {
        "analyzer": (analyzer / scale).astype(np.float32),
        "scale": np.float32(scale),
        "mask": mask.astype(np.uint8),
        "normal": res.normal, "kd": res.kd, "wi": res.wi, "wo": res.wo,
        "alpha": np.float32(alpha), "eta": np.float32(eta),
        "s_in": s_in.astype(np.float32),
        "mueller": (m_rad * (k / scale)).astype(np.float32),
        "family": np.int16(family), "index": np.int64(index),
        "stage_deg": np.float32(stage_deg), "lit": lit.astype(np.uint8),
        "stage_zero_axis": (scene.camera.R @ scene.stage_zero_axis).astype(np.float32),
        "material_kind": np.int16(MATERIAL_KINDS.index(material_kind(material))),
    }


def _shard_bytes(samples: list[dict[str, Any]], compress: bool) -> bytes:
    arrays = {k: np.stack([np.asarray(s[k]) for s in samples]).astype(SHARD_ARRAYS[k][1])
              for k in SHARD_ARRAYS}
    return npz_bytes(arrays, compress)


def shard_name(k: int) -> str:
    return f"shard-{k:05d}.npz"


def shard_complete(path: pathlib.Path, n_expected: int) -> bool:
    """Whether ``path`` is a readable shard with every array and ``n_expected`` samples."""
    if not path.is_file():
        return False
    try:
        with np.load(path, allow_pickle=False) as z:
            if set(SHARD_ARRAYS) - set(z.files):
                return False
            return len(z["index"]) == n_expected
    except (OSError, ValueError, zipfile.BadZipFile, EOFError):
        return False


def _manifest(out: pathlib.Path, *, count: int, width: int, height: int, seed: int,
              holdout: bool, shard_size: int, compress: bool, model: SensorModel,
              stage_zero_axes: str = "random", families: Sequence[str] | None = None,
              material_mix: str = "baek", indirect_samples: int = 0) -> dict:
    cam = default_camera(width, height, focal_per_px=RANDOM_FOCAL_PER_PX)
    n_shards = -(-count // shard_size)
    return {
        "format": DATASET_FORMAT, "version": DATASET_VERSION,
        "conventions_version": CONVENTIONS_VERSION,
        "count": count, "width": width, "height": height, "seed": seed,
        "holdout": bool(holdout), "shard_size": shard_size, "n_shards": n_shards,
        "shards": [shard_name(k) for k in range(n_shards)], "compressed": bool(compress),
        "sensor": "imx250myr", "layout": "imx250myr", "channels": ["R", "G", "B"],
        "analyzer_order_deg": [0, 45, 90, 135],
        "families": list(FAMILIES), "families_present": [FAMILIES[i] for i in families_for(holdout, families)],
        "holdout_families": list(HOLDOUT_FAMILIES),
        "intrinsics": {"fx": cam.fx, "fy": cam.fy, "cx": cam.cx, "cy": cam.cy,
                       "varies": False},
        "frames": {"vectors": "camera (OpenCV: X right, Y down, Z forward)",
                   # kept for readers of version-1 datasets: the axis of "camera-up" sets;
                   # the per-sample axis is the shard array ``stage_zero_axis``
                   "stage_zero_axis_camera": [0.0, -1.0, 0.0],
                   "stage_zero_axes": stage_zero_axes,
                   "stage_zero_axis_varies": stage_zero_axes != "camera-up",
                   "camera_x_axis_camera": [1.0, 0.0, 0.0]},
        "noise": {"model": "polrig.sensor.noise.SensorModel, independent per analyzer value",
                  "sensor_model": dataclasses.asdict(model),
                  "exposure_us_for_dark": DATASET_EXPOSURE_US,
                  "analyzer": "ideal (0/45/90/135 deg), full resolution per colour, no demosaicing"},
        "normalisation": {"scale": f"{SCALE_PERCENTILE} percentile of the noisy analyzer values "
                                   "inside the mask (all colours and angles), at least 1 DN",
                          "analyzer": "black-subtracted DN / scale",
                          "mueller": "DN per unit incident S0 / scale"},
        "materials": {"mix": material_mix, "probabilities": MATERIAL_MIXES[material_mix],
                      "kinds": list(MATERIAL_KINDS),
                      "material_kind": "index into kinds per sample (shard array material_kind)",
                      "rng": "(seed, holdout, index, 2); the geometry, light, pose, state and "
                             "exposure are those of the same sample of the baek mix",
                      "ground_truth_parameters": GROUND_TRUTH_PARAMETERS},
        "transport": {"indirect_samples": int(indirect_samples),
                      "bounces": 1 if indirect_samples else 0,
                      "indirect": "polrig.sim.interreflection.one_bounce, Monte Carlo, seed "
                                  "polrig.sim.dataset.indirect_seed_for(seed, holdout, index); in the "
                                  "analyzer images and the mueller truth alike"},
        "arrays": {k: {"shape": v[0], "dtype": v[1]} for k, v in SHARD_ARRAYS.items()},
    }


def recorded_transport(manifest: dict) -> tuple[str, int]:
    """``(material mix, indirect samples)`` a manifest records (``("baek", 0)`` for sets made
    before either existed)."""
    mats, trans = manifest.get("materials"), manifest.get("transport")
    mix = mats.get("mix", "baek") if isinstance(mats, dict) else "baek"
    n = trans.get("indirect_samples", 0) if isinstance(trans, dict) else 0
    return mix, n


_RESUME_KEYS = ("format", "version", "count", "width", "height", "seed", "holdout",
                "shard_size", "compressed", "families_present")


def generate_dataset(out: str | pathlib.Path, *, count: int, width: int = 256,
                     height: int | None = None, seed: int = 0, holdout: bool = False,
                     shard_size: int = 16, compress: bool = True, progress: bool = True,
                     max_shards: int | None = None, stage_zero_axes: str = "random",
                     families: Sequence[str] | None = None, material_mix: str = "baek",
                     indirect_samples: int = 0,
                     runner: Callable[[Callable, list], Iterator[tuple[Any, Any]]] | None = None
                     ) -> dict[str, int]:
    """Write (or resume) a dataset; returns ``{"written": shards made, "skipped": shards
    already complete}``. ``max_shards`` stops after that many new shards (for tests and
    partial runs). ``stage_zero_axes``: how each sample's polarizer stage zero axis is chosen
    (:data:`STAGE_ZERO_AXES`). ``families``: shape families to draw from (default: every
    family of the chosen side, :func:`families_for`). ``material_mix`` and
    ``indirect_samples``: see :func:`make_sample`; both are recorded in the manifest
    (``materials``, ``transport``). A folder holding a different dataset (these two included)
    raises :class:`ConfigError`, as do sides that are not multiples of :data:`SIZE_MULTIPLE`, a
    negative seed and an ``out`` that is (or lies in) a file; all before anything is written.
    ``runner(fn, jobs)`` (e.g. :meth:`polrig.app.cluster.DaskRunner.map_unordered`) runs
    :func:`write_shard` on every :class:`ShardJob` elsewhere and yields ``(job, samples)`` as
    each finishes; each shard is the same bytes as in the serial run (default: this process,
    one shard after the other)."""
    from tqdm import tqdm

    height = width if height is None else int(height)
    if count < 1 or shard_size < 1:
        raise ConfigError("count and shard size must be >= 1")
    if stage_zero_axes not in STAGE_ZERO_AXES:
        raise ConfigError(f"stage_zero_axes must be one of {STAGE_ZERO_AXES}, got {stage_zero_axes!r}")
    if not (8 <= width <= 4096 and 8 <= height <= 4096):
        raise ConfigError(f"dataset size {width}x{height} out of range (8..4096)")
    if width % SIZE_MULTIPLE or height % SIZE_MULTIPLE:
        raise ConfigError(f"dataset size {width}x{height}: the sides must be multiples of {SIZE_MULTIPLE} "
                          f"(the networks' size multiple, polrig.models.runtime.SIZE_MULTIPLE)")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be an integer >= 0, got {seed!r}")
    families_for(holdout, families)  # a bad family list fails before anything is written
    check_transport(material_mix, indirect_samples)
    out = check_output_folder(out)
    out.mkdir(parents=True, exist_ok=True)
    model = dataset_sensor_model()
    manifest = _manifest(out, count=count, width=width, height=height, seed=seed,
                         holdout=holdout, shard_size=shard_size, compress=compress, model=model,
                         stage_zero_axes=stage_zero_axes, families=families,
                         material_mix=material_mix, indirect_samples=indirect_samples)
    mpath = out / "manifest.json"
    if mpath.is_file():
        try:
            old = json.loads(mpath.read_text())
        except (OSError, ValueError):
            raise FormatError(f"{mpath}: not a JSON dataset manifest") from None
        if not isinstance(old, dict):
            raise FormatError(f"{mpath}: not a dataset manifest (a JSON object expected, got "
                              f"{type(old).__name__}); choose another --out")
        diff = [k for k in _RESUME_KEYS if old.get(k) != manifest[k]]
        if old.get("frames", {}).get("stage_zero_axes", "camera-up") != stage_zero_axes:
            diff.append("stage_zero_axes")
        old_mix, old_indirect = recorded_transport(old)
        if old_mix != material_mix:
            diff.append(f"materials: {old_mix} there, {material_mix} asked")
        if old_indirect != indirect_samples:
            diff.append(f"indirect samples: {old_indirect} there, {indirect_samples} asked")
        if diff:
            raise ConfigError(f"{out} holds a different dataset ({', '.join(diff)} differ); "
                              f"choose another --out")
    else:
        atomic_write_text(mpath, json.dumps(manifest, indent=1))
    written = skipped = 0
    n_shards = manifest["n_shards"]
    todo = []
    root = str(out.resolve())
    present = {p.name for p in out.glob("shard-*.npz")}  # one listing, not a stat per shard
    for k in range(n_shards):
        n_k = min(shard_size, count - k * shard_size)
        if shard_name(k) in present and shard_complete(out / shard_name(k), n_k):
            skipped += 1
        else:
            todo.append(ShardJob(root, k, k * shard_size, n_k, seed, width, height,
                                 bool(holdout), stage_zero_axes,
                                 None if families is None else tuple(families), compress,
                                 material_mix, int(indirect_samples)))
    initial = count - sum(j.n for j in todo)
    if max_shards is not None:
        todo = todo[:max_shards]
    bar = tqdm(total=count, initial=initial, unit="sample", disable=not progress,
               desc=f"sim dataset -> {out.name}")
    try:
        if runner is None:
            for job in todo:
                write_shard(job, on_sample=lambda: bar.update(1))
                written += 1
        else:  # shards as tasks; a sample's numbers depend on its index only
            for job, n in runner(write_shard, todo):
                bar.update(n)
                written += 1
    finally:
        bar.close()
        for tmp in out.glob(".shard-*.tmp*"):  # of a worker killed mid-write
            tmp.unlink(missing_ok=True)
    return {"written": written, "skipped": skipped}


@dataclasses.dataclass(frozen=True)
class ShardJob:
    """One shard to make: ``n`` samples from index ``start`` into ``out/shard_name(k)``,
    with the dataset's parameters (:func:`generate_dataset`)."""

    out: str
    k: int
    start: int
    n: int
    seed: int
    width: int
    height: int
    holdout: bool
    stage_zero_axes: str
    families: tuple[str, ...] | None
    compress: bool
    material_mix: str = "baek"
    indirect_samples: int = 0


def write_shard(job: ShardJob, on_sample: Callable[[], Any] | None = None) -> int:
    """Make shard ``job.k`` and write it atomically (temporary file + rename); returns its
    sample count. Runs in this process or as a task on a worker that sees ``job.out``."""
    model = dataset_sensor_model()
    samples = []
    for i in range(job.start, job.start + job.n):
        samples.append(make_sample(i, seed=job.seed, width=job.width, height=job.height,
                                   holdout=job.holdout, model=model,
                                   stage_zero_axes=job.stage_zero_axes, families=job.families,
                                   material_mix=job.material_mix,
                                   indirect_samples=job.indirect_samples))
        if on_sample is not None:
            on_sample()
    atomic_write_bytes(pathlib.Path(job.out) / shard_name(job.k), _shard_bytes(samples,
                                                                             job.compress))
    return job.n


def load_shard(path: str | pathlib.Path) -> dict[str, np.ndarray]:
    """All arrays of a shard."""
    with np.load(path, allow_pickle=False) as z:
        return {k: z[k] for k in z.files}
