"""Single-shot Mueller reconstruction (PIPNet + analytic pBRDF initialization + PMMNet).

Runtime (onnxruntime only, never torch; imports nothing from evaluation or training):
:mod:`polrig.models.runtime` (``SingleShotModel``) with the shipped graphs in
``models/weights/`` (``MODEL_CARD.md``), :mod:`polrig.models.devices` (CPU or CUDA execution provider),
:mod:`polrig.models.full_resolution` (the lift to the raw frame's resolution, network binning),
:mod:`polrig.models.uncertainty` (the calibrated error model), :mod:`polrig.models.mirror`, :mod:`polrig.models.size`.
Training (``train`` extra, PyTorch): :mod:`polrig.models.pipnet`, :mod:`polrig.models.pmmnet`,
:mod:`polrig.models.pbrdf_torch`, :mod:`polrig.models.layers`, :mod:`polrig.models.data`, :mod:`polrig.models.train`,
:mod:`polrig.models.export`, :mod:`polrig.models.paper_scale` (a whole run in a wall-clock budget),
:mod:`polrig.models.scenes_torch` and :mod:`polrig.models.train_on_device` (training scenes made on the device).
Evaluation and fitting tools: :mod:`polrig.models.evaluate`, :mod:`polrig.models.evaluate_full_resolution`,
:mod:`polrig.models.uncertainty_fit`, :mod:`polrig.models.diagnose`, :mod:`polrig.models.continuum` (the
network as the prior of :func:`polrig.solve.hybrid.solve_hybrid`, one state to four). ``tests/test_models_imports.py``
keeps the package free of import cycles. The single-shot route from a raw frame to a result (used by
``polrig infer``, sessions and the GUI) is :class:`polrig.app.single_shot.SingleShot`.
"""
