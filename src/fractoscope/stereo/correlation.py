"""Zero-mean normalized cross-correlation (ZNCC) of image windows, the primitive every matching
method here shares: window statistics and scores as box filters (one candidate shift costs a few
passes over the image whatever the window size), warps along rows, and the location error of a
correlation peak.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

SIGMA_CALIBRATION = 3.5


def normalized(image: np.ndarray) -> np.ndarray:
    values = image.astype(np.float32)
    values -= values.mean()
    values /= max(float(values.std()), 1e-6)
    return values


def box_mean(values: np.ndarray, window_px: int) -> np.ndarray:
    return cv2.boxFilter(values, cv2.CV_32F, (window_px, window_px), borderType=cv2.BORDER_REFLECT)


def warp_along_rows(image: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """image sampled at (row, col + disparity), bilinear, edges replicated."""
    rows, cols = disparity.shape
    map_cols = np.arange(cols, dtype=np.float32)[None, :] + disparity
    map_rows = np.broadcast_to(np.arange(rows, dtype=np.float32)[:, None], disparity.shape)
    return cv2.remap(image, map_cols, np.ascontiguousarray(map_rows), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def sample_along_rows(field: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    return warp_along_rows(field, np.nan_to_num(disparity))


@dataclass(frozen=True)
class WindowStats:
    """Mean and inverse standard deviation of every window of one image, (rows, cols) float32."""

    mean: np.ndarray
    inverse_std: np.ndarray


def window_stats(image: np.ndarray, window_px: int) -> WindowStats:
    mean = box_mean(image, window_px)
    variance = box_mean(image * image, window_px)
    variance -= mean * mean
    return WindowStats(mean, 1.0 / np.sqrt(np.maximum(variance, 1e-8)))


def zncc_scores(left: np.ndarray, left_stats: WindowStats, warped: np.ndarray, window_px: int, radius: int) -> list[np.ndarray]:
    """ZNCC of the left windows with the warped windows shifted by -radius..radius columns, in
    that order, (rows, cols) float32 each."""
    return list(zncc_scores_by_shift(left, left_stats, warped, window_px, radius))


def zncc_scores_by_shift(left: np.ndarray, left_stats: WindowStats, warped: np.ndarray, window_px: int, radius: int):
    """`zncc_scores` one shift at a time (a generator). Shifted copies are views into arrays
    padded once (edges replicated)."""
    warped_stats = window_stats(warped, window_px)
    cols = left.shape[1]

    def padded(values):
        return cv2.copyMakeBorder(values, 0, 0, radius, radius, cv2.BORDER_REPLICATE)

    warped_p, mean_p, inverse_std_p = padded(warped), padded(warped_stats.mean), padded(warped_stats.inverse_std)
    for start in range(2 * radius + 1):
        columns = slice(start, start + cols)
        score = box_mean(left * warped_p[:, columns], window_px)
        score -= left_stats.mean * mean_p[:, columns]
        score *= left_stats.inverse_std
        score *= inverse_std_p[:, columns]
        yield score


def peak_sigma_px(score, curvature, window_px):
    """Location error of a correlation peak, sqrt((1 - γ) / (N |γ''| / 2)) for N window pixels
    (white-noise theory), times 3.5: on synthetic SEM pairs, where the views also differ by
    tilt-dependent shading, 68 % of errors then fall within one sigma. A floor of 0.02 px stands
    for interpolation bias."""
    half_curvature = np.maximum(-0.5 * curvature, 1e-4)
    noise = np.maximum(1.0 - score, 0.0)
    return np.sqrt(SIGMA_CALIBRATION**2 * noise / (window_px**2 * half_curvature) + 0.02**2)
