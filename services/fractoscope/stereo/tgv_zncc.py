"""The default matching method: semi-global matching's disparities (`semi_global`, which
places steps and keeps facets whole), the window ZNCC matcher's (`window_zncc`) where it has
none, refined in both directions by TGV² over a 5 × 5 px ZNCC data term (`tgv_refinement`),
which recovers structure finer than the window, such as dimple rims and river steps, and
averages noise where the surface is smooth.

Before the refinement every pixel that semi-global matching left without a disparity tries the
disparities found 8, 16 and 32 px to its left, right, above and below, scored by a 9 × 9 px
window, and keeps one that correlates clearly better than its own (`_propagated`): next to a wall
the window takes the wall's side, and the refinement's data term only looks ±1 px around its
start. Where semi-global matching has a disparity it is kept.

A pixel is kept where the refined directions agree within `task.max_lr_difference_px` and either
the window matcher trusts it (as `window_zncc.match_strip` masks) or the refined directions agree
within `AGREEING_PX` on a textured window: two independent refinements that meet so closely have
found the same surface point, even where the window's correlation is weak.

The measurements behind these choices and constants: docs/matching-notes.md.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import numpy as np

from fractoscope.stereo import correlation, semi_global, tgv_refinement, visibility, window_zncc
from fractoscope.stereo.disparity import DisparityResult, StripTask

# The refined disparities' sigma, per pixel: sqrt((0.6 σ_window)² + (4 D)²), σ_window the window
# matcher's calibrated peak sigma and D the strip's robust RMS half-disagreement of the two
# refined directions (`calibrated_sigma_px`). The directions share most of their error (the views'
# different shading misleads both alike): the true errors are 3-8 times D, and D grows where the
# shading differs more. Both constants were fitted on the default renderer only (docs/matching-notes.md).
_WINDOW_SIGMA_SCALE = 0.6
_DISAGREEMENT_SCALE = 4.0
# The median of a squared unit normal: turns a median of squares into a variance.
_MEDIAN_OF_CHI2_1 = 0.455
# How closely the two refined directions must meet to keep a pixel the window does not trust, px.
AGREEING_PX = 0.75
# A small window that locates its match within this many px supports it (`visibility`).
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
    # so they overlap (semi-global matching, the propagation and the TGV² sweeps run on one thread each).
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
    window_sigma_px = correlation.peak_sigma_px(window.score, window.curvature, task.window_px)
    sigma_px = calibrated_sigma_px(window_sigma_px, forward + backward_at_match, valid)
    return window_zncc.kept_result(task, valid, disparity, window.score, sigma_px)


def calibrated_sigma_px(window_sigma_px: np.ndarray, disagreement_px: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """The refined disparities' one-sigma uncertainty, (rows, cols) float32 px: the window
    matcher's peak sigma (`window_sigma_px`) in quadrature with the disagreement of the two
    refined directions (`disagreement_px`, forward plus backward at the match: their mean's error
    is half of it where they err independently) as this strip shows it over its `valid` pixels,
    robustly (a median), each scaled as measured (`_WINDOW_SIGMA_SCALE`, `_DISAGREEMENT_SCALE`)."""
    half_squared = 0.25 * np.square(disagreement_px[valid], dtype=np.float64)
    spread_px = float(np.sqrt(np.median(half_squared) / _MEDIAN_OF_CHI2_1)) if half_squared.size else 0.0
    return np.sqrt(
        np.square(np.float32(_WINDOW_SIGMA_SCALE) * window_sigma_px) + np.float32(_DISAGREEMENT_SCALE * spread_px) ** 2
    ).astype(np.float32)


def _peaked(directions: window_zncc.Directions, disparity_px: np.ndarray) -> np.ndarray:
    """Where the refinement's data term at `disparity_px` has a correlation peak of its own that
    locates the match within `_PEAK_SIGMA_PX`, (rows, cols) bool."""
    window_px = tgv_refinement.DATA_WINDOW_PX
    stats = correlation.window_stats(directions.left, window_px)
    disparity_px = np.nan_to_num(disparity_px).astype(np.float32)
    _, precision = tgv_refinement.data_term(directions.left, stats, directions.right, disparity_px, window_px)
    return precision >= 1.0 / _PEAK_SIGMA_PX**2


def _refined(left: np.ndarray, right: np.ndarray, window_disparity_px: np.ndarray) -> np.ndarray:
    """One direction's disparities: semi-global matching's where it has them, the window
    matcher's (`window_disparity_px`) propagated elsewhere, refined."""
    seed = semi_global.seed_disparity(left, right, window_disparity_px)
    start = visibility.hidden_bands_filled(seed, window_disparity_px)
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
