"""Cleaning a height map before meshing: isolated peaks out, small holes filled, optional
edge-preserving smoothing. Heights are (rows, cols) float32 micrometres with NaN where unknown."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

OUTLIER_THRESHOLD_SIGMA = 8.0
MAX_FILL_DISTANCE_PX = 8
# Spikes: peaks and pits narrower than this (px) whose flanks are steeper than the pair measures.
SPIKE_WIDTH_PX = 5
SPIKE_SIGMAS = 3.0


@dataclass(frozen=True)
class FilterReport:
    """How many points each step changed."""

    outliers_removed: int
    holes_filled: int
    points_smoothed: int


@dataclass(frozen=True)
class FilteredHeights:
    """z_um: cleaned heights, NaN where still unknown; filled: True where a height was
    interpolated rather than measured (holes and removed outliers); sigma_um: the heights'
    one-sigma uncertainty when one was given, filled points carrying the same weighted mean of
    their neighbours' (which leaves out the interpolation's own error), else None."""

    z_um: np.ndarray
    filled: np.ndarray
    report: FilterReport
    sigma_um: np.ndarray | None = None


def filter_heights(
    z_um: np.ndarray,
    *,
    outlier_threshold_sigma: float = OUTLIER_THRESHOLD_SIGMA,
    max_fill_distance_px: int = MAX_FILL_DISTANCE_PX,
    smoothing_um: float = 0.0,
    sigma_um: np.ndarray | None = None,
    max_slope: float | None = None,
    pixel_size_um: float | None = None,
) -> FilteredHeights:
    """Removes isolated peaks (points outside the range of their eight neighbours by more than
    twice that range and by more than `outlier_threshold_sigma` robust standard deviations), fills
    unknown points within `max_fill_distance_px` of measured ones by normalized Gaussian
    convolution, and, when `smoothing_um` > 0, applies a bilateral filter whose height scale is
    `smoothing_um`, so steps much higher than that stay sharp. `sigma_um` (the shape of z_um, µm)
    is carried along: removed where the height is, filled where it is. With the steepest slope the
    pair measures (`max_slope`) and the grid's `pixel_size_um`, spikes go too (`_spikes`)."""
    if z_um.ndim != 2:
        raise ValueError(f"z_um must be 2D, got shape {z_um.shape}")
    heights = z_um.astype(np.float32)
    measured = np.isfinite(heights)

    # An isolated peak lies outside the range of its eight measured neighbours by more than twice
    # that range and by more than `outlier_threshold_sigma` robust standard deviations. Smooth
    # surfaces and steps keep their points within (or just beyond) their neighbours' range.
    ring = np.ones((3, 3), np.uint8)
    ring[1, 1] = 0
    highest = cv2.dilate(np.where(measured, heights, -np.inf).astype(np.float32), ring, borderType=cv2.BORDER_REPLICATE)
    lowest = cv2.erode(np.where(measured, heights, np.inf).astype(np.float32), ring, borderType=cv2.BORDER_REPLICATE)
    with np.errstate(invalid="ignore"):  # points without measured neighbours give NaN: never peaks
        excess = np.maximum(heights - highest, lowest - heights)
        spread = highest - lowest
        scale = _robust_scale(heights - 0.5 * (highest + lowest), measured & np.isfinite(spread))
        outliers = measured & (excess > 2.0 * spread) & (excess > outlier_threshold_sigma * scale)
    if max_slope and pixel_size_um:
        outliers |= _spikes(heights, measured, max_slope * pixel_size_um, sigma_um)
    kept = measured & ~outliers

    # Unknown points within the fill distance get the Gaussian-weighted mean of measured ones
    # (normalized convolution).
    distance = cv2.distanceTransform((~kept).astype(np.uint8), cv2.DIST_L2, 3)
    fillable = ~kept & (distance <= max_fill_distance_px)
    width = max(max_fill_distance_px / 2.0, 0.5)
    interpolated = normalized_mean(heights, kept, width)
    filled = fillable & np.isfinite(interpolated)
    known = kept | filled
    result = np.where(kept, heights, np.where(filled, interpolated, np.nan)).astype(np.float32)
    sigma_result = _carried_sigma(sigma_um, kept, filled, width) if sigma_um is not None else None

    smoothed_count = 0
    if smoothing_um > 0:
        smoothed = cv2.bilateralFilter(np.where(known, result, 0.0).astype(np.float32), 5, smoothing_um, 1.5)
        changed = known & (np.abs(smoothed - result) > 1e-6)
        result = np.where(known, smoothed, np.nan).astype(np.float32)
        smoothed_count = int(changed.sum())
    report = FilterReport(int(outliers.sum()), int((filled & ~outliers).sum()), smoothed_count)
    return FilteredHeights(result, filled, report, sigma_result)


