"""Dense zero-mean normalized cross-correlation (ZNCC) matching of a rectified stereo pair.

The paper's γ(u, v): a pattern window of the left image is compared with windows of the right
image along the same row. Each window statistic is a box filter, so one candidate shift costs a
few passes over the image whatever the window size. A coarse-to-fine pyramid finds large
disparities without a manual search range; at each finer level the right image is warped by the
current disparity field and only a few residual shifts are tried, which also matches slanted
surfaces well. Sub-pixel disparities come from iterated parabola fits on the warped image.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import cv2
import numba
import numpy as np

from fractoscope.stereo import correlation
from fractoscope.stereo.disparity import DisparityResult, StripTask

_SUBPIXEL_ITERATIONS = 1
_MAX_SPECKLE_PIXELS = 400


def match_strip(task: StripTask) -> DisparityResult:
    """Dense disparity of one strip of a rectified pair (the unit of work that replicas share).
    Masks (NaN) pixels whose peak correlation is below `task.min_confidence`, whose
    left-to-right and right-to-left disparities differ by more than `task.max_lr_difference_px`,
    whose window lies on a flat (textureless) patch, or that form small isolated islands among
    masked pixels. Every pyramid level but the finest also lets each pixel try its neighbours'
    disparities (`_propagate`); `task.propagate_at_full_resolution` does so at the finest level
    too."""
    directions = match_directions(task)
    valid, disparity = consistent(task, directions, directions.forward.disparity, directions.backward_px)
    forward = directions.forward
    sigma_px = correlation.peak_sigma_px(forward.score, forward.curvature, task.window_px)
    return kept_result(task, valid, disparity, forward.score, sigma_px)


@dataclass(frozen=True)
class Directions:
    """The window matcher's disparities of one strip in both directions, before any masking.

    left, right: (rows, cols) float32, the strip's images normalized to zero mean, unit variance.
    forward: left-to-right disparity with its peak ZNCC and the peak's second difference.
    backward_px: (rows, cols) float32, right-to-left disparity.
    left_stats: window statistics of `left` at the window size."""

    left: np.ndarray
    right: np.ndarray
    forward: Refinement
    backward_px: np.ndarray
    left_stats: correlation.WindowStats


def match_directions(task: StripTask) -> Directions:
    """Coarse-to-fine window ZNCC of `task`'s strip, left to right and right to left."""
    left_f, right_f = correlation.normalized(task.left), correlation.normalized(task.right)
    window_px, max_disparity_px = task.window_px, task.max_disparity_px
    levels = _level_count(left_f.shape, max_disparity_px, window_px)
    left_pyramid, right_pyramid = _pyramid(left_f, levels), _pyramid(right_f, levels)
    coarse_radius = int(np.ceil(max_disparity_px / 2 ** (levels - 1))) + 1
    # The two directions are independent; OpenCV and numpy release the GIL, so they overlap. Both
    # get the sub-pixel pass: the consistency check compares them to 1 px, and without it the
    # backward direction's coarser estimate failed 1-2 % of good dimple pixels.
    finest_left_stats = correlation.window_stats(left_f, window_px)  # also tells textureless windows
    with ThreadPoolExecutor(max_workers=2) as pool:
        at_full = task.propagate_at_full_resolution
        forward_job = pool.submit(
            _coarse_to_fine, left_pyramid, right_pyramid, window_px, coarse_radius, at_full, finest_left_stats
        )
        backward_job = pool.submit(_coarse_to_fine, right_pyramid, left_pyramid, window_px, coarse_radius, at_full)
        forward, backward = forward_job.result(), backward_job.result().disparity
    return Directions(left_f, right_f, forward, backward, finest_left_stats)


