"""The left-right mirror image of a single-shot capture, for mirror averaging.

Reflecting the world in the camera's ``Y-Z`` plane (camera ``X -> -X``, ``docs/conventions.md``)
turns one valid capture into another: the pBRDF is isotropic, the pinhole camera maps the
mirrored rays to the mirrored pixels (image columns reversed, ``wo`` with ``x`` negated, which
also carries an off-centre principal point), and a training rig whose stage zero axis is the
camera's up direction keeps that axis. Polarization angles change sign, ``psi -> -psi``, in
both the emergent frame (``x`` from camera ``X``) and the incident frame (``x`` from the
mirrored stage zero axis; the reflection also flips ``y = k x x``), so ``S2 -> -S2`` and a
linear Mueller block becomes ``D M D`` with ``D = diag(1, 1, -1)``. (With ``P`` the
reflection, a field ``cos psi x + sin psi y`` maps to ``cos psi Px + sin psi Py``; the
mirrored frames are ``(-Px, Py)`` in the emergent frame, whose ``x`` stays camera ``X``, and
``(Px, -Py)`` in the incident frame, since ``(Pk) x (Pa) = -P(k x a)``: either way the angle
is ``-psi`` modulo 180 deg. ``tests/test_models_mirror.py`` checks this against
:func:`polrig.optics.pbrdf.linear_rig_mueller`.)
The analyzer at ``t`` becomes the one at ``-t``: 0 and 90 deg stay, 45 and 135 deg swap.

The networks are not exactly mirror-equivariant (they learn from finite data), so running
the graph on the capture and on its mirror image and averaging the two answers mapped back
(:meth:`polrig.models.runtime.SingleShotModel.run_rig_frame` with ``mirror_average=True``) lowers
the error at twice the network time (measured in ``models/MODEL_CARD.md``, "Mirror
averaging"). The average of two realizable Mueller matrices is realizable (the set of
matrices with a positive semidefinite coherency matrix is convex).

Every function takes the plane-first arrays of :mod:`polrig.models.runtime` (spatial axes last),
numpy arrays or torch tensors alike (training mirrors a random part of each batch,
``polrig.models.train``; this module never imports torch), and is its own inverse.
"""

from __future__ import annotations

import numpy as np

#: Sign of ``S0, S1, S2`` under the mirror.
STOKES_SIGN = np.array([1.0, 1.0, -1.0])
#: Analyzer order 0, 45, 90, 135 deg -> the order of the mirrored analyzers (``t -> -t``).
ANALYZER_ORDER = (0, 3, 2, 1)
#: Sign of camera-frame vector components ``x, y, z`` under the mirror.
VECTOR_SIGN = np.array([-1.0, 1.0, 1.0])


def _is_tensor(a) -> bool:
    return type(a).__module__.startswith("torch")


def _columns(a):
    return a.flip(-1) if _is_tensor(a) else np.ascontiguousarray(np.asarray(a)[..., ::-1])


def _times(a, sign: np.ndarray):
    """``a * sign`` in ``a``'s own array type and dtype."""
    if _is_tensor(a):
        return a * a.new_tensor(sign)
    a = np.asarray(a)
    return a * sign.astype(a.dtype)


def analyzer(a):
    """Analyzer images ``(..., 4, H, W)`` (0, 45, 90, 135 deg) of the mirror image."""
    return _columns(a[..., list(ANALYZER_ORDER), :, :])


def image(a):
    """A scalar image ``(..., H, W)`` (mask, albedo plane) of the mirror image."""
    return _columns(a)


def stokes(s):
    """Stokes vectors ``(..., 3)`` of the mirror image."""
    return _times(s, STOKES_SIGN)


def vectors(v):
    """Camera-frame vectors ``(..., 3)`` (a stage zero axis, a light direction) mirrored."""
    return _times(v, VECTOR_SIGN)


def vector_image(v):
    """A camera-frame vector image ``(..., 3, H, W)`` (normals, ``wi``, ``wo``) of the mirror image."""
    return _columns(_times(v, VECTOR_SIGN[:, None, None]))


def mueller_image(m):
    """A Mueller image ``(..., 3, 3, H, W)`` of the mirror image: columns reversed, ``D M D``."""
    return _columns(_times(m, (STOKES_SIGN[:, None] * STOKES_SIGN[None, :])[:, :, None, None]))


def scalar(a):
    """A per-image scalar (roughness): unchanged."""
    return a


#: How each graph output (:mod:`polrig.models.export`) maps to the mirror image; scalars are unchanged.
OUTPUTS = {"mueller": mueller_image, "mueller_init": mueller_image, "normal": vector_image,
           "wi": vector_image, "kd": image, "alpha": scalar}


def outputs(out: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """The graph's outputs ``(B, ...)`` of a mirrored capture, mapped back to the capture."""
    return {k: OUTPUTS[k](v) if k in OUTPUTS else v for k, v in out.items()}


def average(a: dict[str, np.ndarray], b: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Mean of two output sets of the same capture; unit vectors (``normal``, ``wi``) are
    renormalised; ``incident_rotation_deg`` is ``a``'s."""
    res = {}
    for k, v in a.items():
        if k == "incident_rotation_deg":
            res[k] = v
            continue
        mean = 0.5 * (v + b[k])
        if OUTPUTS.get(k) is vector_image:
            mean = mean / np.maximum(np.linalg.norm(mean, axis=-3, keepdims=True), 1e-12)
        res[k] = mean.astype(v.dtype)
    return res