def _carried_sigma(sigma_um: np.ndarray, kept: np.ndarray, filled: np.ndarray, width_px: float) -> np.ndarray:
    """The sigma of the filtered heights: the kept points' own, the filled points' the Gaussian
    mean of their kept neighbours' (`width_px`), NaN elsewhere (float32 µm)."""
    sigma = np.asarray(sigma_um, np.float32)
    with_sigma = kept & np.isfinite(sigma)
    filled_sigma = normalized_mean(sigma, with_sigma, width_px)
    return np.where(with_sigma, sigma, np.where(filled, filled_sigma, np.nan)).astype(np.float32)


def _spikes(heights: np.ndarray, measured: np.ndarray, height_per_px_um: float, sigma_um) -> np.ndarray:
    """Peaks and pits narrower than SPIKE_WIDTH_PX (what a grey opening, resp. closing, of that
    width takes away, unknown points left out) that stand out of it by more than a measurable
    slope (`height_per_px_um`: the most the height can change from one pixel to the next) allows
    over half that width, plus SPIKE_SIGMAS of their sigma: a pair cannot see such flanks, so
    the spike is a mismatch (as along a measured area's edge), while a step keeps its plateaus."""
    kernel = np.ones((SPIKE_WIDTH_PX, SPIKE_WIDTH_PX), np.uint8)
    low = np.where(measured, heights, np.inf).astype(np.float32)
    high = np.where(measured, heights, -np.inf).astype(np.float32)
    opened = cv2.dilate(np.where(measured, cv2.erode(low, kernel), -np.inf).astype(np.float32), kernel)
    closed = cv2.erode(np.where(measured, cv2.dilate(high, kernel), np.inf).astype(np.float32), kernel)
    sigma = np.nan_to_num(np.asarray(sigma_um, np.float32)) if sigma_um is not None else np.float32(0)
    allowed = height_per_px_um * (SPIKE_WIDTH_PX // 2) + SPIKE_SIGMAS * sigma
    with np.errstate(invalid="ignore"):
        return measured & ((heights - opened > allowed) | (closed - heights > allowed))


def normalized_mean(values: np.ndarray, kept: np.ndarray, width_px: float) -> np.ndarray:
    """The Gaussian-weighted (sigma `width_px`) mean of the `kept` values around every point
    (normalized convolution), NaN where none is near enough to weigh."""
    total = cv2.GaussianBlur(np.where(kept, values, 0.0).astype(np.float32), (0, 0), width_px)
    count = cv2.GaussianBlur(kept.astype(np.float32), (0, 0), width_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(count > 1e-6, total / count, np.nan)


def _robust_scale(values: np.ndarray, mask: np.ndarray, *, max_samples: int = 1_000_000) -> float:
    """1.4826 x median absolute value (the standard deviation of Gaussian values, robustly), from
    at most `max_samples` evenly spread values."""
    selected = np.abs(values[mask])
    selected = selected[:: max(selected.size // max_samples, 1)]
    return 1.4826 * float(np.median(selected)) if selected.size else 0.0