def consistent(task: StripTask, directions: Directions, forward_px: np.ndarray, backward_px: np.ndarray):
    """(valid, disparity): the mean of the two directions' disparities (they err independently),
    and where it is trusted: the window's peak correlation reaches `task.min_confidence`, the
    directions agree within `task.max_lr_difference_px`, the window is textured, the match lies
    in the image, and the pixel is not in a small island of such pixels."""
    backward_at_match = correlation.sample_along_rows(backward_px, forward_px)
    lr_difference = np.abs(forward_px + backward_at_match)
    disparity = 0.5 * (forward_px - backward_at_match)
    valid = (
        (directions.forward.score >= task.min_confidence)
        & (lr_difference <= task.max_lr_difference_px)
        & textured(directions)
        & in_bounds(disparity)
        & np.isfinite(disparity)
    )
    valid &= ~speckles(disparity, valid)
    return valid, disparity


def textured(directions: Directions) -> np.ndarray:
    """Where the left window is not a flat, textureless patch, (rows, cols) bool."""
    return directions.left_stats.inverse_std < 1e3


def kept_result(task: StripTask, valid, disparity, score, sigma_px) -> DisparityResult:
    """The strip's rows that `task` keeps, NaN where not valid or where the match lies within
    1 px of the search's limit (±`task.max_disparity_px`) or beyond it: a peak at the edge of
    the search may belong to a disparity outside it, and the refinement is not bound by it."""
    kept = slice(*task.keep_rows) if task.keep_rows else slice(None)
    valid, score, disparity, sigma_px = valid[kept], score[kept], disparity[kept], sigma_px[kept]
    valid = valid & (np.abs(disparity) < task.max_disparity_px - 1.0)
    confidence = np.clip(score, 0.0, 1.0).astype(np.float32)
    disparity = np.where(valid, disparity, np.nan).astype(np.float32)
    sigma_px = np.where(valid, sigma_px, np.nan).astype(np.float32)
    return DisparityResult(disparity, confidence, sigma_px)


def _coarse_to_fine(
    left_pyramid,
    right_pyramid,
    window_px,
    coarse_radius,
    propagate_at_full_resolution=False,
    finest_left_stats=None,
) -> Refinement:
    """Full search at the coarsest level, ±2 px residual searches on warped images at the
    intermediate levels, ±1 px at full resolution, then sub-pixel iterations. Each level's result
    but the finest's (and that one too with `propagate_at_full_resolution`) also competes with
    its neighbours' (`_propagate`). The window statistics of the full-resolution left image are
    computed here unless given."""
    levels = len(left_pyramid)
    disparity = np.zeros(left_pyramid[-1].shape, np.float32)
    for level in range(levels - 1, -1, -1):
        left_level, right_level = left_pyramid[level], right_pyramid[level]
        given = level == 0 and finest_left_stats is not None
        left_stats = finest_left_stats if given else correlation.window_stats(left_level, window_px)
        if level < levels - 1:
            disparity = 2.0 * cv2.resize(disparity, left_level.shape[::-1], interpolation=cv2.INTER_LINEAR)
        radius = coarse_radius if level == levels - 1 else (2 if level > 0 else 1)
        refined = residual_search(left_level, left_stats, right_level, disparity, window_px, radius)
        if level > 0 or propagate_at_full_resolution:
            refined = _propagate(left_level, left_stats, right_level, refined, window_px)
        disparity = _clean_for_upsampling(refined.disparity, refined.score) if level > 0 else refined.disparity
    for _ in range(_SUBPIXEL_ITERATIONS):
        refined = residual_search(left_pyramid[0], left_stats, right_pyramid[0], refined.disparity, window_px, 1)
    return refined


def coarse_disparity(left: np.ndarray, right: np.ndarray, window_px: int, max_disparity_px: int) -> np.ndarray:
    """`_coarse_to_fine`'s full search at its coarsest level alone (without the propagation):
    `left` matched to `right` (normalized (rows, cols) float32 images) over ±`max_disparity_px`
    at the pyramid level where that is a few pixels, poor matches replaced by their
    neighbourhood's median, upsampled to (rows, cols) float32 px. A start for methods that
    search no range themselves (`optical_flow`)."""
    levels = _level_count(left.shape, max_disparity_px, window_px)
    coarse_left, coarse_right = _pyramid(left, levels)[-1], _pyramid(right, levels)[-1]
    radius = int(np.ceil(max_disparity_px / 2 ** (levels - 1))) + 1
    found = residual_search(
        coarse_left,
        correlation.window_stats(coarse_left, window_px),
        coarse_right,
        np.zeros(coarse_left.shape, np.float32),
        window_px,
        radius,
    )
    disparity = _clean_for_upsampling(found.disparity, found.score)
    return np.float32(2 ** (levels - 1)) * cv2.resize(disparity, left.shape[::-1], interpolation=cv2.INTER_LINEAR)


