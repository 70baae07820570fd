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
    cols) float32 each: `zncc_scores_by_shift` at radius 1 (within float32 rounding: the window
    sums run in float64 here), in one compiled pass over the rows that keeps the window's rows in
    cache, instead of five box filters over whole arrays and their products."""
    left, warped = np.ascontiguousarray(left, np.float32), np.ascontiguousarray(warped, np.float32)
    return _scores_within_one_px(left, warped, left_stats.mean, left_stats.inverse_std, window_px // 2)


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


_JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")


@numba.njit(**_JIT)
def _scores_within_one_px(left, warped, left_mean, left_inverse_std, half):  # pragma: no cover
    """`zncc_scores_within_one_px`: the window sums of left × warped at -1, 0, +1 columns, warped
    and warped² (edges reflected, as `box_mean`), as column sums over the window's rows that
    move down one row at a time (a row in, a row out), then sums along the row."""
    rows, cols = left.shape
    width = cols + 2 * half
    column_sums = np.zeros((5, width), np.float64)
    row_values = np.empty((5, width), np.float32)
    means = np.empty((5, cols), np.float32)
    scores = (np.empty_like(left), np.empty_like(left), np.empty_like(left))
    for k in range(-half, half + 1):
        _row_values(left, warped, _reflected(k, rows), half, row_values)
        column_sums += row_values
    scale = np.float64(1.0 / (2 * half + 1) ** 2)
    for i in range(rows):
        if i > 0:
            _row_values(left, warped, _reflected(i + half, rows), half, row_values)
            column_sums += row_values
            _row_values(left, warped, _reflected(i - half - 1, rows), half, row_values)
            column_sums -= row_values
        _window_means(column_sums, half, scale, means)
        _normalized_row(means, left_mean[i], left_inverse_std[i], scores[0][i], scores[1][i], scores[2][i])
    return scores


@numba.njit(inline="always", **_JIT)
def _reflected(index, size):  # pragma: no cover
    """OpenCV's BORDER_REFLECT (edge pixel repeated): -1 → 0, size → size - 1, and again where
    a window reaches beyond the far edge."""
    while index < 0 or index >= size:
        index = -index - 1 if index < 0 else 2 * size - index - 1
    return index


@numba.njit(**_JIT)
def _row_values(left, warped, row, half, out):  # pragma: no cover
    """Row `row`'s left × warped at -1, 0, +1 columns (edges replicated), warped and warped², in
    columns padded by `half` on either side (reflected), into `out` (5, cols + 2 half)."""
    cols = left.shape[1]
    l_row, w_row = left[row], warped[row]
    for j in range(cols):
        value, w = l_row[j], w_row[j]
        out[0, half + j] = value * w_row[max(j - 1, 0)]
        out[1, half + j] = value * w
        out[2, half + j] = value * w_row[min(j + 1, cols - 1)]
        out[3, half + j] = w
        out[4, half + j] = w * w
    for m in range(half):
        before, after = half + _reflected(-1 - m, cols), half + _reflected(cols + m, cols)
        for q in range(5):
            out[q, half - 1 - m] = out[q, before]
            out[q, half + cols + m] = out[q, after]


@numba.njit(**_JIT)
def _window_means(column_sums, half, scale, means):  # pragma: no cover
    """Means over 2 half + 1 consecutive padded columns of each of the five column sums."""
    cols = means.shape[1]
    for q in range(5):
        sums = column_sums[q]
        total = np.float64(0.0)
        for m in range(2 * half + 1):
            total += sums[m]
        means[q, 0] = total * scale
        for j in range(1, cols):
            total += sums[j + 2 * half] - sums[j - 1]
            means[q, j] = total * scale


@numba.njit(**_JIT)
def _normalized_row(means, lm, lis, before, centre, after):  # pragma: no cover
    """The three shifts' ZNCC along one row from their window means (`means`: the products at
    -1, 0, +1, warped, warped²), as `window_stats` and `zncc_scores_by_shift` compute it. Loops
    without branches, the edge columns apart, so that LLVM vectorizes them."""
    cols = centre.shape[0]
    one, least = np.float32(1.0), np.float32(1e-8)
    mean, square_mean = means[3], means[4]
    inverse_std = np.empty(cols, np.float32)
    for j in range(cols):
        inverse_std[j] = one / np.sqrt(max(square_mean[j] - mean[j] * mean[j], least))
    for j in range(cols):
        centre[j] = (means[1, j] - lm[j] * mean[j]) * lis[j] * inverse_std[j]
    for j in range(1, cols):
        before[j] = (means[0, j] - lm[j] * mean[j - 1]) * lis[j] * inverse_std[j - 1]
    for j in range(cols - 1):
        after[j] = (means[2, j] - lm[j] * mean[j + 1]) * lis[j] * inverse_std[j + 1]
    # The edge columns: their shifted window is their own (edges replicated).
    before[0] = (means[0, 0] - lm[0] * mean[0]) * lis[0] * inverse_std[0]
    after[cols - 1] = (means[2, cols - 1] - lm[cols - 1] * mean[cols - 1]) * lis[cols - 1] * inverse_std[cols - 1]


def peak_sigma_px(score, curvature, window_px):
    """Location error of a correlation peak, sqrt((1 - γ) / (N |γ''| / 2)) for N window pixels
    (white-noise theory), times 3.5: on synthetic SEM pairs, where the views also differ by
    tilt-dependent shading, 68 % of errors then fall within one sigma. A floor of 0.02 px stands
    for interpolation bias."""
    half_curvature = np.maximum(-0.5 * curvature, 1e-4)
    noise = np.maximum(1.0 - score, 0.0)
    return np.sqrt(SIGMA_CALIBRATION**2 * noise / (window_px**2 * half_curvature) + 0.02**2)
