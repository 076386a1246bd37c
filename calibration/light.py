"""Point-light position from the specular highlights on mirror (chrome) spheres of known radius.

Per image: the sphere's silhouette (a dark disc on a brighter background) gives edge points;
their back-projected unit rays ``d_j`` all make the same angle ``a`` with the direction to the
sphere centre ``c``, so ``d_j . (c / cos a) = 1`` is linear in ``w = c / cos a``; then
``|C| = r / sin a`` (exact under perspective, no circle/ellipse approximation). The highlight's
sub-pixel position is the intensity-weighted centroid of the pixels above half its peak
(background removed); its ray hits the sphere at ``P`` with normal ``n``; the light lies on the
reflected ray ``P + s (d - 2 (d.n) n)``. Several spheres (or one sphere at several turntable
angles) give several rays, whose least-squares intersection is the light position, with a
covariance from the residuals (``sigma^2 (sum_i (I - l_i l_i^T))^-1``) plus the sphere model's
own systematic (:data:`MODEL_SYSTEMATIC_REL`, a Type B term).

References: K.-Y. K. Wong, D. Schnieders, S. Li, "Recovering light directions and camera
poses from a single sphere", ECCV 2008 (sphere from its silhouette cone); W. Zhou and
C. Kambhamettu, "Estimation of illuminant direction and intensity of multiple light sources",
ECCV 2002 (mirror-sphere highlights); closest point to a set of lines: Hartley and Zisserman,
*Multiple View Geometry*, 2nd ed., sec. 12 (linear triangulation).

Pixel and camera coordinates follow ``docs/conventions.md`` (OpenCV camera frame, metres).
"""

from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from polrig.calibration.errors import (
    CalibrationError,
    SphereNotFound,
    SphereSaturated,
    TooFewAngles,
)


def pixel_rays(points_px: np.ndarray, K: np.ndarray, dist: np.ndarray | None = None) -> np.ndarray:
    """Unit camera-frame rays ``(N, 3)`` through pixel positions ``(N, 2)`` (``u, v``),
    undistorting with OpenCV coefficients ``dist`` when given."""
    pts = np.asarray(points_px, dtype=np.float64).reshape(-1, 2)
    if dist is not None and np.any(np.asarray(dist) != 0):
        n = cv2.undistortPoints(pts.reshape(-1, 1, 2), K, np.asarray(dist, float)).reshape(-1, 2)
    else:
        n = np.stack([(pts[:, 0] - K[0, 2]) / K[0, 0], (pts[:, 1] - K[1, 2]) / K[1, 1]], axis=1)
    d = np.concatenate([n, np.ones((len(n), 1))], axis=1)
    return d / np.linalg.norm(d, axis=1, keepdims=True)


@dataclasses.dataclass(frozen=True)
class SphereObservation:
    """One mirror sphere in one image: silhouette edge points ``edge_px`` ``(N, 2)``, the
    highlight centroid ``highlight_px`` ``(2,)`` and its 1-sigma uncertainty (pixels)."""

    edge_px: np.ndarray
    highlight_px: np.ndarray
    highlight_std_px: float
    highlight_peak_dn: float


