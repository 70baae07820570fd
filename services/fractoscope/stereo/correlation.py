"""Zero-mean normalized cross-correlation (ZNCC) of image windows, the primitive every matching
method here shares: window statistics and scores as box filters (one candidate shift costs a few
passes over the image whatever the window size), warps along rows, and the location error of a
correlation peak.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np

SIGMA_CALIBRATION = 3.5


def normalized(image: np.ndarray) -> np.ndarray:
    values = image.astype(np.float32)
    values -= values.mean()
    values /= max(float(values.std()), 1e-6)
    return values


# OpenCV's box filter has a fast path up to 5 px only: from 7 to 19 px its separable filter with
# equal taps is 1.3-2.1 times as fast (1024², 9 px: 1.3 against 2.7 ms), beyond that slower.
_SEPARABLE_BOX_PX = range(7, 20)


def box_mean(values: np.ndarray, window_px: int) -> np.ndarray:
    """Mean of every `window_px` square window of (rows, cols) `values`, float32, edges reflected."""
    if window_px in _SEPARABLE_BOX_PX:
        taps = np.full(window_px, 1.0 / window_px, np.float32)
        return cv2.sepFilter2D(values, cv2.CV_32F, taps, taps, borderType=cv2.BORDER_REFLECT)
    return cv2.boxFilter(values, cv2.CV_32F, (window_px, window_px), borderType=cv2.BORDER_REFLECT)


def warp_along_rows(image: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    """image sampled at (row, col + disparity), bilinear, edges replicated."""
    rows, cols = disparity.shape
    map_cols = np.arange(cols, dtype=np.float32)[None, :] + disparity
    map_rows = np.broadcast_to(np.arange(rows, dtype=np.float32)[:, None], disparity.shape)
    return cv2.remap(image, map_cols, np.ascontiguousarray(map_rows), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def sample_along_rows(field: np.ndarray, disparity: np.ndarray) -> np.ndarray:
    return warp_along_rows(field, np.nan_to_num(disparity))


def nearest_known_along_rows(known: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(before, after): for each pixel the column of the nearest `known` pixel of its row at or
    left of it (-1 where there is none) and at or right of it (cols where there is none), (rows,
    cols) int32 each; `known` (rows, cols) bool."""
    rows, cols = known.shape
    columns = np.broadcast_to(np.arange(cols, dtype=np.int32), (rows, cols))
    before = np.maximum.accumulate(np.where(known, columns, np.int32(-1)), axis=1)
    after = np.minimum.accumulate(np.where(known, columns, np.int32(cols))[:, ::-1], axis=1)[:, ::-1]
    return before, after


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


def zncc_scores_within_one_px(left: np.ndarray, left_stats: WindowStats, warped: np.ndarray, window_px: int):
    """ZNCC of the left windows with the warped windows shifted by -1, 0 and +1 column, (rows,
    cols) float32 each: `zncc_scores_by_shift` at radius 1, the same values, with the products
    and the normalization each in one compiled pass instead of a dozen array operations."""
    products = _products_within_one_px(left, warped)
    sums = [box_mean(values, window_px) for values in (*products, warped, warped * warped)]
    return _normalized_within_one_px(*sums, left_stats.mean, left_stats.inverse_std)


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


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _products_within_one_px(left, warped):  # pragma: no cover
    """left × warped shifted by -1, 0 and +1 column (edges replicated)."""
    rows, cols = left.shape
    before, centre, after = np.empty_like(left), np.empty_like(left), np.empty_like(left)
    for i in range(rows):
        for j in range(cols):
            value = left[i, j]
            before[i, j] = value * warped[i, max(j - 1, 0)]
            centre[i, j] = value * warped[i, j]
            after[i, j] = value * warped[i, min(j + 1, cols - 1)]
    return before, centre, after


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _normalized_within_one_px(
    before, centre, after, warped_mean, warped_square_mean, left_mean, left_inverse_std
):  # pragma: no cover
    """The three shifts' ZNCC from their window means, as `window_stats` and
    `zncc_scores_by_shift` compute it, operation for operation (IEEE float32). Row loops without
    branches, the edge columns apart, so that LLVM vectorizes them."""
    rows, cols = centre.shape
    one, least = np.float32(1.0), np.float32(1e-8)
    inverse_std = np.empty(cols, np.float32)
    scores = (np.empty_like(centre), np.empty_like(centre), np.empty_like(centre))
    for i in range(rows):
        mean, lm, lis = warped_mean[i], left_mean[i], left_inverse_std[i]
        for j in range(cols):
            inverse_std[j] = one / np.sqrt(max(warped_square_mean[i, j] - mean[j] * mean[j], least))
        for shift, products in zip((-1, 0, 1), (before, centre, after)):
            score, product = scores[shift + 1][i], products[i]
            first, stop = max(-shift, 0), cols - max(shift, 0)
            for j in range(first, stop):
                score[j] = (product[j] - lm[j] * mean[j + shift]) * lis[j] * inverse_std[j + shift]
            if shift != 0:  # the edge column: its shifted window is its own (edges replicated)
                j = 0 if shift < 0 else cols - 1
                score[j] = (product[j] - lm[j] * mean[j]) * lis[j] * inverse_std[j]
    return scores


def peak_sigma_px(score, curvature, window_px):
    """Location error of a correlation peak, sqrt((1 - γ) / (N |γ''| / 2)) for N window pixels
    (white-noise theory), times 3.5: on synthetic SEM pairs, where the views also differ by
    tilt-dependent shading, 68 % of errors then fall within one sigma. A floor of 0.02 px stands
    for interpolation bias."""
    half_curvature = np.maximum(-0.5 * curvature, 1e-4)
    noise = np.maximum(1.0 - score, 0.0)
    return np.sqrt(SIGMA_CALIBRATION**2 * noise / (window_px**2 * half_curvature) + 0.02**2)
