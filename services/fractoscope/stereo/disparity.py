"""What a dense matching method takes and gives: one strip of a rectified pair with the matcher's
settings (`StripTask`), and the dense disparity found (`DisparityResult`).

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class DisparityResult:
    """Dense disparity of a rectified pair.

    disparity_px: (rows, cols) float32, NaN where masked.
    confidence: (rows, cols) float32, peak ZNCC clipped to [0, 1].
    sigma_px: (rows, cols) float32, one-sigma disparity uncertainty, NaN where masked.
    """

    disparity_px: np.ndarray
    confidence: np.ndarray
    sigma_px: np.ndarray


# The matching method by default (a key of matching.METHODS), accuracy first.
DEFAULT_METHOD = "tgv_zncc"


@dataclass(frozen=True)
class StripTask:
    """One strip of rows of a rectified pair with the matcher's settings: a complete stereo
    problem, since parallax runs along rows (see `matching.strip_bounds`). `keep_rows` (first, stop): the
    rows of the strip whose results are wanted (None: all); the rest only give context. `method`: the
    name of the method that matches it, a key of `matching.METHODS`."""

    left: np.ndarray
    right: np.ndarray
    window_px: int
    max_disparity_px: int
    min_confidence: float
    max_lr_difference_px: float
    keep_rows: tuple[int, int] | None = None
    propagate_at_full_resolution: bool = False
    method: str = DEFAULT_METHOD


# Matches strips, yielding their results in order: `match_strips` here, or peers over the network.
StripMatcher = Callable[[Iterable[StripTask]], Iterator[DisparityResult]]
