"""The virtual polarizer: the image a measured Mueller block predicts for any incident linear
state (or unpolarized light) seen through any analyzer angle.

``I = a(theta)^T M s_in(psi)`` with the conventions of ``docs/conventions.md``:

* ``s_in(psi)`` is the normalised incident Stokes vector of the rig's polarizer at ``psi``
  (incident frame, from the stage zero axis ``x`` towards ``y``):
  :func:`polrig.optics.mueller.polarizer_stokes` with ``intensity=1``, ``0.5 (1, cos 2psi,
  sin 2psi)``, exactly the ``S_in`` a reference capture is solved with ("Radiometric units").
  Unpolarized light is ``(0.5, 0, 0)``: the same ``S0``, i.e. the mean of the polarized images
  over all polarizer angles (the lamp without its polarizer would be twice as bright).
* ``a(theta)`` is the ideal analyzer at ``theta`` (emergent frame, from the image ``+u`` axis
  towards image up): ``I(t) = (S0 + S1 cos 2t + S2 sin 2t) / 2``, the first row of
  :func:`polrig.optics.mueller.polarizer_at` ``(theta)``'s linear block; ``None`` is no analyzer
  (``a = (1, 0, 0)``, the total intensity ``S0``).

With a measured block in DN per unit incident ``S0`` the result is in DN at the capture's
exposure and gain: for ``psi`` one of the capture's states and ``theta`` one of the DoFP
analyzer angles 0/45/90/135 it is what that analyzer's pixels read (black level removed), the most
direct check of a result against a photograph. Its standard deviation from independent
per-element sigmas is exact (the image is linear in ``M``): ``sigma_I^2 = sum_ij (a_i s_j
sigma_ij)^2``.
"""

from __future__ import annotations

import numpy as np

from polrig.optics.mueller import linear_block, polarizer_at, polarizer_stokes

__all__ = ["analyzer_row", "incident_stokes", "virtual_polarizer", "virtual_polarizer_image"]


def analyzer_row(analyzer_deg=None) -> np.ndarray:
    """Row ``a (..., 3)`` with ``I = a . S_out``: the ideal analyzer at ``analyzer_deg``
    (``0.5 (1, cos 2t, sin 2t)``), or ``(1, 0, 0)`` for ``None`` (no analyzer)."""
    if analyzer_deg is None:
        return np.array([1.0, 0.0, 0.0])
    return linear_block(polarizer_at(np.deg2rad(np.asarray(analyzer_deg, float))))[..., 0, :]


def incident_stokes(incident_deg=None) -> np.ndarray:
    """Normalised incident linear Stokes ``(..., 3)``: the rig's ideal polarizer at
    ``incident_deg`` (``0.5 (1, cos 2p, sin 2p)``), or unpolarized ``(0.5, 0, 0)`` for
    ``None`` (module docstring)."""
    if incident_deg is None:
        return np.array([0.5, 0.0, 0.0])
    return polarizer_stokes(np.deg2rad(np.asarray(incident_deg, float)), intensity=1.0)


def virtual_polarizer(m, incident_deg=None, analyzer_deg=None, sigma=None
                      ) -> tuple[np.ndarray, np.ndarray | None]:
    """``I = a(analyzer_deg)^T M s_in(incident_deg)`` of blocks ``m (..., 3, 3)``.

    ``incident_deg``/``analyzer_deg``: degrees (scalars or arrays that broadcast against the
    leading shape), ``None`` for unpolarized light / no analyzer. Returns ``(I, sigma_I)``, each
    ``(...)`` float64 in the units of ``m``; ``sigma_I`` is None without ``sigma`` (per-element
    standard deviations ``(..., 3, 3)``, taken independent). NaN elements give NaN where they
    are used (an element multiplied by a zero weight does not count).
    """
    m = np.asarray(m, dtype=np.float64)
    if m.ndim < 2 or m.shape[-2:] != (3, 3):
        raise ValueError(f"expected 3x3 linear Mueller blocks of shape (..., 3, 3), got {m.shape}")
    a, s = analyzer_row(analyzer_deg), incident_stokes(incident_deg)
    w = a[..., :, None] * s[..., None, :]  # (..., 3, 3) weights a_i s_j
    with np.errstate(invalid="ignore"):
        intensity = np.sum(np.where(w == 0, 0.0, w * m), axis=(-2, -1))
        if sigma is None:
            return intensity, None
        sg = np.asarray(sigma, dtype=np.float64)
        var = np.sum(np.where(w == 0, 0.0, (w * sg) ** 2), axis=(-2, -1))
    return intensity, np.sqrt(var)


def virtual_polarizer_image(mueller, incident_deg=None, analyzer_deg=None, sigma=None
                            ) -> tuple[np.ndarray, np.ndarray | None]:
    """:func:`virtual_polarizer` of a Mueller image ``(C, 3, 3, H, W)`` (plane-first,
    ``docs/conventions.md``) with scalar angles: ``(I, sigma_I)`` float32 ``(C, H, W)``
    (``sigma_I`` None without ``sigma`` of the image's shape)."""
    img = np.asarray(mueller)
    if img.ndim != 5 or img.shape[1:3] != (3, 3):
        raise ValueError(f"Mueller images must have shape (C, 3, 3, H, W), got {img.shape}")
    a, s = analyzer_row(analyzer_deg), incident_stokes(incident_deg)
    if a.shape != (3,) or s.shape != (3,):
        raise ValueError("virtual_polarizer_image takes scalar angles (or None)")
    intensity = np.zeros((img.shape[0],) + img.shape[-2:], np.float64)
    var = None if sigma is None else np.zeros_like(intensity)
    sg = None if sigma is None else np.broadcast_to(np.asarray(sigma), img.shape)
    for i in range(3):  # nine weighted planes: no (C, 3, 3, H, W) float64 temporary
        for j in range(3):
            w = a[i] * s[j]
            if w == 0:
                continue
            intensity += w * img[:, i, j].astype(np.float64)
            if var is not None:
                var += (w * sg[:, i, j].astype(np.float64)) ** 2
    return (intensity.astype(np.float32),
            None if var is None else np.sqrt(var).astype(np.float32))
