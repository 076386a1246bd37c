"""A pixel's footprint on a textured surface: the area mean of a region's albedo.

The renderer casts one ray through each pixel centre (:mod:`polrig.sim.render`). For a surface
whose albedo changes inside a pixel (a printed calibration board's square and marker edges)
that point sample is not what a sensor pixel records: the pixel integrates the light over its
area, so an edge through it gives an intermediate value that moves continuously with the edge.
Point sampling instead snaps every edge to the pixel grid, and a corner detector then sees a
position error fixed by the geometry (the same on every frame, with any sensor noise), which
no least-squares fit of many views averages away as it would noise.

:func:`footprint_albedo` replaces, on the objects that ask for it
(:attr:`polrig.sim.scene.SceneObject.footprint_samples` ``n > 1``), each hit pixel's diffuse
albedo by its mean over ``n x n`` stratified sub-pixel rays, each intersected with the hit's
tangent plane (exact for planes) and looked up in the object's region. Only the pixels at an
edge are sampled (:func:`edge_pixels`: a centre sample with a neighbour of another material or
object); elsewhere the footprint's mean is the centre's. The pBRDF is linear in
the diffuse albedo, so for materials that differ in ``kd`` alone (checked when the object is
made) the mean albedo at the centre ray's geometry is the pixel's area integral of the
texture; the shading's own change across one pixel is left to the centre sample, as before.
A 100 % fill factor is assumed: the sensor's on-chip lens over each pixel gathers the light of
its whole area (Sony's Polarsens forms the polarizer under the on-chip lens layer:
https://www.sony-semicon.co.jp/e/products/IS/industry/technology/polarization.html).
"""

from __future__ import annotations

import numpy as np

from polrig.sim.geometry import rows_times
from polrig.sim.raycast import Hits
from polrig.sim.scene import Scene

#: Smallest ``|cos|`` between a sub-pixel ray and the hit's tangent plane normal for which the
#: plane is intersected; a more grazing pixel keeps its centre sample.
GRAZING_COS = 1e-3


def stratified_offsets(n: int) -> np.ndarray:
    """Offsets ``(n,)`` in pixels of ``n`` strata centres across one pixel, centred on 0:
    ``(k + 0.5) / n - 0.5`` for ``k = 0 .. n-1``."""
    return (np.arange(int(n), dtype=np.float64) + 0.5) / int(n) - 0.5


def edge_pixels(material: np.ndarray) -> np.ndarray:
    """Pixels ``(H, W)`` bool whose centre sample's ``material`` (an index per pixel, ``(H, W)``
    int, any value for background) differs from one of its 8 neighbours'.

    A straight boundary through a pixel's footprint ``[-1/2, 1/2]^2`` passes within ``1/sqrt(2)``
    of its centre, and the neighbour most along the boundary's normal lies at least
    ``cos(22.5 deg) = 0.92`` pixels along it, so it sees the other side: every pixel a boundary
    crosses is found, except across a feature narrower than about one pixel, which the centre
    samples cannot see either.
    """
    m = np.asarray(material)
    h, w = m.shape
    pad = np.pad(m, 1, mode="constant", constant_values=m.min(initial=0) - 1)
    out = np.zeros((h, w), dtype=bool)
    for dy in (0, 1, 2):
        for dx in (0, 1, 2):
            if dy != 1 or dx != 1:
                out |= pad[dy:dy + h, dx:dx + w] != m
    return out


def footprint_albedo(scene: Scene, turntable_deg: float, hits: Hits,
                     kd: np.ndarray) -> np.ndarray:
    """Diffuse albedo ``(M, 3)`` of the hits, the footprint's mean where an object asks for it.

    ``hits`` are the camera rays' hits (:func:`polrig.sim.raycast.surface_hits` of
    :meth:`polrig.sim.geometry.PinholeCamera.ray_directions`, row-major pixel indices), ``kd``
    ``(M, 3)`` their albedo per colour at the pixel centres (unitless, in [0, 1]). Objects with
    ``footprint_samples`` 1 keep ``kd`` unchanged; a new array is returned when any changes.
    """
    objects = [k for k, ob in enumerate(scene.objects)
               if ob.footprint_samples > 1 and ob.region is not None and len(ob.materials) > 1]
    if not objects:
        return kd
    cam = scene.camera
    origin = cam.centre_m
    material = np.full(cam.height * cam.width, -1, dtype=np.int64)
    material[hits.index] = hits.mat_index
    at_edge = edge_pixels(material.reshape(cam.height, cam.width)).reshape(-1)[hits.index]
    out = np.array(kd, dtype=np.float64, copy=True)
    for k in objects:
        ob = scene.objects[k]
        sel = np.nonzero((hits.obj == k) & at_edge)[0]
        if not sel.size:
            continue
        kd_tab = np.array([m.kd for m in ob.materials])
        rot, pos = ob.world_pose(scene.turntable, turntable_deg)
        row, col = np.divmod(hits.index[sel], cam.width)
        p, ng = hits.p[sel], hits.ng[sel]
        plane = np.einsum("ij,ij->i", p - origin, ng)
        offsets = stratified_offsets(ob.footprint_samples)
        total = np.zeros((sel.size, 3))
        ok = np.ones(sel.size, dtype=bool)
        d_cam = np.empty((sel.size, 3))
        d_cam[:, 2] = 1.0
        for dv in offsets:
            d_cam[:, 1] = (row + dv - cam.cy) / cam.fy
            for du in offsets:
                d_cam[:, 0] = (col + du - cam.cx) / cam.fx
                d = rows_times(d_cam, cam.R)  # R^T d_cam: world directions, not unit
                cos = np.einsum("ij,ij->i", d, ng)
                ok &= np.abs(cos) > GRAZING_COS * np.linalg.norm(d, axis=1)
                t = plane / np.where(ok, cos, 1.0)
                p_local = rows_times(origin + t[:, None] * d - pos, rot)  # R^T (p - t)
                total += kd_tab[ob.material_index(p_local)]
        mean = total / offsets.size ** 2
        out[sel[ok]] = mean[ok]
    return out
