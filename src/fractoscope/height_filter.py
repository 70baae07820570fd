"""Cleaning a height map before meshing: isolated peaks out, small holes filled, optional
edge-preserving smoothing. Heights are (rows, cols) float32 micrometres with NaN where unknown."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class FilterReport:
    """How many points each step changed."""

    outliers_removed: int
    holes_filled: int
    points_smoothed: int


@dataclass(frozen=True)
class FilteredHeights:
    """z_um: cleaned heights, NaN where still unknown; filled: True where a height was
    interpolated rather than measured (holes and removed outliers)."""

    z_um: np.ndarray
    filled: np.ndarray
    report: FilterReport


def filter_heights(
    z_um: np.ndarray,
    *,
    outlier_threshold_sigma: float = 8.0,
    max_fill_distance_px: int = 8,
    smoothing_um: float = 0.0,
) -> FilteredHeights:
    """Removes isolated peaks (points outside the range of their eight neighbours by more than twice
    that range and by more than `outlier_threshold_sigma` robust standard deviations), fills unknown
    points within `max_fill_distance_px` of measured ones by neighbour averaging, and, when `smoothing_um` > 0, applies a bilateral filter
    whose height scale is `smoothing_um`, so steps much higher than that stay sharp."""
    if z_um.ndim != 2:
        raise ValueError(f"z_um must be 2D, got shape {z_um.shape}")
    heights = z_um.astype(np.float32)
    measured = np.isfinite(heights)

    # An isolated peak lies outside the range of its eight neighbours by more than twice that
    # range and by more than `outlier_threshold_sigma` robust standard deviations. Smooth surfaces
    # and steps keep their points within (or just beyond) their neighbours' range.
    provisional, known = _grow(heights, measured, 1)
    provisional = np.where(known, provisional, np.nan).astype(np.float32)
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0
    highest = cv2.dilate(np.nan_to_num(provisional, nan=-np.inf), ring, borderType=cv2.BORDER_REPLICATE)
    lowest = cv2.erode(np.nan_to_num(provisional, nan=np.inf), ring, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore"):  # points without measured neighbours give NaN: never peaks
        excess = np.maximum(heights - highest, lowest - heights)
        spread = highest - lowest
        scale = _robust_scale(heights - 0.5 * (highest + lowest), measured & np.isfinite(spread))
    outliers = measured & (excess > 2.0 * spread) & (excess > outlier_threshold_sigma * scale)
    kept = measured & ~outliers

    grown, known = _grow(heights, kept, max_fill_distance_px)
    filled = known & ~kept
    result = np.where(known, grown, np.nan).astype(np.float32)

    smoothed_count = 0
    if smoothing_um > 0:
        smoothed = cv2.bilateralFilter(np.where(known, result, 0.0).astype(np.float32), 5, smoothing_um, 1.5)
        changed = known & (np.abs(smoothed - result) > 1e-6)
        result = np.where(known, smoothed, np.nan).astype(np.float32)
        smoothed_count = int(changed.sum())
    report = FilterReport(int(outliers.sum()), int((filled & ~outliers).sum()), smoothed_count)
    return FilteredHeights(result, filled, report)


def _robust_scale(values: np.ndarray, mask: np.ndarray) -> float:
    """1.4826 x median absolute value: the standard deviation of Gaussian values, robustly."""
    selected = np.abs(values[mask])
    return 1.4826 * float(np.median(selected)) if selected.size else 0.0


def _grow(heights: np.ndarray, known: np.ndarray, rings: int) -> tuple[np.ndarray, np.ndarray]:
    """Extends known heights `rings` pixels outwards; each new point is the mean of its known
    3x3 neighbours. Returns the values (garbage where still unknown) and the known mask."""
    values = np.where(known, heights, 0.0).astype(np.float32)
    known = known.copy()
    for _ in range(rings):
        weight = known.astype(np.float32)
        total = cv2.boxFilter(values * weight, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        count = cv2.boxFilter(weight, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        growing = ~known & (count > 0)
        if not growing.any():
            break
        values[growing] = total[growing] / count[growing]
        known |= growing
    return values, known
