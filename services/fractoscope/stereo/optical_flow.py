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

A pair matched in strips differs slightly from the pair matched whole: DIS's coarsest patches
reach beyond a strip's context rows. The measurements behind the method and its constants:
docs/matching-notes.md.

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
# quarter of the resolution) with patches every 3 px instead of 4: more of stepped surfaces kept
# for a few per cent of the time; after the residual searches a finer flow gains little.
_PATCH_STRIDE_PX = 3
# Two residual searches: the first moves a pixel by whole pixels where the flow is more than
# half a pixel off (a peak at the search's edge gets no parabola), the second centres it.
_REFINEMENT_PASSES = 2
# The pair is rectified: a match more than this far across rows is a false one (DIS settles some
# cleavage facets wrongly).
_MAX_ACROSS_ROWS_PX = 1.0
# The refined disparities err less than the window's calibrated peak sigma says.
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
