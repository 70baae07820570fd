"""The default matching method: the window ZNCC matcher's disparities (`window_zncc`), refined in
both directions by TGV² over a 5 × 5 px ZNCC data term (`tgv_refinement`), which recovers
structure finer than the window, such as dimple rims, and averages noise where the surface is
smooth. A pixel is kept where the window matcher trusts it and the refined directions agree.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

import numpy as np

from fractoscope.stereo import correlation, tgv_refinement, window_zncc
from fractoscope.stereo.disparity import DisparityResult, StripTask


def match_strip(task: StripTask) -> DisparityResult:
    """Dense disparity of one strip of a rectified pair (the unit of work that replicas share),
    masked as `window_zncc.match_strip` masks it and where the refined directions differ by more
    than `task.max_lr_difference_px`."""
    directions = window_zncc.match_directions(task)
    forward = tgv_refinement.refine_disparity(directions.left, directions.right, directions.forward.disparity)
    backward = tgv_refinement.refine_disparity(directions.right, directions.left, directions.backward_px)
    window_valid, _ = window_zncc.consistent(task, directions, directions.forward.disparity, directions.backward_px)
    backward_at_match = correlation.sample_along_rows(backward.disparity_px, forward.disparity_px)
    disparity = 0.5 * (forward.disparity_px - backward_at_match)
    valid = window_valid & (np.abs(forward.disparity_px + backward_at_match) <= task.max_lr_difference_px)
    sigma_px = refined_sigma_px(forward.precision)
    return window_zncc.kept_result(task, valid, disparity, directions.forward.score, sigma_px)


def refined_sigma_px(precision: np.ndarray) -> np.ndarray:
    """Placeholder until calibrated."""
    return (1.0 / np.sqrt(np.maximum(precision, 1e-6))).astype(np.float32)