def find_sphere(image: np.ndarray, saturation_dn: float | None = None,
                min_radius_px: float = 4.0, highlight_image: np.ndarray | None = None,
                edge_image: np.ndarray | None = None) -> SphereObservation:
    """Silhouette edge points and highlight of a mirror sphere in a grey image (DN, 2-D).

    The sphere is the largest connected region darker than the Otsu threshold of the image
    that does not touch the border (a chrome sphere reflects the dark surroundings), holes
    (the highlight) filled. Edge points are the sub-pixel crossings of the mid level between
    neighbouring inside/outside pixels (4-neighbours). Raises :class:`SphereNotFound` or
    :class:`SphereSaturated` (when more than one highlight pixel reaches ``saturation_dn``)
    with what to change. ``highlight_image`` (same shape; e.g. a shorter exposure in which the
    highlight is not clipped) is used for the highlight instead of ``image``, and
    ``edge_image`` (e.g. the same frame without smoothing) for the edge points.
    """
    img = np.asarray(image, dtype=np.float64)
    if img.ndim != 2:
        raise ValueError(f"sphere detection needs a 2-D grey image, got shape {img.shape}")
    img = np.where(np.isfinite(img), img, 0.0)
    lo, hi = np.percentile(img, [1, 99.5])
    if hi - lo <= 0:
        raise SphereNotFound("image is uniform: no sphere silhouette; light the background "
                             "behind the mirror sphere or raise exposure")
    g8 = np.clip((img - lo) / (hi - lo) * 255, 0, 255).astype(np.uint8)
    thr, dark = cv2.threshold(g8, 0, 1, cv2.THRESH_BINARY_INV + cv2.THRESH_OTSU)
    n, labels, stats, _ = cv2.connectedComponentsWithStats(dark, connectivity=4)
    h, w = img.shape
    hil = img if highlight_image is None else np.asarray(highlight_image, dtype=np.float64)
    hil = np.where(np.isfinite(hil), hil, 0.0)
    # candidates: dark discs inside the image; the sphere is the one holding the brightest
    # highlight (a shadow of the sphere on the backdrop is dark too, but has no highlight)
    best, best_peak, filled = -1, -np.inf, None
    for k in range(1, n):
        x, y, ww, hh, area = stats[k]
        if x == 0 or y == 0 or x + ww >= w or y + hh >= h or area < np.pi * min_radius_px ** 2:
            continue
        region = (labels == k).astype(np.uint8)
        contours, _ = cv2.findContours(region, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_NONE)
        f = np.zeros_like(region)
        cv2.drawContours(f, contours, -1, 1, thickness=cv2.FILLED)
        core_k = cv2.erode(f, np.ones((3, 3), np.uint8)).astype(bool)
        peak_k = float(np.max(hil[core_k])) if core_k.any() else -np.inf
        if peak_k > best_peak:
            best, best_peak, filled = k, peak_k, f
    if best < 0:
        raise SphereNotFound("no mirror sphere silhouette found (need a dark disc of radius "
                             f">= {min_radius_px:.0f} px fully inside the image on a lit "
                             "background); move the sphere into view or light the background")
    inside = filled.astype(bool)
    # edge points from the unsmoothed image when given (sharper), else from ``image``
    e_img = img if edge_image is None else np.where(np.isfinite(edge_image), edge_image, 0.0)
    band = cv2.dilate(filled, np.ones((7, 7), np.uint8)).astype(bool) & \
        ~cv2.erode(filled, np.ones((7, 7), np.uint8)).astype(bool)
    ring_out = cv2.dilate(filled, np.ones((9, 9), np.uint8)).astype(bool) & \
        ~cv2.dilate(filled, np.ones((5, 5), np.uint8)).astype(bool)
    ring_in = cv2.erode(filled, np.ones((5, 5), np.uint8)).astype(bool) & \
        ~cv2.erode(filled, np.ones((9, 9), np.uint8)).astype(bool)
    bg, fg = np.median(e_img[ring_out]), np.median(e_img[ring_in])
    mid = 0.5 * (bg + fg)
    dark_px = (e_img < mid) & band | (inside & ~band)
    pts = []
    for axis in (0, 1):
        a_in = dark_px[:, :-1] if axis == 1 else dark_px[:-1, :]
        b_in = dark_px[:, 1:] if axis == 1 else dark_px[1:, :]
        a_v = e_img[:, :-1] if axis == 1 else e_img[:-1, :]
        b_v = e_img[:, 1:] if axis == 1 else e_img[1:, :]
        a_b = band[:, :-1] if axis == 1 else band[:-1, :]
        tr = (a_in != b_in) & a_b
        r, c = np.nonzero(tr)
        va, vb = a_v[r, c], b_v[r, c]
        den = vb - va
        f = np.where(np.abs(den) > 1e-12, (mid - va) / np.where(den == 0, 1, den), 0.5)
        f = np.clip(f, 0.0, 1.0)
        if axis == 1:
            pts.append(np.stack([c + f, r.astype(float)], axis=1))
        else:
            pts.append(np.stack([c.astype(float), r + f], axis=1))
    edge = np.concatenate(pts)
    # highlight: brightest pixels inside the disc (away from the rim)
    core = cv2.erode(filled, np.ones((3, 3), np.uint8)).astype(bool)
    if highlight_image is not None:
        img = np.asarray(highlight_image, dtype=np.float64)
        if img.shape != inside.shape:
            raise ValueError(f"highlight image shape {img.shape} differs from {inside.shape}")
        img = np.where(np.isfinite(img), img, 0.0)
    vals = np.where(core, img, -np.inf)
    peak_idx = np.unravel_index(np.argmax(vals), img.shape)
    peak = img[peak_idx]
    base = np.median(img[core]) if np.any(core) else fg
    if not np.isfinite(peak) or peak <= base + 1e-9:
        raise SphereNotFound("no specular highlight on the mirror sphere; check that the light "
                             "is on and reflected by the sphere towards the camera")
    if saturation_dn is not None:
        nsat = int(np.sum(core & (img >= saturation_dn)))
        if nsat > 1:
            raise SphereSaturated(f"sphere highlight saturated ({nsat} pixels at "
                                  f"{saturation_dn:.0f} DN); lower the exposure or light level")
    # intensity-weighted centroid with weights falling continuously to zero at 10 % of the
    # peak (no truncation step that would pull the centroid towards the peak pixel)
    thr = 0.1 * (peak - base)
    r0, c0 = peak_idx
    win = 8
    rs, cs = slice(max(r0 - win, 0), r0 + win + 1), slice(max(c0 - win, 0), c0 + win + 1)
    patch = img[rs, cs] - base
    m = (patch > thr) & core[rs, cs]
    lab_n, lab = cv2.connectedComponents(m.astype(np.uint8), connectivity=8)
    m = lab == lab[r0 - rs.start, c0 - cs.start]
    wgt = np.where(m, patch - thr, 0.0)
    yy, xx = np.mgrid[rs, cs]
    tot = wgt.sum()
    u, v = (wgt * xx).sum() / tot, (wgt * yy).sum() / tot
    # centroid noise: sum of w^2 var(x) / W^2 with a read-noise-like floor from the background
    noise = np.std(img[ring_in]) if np.any(ring_in) else 1.0
    npx = max(int(m.sum()), 1)
    spread = np.sqrt(((wgt * ((xx - u) ** 2 + (yy - v) ** 2)).sum() / tot) / 2)
    std = float(np.sqrt(npx) * noise * max(spread, 0.3) / tot + 1.0 / np.sqrt(12) / np.sqrt(npx))
    return SphereObservation(edge, np.array([u, v]), std, float(peak))


