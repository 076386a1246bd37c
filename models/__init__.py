"""Single-shot Mueller reconstruction (PIPNet + analytic pBRDF initialization + PMMNet).

Runtime (onnxruntime only, never torch): :mod:`models.runtime` (``SingleShotModel``,
``infer_frame``) with the shipped graphs in ``models/weights/`` (``MODEL_CARD.md``).
Training (``train`` extra, PyTorch): :mod:`models.pipnet`, :mod:`models.pmmnet`,
:mod:`models.pbrdf_torch`, :mod:`models.layers`, :mod:`models.data`, :mod:`models.train`,
:mod:`models.export`. Evaluation: :mod:`models.evaluate`.
"""
