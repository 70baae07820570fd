"""The ZNCC primitives against direct computations."""

import numpy as np
import pytest

from fractoscope.stereo import correlation


def _noise(shape, seed):
    return correlation.normalized(np.random.default_rng(seed).normal(size=shape).astype(np.float32))


@pytest.mark.parametrize("window_px", [3, 5, 9, 15, 25])
def test_box_mean_is_the_mean_over_each_window_with_edges_reflected(window_px):
    values = _noise((40, 57), seed=window_px)
    half = window_px // 2
    padded = np.pad(values.astype(np.float64), half, mode="symmetric")  # OpenCV's BORDER_REFLECT
    windows = np.lib.stride_tricks.sliding_window_view(padded, (window_px, window_px))
    np.testing.assert_allclose(correlation.box_mean(values, window_px), windows.mean(axis=(2, 3)), atol=2e-6)


@pytest.mark.parametrize("shape", [(48, 64), (6, 7)])  # (6, 7): windows reach beyond the far edge
@pytest.mark.parametrize("window_px", [5, 9])
def test_scores_within_one_px_are_the_general_search_at_radius_one(window_px, shape):
    left, warped = _noise(shape, seed=1), _noise(shape, seed=2)
    stats = correlation.window_stats(left, window_px)
    general = list(correlation.zncc_scores_by_shift(left, stats, warped, window_px, 1))
    for fused, expected in zip(
        correlation.zncc_scores_within_one_px(left, stats, warped, window_px), general, strict=True
    ):
        np.testing.assert_allclose(fused, expected, atol=1e-6)


def test_the_score_peaks_at_one_at_the_shift_that_matches():
    left = _noise((40, 60), seed=3)
    warped = np.roll(left, 1, axis=1)  # warped[col] = left[col - 1]: the +1 px shift matches
    before, centre, after = correlation.zncc_scores_within_one_px(left, correlation.window_stats(left, 9), warped, 9)
    inner = (slice(5, -5), slice(6, -6))
    np.testing.assert_allclose(after[inner], 1.0, atol=1e-5)
    assert np.all(centre[inner] < 0.5) and np.all(before[inner] < 0.5)