@dataclasses.dataclass(frozen=True)
class SphereFit:
    """Sphere centre in camera coordinates (metres) and the reflected ray of the highlight."""

    centre_cam_m: np.ndarray
    radius_m: float
    edge_residual_rms: float  # of d . w - 1 (dimensionless)
    hit_cam_m: np.ndarray
    reflected_dir: np.ndarray


def fit_sphere_centre(edge_rays: np.ndarray, radius_m: float) -> tuple[np.ndarray, float]:
    """Sphere centre ``(3,)`` (camera frame, metres) from unit silhouette rays ``(N, 3)`` of a
    sphere of ``radius_m``; returns the centre and the RMS of ``d . w - 1``."""
    d = np.asarray(edge_rays, dtype=np.float64)
    if len(d) < 8:
        raise SphereNotFound(f"sphere silhouette has only {len(d)} edge points; move the "
                             "sphere closer or use a larger sphere")
    w, *_ = np.linalg.lstsq(d, np.ones(len(d)), rcond=None)
    keep = np.ones(len(d), bool)
    # robust re-fits: drop edge points far from the cone (a shadow or another dark object
    # touching the silhouette), with a MAD-based threshold
    for _ in range(8):
        r_all = d @ w - 1.0
        sig = 1.4826 * np.median(np.abs(r_all[keep] - np.median(r_all[keep]))) + 1e-12
        new = np.abs(r_all) <= max(3.0 * sig, 1e-9)
        if new.sum() < 8 or np.array_equal(new, keep):
            break
        keep = new
        w, *_ = np.linalg.lstsq(d[keep], np.ones(int(keep.sum())), rcond=None)
    res = d[keep] @ w - 1.0
    nw = np.linalg.norm(w)
    if not np.isfinite(nw) or nw <= 1.0:
        raise SphereNotFound("sphere silhouette does not fit a sphere (degenerate cone)")
    cos_a = 1.0 / nw
    sin_a = np.sqrt(max(1.0 - cos_a ** 2, 1e-300))
    return (w / nw) * (radius_m / sin_a), float(np.sqrt(np.mean(res ** 2)))


