"""The compiled reference solve (polrig.solve.reference, polrig.solve._reference_kernel) against the
previous numpy implementation (polrig.solve._reference_numpy, the oracle); determinism; memory;
option checks and output-range masking (issue 20, item 8); numba without a cache."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import tracemalloc
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from polrig.errors import ConfigError
from polrig.optics import mueller as mu
from polrig.sensor.noise import SensorModel
from polrig.sensor.stokes import ideal_analyzer_matrix
from polrig.solve import _reference_kernel as kern
from polrig.solve import reference as ref
from polrig.solve._reference_numpy import solve_reference_numpy

A_TOL = (0.01, 0.5, 0.02)
G_TOL = (2.0, 0.006)
ROOT = Path(__file__).resolve().parents[1]


def states(*angles_deg, er=np.inf):
    return mu.polarizer_stokes(np.radians(angles_deg), er)


def noisy_capture(rng, s, c, h, w, rows=None, exclude=0.0, bad=0.0):
    """Noisy samples of random Mueller images with sensor-model variances; ``exclude`` and
    ``bad``: fractions of samples marked invalid and made non-finite."""
    m = rng.normal(size=(c, 3, 3, h, w)) * 300.0
    m[:, 0, 0] = rng.uniform(500.0, 4000.0, (c, h, w))
    mean = ref.forward_measurements(m, s, rows)
    var = SensorModel().variance_dn2(np.clip(mean, 0, None), 10_000.0) + 1.0
    meas = mean + rng.normal(size=mean.shape) * np.sqrt(var)
    valid = rng.random(meas.shape) >= exclude
    nan = rng.random(meas.shape) < bad
    meas[nan] = np.nan
    return meas, var, valid


def assert_agrees(new, old, rtol=1e-9):
    """Identical masks, sample counts and pixel conditions; estimates, sigmas and residuals
    within ``rtol`` of each pixel's scale (the pixel's largest |element|)."""
    np.testing.assert_array_equal(new.mask, old.mask)
    np.testing.assert_array_equal(new.n_samples, old.n_samples)
    np.testing.assert_array_equal(new.pixel_condition, old.pixel_condition)
    assert new.condition_number == old.condition_number
    for name in ("mueller", "sigma", "sigma_noise"):
        a, b = getattr(new, name), getattr(old, name)
        scale = np.abs(b).max(axis=(1, 2), keepdims=True)
        assert np.all(np.abs(a - b) <= rtol * scale), name
    assert np.all(np.abs(new.residual - old.residual) <= rtol * np.maximum(old.residual, 1.0))


CASES = {
    "4 states, all valid": dict(n=(0, 45, 90, 135)),
    "4 states, excluded and NaN samples": dict(n=(0, 45, 90, 135), exclude=0.05, bad=0.02),
    "3 states, excluded samples": dict(n=(0, 60, 120), exclude=0.05),
    "6 partial polarizers": dict(n=(0, 30, 60, 90, 120, 150), er=300.0, exclude=0.03),
    "17 states (two pattern words)": dict(n=tuple(np.linspace(0, 170, 17)), exclude=0.1),
    "per-pixel rows, excluded samples": dict(n=(0, 45, 90, 135), rows=True, exclude=0.05),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.parametrize("tolerances", [False, True])
def test_agrees_with_the_numpy_implementation(case, tolerances):
    cfg = CASES[case]
    rng = np.random.default_rng(zlib.crc32(case.encode()))
    s = states(*cfg["n"], er=cfg.get("er", np.inf))
    c, h, w = 2, 9, 70  # rows longer than a block of lanes, and a partial block
    rows = None
    if cfg.get("rows"):
        rows = ideal_analyzer_matrix()[None, :, :, None, None] * (
            1 + 0.03 * rng.normal(size=(c, 4, 3, h, w)))
    meas, var, valid = noisy_capture(rng, s, c, h, w, rows, cfg.get("exclude", 0.0),
                                     cfg.get("bad", 0.0))
    kw = dict(analyzer_tolerance=A_TOL, generator_tolerance=G_TOL) if tolerances else {}
    new = ref.solve_reference(s, meas, var, valid, rows, dtype=np.float64, **kw)
    old = solve_reference_numpy(s, meas, var, valid, rows, dtype=np.float64, **kw)
    assert_agrees(new, old)
    # the case exercises what it says: masks of every kind occur where samples are removed
    if cfg.get("exclude"):
        assert np.any(new.mask & ref.SATURATED) and np.any(new.mask == 0)
    assert (new.sigma_noise is new.sigma) == (not tolerances)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(3, 8), per_pixel=st.booleans(),
       exclude=st.sampled_from([0.0, 0.1, 0.4]), tol=st.booleans(),
       f32=st.booleans())
def test_agrees_with_the_numpy_implementation_hypothesis(seed, n, per_pixel, exclude, tol, f32):
    rng = np.random.default_rng(seed)
    ang = np.linspace(0, 180, n, endpoint=False) + rng.uniform(-5, 5, n)
    s = states(*ang, er=rng.uniform(50, 1e4)) * rng.uniform(0.5, 2.0, (n, 1))
    c, h, w = 1, 3, int(rng.integers(1, 140))
    rows = None
    if per_pixel:
        rows = ideal_analyzer_matrix()[:, :, None, None] * (1 + 0.05 * rng.normal(size=(4, 3, h, w)))
    meas, var, valid = noisy_capture(rng, s, c, h, w, rows, exclude)
    if f32:  # float32 inputs are read as they are: the same numbers as their float64 values
        meas, var = meas.astype(np.float32), var.astype(np.float32)
    kw = dict(analyzer_tolerance=A_TOL, generator_tolerance=G_TOL) if tol else {}
    new = ref.solve_reference(s, meas, var, valid, rows, dtype=np.float64, **kw)
    old = solve_reference_numpy(s, meas.astype(np.float64), var.astype(np.float64), valid, rows,
                                dtype=np.float64, **kw)
    assert_agrees(new, old)


def test_float32_output_agrees_and_extreme_samples_give_the_same_masks():
    """Default float32 output; dark, saturated, all-excluded and non-positive-variance pixels."""
    rng = np.random.default_rng(3)
    s = states(0, 45, 90, 135)
    meas, var, valid = noisy_capture(rng, s, 3, 20, 33, exclude=0.02, bad=0.01)
    meas[..., 0, :5] = rng.normal(size=meas[..., 0, :5].shape)  # dark
    valid[:, 1, :, 3, :4] = False  # nothing left
    var[2, 2, 1, 5, 5] = 0.0
    var[:, 0, :, 6, 6] = -1.0
    new = ref.solve_reference(s, meas, var, valid, analyzer_tolerance=A_TOL)
    old = solve_reference_numpy(s, meas, var, valid, analyzer_tolerance=A_TOL)
    assert new.mueller.dtype == np.float32
    assert_agrees(new, old, rtol=1e-6)
    counts = new.reason_counts()
    assert all(counts[k] > 0 for k in ("dark", "saturated", "ill_conditioned", "nonfinite"))


def test_kernel_mask_bits_are_the_public_ones():
    assert (kern._DARK, kern._SATURATED, kern._ILL_CONDITIONED, kern._NONFINITE) == (
        ref.DARK, ref.SATURATED, ref.ILL_CONDITIONED, ref.NONFINITE)


# ---------------------------------------------------------------------------- determinism
def test_bit_identical_for_any_tile_size_and_thread_count(monkeypatch):
    rng = np.random.default_rng(8)
    s = states(0, 45, 90, 135)
    meas, var, valid = noisy_capture(rng, s, 3, 17, 101, exclude=0.05)
    meas = meas.astype(np.float32)
    runs = []
    for threads, chunk in ((1, 4096), (2, 4096), (3, 7), (2, 250), (1, 10**6)):
        monkeypatch.setattr(kern, "THREADS", threads)
        runs.append(ref.solve_reference(s, meas, var, valid, analyzer_tolerance=A_TOL,
                                        generator_tolerance=G_TOL, chunk_pixels=chunk))
    for r in runs[1:]:
        for name in ("mueller", "sigma", "sigma_noise", "residual", "mask", "pixel_condition",
                     "n_samples"):
            assert getattr(r, name).tobytes() == getattr(runs[0], name).tobytes(), name


def test_shared_rows_and_the_same_rows_per_pixel_agree_bit_for_bit():
    rng = np.random.default_rng(9)
    s = states(0, 45, 90, 135)
    meas, var, valid = noisy_capture(rng, s, 2, 5, 70, exclude=0.05)
    rows = np.broadcast_to(ideal_analyzer_matrix()[None, :, :, None, None], (2, 4, 3, 5, 70))
    kw = dict(analyzer_tolerance=A_TOL, generator_tolerance=G_TOL, dtype=np.float64)
    shared = ref.solve_reference(s, meas, var, valid, **kw)
    per_pixel = ref.solve_reference(s, meas, var, valid, rows, **kw)
    for name in ("mueller", "sigma", "sigma_noise", "residual", "mask", "pixel_condition"):
        assert getattr(shared, name).tobytes() == getattr(per_pixel, name).tobytes(), name


def test_float32_inputs_are_not_copied():
    """A float32 capture is read in place: the solve allocates its outputs plus per-thread
    tile buffers, far less than one float64 copy of the samples."""
    rng = np.random.default_rng(4)
    s = states(0, 45, 90, 135)
    c, h, w = 3, 256, 512
    meas = rng.uniform(100, 200, (4, c, 4, h, w)).astype(np.float32)
    var = np.ones_like(meas)
    valid = np.ones(meas.shape, bool)
    ref.solve_reference(s, meas[..., :2, :], var[..., :2, :], valid[..., :2, :])  # compile
    tracemalloc.start()
    try:
        res = ref.solve_reference(s, meas, var, valid)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    outputs = sum(a.nbytes for a in (res.mueller, res.sigma, res.residual, res.mask,
                                     res.pixel_condition, res.n_samples))
    assert peak < outputs + meas.nbytes // 2 < 2 * meas.nbytes  # a float64 copy: 2 x nbytes


def test_views_and_contiguous_arrays_share_one_compiled_kernel():
    """numba compiles a kernel once per argument type, and an array's type holds its layout
    and writability: contiguous samples and prior, then a band view, a read-only broadcast
    and a strided state matrix of the same dtype, run on the same machine code (each extra
    version cost up to 25 s of compile at a fresh install's first capture)."""
    from polrig.solve.hybrid import solve_hybrid

    rng = np.random.default_rng(6)
    s = np.ascontiguousarray(states(0, 60, 120))
    meas, var, valid = (np.asarray(a, t) for a, t in zip(noisy_capture(rng, s, 1, 12, 70),
                                                         (np.float32, np.float32, bool)))
    mean, sigma = np.zeros((1, 3, 3, 12, 70), np.float32), np.ones((1, 3, 3, 12, 70), np.float32)
    kernels = (kern.load_tile, kern.load_prior, kern.solve_blocks, kern.store_tile)

    def solve(s, meas, var, valid, mean, sigma):
        ref.solve_reference(s, meas, var, valid)
        solve_hybrid(s, meas, var, valid, prior_mean=mean, prior_sigma=sigma, seen_state=0)
        return [set(k.signatures) for k in kernels]

    first = solve(s, meas, var, valid, mean, sigma)
    strided_s = np.concatenate([s, s], 1)[:, :3]
    read_only = valid.copy()
    read_only.flags.writeable = False
    assert not strided_s.flags.c_contiguous
    band = meas[..., 2:9, :]
    again = solve(strided_s, band, np.broadcast_to(var[..., 2:3, :], band.shape), read_only[..., 2:9, :],
                  mean[..., 2:9, :], np.broadcast_to(np.float32(1.0), mean[..., 2:9, :].shape))
    assert again == first


def test_a_large_strided_capture_is_read_in_place(monkeypatch):
    """Past :data:`KERNEL_COPY_LIMIT` a strided capture (a band view of a larger array) is not
    copied for the kernels: the solve's peak stays far below one copy of its samples (here the
    limit is lowered to 1 MiB to keep the arrays small)."""
    monkeypatch.setattr(ref, "KERNEL_COPY_LIMIT", 2**20)
    rng = np.random.default_rng(5)
    s = states(0, 45, 90, 135)
    meas = rng.uniform(100, 200, (4, 3, 4, 130, 256)).astype(np.float32)
    var = np.ones_like(meas)
    band_m, band_v = meas[..., 1:129, :], var[..., 1:129, :]
    assert not band_m.flags.c_contiguous and band_m.nbytes > ref.KERNEL_COPY_LIMIT
    ref.solve_reference(s, band_m, band_v)  # compile (the strided inputs' own version)
    tracemalloc.start()
    try:
        res = ref.solve_reference(s, band_m, band_v)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    outputs = sum(a.nbytes for a in (res.mueller, res.sigma, res.residual, res.mask,
                                     res.pixel_condition, res.n_samples))
    assert peak < outputs + band_m.nbytes  # copies of the samples and variances: 2 x nbytes
    np.testing.assert_array_equal(res.mueller, ref.solve_reference(s, band_m.copy(), band_v.copy()).mueller)


# ---------------------------------------------------------------------------- options (item 8)
@pytest.mark.parametrize("kw,match", [
    (dict(max_condition=float("nan")), "max_condition must be >= 1"),
    (dict(max_condition=-1.0), "max_condition must be >= 1"),
    (dict(max_condition=0.5), "max_condition must be >= 1"),
    (dict(max_condition="big"), "max_condition must be a number"),
    (dict(min_snr=float("nan")), "min_snr must be finite and >= 0"),
    (dict(min_snr=float("inf")), "min_snr must be finite and >= 0"),
    (dict(min_snr=-1.0), "min_snr must be finite and >= 0"),
    (dict(dtype=np.int32), "dtype must be float32 or float64"),
    (dict(dtype=np.float16), "dtype must be float32 or float64"),
    (dict(dtype="not a dtype"), "dtype must be float32 or float64"),
    (dict(chunk_pixels=0), "chunk_pixels must be a positive integer"),
])
def test_bad_options_are_config_errors(kw, match):
    s = states(0, 45, 90, 135)
    m = np.ones((4, 1, 4, 2, 2))
    with pytest.raises(ConfigError, match=match):
        ref.solve_reference(s, m, m, **kw)
    if "max_condition" in kw:
        with pytest.raises(ConfigError, match=match):
            ref.validate_states(s, kw["max_condition"])


def test_no_limit_on_the_condition_number_is_allowed():
    s = states(0, 10, 20)  # condition 96: refused by the default limit of 50
    meas = ref.forward_measurements(np.eye(3)[None, :, :, None, None] * 1000.0, s)
    res = ref.solve_reference(s, meas, np.ones_like(meas), max_condition=np.inf,
                              dtype=np.float64)
    assert np.all(res.mask == 0) and np.allclose(res.mueller[0, :, :, 0, 0], np.eye(3) * 1000)


def test_results_beyond_float32_are_masked_not_inf():
    """Samples near float64's range solve to Mueller elements beyond float32's: the pixel is
    ILL_CONDITIONED with zero outputs (finite), not inf with mask 0; float64 output keeps it."""
    s = states(0, 45, 90, 135)
    m = np.zeros((1, 3, 3, 1, 3))
    m[0, :, :, 0, 0] = np.eye(3) * 1000.0
    m[0, :, :, 0, 1] = np.eye(3) * 1e39  # beyond float32 (3.4e38)
    m[0, :, :, 0, 2] = np.eye(3) * 1e37  # fits, but its residual (w r^2) does not
    meas = ref.forward_measurements(m, s)
    var = np.ones_like(meas)
    var[..., 2] = 1e-60
    meas[0, 0, 0, 0, 2] *= 1.0 + 1e-6
    r32 = ref.solve_reference(s, meas, var)
    for arr in (r32.mueller, r32.sigma, r32.residual):
        assert np.isfinite(arr).all()
    assert r32.mask[0, 0, 0] == 0
    assert r32.mask[0, 0, 1] == ref.ILL_CONDITIONED and r32.mask[0, 0, 2] == ref.ILL_CONDITIONED
    assert np.all(r32.mueller[0, :, :, 0, 1:] == 0) and np.all(r32.residual[0, 0, 1:] == 0)
    r64 = ref.solve_reference(s, meas, var, dtype=np.float64)
    assert np.all(r64.mask == 0)
    assert r64.mueller[0, 0, 0, 0, 1] == pytest.approx(1e39)
    assert r64.residual[0, 0, 2] > np.finfo(np.float32).max


def test_integer_samples_are_accepted_as_numbers():
    s = states(0, 45, 90, 135)
    meas = np.round(ref.forward_measurements(np.eye(3)[None, :, :, None, None] * 1000.0, s))
    res = ref.solve_reference(s, meas.astype(np.uint16), np.ones(meas.shape, np.int32),
                              dtype=np.float64)
    ref64 = ref.solve_reference(s, meas, np.ones(meas.shape), dtype=np.float64)
    np.testing.assert_array_equal(res.mueller, ref64.mueller)


# ---------------------------------------------------------------------------- numba cache
def test_works_where_numba_has_no_cache_directory(tmp_path):
    """With no writable cache location the kernels compile in memory: import and solve
    succeed (a fresh process; numba offered only a cache directory that cannot be created)."""
    blocker = tmp_path / "file"
    blocker.write_text("")
    # NUMBA_OPT=0: the compile without a cache is what is tested, not the optimised code
    # (about 40 % less compile time)
    env = dict(os.environ, NUMBA_CACHE_DIR=str(blocker / "cache"), NUMBA_OPT="0",
               NUMBA_CACHE_LOCATOR_CLASSES="UserProvidedCacheLocator",
               PYTHONPATH=str(ROOT) + os.pathsep + os.environ.get("PYTHONPATH", ""))
    code = textwrap.dedent("""
        import numpy as np
        from polrig.solve import _reference_kernel as kern, reference as ref
        from polrig.optics import mueller as mu
        assert not kern.solve_blocks._cache.__class__.__name__.endswith("FunctionCache")
        s = mu.polarizer_stokes(np.radians([0, 45, 90, 135]))
        meas = ref.forward_measurements(np.eye(3)[None, :, :, None, None] * 100.0, s)
        res = ref.solve_reference(s, meas, np.ones_like(meas), dtype=np.float64)
        assert np.allclose(res.mueller[0, :, :, 0, 0], 100 * np.eye(3)) and res.mask.max() == 0
        print("ok")
    """)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True,
                         timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert out.stdout.strip() == "ok"
    assert not (blocker / "cache").exists()
