"""Tilt self-calibration from three or more views: known angles recovered from disparities."""

from __future__ import annotations

import numpy as np
import pytest

from fractoscope import stereo_geometry, tilt_series


def _views(true_tilt_deg, *, noise_px=0.05, points=20_000, seed=0):
    rng = np.random.default_rng(seed)
    x = rng.uniform(-320, 320, points)
    z = rng.normal(0, 25, points)
    angles = np.radians(true_tilt_deg)
    offsets = rng.normal(0, 2, len(angles))
    seen = np.stack([x * np.cos(a) + z * np.sin(a) + o for a, o in zip(angles, offsets)])
    disparities = seen - seen[0] + rng.normal(0, noise_px, seen.shape)
    return x, z, seen[0], disparities


@pytest.mark.parametrize("nominal", [(-5.3, 0.4, 4.6), (-5.0, 0.5, 5.5), (-4.5, -0.5, 5.0)])
def test_tilt_differences_are_recovered_from_wrong_nominal_angles(nominal):
    true = np.array([-5.0, 0.0, 5.0])
    _, _, seen_first, disparities = _views(true)
    estimate = tilt_series.estimate_tilts(seen_first, disparities, nominal)
    assert estimate.tilt_deg[0] == nominal[0]  # the reference keeps its tilt: only differences are observable
    assert np.abs(np.diff(estimate.tilt_deg) - np.diff(true)).max() < 0.01
    assert 0 < estimate.sigma_deg[1] < 0.01 and estimate.residual_px == pytest.approx(0.05 / np.sqrt(2), rel=0.3)


def test_two_views_reduce_to_the_pair_formula():
    tilts = (-4.0, 6.0)
    _, _, seen_first, disparities = _views(np.array(tilts), noise_px=0.0)
    z_px, _ = tilt_series.heights_px(seen_first, disparities, tilts)
    pair = stereo_geometry.heights_um(seen_first, disparities[1], tilt_deg=tilts, pixel_size_um=1.0)
    assert np.allclose(z_px - z_px.mean(), pair - pair.mean(), atol=1e-9)


def test_two_views_cannot_be_calibrated():
    _, _, seen_first, disparities = _views(np.array([-5.0, 5.0]))
    with pytest.raises(ValueError, match="three or more"):
        tilt_series.estimate_tilts(seen_first, disparities, (-5.0, 5.0))