def context_rows(strip_shape: tuple[int, int], *, window_px: int, max_disparity_px: int) -> int:
    """Rows of context a strip of `strip_shape` (rows, cols) needs on either side of the rows it
    keeps: the support of one window at the coarsest pyramid level."""
    return window_px * 2 ** (_level_count(strip_shape, max_disparity_px, window_px) - 1)


def _level_count(shape: tuple[int, int], max_disparity_px: int, window_px: int) -> int:
    """Halve until the remaining search radius is small, keeping the coarsest image matchable."""
    levels = 1
    while max_disparity_px / 2 ** (levels - 1) > 6 and min(shape) / 2**levels >= 4 * window_px:
        levels += 1
    return levels


def _pyramid(image: np.ndarray, levels: int) -> list[np.ndarray]:
    pyramid = [image]
    for _ in range(levels - 1):
        pyramid.append(cv2.pyrDown(pyramid[-1]))
    return pyramid


@dataclass(frozen=True)
class Refinement:
    """Disparity after one residual search, with the peak ZNCC and its second difference."""

    disparity: np.ndarray
    score: np.ndarray
    curvature: np.ndarray


def residual_search(left, left_stats, right, disparity, window_px, radius) -> Refinement:
    """Best integer residual shift within ±radius on the warped right image, then a parabola
    through the neighbouring scores.

    The warp uses the disparity smoothed over about a window: each window then sees one
    consistent deformation, and per-pixel noise is not fed back into the next iteration."""
    disparity = cv2.GaussianBlur(disparity, (0, 0), window_px / 4.0)
    warped = correlation.warp_along_rows(right, disparity)
    if radius == 1:  # the full-resolution case, run most often: one compiled pass
        return Refinement(
            *_peak_of_three(*correlation.zncc_scores_within_one_px(left, left_stats, warped, window_px), disparity)
        )
    # A full search at the coarsest level can span thousands of shifts: the scores come one shift
    # at a time, and only the best and its two neighbours are kept, so memory does not grow with them.
    best_index = np.zeros(left.shape, np.int32)
    best = before = after = previous = newly_best = None
    for index, score in enumerate(correlation.zncc_scores_by_shift(left, left_stats, warped, window_px, radius)):
        if best is None:
            best, before, after, newly_best = (
                score.copy(),
                np.zeros_like(score),
                np.zeros_like(score),
                np.zeros(left.shape, bool),
            )
        else:
            np.copyto(after, score, where=newly_best)  # the shift after the best so far
            newly_best = score > best
            np.copyto(best, score, where=newly_best)
            np.copyto(before, previous, where=newly_best)
            np.copyto(best_index, index, where=newly_best)
        previous = score
    at_edge = (best_index == 0) | (best_index == 2 * radius)  # no neighbour on one side
    before[at_edge] = 0.0
    after[at_edge] = 0.0
    curvature = before - 2.0 * best + after
    at_centre = (best_index > 0) & (best_index < 2 * radius) & (curvature < 0)
    offset = best_index.astype(np.float32) - radius
    with np.errstate(invalid="ignore", divide="ignore"):
        fraction = np.where(at_centre, 0.5 * (before - after) / curvature, 0.0)
    fraction = np.clip(fraction, -0.5, 0.5)
    return Refinement((disparity + offset + fraction).astype(np.float32), best, curvature)


