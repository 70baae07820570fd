"""The FAST matching method: dense inverse search (DIS) optical flow, the quickest path to dense
disparities that still beats semi-global matching clearly.

DIS (OpenCV's DISOpticalFlow) fits small patches by inverse-compositional gradient descent,
coarse to fine over an image pyramid, and densifies them with a few variational refinement
iterations. Its patches only descend: they follow displacements of a few patches at its
coarsest scale, not a facet or a grain standing 100 px off its surroundings. So it starts from
the window matcher's full search over ±`max_disparity_px` at its coarsest pyramid level
(`window_zncc.coarse_disparity`, a few ms). Its flow is computed at a quarter of the resolution
and is smooth, so it is a start too: the left image's `window_px` windows are then matched by
two ±1 px ZNCC residual searches around it (`window_zncc.residual_search`, as the window
matcher's finest level does), which give the disparity its sub-pixel precision, the confidence
(the peak ZNCC) and the sigma (the peak's curvature, `correlation.peak_sigma_px`). The flow is
computed both ways for the left-right check; a rectified pair's flow runs along rows, so a flow
that needs more than `_MAX_ACROSS_ROWS_PX` across them is no match along the row.

Measured on 1024² synthetic pairs at ±5° (`benchmarks/matching.py`'s self-affine pair, ±32 px):
0.82 times StereoSGBM's matching time (0.16 against 0.20 s) at 0.29 times its RMS height error
(0.75 against 2.61 % of the range; window correlation: 1.0 and 0.26 times). SGBM's time grows
with the disparity range: timed in one process (where that pair measures 1.0 times), FAST took
1.6-1.8 times SGBM's time on the reference self-affine and dimple surfaces (disparities within
±15 px), 0.7-0.8 times on cleavage (-41 to +58 px); RMS error 0.65, 0.28-0.34 and 0.18-0.25
times SGBM's (seeds 1-3), but on cleavage 63-72 % of the pixels kept against SGBM's 88-90 %:
DIS settles some facets wrongly, which the checks then mask. On the real pollen pairs
(2048 × 1536 px) it keeps 38, 25 and 22 % at ±3, ±6 and ±9° (without the coarse start 38, 12
and 8 %). A pair matched in strips differs slightly from the pair matched whole (DIS's coarsest
patches reach beyond a strip's context rows; median 0.01-0.02 px), at the same accuracy.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).

Reference: T. Kroeger, R. Timofte, D. Dai and L. Van Gool, "Fast Optical Flow using Dense Inverse
Search", ECCV 2016, doi:10.1007/978-3-319-46493-0_29.
"""

from __future__ import annotations

import cv2
import numpy as np

from fractoscope.stereo import correlation, semi_global, window_zncc
from fractoscope.stereo.disparity import DisparityResult, StripTask

# OpenCV's PRESET_FAST (8 px patches, 16 gradient-descent and 5 variational iterations, flow at a
# quarter of the resolution) with patches every 3 px instead of 4, measured on 1024² pairs: 0.4-2.4 %
# more of cleavage kept and 1 % more of the benchmark's pair, for a few per cent of the time.
# After the residual searches a finer flow gains little: PRESET_MEDIUM (half the resolution) or
# finest scale 1 took 1.5-1.7 times as long for 0-8 % less RMS error on smooth surfaces (4-6 %
# more of cleavage kept); PRESET_ULTRAFAST (no variational refinement) kept 0-9 % fewer pixels.
_PATCH_STRIDE_PX = 3
# Two residual searches: the first moves a pixel by whole pixels where the flow is more than
# half a pixel off (a peak at the search's edge gets no parabola), the second centres it. With
# one, the self-affine surfaces' RMS error is 0.77-0.82 times SGBM's instead of 0.65; a third
# gains 0-7 % for a sixth to a quarter more time.
_REFINEMENT_PASSES = 2
# The pair is rectified: a match more than this far across rows is a false one. On synthetic
# cleavage (facets DIS settles wrongly) the RMS error falls from 1.7-2.3 % of the range to
# 1.2-1.5 % for 1.4-2 % of the pixels; smooth surfaces lose none (0.5 px drops 3-4 % of them).
_MAX_ACROSS_ROWS_PX = 1.0
# The refined disparities err less than the window's calibrated peak sigma says: scaled by 0.8,
# 56-76 % of the errors on 640² and 1024² self-affine, dimple and cleavage pairs (seeds 1-3) lie
# within one sigma, 68 % on average, 93-100 % within three. Steeper relief, whose windows see
# foreshortening the sigma does not model, errs more: 38-50 % on 256² self-affine pairs, 43 %
# on the benchmark's pair.
_SIGMA_SCALE = 0.8
# OpenCV's DIS fails on images less than 4 patches high or wide, and crashed (OpenCV 5.1) on
# some 8-31 rows high: smaller strips are padded for it.
_MIN_SIDE_PX = 32


