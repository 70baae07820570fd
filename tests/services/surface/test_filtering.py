"""Filtering a height map before meshing: peaks out, holes filled near measured points, steps kept."""

import numpy as np
import pytest

from fractoscope.surface import filtering


def test_isolated_spike_is_removed_and_a_step_is_kept():
    rng = np.random.default_rng(0)
    z = np.where(np.arange(100)[None, :] < 50, 0.0, 2.0) + rng.normal(0, 0.01, (100, 100))
    z = z.astype(np.float32)
    z[20, 20] += 30.0
    result = filtering.filter_heights(z, smoothing_um=0.05)
    assert result.report.outliers_removed == 1
    assert abs(result.z_um[20, 20]) < 0.1 and result.filled[20, 20]
    step = np.median(result.z_um[:, 52:60]) - np.median(result.z_um[:, 40:48])
    assert step == pytest.approx(2.0, abs=0.02)
    assert np.abs(result.z_um[:, 51] - 2.0).max() < 0.1 and np.abs(result.z_um[:, 48] - 0.0).max() < 0.1
    assert result.report.points_smoothed > 5000
    assert np.std(result.z_um[:, 5:45]) < np.std(z[:, 5:45][np.abs(z[:, 5:45]) < 1])


def test_holes_are_filled_only_near_measured_points():
    z = np.zeros((120, 120), np.float32)
    z[10:14, 10:14] = np.nan  # small hole: filled
    z[50:100, 50:100] = np.nan  # large hole: only its rim is filled
    result = filtering.filter_heights(z, max_fill_distance_px=8)
    assert np.isfinite(result.z_um[10:14, 10:14]).all()
    assert np.isnan(result.z_um[60:90, 60:90]).all()
    assert np.isfinite(result.z_um[50:58, 50:100]).all()
    assert result.report.holes_filled == int(result.filled.sum())
    assert result.report.outliers_removed == 0