@numba.njit(nogil=True, cache=True, boundscheck=False, error_model="numpy")
def _peak_of_three(before, centre, after, disparity):  # pragma: no cover
    """`residual_search` at radius 1 in one pass: the best of the scores at -1, 0 and +1 px
    (ties go to +1, then -1), the parabola's sub-pixel fraction where the centre is a peak
    (within ±0.5 px); returns (disparity, best score, second difference), (rows, cols) float32."""
    rows, cols = centre.shape
    refined = np.empty((rows, cols), np.float32)
    best_score = np.empty((rows, cols), np.float32)
    curvature = np.empty((rows, cols), np.float32)
    zero, one, half, two = np.float32(0.0), np.float32(1.0), np.float32(0.5), np.float32(2.0)
    for i in range(rows):
        for j in range(cols):
            b, c, a = before[i, j], centre[i, j], after[i, j]
            best = max(max(b, c), a)
            offset = one if a == best else (-one if b == best else zero)
            second = b - two * c + a
            fraction = zero
            if c == best and second < zero:
                fraction = min(max(half * (b - a) / second, -half), half)
            refined[i, j] = disparity[i, j] + offset + fraction
            best_score[i, j] = best
            curvature[i, j] = second
    return refined, best_score, curvature


def _propagate(left, left_stats, right, refined: Refinement, window_px) -> Refinement:
    """Each pixel also tries the largest and the smallest of the disparities found half a window
    to its left, right, above and below (a ±1 px residual search on the right image warped by
    each), and keeps whichever correlates best. Near a step, or a pit narrower than a coarse
    level's window, the result is a blend of the two sides that the small residual searches of
    the finer levels cannot leave; of the two sides' disparities, one is the largest of the
    neighbours' and the other the smallest."""
    step = window_px // 2
    neighbours = [
        shifted(refined.disparity, row_step, col_step)
        for row_step, col_step in ((0, step), (0, -step), (step, 0), (-step, 0))
    ]
    best = Refinement(refined.disparity.copy(), refined.score.copy(), refined.curvature.copy())
    for pick in (np.maximum, np.minimum):
        candidate = residual_search(
            left,
            left_stats,
            right,
            pick(pick(neighbours[0], neighbours[1]), pick(neighbours[2], neighbours[3])),
            window_px,
            1,
        )
        better = (candidate.score > best.score).view(np.uint8)
        for new, kept in zip(
            (candidate.disparity, candidate.score, candidate.curvature), (best.disparity, best.score, best.curvature)
        ):
            cv2.copyTo(new, better, kept)  # in place, and quicker than numpy's masked copies
    return best


def shifted(field: np.ndarray, row_step: int, col_step: int) -> np.ndarray:
    """field[row + row_step, col + col_step] at (row, col), edges replicated."""
    margin = max(abs(row_step), abs(col_step))
    padded = cv2.copyMakeBorder(field, margin, margin, margin, margin, cv2.BORDER_REPLICATE)
    rows, cols = field.shape
    return np.ascontiguousarray(
        padded[margin + row_step : margin + row_step + rows, margin + col_step : margin + col_step + cols]
    )


def _clean_for_upsampling(disparity, score):
    """Replace poorly matched disparities by a robust local estimate before they seed finer levels."""
    smooth = cv2.medianBlur(disparity, 5)
    poor = (score < 0.3) | (np.abs(disparity - smooth) > 1.5)
    return np.where(poor, smooth, disparity).astype(np.float32)


def speckles(disparity, valid, *, max_pixels=_MAX_SPECKLE_PIXELS, max_step_px=1.0):
    """Small islands of valid disparities: regions (joined where neighbours differ by at most
    `max_step_px`) of fewer than `max_pixels` pixels, typically wrong matches surrounded by
    masked ones. Uses OpenCV's speckle filter in its 1/16 px fixed point."""
    marker = -32768
    fixed = np.full(disparity.shape, marker, np.int16)
    scaled = np.nan_to_num(disparity * np.float32(16.0), copy=False)
    np.clip(scaled, -32000, 32000, out=scaled)
    cv2.copyTo(scaled.astype(np.int16), valid.view(np.uint8), fixed)
    filtered = fixed.copy()
    cv2.filterSpeckles(filtered, marker, max_pixels, int(16 * max_step_px))
    return (filtered == marker) & valid


def in_bounds(disparity):
    """Where the match (row, col + disparity) lies inside the strip, (rows, cols) bool."""
    cols = disparity.shape[1]
    target = np.arange(cols, dtype=np.float32)[None, :] + disparity
    return (target >= 0) & (target <= cols - 1)
