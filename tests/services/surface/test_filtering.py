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


def test_spikes_steeper_than_the_pair_measures_go_and_steps_stay():
    """A 3 px pit 9 µm deep along a measured area's edge (as the pollen substrate had) and a 2 px
    peak: a ±3° pair at 0.056 µm/px (slope 9.6) cannot see such flanks, so the filter takes them
    out; a 5 µm step, as steep but with two wide plateaus, and the gentle bumps stay as measured."""
    pixel_size_um, max_slope = 0.056, 9.6
    rows, cols = np.mgrid[0:80, 0:120]
    z = (0.2 * np.sin(cols / 7.0) + np.where(cols >= 60, 5.0, 0.0)).astype(np.float32)
    z[:, 100:] = np.nan  # the measured area ends at column 100
    z[30:33, 97:100] = -9.0  # a pit at its edge
    z[50:52, 20:22] += 6.0  # a peak on the plateau
    result = filtering.filter_heights(z, max_slope=max_slope, pixel_size_um=pixel_size_um)
    assert result.report.outliers_removed == 9 + 4
    assert result.filled[30:33, 97:100].all() and result.filled[50:52, 20:22].all()
    untouched = np.isfinite(z) & ~result.filled
    assert untouched.sum() == np.isfinite(z).sum() - 13 and np.array_equal(result.z_um[untouched], z[untouched])
    without = filtering.filter_heights(z)  # the isolated-peak test alone keeps both
    assert without.report.outliers_removed == 0
