"""Scoring a result against the simulator's truth (polrig.processing.score_against_truth)."""

from __future__ import annotations

import math

import numpy as np

from polrig.processing import format_score, score_against_truth
from polrig.reference import ReferenceResult


def _result(mueller: np.ndarray, sigma: float = 0.1) -> ReferenceResult:
    c, h, w = mueller.shape[0], mueller.shape[-2], mueller.shape[-1]
    zeros = np.zeros((c, h, w), np.float32)
    return ReferenceResult(mueller.astype(np.float32), np.full_like(mueller, sigma, np.float32), zeros,
                           np.zeros((c, h, w), np.uint8), 1.0, zeros + 1.0, np.full((c, h, w), 4, np.uint16))


def _depolarizer(value: float, shape=(3, 3, 3, 4, 5)) -> np.ndarray:
    m = np.zeros(shape)
    m[:, 0, 0] = value
    return m


def test_psnr_is_peak_over_rmse():
    truth = _depolarizer(2.0)
    result = _result(truth + 0.02)
    score = score_against_truth(result, truth)
    assert math.isclose(score["rmse"], 0.02, rel_tol=1e-5)
    assert math.isclose(score["psnr_db"], 20 * math.log10(2.0 / 0.02), rel_tol=1e-5)
    assert score["pixels_compared"] == 3 * 4 * 5
    assert "PSNR 40.0 dB" in format_score(score)


def test_exact_result_scores_inf():
    truth = _depolarizer(2.0)
    score = score_against_truth(_result(truth), truth)
    assert score["psnr_db"] == float("inf") and score["rmse"] == 0.0
    assert "PSNR inf" in format_score(score)


def test_dark_truth_has_no_psnr_but_keeps_the_error():
    """An object turned so that only its unlit back faces the camera: every compared truth
    pixel is 0. The PSNR has no peak; the score must say so, not raise (a turntable capture
    used to abort here)."""
    truth = _depolarizer(0.0)
    score = score_against_truth(_result(truth + 0.05), truth)
    assert score["psnr_db"] is None
    assert math.isclose(score["rmse"], 0.05, rel_tol=1e-5)
    line = format_score(score)
    assert "PSNR n/a" in line and "RMSE 0.05" in line


def test_object_mask_limits_the_pixels():
    truth = _depolarizer(1.0)
    obj = np.zeros((4, 5), bool)
    obj[1:3, 1:4] = True
    score = score_against_truth(_result(truth), truth, obj)
    assert score["pixels_compared"] == 3 * 6
    empty = score_against_truth(_result(truth), truth, np.zeros((4, 5), bool))
    assert empty["pixels_compared"] == 0 and empty["psnr_db"] is None
    assert format_score(empty) == "no pixels to score"
