"""Views that count (issue 37, item 3): each view weighted by its disparity's information, the
views behind every height counted, and a series measuring better than its widest pair alone."""

from __future__ import annotations

import numpy as np
import pytest

from fractoscope.stereo import tilt_series


def _disparities(tilt_deg, sigma_px, *, points=40_000, seed=0):
    """Disparities to view 0 of random points, each view with its own noise sigma (px)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-300, 300, points)
    z = rng.normal(0, 20, points)
    a, b = tilt_series.coefficients(tilt_deg)
    clean = x * a[:, None] + z * b[:, None]
    noisy = clean + rng.normal(0, 1, clean.shape) * np.asarray(sigma_px)[:, None]
    sigmas = np.broadcast_to(np.asarray(sigma_px, np.float64)[:, None], clean.shape)
    return x, z, noisy, sigmas


def test_views_weighted_by_their_sigma_reach_the_information_limit():
    """A view ten times noisier than the others: weighted by 1/σ² the heights' error is the one
    the views' information b²/σ² allows (as geometry.height_sigma_um states it), while equal
    weights let the noisy view spoil them."""
    tilt_deg = (-5.0, 0.0, 5.0)
    sigma_px = np.array([0.0, 1.0, 0.1])
    x, z, disparities, sigmas = _disparities(tilt_deg, sigma_px)
    weighted, _ = tilt_series.heights_px(x, disparities, tilt_deg, sigmas_px=sigmas)
    equal, _ = tilt_series.heights_px(x, disparities, tilt_deg)
    _, b = tilt_series.coefficients(tilt_deg)
    limit_px = 1 / np.sqrt(np.sum((b[1:] / sigma_px[1:]) ** 2))
    assert np.sqrt(np.mean((weighted - z) ** 2)) == pytest.approx(limit_px, rel=0.03)
    assert np.sqrt(np.mean((equal - z) ** 2)) > 1.5 * limit_px


def test_a_pair_gives_the_same_heights_with_or_without_sigmas():
    tilt_deg = (-5.0, 5.0)
    x, _, disparities, sigmas = _disparities(tilt_deg, [0.0, 0.2])
    weighted, _ = tilt_series.heights_px(x, disparities, tilt_deg, sigmas_px=sigmas)
    direct, _ = tilt_series.heights_px(x, disparities, tilt_deg)
    np.testing.assert_allclose(weighted, direct, rtol=1e-9, atol=1e-9)


def test_views_used_counts_the_views_behind_each_height():
    """Unmatched (NaN) disparities and disparities without a usable sigma count for nothing;
    the reference always counts."""
    disparities = np.array([[0.0, 0.0, 0.0, 0.0], [1.0, np.nan, 1.0, 1.0], [2.0, 2.0, np.nan, 2.0]])
    sigmas = np.array([[1.0] * 4, [0.1, 0.1, 0.1, np.nan], [0.1, 0.1, 0.1, 0.0]])
    np.testing.assert_array_equal(tilt_series.views_used(disparities), [3, 2, 2, 3])
    np.testing.assert_array_equal(tilt_series.views_used(disparities, sigmas_px=sigmas), [3, 2, 2, 1])
    z, _ = tilt_series.heights_px(np.zeros(4), disparities, (-5.0, 0.0, 5.0), sigmas_px=sigmas)
    assert np.isfinite(z[:3]).all() and np.isnan(z[3])  # no view with a usable sigma: no height


@pytest.mark.slow
def test_a_series_measures_better_than_its_widest_pair_and_counts_its_views():
    """A dimple surface at -5, -2.5, 0, 2.5 and 5°, 2 % noise per image: the ±5° pair alone, the
    -5/0/+5° series and all five views of the same images. Over seeds 1, 2, 3 and 5 (640²,
    `python -m benchmarks.views --seeds 1 2 3 5`) the three views measured 0.92-0.98x the pair's
    RMS error and the five 0.89-0.95x (this seed: 0.95x and 0.94x); the margins below hold for
    every seed measured, not for a series that adds nothing (1.00x). On the self-affine surface
    the series add next to nothing (0.98-1.01x), so it is not asserted here. Where every view
    matched, a height rests on all of them."""
    from fractoscope import synthetic
    from fractoscope.sem.image import SemImage
    from fractoscope.stereo.pipeline import compute_series_height_map

    tilt_deg = (-5.0, -2.5, 0.0, 2.5, 5.0)
    surface = synthetic.reference_surface("dimples", 704, seed=5)
    images, truth = synthetic.render_tilt_series(
        surface, pixel_size_um=0.1, tilt_deg=tilt_deg, output_shape=(640, 640), seed=5
    )

    def measured(subset):
        views = [SemImage(images[i], None, 0.1, 0) for i in subset]
        result = compute_series_height_map(views, tilt_deg=[tilt_deg[i] for i in subset])
        return result, synthetic.height_errors(result.z_um, truth, border_px=16).rms_of_range

    pair, pair_rms = measured((0, 4))
    three, three_rms = measured((0, 2, 4))
    five, five_rms = measured((0, 1, 2, 3, 4))
    assert three_rms < 0.985 * pair_rms
    assert five_rms < 0.97 * pair_rms
    for result, views in ((pair, 2), (three, 3), (five, 5)):
        known = np.isfinite(result.z_um)
        assert result.views_used.dtype == np.uint8 and np.all(result.views_used[~known] == 0)
        assert np.all((result.views_used[known] >= 2) & (result.views_used[known] <= views))
        assert np.mean(result.views_used[known] == views) > 0.95
