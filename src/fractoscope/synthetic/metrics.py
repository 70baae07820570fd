"""How a measured height map recovers a known surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fractoscope.surface import roughness


@dataclass(frozen=True)
class HeightErrors:
    """Measured heights against the truth, away from a border.

    valid_fraction: share of the inner pixels with a height.
    rms_of_range: RMS error after the mean offset, as a fraction of the true height range.
    sa_relative: Sa (after a plane fit) measured / true - 1, both over the valid pixels.
    """

    valid_fraction: float
    rms_of_range: float
    sa_relative: float


def height_errors(z_um: np.ndarray, truth_um: np.ndarray, *, border_px: int = 16) -> HeightErrors:
    """How `z_um` (rows, cols, NaN unknown, any constant offset) recovers `truth_um`, µm."""
    inner = np.zeros(truth_um.shape, bool)
    inner[border_px:-border_px, border_px:-border_px] = True
    valid = np.isfinite(z_um) & inner
    error = z_um[valid] - truth_um[valid]
    error = error - error.mean()
    span = np.ptp(truth_um[inner])
    sa_measured = roughness.height_parameters_after_plane(np.where(valid, z_um, np.nan))["Sa"]
    sa_true = roughness.height_parameters_after_plane(np.where(valid, truth_um, np.nan))["Sa"]
    return HeightErrors(float(valid[inner].mean()), float(np.sqrt(np.mean(error**2)) / span), float(sa_measured / sa_true - 1.0))
