"""Stokes bases and basis changes (polrig.optics.bases) against their definitions and physics."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from polrig.optics import bases as frames
from polrig.optics import mueller as mu

finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)
vec = arrays(np.float64, (3,), elements=finite)
vecs = arrays(np.float64, (8, 3), elements=finite)


def _nonzero(v):
    return np.linalg.norm(v, axis=-1) > 1e-6


def _assert_frame_ok(f: frames.StokesFrame, atol=1e-12):
    for a in (f.x, f.y, f.k):
        assert np.all(np.isfinite(a))
        np.testing.assert_allclose(np.linalg.norm(a, axis=-1), 1.0, atol=atol)
    np.testing.assert_allclose(frames.dot(f.x, f.k), 0.0, atol=atol)
    np.testing.assert_allclose(frames.dot(f.y, f.k), 0.0, atol=atol)
    np.testing.assert_allclose(frames.dot(f.x, f.y), 0.0, atol=atol)
    # right-handed: x cross y = k
    np.testing.assert_allclose(np.cross(f.x, f.y), f.k, atol=atol)


@settings(max_examples=200, deadline=None)
@given(vecs, vecs)
def test_frames_are_right_handed_orthonormal(k, ref):
    f = frames.frame(k, ref)
    ok = _nonzero(k)
    _assert_frame_ok(frames.StokesFrame(f.x[ok], f.y[ok], f.k[ok]))
    # x lies in the plane of k and the reference where the reference is usable
    kk = k[ok] / np.linalg.norm(k[ok], axis=-1, keepdims=True)
    r = ref[ok] / np.maximum(np.abs(ref[ok]).max(axis=-1, keepdims=True), 1e-300)
    rperp = r - frames.dot(r, kk)[:, None] * kk
    usable = np.linalg.norm(rperp, axis=-1) > 1e-6 * np.maximum(np.linalg.norm(r, axis=-1), 1e-300)
    if usable.any():
        expected = rperp[usable] / np.linalg.norm(rperp[usable], axis=-1, keepdims=True)
        np.testing.assert_allclose(f.x[ok][usable], expected, atol=1e-9)


@settings(max_examples=200, deadline=None)
@given(vecs)
def test_stokes_basis_orthonormal(k):
    ok = _nonzero(k)
    x = frames.stokes_basis(k)
    assert np.all(np.isfinite(x))
    kk = k[ok] / np.linalg.norm(k[ok], axis=-1, keepdims=True)
    np.testing.assert_allclose(np.linalg.norm(x[ok], axis=-1), 1.0, atol=1e-12)
    np.testing.assert_allclose(frames.dot(x[ok], kk), 0.0, atol=1e-12)


def test_degenerate_references_fall_back_without_nan():
    k = np.array([[0.0, 0, 1], [0, 0, -1], [0.3, -0.2, 0.9], [1, 0, 0], [0, 0, 1], [0, 0, 1]])
    ref = np.array([[0.0, 0, 5], [0, 0, 1], [0.3, -0.2, 0.9], [np.nan, 0, 0], [0, 0, 0], [np.inf, 1, 0]])
    x = frames.basis_from_reference(k, ref)
    np.testing.assert_allclose(x, frames.stokes_basis(k), atol=1e-15)
    # zero / non-finite directions give a finite frame (callers mask them)
    f = frames.frame(np.array([[0.0, 0, 0], [np.nan, 1, 0]]), [1.0, 0, 0])
    assert np.all(np.isfinite(f.x)) and np.all(np.isfinite(f.y)) and np.all(np.isfinite(f.k))
    np.testing.assert_array_equal(frames.valid_direction(np.array([[0.0, 0, 0], [np.nan, 1, 0], [1, 0, 0]])),
                                  [False, False, True])


def test_bad_shapes_raise_clear_errors():
    with pytest.raises(ValueError, match="trailing axis of length 3"):
        frames.stokes_basis(np.zeros((4, 2)))
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\) or \(\.\.\., 4, 4\)"):
        frames.rotate_mueller_basis(np.zeros((2, 5)), [0, 0, 1.0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 0, 0], [1, 0, 0])


def test_rig_frames_central_ray_match_image_convention():
    # Camera (OpenCV) looks along +Z; the ray from the surface to the camera is -Z.
    f = frames.emergent_frame(np.array([0.0, 0.0, -1.0]), camera_x_axis=np.array([1.0, 0, 0]))
    np.testing.assert_allclose(f.x, [1, 0, 0])
    np.testing.assert_allclose(f.y, [0, -1, 0])  # camera -Y: image up
    np.testing.assert_allclose(f.k, [0, 0, -1])
    # Light at +X of the object: wi points to +X, light travels along -X.
    g = frames.incident_frame(np.array([2.0, 0, 0]), stage_zero_axis=np.array([0.0, 1, 0]))
    np.testing.assert_allclose(g.k, [-1, 0, 0])
    np.testing.assert_allclose(g.x, [0, 1, 0])
    np.testing.assert_allclose(g.y, np.cross([-1, 0, 0], [0, 1, 0]))
    # Per-pixel directions with one axis broadcast; an off-axis ray keeps x in the X-k plane.
    wo = np.array([[0.0, 0, -1], [0.2, -0.1, -0.97]])
    e = frames.emergent_frame(wo, [1.0, 0, 0])
    _assert_frame_ok(e)
    np.testing.assert_allclose(frames.dot(np.cross([1.0, 0, 0], e.k), e.x), 0.0, atol=1e-12)


def test_rotate_stokes_basis_documented_example():
    # Mitsuba's mueller.h example: horizontal [1,1,0,0] in basis [1,0,0] reads as +45 deg
    # [1,0,1,0] in the basis [0.707,-0.707,0] (forward +z).
    r = frames.rotate_stokes_basis([0, 0, 1.0], [1.0, 0, 0], [np.sqrt(0.5), -np.sqrt(0.5), 0])
    np.testing.assert_allclose(r @ [1, 1, 0, 0], [1, 0, 1, 0], atol=1e-15)
    # and it is polrig.optics.mueller.rotator of the signed angle
    ang = frames.rotation_angle([0, 0, 1.0], [1.0, 0, 0], [np.sqrt(0.5), -np.sqrt(0.5), 0])
    np.testing.assert_allclose(ang, -np.pi / 4)
    np.testing.assert_allclose(r, mu.rotator(ang), atol=1e-15)


def _stokes_of_field(e, x, y):
    """Fully linearly polarized unit Stokes vector of a field along ``e`` in basis (x, y)."""
    psi = np.arctan2(frames.dot(e, y), frames.dot(e, x))
    return np.stack([np.ones_like(psi), np.cos(2 * psi), np.sin(2 * psi), np.zeros_like(psi)], axis=-1)


@settings(max_examples=100, deadline=None)
@given(vecs, vecs, vecs, vecs)
def test_basis_change_preserves_the_physical_field(k, ra, rb, ef):
    ok = _nonzero(k)
    k, ra, rb, ef = k[ok], ra[ok], rb[ok], ef[ok]
    fa, fb = frames.frame(k, ra), frames.frame(k, rb)
    e = ef - frames.dot(ef, fa.k)[..., None] * fa.k
    usable = np.linalg.norm(e, axis=-1) > 1e-6
    fa = frames.StokesFrame(*(a[usable] for a in fa))
    fb = frames.StokesFrame(*(a[usable] for a in fb))
    e = e[usable]
    s_a, s_b = _stokes_of_field(e, fa.x, fa.y), _stokes_of_field(e, fb.x, fb.y)
    r = frames.rotate_stokes_basis(fa.k, fa.x, fb.x)
    np.testing.assert_allclose(mu.apply(r, s_a), s_b, atol=1e-9)


@settings(max_examples=100, deadline=None)
@given(vecs, vecs, vecs, vecs, vecs, st.floats(0, np.pi))
def test_rotate_mueller_basis_matches_rebuilding_the_element(kin, ra, rb, rc, rd, angle):
    """A polarizer at a physical axis, written in one pair of bases and moved to another, equals
    the same polarizer written directly in the other pair (both sides share k here)."""
    ok = _nonzero(kin)
    k = kin[ok]
    fa, fb = frames.frame(k, ra[ok]), frames.frame(k, rb[ok])
    m_a = mu.polarizer_at(np.full(len(k), angle))  # axis at `angle` from fa.x
    axis = np.cos(angle) * fa.x + np.sin(angle) * fa.y
    angle_b = np.arctan2(frames.dot(axis, fb.y), frames.dot(axis, fb.x))
    m_b = mu.polarizer_at(angle_b)
    moved = frames.rotate_mueller_basis(m_a, k, fa.x, fb.x, k, fa.x, fb.x)
    np.testing.assert_allclose(moved, m_b, atol=1e-9)
    # 3x3 blocks rotate the same way
    np.testing.assert_allclose(frames.rotate_mueller_basis(m_a[..., :3, :3], k, fa.x, fb.x, k, fa.x, fb.x),
                               m_b[..., :3, :3], atol=1e-9)


def test_rotate_rows_cols_equal_matrix_products():
    rng = np.random.default_rng(3)
    m = rng.normal(size=(7, 4, 4))
    th = rng.uniform(-3, 3, size=7)
    c, s = np.cos(2 * th), np.sin(2 * th)
    np.testing.assert_allclose(frames.rotate_rows(m, c, s), mu.rotator(th) @ m, atol=1e-14)
    np.testing.assert_allclose(frames.rotate_cols(m, c, s), m @ np.swapaxes(mu.rotator(th), -1, -2), atol=1e-14)
