"""From one state to four: single-shot, hybrid and reference on the held-out sets (issue 33,
item 4).

``python -m polrig.models.continuum [--count N] [--out FILE.md]`` generates the model card's
held-out sets at 64x64 (``polrig.sim.dataset``; the first ``--count`` samples of each, the same
scenes as the first samples of the card's 256-sample sets), runs the shipped single-shot
network on each sample's own frame (onnxruntime, read only) with its calibrated sigma, and
compares, with the metrics of :mod:`polrig.models.evaluate`:

* **single-shot**: the network's estimate and sigma;
* **hybrid N** (:func:`polrig.solve.hybrid.solve_hybrid`): the network as the prior, the
  sample's own frame as the seen state, plus ``N - 1`` more states;
* **reference N** (:func:`polrig.solve.reference.solve_reference`): the same frames, no prior.

**States.** Offsets from the seen state's polarizer angle (every sample has its own), on a
15 deg grid. The best 2- and 3-state sets (``0/d``, ``0/d1/d2``) are searched by the hybrid's
mean matrix PSNR (over pixels unclipped in every state) on sets none of the reported ones
holds (the uncertainty calibration's scenes, seed 11: all six families, and the held-out
families); four states are 0/45/90/135.

**Frames.** The seen frame is the dataset's own (the simulator's sensor model: shot, read, dark
and quantisation noise, clipping). The other states' frames are rendered from the truth and
sampled with the same sensor model and exposure (:meth:`polrig.sensor.noise.SensorModel.sample_raw`,
as the dataset does), so every state has the same noise and clips where the sensor would. Each
sample's variance is the sensor model's at its measured value, samples at or above the
saturation level are excluded (as :mod:`polrig.app.processing` does). So the reference rows
differ from the card's "four-state reference" row, which adds Gaussian noise of a fitted
model and never clips.

**Equal capture time.** The hybrid with 3 states of 4 frames each against 4 states of 3 (the
rendered frames averaged, their variance the sensor model's for the mean of that many; the
seen state's first frame is the network's input); every other row has one frame per state.

**The prior** is the one captures use: the calibration's joint prior (``joint_prior`` in
``uncertainty.json``, :mod:`polrig.solve.hybrid` "Joint prior") where it holds one, else the
per-element sigma; every hybrid row, the adaptive one and the two-state model rows use it
(``--joint-compare`` measures the two against each other). Tables written before the joint
prior say "per element". Its sigma is scaled per sample as captures scale it (:func:`scaled_sigma`,
:mod:`polrig.solve.prior_scale`: by the states after the seen one; factor 1 at one state), in
every hybrid row, the adaptive capture's solve and design and the two-state model rows; the
rows ``hybrid<N>_calibrated`` (the "prior's scale" table) and the :data:`VARIANTS` keep it as
calibrated, as does ``--joint-compare``. Tables written before the scale have no such table.

**Metrics.** Matrix PSNR (peak the largest true ``|m|`` on the object, over the object mask;
and over the object's pixels with no clipped sample in any frame of any state: a highlight
clipped in every state, a few tenths of a per cent of the pixels, is recovered by no number of
states and sets the first PSNR of every method alike), forward Stokes relative L2 over the 11 held-out incident states
(:func:`polrig.models.evaluate.forward_l2`), and coverage: the fraction of the elements of the
object's pixels (per colour) whose error is within 2 sigma, over pixels whose seen frame is
not clipped (as the single-shot sigma's coverage is measured) and that the solve did not mask
``ILL_CONDITIONED``. Each coverage figure comes with its 90 % bootstrap interval over the set's
samples and the 10th-90th percentile of the samples' own coverage
(:mod:`polrig.models.scene_bootstrap`; ``coverage_interval``, ``coverage_scenes``): a scene's
errors cover or miss together, so how far a set's figure can be trusted is set by how many
scenes it holds, not by its pixels.

**Highlights** (:data:`BRACKET`, the "Highlights" table): single-shot, hybrid 1 and hybrid 2
with every state's frame merged with shorter exposures (:func:`sample_frames`' ``bracket``); the
network sees the reference exposure and, where it clipped but a shorter exposure measured the
pixel, its estimate takes the measured intensity (:func:`bracket_prior`,
:mod:`polrig.models.highlights`), as the capture's single-shot route does with
``--exposure T,T/16,T/256``. Scored as above (``clean`` the reference exposure's), plus the
coverage at those highlights. ``--fit-highlights`` fits their sigma factor
(:func:`fit_highlight_factor`) on the calibration scenes.

**Adaptive** (issue 33 item 2; :func:`adaptive`): the adaptive capture's rule on each sample,
at each of ``--targets`` (relative posterior sigma; 95 % of the object pixels, at most 4
states), the equiangular set through the seen state first, then choosing among the 15 deg
offsets (one frame each; :func:`polrig.solve.design.next_candidates`). **Acquisition time**
(:func:`acquisition_time_s`): the simulated rig's hardware time of one pose taking a method's
states (stage motion, exposure, readout), with its states per pose.

**The rig's size** (``--rig-scenes [LIST] [--rig-poses 0,60,...] [--size N]``, :func:`rig_set`):
instead of the held-out sets, the default simulated rig's named scenes (:data:`RIG_SCENES`) at
its analyzer grid (:func:`rig_size`: 128x128, its 512x512 colour sensor over the 4x4 mosaic), one
sample per turntable angle, with the dataset's random polarizer state, exposure and noise
(:func:`polrig.sim.dataset.capture_sample`) and the states searched at 64x64 (:data:`RIG_TWO`,
:data:`RIG_THREE`).

**The trade plot** (:func:`plot_trade`, written beside ``--out`` as ``.png``; ``--plot-only
FILE.json`` redraws it from a results JSON alone): matrix PSNR and forward Stokes L2 against the
acquisition time per pose, a point per set and method and the median over the sets with its
range.

**Lower-order models at two states** (``--models-only`` runs only this; the full run adds it as
its last table; :func:`models_rows`): at the 2-state set, single-shot, hybrid 2 and hybrid 2 with
:func:`polrig.solve.model_selection.select_models` (the network's prior given: at two states the
test runs on the hybrid's posterior system), scored over every object pixel and over those where
a lower-order model holds (:func:`model_holds`: the truth within :data:`HOLDS_REL` relative
Frobenius of its nearest candidate in every colour, the pixel lit, :func:`lit_pixels`, and
unclipped), with the share given a reduced model and the false acceptance where the truth is
detectably off every candidate (:func:`detectably_off_every_model`); and the selection's result
with the direction the two states leave open predicted from the diffuse term's geometry where it
chose ``rank_one`` (:func:`polrig.solve.diffuse_geometry.complete_diffuse`; the geometry of
:func:`frame_geometry`: the intrinsics' view directions, two candidate light fields per sample,
the network's normals as the first pass's guess, the neighbours' mean as the second's).

**Variants of the seen state's treatment** (the double-counting question of
:mod:`polrig.solve.hybrid`), at 1 and 2 states: ``marginal`` (the plain marginal on the
unobserved plane, without the row's prior variance along the seen direction kept in it),
``naive`` (the whole prior and
every frame: the seen frame counted twice) and ``exclude`` (the whole prior, the seen frame
dropped).

**Modules** (each imports only those before it in this list): ``sets`` (the sets, the
rig's scenes and poses, the states and budgets), ``frames`` (one sample's :class:`Frames`),
``methods`` (the estimators, the adaptive rule, acquisition time, :func:`score`),
``lower_order`` (the two-state model rows), ``report`` (tables and plot), ``run`` (a set, the
whole run, the joint-prior comparison), ``cli`` (``main``). Every name listed below is
importable from this package.
"""

