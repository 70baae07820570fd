"""The default matching method: semi-global matching's disparities (`semi_global`, which
places steps and keeps facets whole), the window ZNCC matcher's
(`window_zncc`) where it has none, refined in both directions by TGV² over a 5 × 5 px ZNCC data
term (`tgv_refinement`), which recovers structure finer than the window, such as dimple rims and
river steps, and averages noise where the surface is smooth.

Before the refinement every pixel that semi-global matching left without a disparity tries
the disparities found 8, 16 and 32 px to its left, right, above and below, scored by a 9 × 9 px
window, and keeps one that correlates clearly better than its own (`_propagated`). Next to a
wall between cleavage facets the 15 px window is dominated by the wall's bright texture and
takes the other side's disparity; the refinement's data term only looks ±1 px around it, so the
right side's disparity has to be offered (on synthetic cleavage at ±5° this took the RMS error
from 2.6 % to 1.6 % of the range, before the semi-global seed). Where semi-global matching has a
disparity it is kept: it places steps where the pixels put them, and a 9 × 9 px window next to
a wall is still dominated by it, so propagating there spread the other side's disparity in
blobs that the left-right check then masked. Seeded pixels kept as they are, synthetic cleavage
(seeds 1-4) measures 1.23, 1.55, 1.42, 1.16 % at ±5° and 88, 87, 91, 87 % valid (propagated
everywhere: 1.24, 1.71, 1.52, 1.11 %; 84, 83, 89, 85 %), 2.60, 3.08, 3.25, 2.62 % at 0/10° and
90, 87, 91, 87 % valid (2.55, 3.11, 3.31, 2.66 %; 87, 85, 90, 86 %); dimples, the self-affine
surface and the overview within 0.02 points. Trying 4 px away as well measured no better on
three surfaces of each kind (cleavage ±5°: 1.79, 3.73 and 1.90 % against 1.56, 3.57 and 1.85 %;
dimples and self-affine within 0.03 points), at a third more of the propagation's time.

A pixel is kept where the refined directions agree within `task.max_lr_difference_px` and either
the window matcher trusts it (as `window_zncc.match_strip` masks) or the refined directions
agree within three quarters of a pixel on a textured window: two independent refinements that
meet so closely have found the same surface point, even where the window's correlation is weak
(faint facets, a flat substrate).

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from fractoscope.stereo import correlation, semi_global, tgv_refinement, visibility, window_zncc
from fractoscope.stereo.disparity import DisparityResult, StripTask

# The refined disparities err less than the window's: on the synthetic surfaces 68 % of their
# errors fall within 0.5-0.86 of the window matcher's calibrated peak sigma (dimples 0.5,
# cleavage 0.7, self-affine 0.85), which ranks them better than the data term's own precision.
# 0.8 leaves 60-65 % of the self-affine surface's errors within one sigma, more of the others'.
_REFINED_SIGMA_SCALE = 0.8
# Within half a pixel the real pollen pair (±3°) is 63 % measured, within 0.75 px 70 % (grain
# heights and substrate flatness unchanged); synthetic cleavage then keeps 86-88 % instead of
# 84-87 % at 1.8 % RMS (±5°) instead of 1.6 %, dimples 3.0-3.1 % instead of 2.9-3.0 %.
AGREEING_PX = 0.75
# A small window that locates its match within a pixel supports it (`visibility`): 0.7 and 1.5
# px measured up to 0.2 points of RMS error worse on synthetic cleavage at 0/10° (seeds 1, 2).
_PEAK_SIGMA_PX = 1.0
_PROPAGATION_WINDOW_PX = 9
_PROPAGATION_STEPS_PX = (8, 16, 32)
# A neighbour's disparity replaces a pixel's own only if its score is this much higher: equal
# scores are noise, and the replacement would then only shuffle the texture's errors.
_PROPAGATION_MARGIN = 0.02


def match_strip(task: StripTask) -> DisparityResult:
    """Dense disparity of one strip of a rectified pair (the unit of work that replicas share)."""
    directions = window_zncc.match_directions(task)
    window_valid, _ = window_zncc.consistent(task, directions, directions.forward.disparity, directions.backward_px)
    # The directions are independent, and OpenCV, numpy and the compiled kernels release the GIL,
    # so they overlap (semi-global matching and the propagation run on one thread each).
    with ThreadPoolExecutor(max_workers=2) as pool:
        forward_job = pool.submit(_refined, directions.left, directions.right, directions.forward.disparity)
        backward = _refined(directions.right, directions.left, directions.backward_px)
        forward = forward_job.result()
    backward_at_match = correlation.sample_along_rows(backward, forward)
    disparity = 0.5 * (forward - backward_at_match)  # the directions err independently
    difference = np.abs(forward + backward_at_match)
    agreeing = (difference <= AGREEING_PX) & window_zncc.textured(directions) & window_zncc.in_bounds(disparity)
    agreeing &= ~window_zncc.speckles(disparity, agreeing)
    valid = (window_valid | agreeing) & (difference <= task.max_lr_difference_px)
    valid &= ~visibility.unsupported_beside_occlusions(disparity, valid, _peaked(directions, disparity))
    window = directions.forward
    sigma_px = _REFINED_SIGMA_SCALE * correlation.peak_sigma_px(window.score, window.curvature, task.window_px)
    return window_zncc.kept_result(task, valid, disparity, window.score, sigma_px)


def _peaked(directions: window_zncc.Directions, disparity_px: np.ndarray) -> np.ndarray:
    """Where the refinement's data term at `disparity_px` has a correlation peak of its own that
    locates the match within `_PEAK_SIGMA_PX`, (rows, cols) bool."""
    window_px = tgv_refinement.DATA_WINDOW_PX
    stats = correlation.window_stats(directions.left, window_px)
    disparity_px = np.nan_to_num(disparity_px).astype(np.float32)
    _, precision = tgv_refinement.data_term(directions.left, stats, directions.right, disparity_px, window_px)
    return precision >= 1.0 / _PEAK_SIGMA_PX**2


def _refined(left: np.ndarray, right: np.ndarray, window_px: np.ndarray) -> np.ndarray:
    """One direction's disparities: semi-global matching's where it has them, the window
    matcher's (`window_px`) propagated elsewhere, refined."""
    seed = semi_global.seed_disparity(left, right, window_px)
    start = visibility.hidden_bands_filled(seed, window_px)
    start = np.where(np.isfinite(seed), start, _propagated(left, right, start))
    return tgv_refinement.refine_disparity(left, right, start)


def _propagated(left: np.ndarray, right: np.ndarray, disparity_px: np.ndarray) -> np.ndarray:
    """`disparity_px` (rows, cols float32) after each pixel has tried its neighbours' disparities
    at `_PROPAGATION_STEPS_PX` along rows and columns, one after another, with a ±1 px residual
    search scored by a `_PROPAGATION_WINDOW_PX` window; `left` and `right` normalized images."""
    stats = correlation.window_stats(left, _PROPAGATION_WINDOW_PX)
    best = window_zncc.residual_search(left, stats, right, disparity_px, _PROPAGATION_WINDOW_PX, 1)
    disparity, score = best.disparity, best.score
    for step in _PROPAGATION_STEPS_PX:
        for row_step, col_step in ((0, step), (0, -step), (step, 0), (-step, 0)):
            candidate = window_zncc.residual_search(
                left, stats, right, window_zncc.shifted(disparity, row_step, col_step), _PROPAGATION_WINDOW_PX, 1
            )
            better = candidate.score > score + _PROPAGATION_MARGIN
            disparity = np.where(better, candidate.disparity, disparity).astype(np.float32)
            score = np.where(better, candidate.score, score)
    return disparity