def match_strip(task: StripTask) -> DisparityResult:
    """Dense disparity of one strip of a rectified pair (the unit of work that replicas share).
    Masks (NaN) pixels whose peak correlation is below `task.min_confidence`, whose two flows
    disagree by more than `task.max_lr_difference_px`, whose flow crosses rows by more than
    1 px, whose window lies on a flat (textureless) patch, or that form small isolated islands
    among masked pixels; `kept_result` masks what lies at or beyond the search's limit.
    `task.propagate_at_full_resolution` is the window matcher's and not used here."""
    left, right = correlation.normalized(task.left), correlation.normalized(task.right)
    left_grey, right_grey = semi_global.grey_levels(left), semi_global.grey_levels(right)
    window_px, max_disparity_px = task.window_px, task.max_disparity_px
    forward = dense_flow(left_grey, right_grey, window_zncc.coarse_disparity(left, right, window_px, max_disparity_px))
    backward = dense_flow(right_grey, left_grey, window_zncc.coarse_disparity(right, left, window_px, max_disparity_px))
    forward_px, backward_px = np.ascontiguousarray(forward[..., 0]), np.ascontiguousarray(backward[..., 0])
    left_stats = correlation.window_stats(left, window_px)
    refined = refined_disparity(left, left_stats, right, forward_px, window_px)
    directions = window_zncc.Directions(left, right, refined, backward_px, left_stats)
    valid, _ = window_zncc.consistent(task, directions, forward_px, backward_px)
    valid &= window_zncc.in_bounds(refined.disparity) & (np.abs(forward[..., 1]) <= _MAX_ACROSS_ROWS_PX)
    sigma_px = _SIGMA_SCALE * correlation.peak_sigma_px(refined.score, refined.curvature, window_px)
    return window_zncc.kept_result(task, valid, refined.disparity, refined.score, sigma_px)


def dense_flow(first: np.ndarray, second: np.ndarray, start_px: np.ndarray) -> np.ndarray:
    """DIS optical flow from `first` to `second`, uint8 (rows, cols) each, starting from
    displacements `start_px` along rows ((rows, cols) float32): (rows, cols, 2) float32,
    [..., 0] the displacement along rows (the disparity), [..., 1] across them; pixel (row, col)
    of `first` shows what `second` shows at (row + [..., 1], col + [..., 0])."""
    rows, cols = first.shape
    pad_rows, pad_cols = max(_MIN_SIDE_PX - rows, 0), max(_MIN_SIDE_PX - cols, 0)
    start = np.zeros((rows + pad_rows, cols + pad_cols, 2), np.float32)
    start[:rows, :cols, 0] = start_px
    if pad_rows or pad_cols:
        first, second = (
            cv2.copyMakeBorder(image, 0, pad_rows, 0, pad_cols, cv2.BORDER_REPLICATE) for image in (first, second)
        )
    flow = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_FAST)  # one per call: calls may run on threads
    flow.setPatchStride(_PATCH_STRIDE_PX)
    return flow.calc(first, second, start)[:rows, :cols]


def refined_disparity(
    left: np.ndarray,
    left_stats: correlation.WindowStats,
    right: np.ndarray,
    disparity_px: np.ndarray,
    window_px: int,
) -> window_zncc.Refinement:
    """`disparity_px` ((rows, cols) float32) after `_REFINEMENT_PASSES` ±1 px ZNCC residual
    searches of `window_px` windows of `left` on `right` (normalized images, `left_stats` their
    window statistics), with the last search's peak score and second difference."""
    refined = window_zncc.residual_search(left, left_stats, right, disparity_px, window_px, 1)
    for _ in range(_REFINEMENT_PASSES - 1):
        refined = window_zncc.residual_search(left, left_stats, right, refined.disparity, window_px, 1)
    return refined
