"""Dense matching of a rectified stereo pair, whatever the method: both images are freed of smooth
shading (`local_contrast`), cut into overlapping strips of rows (`strip_bounds`, parallax runs
along rows, so a strip is a complete stereo problem), the strips are matched here or by peers
(`StripMatcher`) and stitched (`match_disparity`). The method that matches one strip is the
task's, by name in the one registry of methods (`METHODS`).

Cores: a strip's layout depends on the image and `strip_pixels` only, never on the machine, and
each strip is matched by the same code whatever runs beside it, so the result is the same on any
number of cores. Here strips are matched `strip_workers()` at a time on threads (the kernels are
OpenCV's and numba's, which release the GIL); each strip also runs its own work on two threads.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

from fractoscope.progress import ProgressCallback, silent
from fractoscope.stereo import optical_flow, tgv_zncc, window_zncc
from fractoscope.stereo.disparity import DEFAULT_METHOD, DisparityResult, StripMatcher, StripTask

DEFAULT_WINDOW_PX = 15
DEFAULT_MIN_CONFIDENCE = 0.3
DEFAULT_MAX_LR_DIFFERENCE_PX = 1.0
# The default search reaches a quarter of the width, at most this far: a thin strip of an image
# cannot be matched coarse to fine, and its full search costs a pass over the image per shift.
# 1024 px covers ±9° pairs of relief several times the pollen grain's (disparities over 200 px).
_MAX_DEFAULT_DISPARITY_PX = 1024
# Pixels per strip: bounds the matcher's memory, and is the unit of work replicas share.
DEFAULT_STRIP_PIXELS = 2_000_000
_LOCAL_CONTRAST_SIGMA_PX = 6.0


def match_disparity(
    left: np.ndarray,
    right: np.ndarray,
    *,
    window_px: int = DEFAULT_WINDOW_PX,
    max_disparity_px: int | None = None,
    min_confidence: float = DEFAULT_MIN_CONFIDENCE,
    max_lr_difference_px: float = DEFAULT_MAX_LR_DIFFERENCE_PX,
    normalize_local_contrast: bool = True,
    propagate_at_full_resolution: bool = False,
    method: str = DEFAULT_METHOD,
    strip_pixels: int = DEFAULT_STRIP_PIXELS,
    strip_matcher: StripMatcher | None = None,
    progress: ProgressCallback | None = None,
) -> DisparityResult:
    """Matches `left` to `right`, both (rows, cols) grey images of one size, rectified so that
    parallax runs along rows. Masks (NaN) pixels whose peak correlation is below `min_confidence`,
    whose left-to-right and right-to-left disparities differ by more than
    `max_lr_difference_px`, whose window lies on a flat (textureless) patch, or that form small
    isolated islands among masked pixels. With `normalize_local_contrast` both images are first
    freed of smooth shading and evened out in contrast (see `local_contrast`). Strips are
    matched by `method` (a key of `METHODS`). The window ZNCC method (`window_zncc.match_strip`, where
    the default starts) lets each pixel try its neighbours' disparities at every pyramid level
    but the finest; `propagate_at_full_resolution` does so at the finest level too, for surfaces
    with steps, at about 1.5 times the matching time.

    Large images are matched in overlapping strips of rows of about `strip_pixels` pixels each,
    which bounds memory; parallax runs along rows, so a strip is a complete stereo problem.
    `strip_matcher` matches them: here by default, `strip_workers()` at a time (`match_strips`),
    or by peers; the result is the same either way."""
    if left.shape != right.shape or left.ndim != 2:
        raise ValueError(f"left and right must be 2D of one shape, got {left.shape} and {right.shape}")
    if window_px < 3 or window_px % 2 == 0:
        raise ValueError(f"window_px must be odd and >= 3, got {window_px}")
    report = progress or silent
    if max_disparity_px is None:
        max_disparity_px = default_max_disparity_px(left.shape[1])
    if normalize_local_contrast:  # on the whole images, so that every strip sees the same values
        with ThreadPoolExecutor(max_workers=2) as pool:  # OpenCV releases the GIL
            left, right = pool.map(local_contrast, (left, right))
    bounds = strip_bounds(left.shape, window_px=window_px, max_disparity_px=max_disparity_px, strip_pixels=strip_pixels)
    tasks = (
        StripTask(
            left[top:bottom],
            right[top:bottom],
            window_px,
            max_disparity_px,
            min_confidence,
            max_lr_difference_px,
            keep_rows=(start - top, stop - top),
            propagate_at_full_resolution=propagate_at_full_resolution,
            method=method,
        )
        for top, start, stop, bottom in bounds
    )
    report(0.0, f"matching {len(bounds)} strip{'s' if len(bounds) > 1 else ''}")
    return _stitched(left.shape, bounds, (strip_matcher or match_strips)(tasks), report)


def _stitched(
    shape: tuple[int, int],
    bounds: list[tuple[int, int, int, int]],
    strips: Iterable[DisparityResult],
    report: ProgressCallback,
) -> DisparityResult:
    """One result of `shape` (rows, cols), float32, from the `strips` matched on `bounds` (see
    strip_bounds), each giving its rows start:stop; progress is reported as each strip arrives."""
    disparity = np.empty(shape, np.float32)
    confidence = np.empty(shape, np.float32)
    sigma_px = np.empty(shape, np.float32)
    for index, ((_, start, stop, _), strip) in enumerate(zip(bounds, strips)):
        for out, values in zip(
            (disparity, confidence, sigma_px), (strip.disparity_px, strip.confidence, strip.sigma_px)
        ):
            out[start:stop] = values
        report((index + 1) / len(bounds), f"matched strip {index + 1} of {len(bounds)}")
    return DisparityResult(disparity, confidence, sigma_px)


def default_max_disparity_px(cols: int) -> int:
    """The search range of images `cols` wide when none is given: a quarter of the width, at
    least 8 and at most 1024 px."""
    return min(max(cols // 4, 8), _MAX_DEFAULT_DISPARITY_PX)


def strip_bounds(
    shape: tuple[int, int], *, window_px: int, max_disparity_px: int, strip_pixels: int
) -> list[tuple[int, int, int, int]]:
    """Strips of about `strip_pixels` pixels covering `shape` (rows, cols): (top, start, stop,
    bottom) rows, where rows start:stop are kept from the strip matched on rows top:bottom. The
    overlap is the context the method needs (`window_zncc.context_rows`), so strips join seamlessly."""
    rows, cols = shape
    overlap = window_zncc.context_rows(
        (min(rows, max(strip_pixels // cols, 1)), cols), window_px=window_px, max_disparity_px=max_disparity_px
    )
    core_rows = max(strip_pixels // cols - 2 * overlap, 4 * overlap)
    bounds = []
    for start in range(0, rows, core_rows):
        stop = min(start + core_rows, rows)
        if rows - stop < overlap:  # a thin remainder joins this strip
            stop = rows
        bounds.append((max(start - overlap, 0), start, stop, min(stop + overlap, rows)))
        if stop == rows:
            break
    return bounds


# The matching methods by name, each the function that matches one strip: the one registry of
# them, which the API's MatchingMethod enum names alike (MATCHING_METHOD_<NAME>; the tests hold
# them equal). `tgv_zncc` (the default, accuracy first) refines `window_zncc`'s disparities by
# TGV² over a small-window ZNCC data term; `window_zncc` is the paper's window correlation;
# `fast` refines DIS optical flow by ZNCC residual searches.
METHODS: dict[str, Callable[[StripTask], DisparityResult]] = {
    "tgv_zncc": tgv_zncc.match_strip,
    "window_zncc": window_zncc.match_strip,
    "fast": optical_flow.match_strip,
}


def match_strip(task: StripTask) -> DisparityResult:
    """One strip matched by its task's method."""
    return METHODS[task.method](task)


