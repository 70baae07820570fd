"""Profiles: sample positions along a polyline (their parameters: `profile_parameters`)."""

from __future__ import annotations

import numpy as np


def polyline_positions(points_um: np.ndarray, *, spacing_um: float) -> tuple[np.ndarray, np.ndarray]:
    """Positions every `spacing_um` along a polyline (N, 2) of (x, y) µm, its vertices included.
    Returns ((M, 2) positions µm, (M,) distances along the line µm)."""
    points = np.asarray(points_um, np.float64)
    if points.ndim != 2 or points.shape[1] != 2 or len(points) < 2:
        raise ValueError("a profile needs at least two (x, y) points")
    if not spacing_um > 0:
        raise ValueError("spacing must be positive")
    segment_lengths = np.hypot(*np.diff(points, axis=0).T)
    starts = np.concatenate([[0.0], np.cumsum(segment_lengths)])
    total = starts[-1]
    if total <= 0:
        raise ValueError("the profile's points are all the same")
    distances = np.union1d(np.arange(0.0, total, spacing_um), starts)
    x = np.interp(distances, starts, points[:, 0])
    y = np.interp(distances, starts, points[:, 1])
    return np.column_stack([x, y]), distances
