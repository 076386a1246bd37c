"""Single-shot Mueller reconstruction (PIPNet + analytic pBRDF initialization + PMMNet).

Runtime (onnxruntime only, never torch; imports nothing from evaluation or training):
:mod:`models.runtime` (``SingleShotModel``, ``infer_frame``) with the shipped graphs in
``models/weights/`` (``MODEL_CARD.md``), :mod:`models.devices` (CPU or CUDA execution provider),
:mod:`models.full_resolution` (Mueller images at the raw frame's resolution),
:mod:`models.uncertainty` (the calibrated error model), :mod:`models.mirror`, :mod:`models.size`.
Training (``train`` extra, PyTorch): :mod:`models.pipnet`, :mod:`models.pmmnet`,
:mod:`models.pbrdf_torch`, :mod:`models.layers`, :mod:`models.data`, :mod:`models.train`,
:mod:`models.export`, :mod:`models.paper_scale` (a whole run in a wall-clock budget).
Evaluation and fitting tools: :mod:`models.evaluate`, :mod:`models.evaluate_full_resolution`,
:mod:`models.uncertainty_fit`, :mod:`models.diagnose`. ``tests/test_models_imports.py`` keeps
the package free of import cycles.
"""