def strip_workers() -> int:
    """How many strips this process matches at once: one per two of the CPUs it may run on (each
    strip keeps about two busy, its two directions on threads of their own), at least one."""
    return max(1, len(os.sched_getaffinity(0)) // 2)


def match_strips(tasks: Iterable[StripTask], *, workers: int | None = None) -> Iterator[DisparityResult]:
    """Matches strips in this process, `workers` at a time (default `strip_workers()`), yielding
    their results in the order of `tasks`. The result does not depend on `workers`; peak memory
    grows with it (one strip's per worker)."""
    workers = strip_workers() if workers is None else workers
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if workers == 1:
        yield from map(match_strip, tasks)
        return
    with ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fractoscope-strip") as pool:
        yield from pool.map(match_strip, tasks)


def local_contrast(image: np.ndarray) -> np.ndarray:
    """(rows, cols) grey image minus its local mean (Gaussian, σ = 6 px), divided by its local
    standard deviation (σ = 3 px) where that exceeds the median one, float32. Removes smooth
    shading, which in SEM changes with the tilt, and tones down bright edges and steep walls, so
    that they do not dominate a correlation window; weakly textured areas are not amplified."""
    values = image.astype(np.float32)
    detail = values - cv2.GaussianBlur(values, (0, 0), _LOCAL_CONTRAST_SIGMA_PX)
    spread = np.sqrt(cv2.GaussianBlur(detail * detail, (0, 0), _LOCAL_CONTRAST_SIGMA_PX / 2))
    typical = float(np.median(spread[::4, ::4]))  # every 16th pixel tells the median well enough
    return detail / np.maximum(spread, max(typical, 1e-6))
