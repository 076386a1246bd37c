"""The vocabularies the command line offers, with nothing but the standard library.

``polrig``'s argument parser declares every command's options at start-up, also for
``polrig --version`` and ``polrig --help``; the choices and defaults it shows are defined here,
in the foundation layer, so that declaring them imports no numerical, image or simulation module
(``tests/test_cli_start.py``). Each name is owned by the module named beside it, which imports it
from here (one definition; the owner's name stays valid). Vocabularies whose values are heavy
objects (OpenEXR compression constants, NumPy dtypes) keep those in their owner; only the
names are here, and ``tests/test_cli_start.py`` checks that the two agree.
"""

from __future__ import annotations

# -- polrig.sensor --------------------------------------------------------------------------------
#: Mosaic layout names (keys of :data:`polrig.sensor.layouts.LAYOUTS`).
LAYOUT_NAMES = ("imx250mzr", "imx250myr")
#: Demosaicing methods (:data:`polrig.sensor.demosaic.METHODS`).
DEMOSAIC_METHODS = ("superpixel", "bilinear", "newton")

# -- polrig.formats -------------------------------------------------------------------------------
#: Device tables of a rig configuration (:data:`polrig.formats.config.DEVICE_KINDS`).
DEVICE_KINDS = ("camera", "stage", "turntable", "light")
#: Plane groups of a reconstruction (:data:`polrig.formats.exr.RESULT_PLANES`); ``mueller`` is
#: always written.
RESULT_PLANES = ("mueller", "sigma", "sigma_noise", "mask", "residual")
#: Plane groups written only on request, by the method that has them: ``geometry``, the
#: single-shot networks' surface normal, diffuse albedo, roughness and light direction
#: (:meth:`polrig.app.single_shot.SingleShotResult.extra_planes`).
OPTIONAL_PLANES = ("geometry",)
#: Every plane group a result file may hold, in file order.
PLANE_GROUPS = RESULT_PLANES + OPTIONAL_PLANES
#: Compression names of a result EXR (keys of :data:`polrig.formats.exr.COMPRESSIONS`).
EXR_COMPRESSIONS = ("zip", "piz", "none")
#: Precision names of the uncertainty planes (keys of
#: :data:`polrig.formats.exr.UNCERTAINTY_PRECISIONS`).
EXR_UNCERTAINTY_PRECISIONS = ("float", "half")
#: Where ``polrig analyze`` and ``polrig stats`` take the per-element sigma from (``--sigma``):
#: the result's ``sigma`` planes (noise and calibration), ``sigma_noise`` (noise alone), or none.
SIGMA_SOURCES = ("sigma", "sigma_noise", "none")
#: Spatial units the OME writers accept (NGFF names; OME-XML symbols;
#: :data:`polrig.formats.ome.UNITS`).
OME_UNITS = {"micrometer": "µm", "millimeter": "mm", "nanometer": "nm", "meter": "m"}

# -- polrig.solve ---------------------------------------------------------------------------------
#: Default ``min_snr``: a signal below this many noise standard deviations is ``DARK``
#: (:data:`polrig.solve.reference.MIN_SNR`).
MIN_SNR = 3.0
#: The ``--models`` choices (:data:`polrig.solve.model_selection.MODEL_CHOICES`): ``full`` (the 3x3
#: block everywhere, the default), ``auto`` (the lower-order model selection) and ``diffuse`` (two
#: states: the diffuse term, with the specular term where significant, tested on their samples
#: alone, :mod:`polrig.app.diffuse_route`).
MODEL_CHOICES = ("full", "auto", "diffuse")
#: The ``--prior-scale`` choices (:data:`polrig.solve.prior_scale.METHODS`): ``innovations`` (the
#: hybrid prior's sigma scaled per capture from the states after the seen one), ``geometry``
#: (that, and at two states the prior along the direction they leave open scaled by what the
#: diffuse term's geometry shows of it, :mod:`polrig.solve.open_scale`) and ``calibrated`` (as
#: calibrated).
PRIOR_SCALES = ("innovations", "geometry", "calibrated")
#: The ``--prior-scale`` a new capture or revision takes when none is given.
DEFAULT_PRIOR_SCALE = "geometry"

# -- polrig.acquisition ---------------------------------------------------------------------------
#: Network binnings of the single-shot method
#: (:data:`polrig.acquisition.plan.NETWORK_BINNINGS`): 1 runs the networks on the analyzer grid,
#: 2 on that grid binned 2x2 with the answer lifted back by the grid's measured detail
#: (:func:`polrig.models.full_resolution.reconstruct_binned`).
NETWORK_BINNINGS = (1, 2)

# -- polrig.sim -----------------------------------------------------------------------------------
#: Scenes with materials outside the Baek 2018 family (:class:`polrig.sim.scene.SurfaceMaterial`);
#: ``plastic_metal`` (a sphere, half red plastic, half aluminium: the adaptive capture's test
#: scene, issue 33 item 2) mixes the two and is used for fitting nothing.
MATERIAL_SCENES = ("gold_sphere", "chrome_sphere", "brushed_cylinder", "dispersive_sphere",
                   "film_plane", "textured_blob", "metals", "corner", "crater", "plastic_metal")
#: Named scenes of :func:`polrig.sim.scene.make_scene`.
SCENES = ("sphere", "diffuse_sphere", "mirror_sphere", "rough_sphere", "checker_sphere",
          "plane", "box", "cylinder", "multi", "heightfield", "normalmap", "blob",
          "torus") + MATERIAL_SCENES
#: Kinds of random material: ``baek`` is the initialization's family
#: (:func:`polrig.sim.materials.random_material`); the others are outside it
#: (:func:`polrig.sim.materials.random_surface_material`).
MATERIAL_KINDS = ("baek", "conductor", "dispersive", "anisotropic", "film", "depolarizing")
#: Named dataset material mixes: kind -> probability. ``baek`` is the default (datasets as
#: before); ``train`` is the training mix; ``heldout`` draws only the kinds the training mix
#: leaves out (a thin retarding film, partial depolarization with textures); a single kind is
#: also a mix.
MATERIAL_MIXES: dict[str, dict[str, float]] = {
    "baek": {"baek": 1.0},
    "train": {"baek": 0.4, "conductor": 0.2, "dispersive": 0.2, "anisotropic": 0.2},
    "heldout": {"film": 0.5, "depolarizing": 0.5},
    **{k: {k: 1.0} for k in MATERIAL_KINDS if k != "baek"},
}

# -- polrig.gui -----------------------------------------------------------------------------------
#: Sensor size of the GUI's simulated rig (:data:`polrig.gui.app.DEFAULT_SIM_SIZE`).
GUI_SIM_SIZE = "512x512"
