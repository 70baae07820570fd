"""How a measured height map recovers a known surface."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fractoscope.surface import roughness
from fractoscope.synthetic.rendering import visible_sheet_px


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
    return HeightErrors(
        float(valid[inner].mean()), float(np.sqrt(np.mean(error**2)) / span), float(sa_measured / sa_true - 1.0)
    )


def hidden_in_second_view(z_seen_um: np.ndarray, *, pixel_size_um: float, tilt_deg: tuple[float, float]) -> np.ndarray:
    """Which pixels of a rendered pair's first image show points that its second view cannot see
    (a wall in front of them), (rows, cols) bool: `z_seen_um` is the pair's truth (rows, cols,
    µm) for a tilt axis along the columns (`render_stereo_pair`'s default) and a second view not
    misplaced. In both views a point at x along the rows and height z projects to
    x cos t + z sin t; the second view sees a point only if it is the crossing of its ray nearest to
    the viewer (`rendering.visible_sheet_px`)."""
    first_rad, second_rad = np.radians(tilt_deg)
    cols = z_seen_um.shape[1]
    first_px = np.arange(cols) - (cols - 1) / 2.0
    z_px = z_seen_um / pixel_size_um
    x_px = (first_px[None, :] - z_px * np.sin(first_rad)) / np.cos(first_rad)
    second_px = x_px * np.cos(second_rad) + z_px * np.sin(second_rad)
    return np.abs(second_px - visible_sheet_px(second_px, second_rad)) > 0.25  # a quarter pixel of resampling