def reflected_ray(centre_cam_m: np.ndarray, radius_m: float,
                  ray: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Point on the sphere hit by unit ``ray`` from the camera centre and the mirror-reflected
    unit direction there. Raises :class:`CalibrationError` when the ray misses the sphere."""
    c = np.asarray(centre_cam_m, float)
    d = np.asarray(ray, float) / np.linalg.norm(ray)
    b = d @ c
    disc = b * b - (c @ c - radius_m ** 2)
    if disc < 0:
        # the highlight centroid lies a hair outside the fitted silhouette: take the tangent
        if disc < -(0.05 * radius_m) ** 2:
            raise CalibrationError("sphere highlight lies outside the sphere silhouette; "
                                   "check the sphere radius setting")
        disc = 0.0
    t = b - np.sqrt(disc)
    p = t * d
    n = (p - c) / radius_m
    return p, d - 2.0 * (d @ n) * n


#: The sphere model's own systematic error, a Type B standard uncertainty (JCGM 100:2008,
#: "GUM", sec. 4.3) per axis, relative to the light's distance from the sphere positions:
#: a highlight's intensity centroid is not exactly the specular point, nor the dark disc's
#: mid-level edge exactly the silhouette. Its basis is the method run on the simulated rig
#: with its exact intrinsics (docs/calibration.md, "Light position"): 0.6-1.5 mm at
#: 0.52 m, over 320x240, 256x256 and 512x512 images, so it does not shrink with more pixels
#: or views, and these errors are shared by the views, which the rays' scatter cannot show.
MODEL_SYSTEMATIC_REL = 0.002

#: Acceptance of the light position (docs/calibration.md): its error within 1 % of its distance
#: from where objects are lit. :meth:`LightFit.acceptance` says whether the fit's own
#: uncertainty assures it.
ACCEPTANCE_REL = 0.01


@dataclasses.dataclass(frozen=True)
class LightFit:
    """Least-squares light position (camera frame, metres) with its 3x3 covariance."""

    position_cam_m: np.ndarray
    covariance_m2: np.ndarray
    ray_distances_m: np.ndarray  # per ray, distance of the fitted point from the ray
    spheres: tuple[SphereFit, ...]
    #: indices into the observations of the views kept (the others' silhouettes fitted badly)
    views: tuple[int, ...] = ()

    @property
    def std_m(self) -> np.ndarray:
        return np.sqrt(np.clip(np.diag(self.covariance_m2), 0, None))

    def acceptance(self, limit_rel: float = ACCEPTANCE_REL) -> dict:
        """Whether the reported uncertainty assures the acceptance: twice the 1-sigma along
        the least certain direction (the covariance's largest eigenvalue; about 95 % of the
        errors along it) against ``limit_rel`` of the light's distance from the mean sphere
        centre (the balls sat on the turntable, where objects are lit; metres). Keys
        ``limit_rel``, ``two_sigma_m``, ``distance_m``, ``two_sigma_rel``, ``assured``."""
        sigma = float(np.sqrt(max(np.linalg.eigvalsh(self.covariance_m2)[-1], 0.0)))
        centre = np.mean([s.centre_cam_m for s in self.spheres], axis=0)
        distance = float(np.linalg.norm(self.position_cam_m - centre))
        rel = 2.0 * sigma / distance
        return {"limit_rel": float(limit_rel), "two_sigma_m": 2.0 * sigma,
                "distance_m": distance, "two_sigma_rel": rel, "assured": bool(rel <= limit_rel)}

    def to_json(self) -> dict:
        return {"position_cam_m": self.position_cam_m.tolist(),
                "std_m": self.std_m.tolist(), "covariance_m2": self.covariance_m2.tolist(),
                "ray_distances_m": self.ray_distances_m.tolist(),
                "sphere_centres_cam_m": [s.centre_cam_m.tolist() for s in self.spheres],
                "acceptance": self.acceptance()}


def intersect_rays(points_m: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares point nearest to lines ``points + s directions`` ``(N, 3)``; returns the
    point, its covariance (residual variance with ``2N - 3`` degrees of freedom times
    ``(sum (I - l l^T))^-1``) and the distance from each line."""
    p = np.asarray(points_m, float).reshape(-1, 3)
    l = np.asarray(directions, float).reshape(-1, 3)
    l = l / np.linalg.norm(l, axis=1, keepdims=True)
    proj = np.eye(3)[None] - l[:, :, None] * l[:, None, :]
    A = proj.sum(0)
    b = np.einsum("nij,nj->i", proj, p)
    cond = np.linalg.cond(A)
    if not np.isfinite(cond) or cond > 1e8:
        raise TooFewAngles("reflected rays are (nearly) parallel: the light position is not "
                           "determined; add sphere positions (turntable angles) further apart")
    x = np.linalg.solve(A, b)
    r = np.einsum("nij,nj->ni", proj, x[None] - p)
    dist = np.linalg.norm(r, axis=1)
    dof = max(2 * len(p) - 3, 1)
    sigma2 = float(np.sum(dist ** 2) / dof)
    return x, sigma2 * np.linalg.inv(A), dist


def fit_light_position(observations: list[SphereObservation], radius_m: float, K: np.ndarray,
                       dist: np.ndarray | None = None, views: tuple[int, ...] | None = None) -> LightFit:
    """Light position from mirror-sphere observations (one per image or sphere); at least 2
    (3 recommended, for an uncertainty) with different sphere positions. The views whose
    silhouette fits far worse than the typical one are left out, unless ``views`` names the
    ones to use: a fit at perturbed intrinsics (the uncertainty's propagation,
    :mod:`polrig.calibration.procedures`) must use the same views as the fit it perturbs, or a
    view kept or dropped at the margin moves the position by far more than the perturbation
    does (at 256x256 a 15th view kept at fx + 1 sigma moved it by 350 mm, and the light's
    reported sigma was 0.1-0.23 m against a 6 mm error).

    The covariance is the rays' scatter (:func:`intersect_rays`) plus the sphere model's
    systematic, :data:`MODEL_SYSTEMATIC_REL` of the light's distance from the mean sphere
    centre on every axis."""
    if len(observations) < 2:
        raise TooFewAngles(f"light position needs 2+ mirror-sphere views at different positions, "
                           f"got {len(observations)}; add turntable angles or spheres")
    fits = []
    for ob in observations:
        c, rms = fit_sphere_centre(pixel_rays(ob.edge_px, K, dist), radius_m)
        ray = pixel_rays(ob.highlight_px[None], K, dist)[0]
        p, refl = reflected_ray(c, radius_m, ray)
        fits.append(SphereFit(c, radius_m, rms, p, refl))
    if views is None:
        # a silhouette merged with its shadow or another object fits the cone badly: drop views
        # whose edge residual is far above the typical one
        med = float(np.median([f.edge_residual_rms for f in fits]))
        views = tuple(i for i, f in enumerate(fits) if f.edge_residual_rms <= 5.0 * med)
    if len(views) < 2:
        raise TooFewAngles("fewer than 2 clean mirror-sphere silhouettes; keep the sphere's "
                           "shadow off its outline (move the backdrop back) or add positions")
    fits = [fits[i] for i in views]
    x, cov, dists = intersect_rays(np.array([f.hit_cam_m for f in fits]),
                                   np.array([f.reflected_dir for f in fits]))
    distance = np.linalg.norm(x - np.mean([f.centre_cam_m for f in fits], axis=0))
    cov = cov + (MODEL_SYSTEMATIC_REL * distance) ** 2 * np.eye(3)
    return LightFit(x, cov, dists, tuple(fits), tuple(views))