# The public face: every name of the submodules that other modules, the tests and the documents
# use, importable from here as before the module became a package.
from polrig.models.continuum.sets import (  # noqa: F401
    ADAPTIVE_MAX_STATES,
    ADAPTIVE_MORE_STATES,
    ADAPTIVE_SHARE,
    ADAPTIVE_TARGETS,
    BRACKET,
    FOUR_STATES,
    OFFSETS_DEG,
    RIG_POSES_DEG,
    RIG_SCENES,
    RIG_THREE,
    RIG_TWO,
    SEARCH_SETS,
    SEEN,
    SETS,
    SIM_READOUT_US,
    SIM_STAGE_ACCEL_DEG_S2,
    SIZE,
    VARIANTS,
    adaptive_budget,
    adaptive_key,
    adaptive_label,
    make_set,
    rig_set,
    rig_size,
    set_label,
)
from polrig.models.continuum.frames import (  # noqa: F401
    Frames,
    bracket_prior,
    frame_geometry,
    light_over_depth,
    lit_pixels,
    measured_highlights,
    network_prior,
    rotated_state,
    sample_frames,
    set_samples,
    stack_states,
)
from polrig.models.continuum.methods import (  # noqa: F401
    JOINT_PRIORS,
    acquisition_time_s,
    adaptive,
    estimate,
    hybrid_models_result,
    hybrid_with_models,
    joint_priors,
    marginal_sigma,
    mean_rows,
    open_factor,
    reference_with_models,
    scaled_sigma,
    score,
    sim_hardware_model,
    stage_angles,
)
from polrig.models.continuum.lower_order import (  # noqa: F401
    DETECTABLE_POWER,
    HOLDS_REL,
    POWER_DRAWS,
    detectably_off_diffuse,
    detectably_off_every_model,
    diffuse_row,
    diffuse_test_power,
    model_holds,
    models_rows,
    score_where_models_hold,
    two_state_bound_db,
)
from polrig.models.continuum.report import (  # noqa: F401
    TRADE_METHODS,
    TRADE_METRICS,
    coverage_interval_table,
    diffuse_markdown,
    joint_markdown,
    markdown,
    min_states_markdown,
    models_markdown,
    plot_from_json,
    plot_trade,
    prior_scale_table,
    prior_words,
    search_line,
    trade_figure,
    trade_methods,
    trade_points,
)
from polrig.models.continuum.run import (  # noqa: F401
    evaluate_set,
    fit_highlight_factor,
    joint_compare,
    joint_rows,
    min_states_compare,
    run,
    search_states,
)
from polrig.models.continuum.cli import main  # noqa: F401
