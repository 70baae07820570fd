"""Occlusions next to walls: the band of a lower facet that a wall hides from the other view.

Seen along parallel rays, a surface point's match lies right of the matches of every point left
of it, as long as both views see them. Where the disparity falls by D px across a wall whose top
is on the left, the other view looks past the top straight onto the lower facet D px further
on. The D px of the lower facet right of the wall then have no match: a hidden band, which
belongs to the lower facet. This holds for either direction of matching and either sign of the
tilt. Two consequences are used here:

- Semi-global matching leaves the band without disparities, and a window matcher fills it with
  a blur of both facets' disparities. The refinement should start the band at the lower
  facet's disparity, not at the blur (`hidden_bands_filled`).
- The band's pixels next to the wall take the upper facet's disparity in both directions
  ("foreground fattening"), so the left-right check keeps them. Where the lower facet's texture
  is weak, their small windows have no correlation peak of their own: the regularizer carried
  the disparity there. Such pixels are dropped (`unsupported_beside_occlusions`).

What the two rules gain, and why the ordering constraint itself is not enforced: docs/matching-notes.md.

Convention: disparity d at pixel (row, col) means it matches pixel (row, col + d) of the other
image.
"""

from __future__ import annotations

import numba
import numpy as np

from fractoscope.stereo import correlation

# A fall in disparity across a hole by more than this is taken for a wall hiding a band (smaller
# falls hide less than a pixel).
OCCLUSION_DROP_PX = 1.0


def hidden_bands_filled(seed_px: np.ndarray, fallback_px: np.ndarray) -> np.ndarray:
    """`seed_px` (rows, cols, NaN where unknown) with its holes filled: by the disparity after
    the hole where the one before it is higher by more than `OCCLUSION_DROP_PX` (a hidden band,
    which belongs to the facet after it), by `fallback_px` (rows, cols) elsewhere; float32."""
    known = np.isfinite(seed_px)
    before, after = correlation.nearest_known_along_rows(known)
    cols = seed_px.shape[1]
    at_before = np.take_along_axis(seed_px, np.clip(before, 0, cols - 1), axis=1)
    at_after = np.take_along_axis(seed_px, np.clip(after, 0, cols - 1), axis=1)
    drop_px = at_before - at_after
    width_px = after - before - 1
    hidden = ~known & (before >= 0) & (after < cols) & (drop_px > OCCLUSION_DROP_PX) & (width_px <= 1.5 * drop_px + 2)
    return np.where(known, seed_px, np.where(hidden, at_after, fallback_px)).astype(np.float32)


def unsupported_beside_occlusions(disparity_px: np.ndarray, valid: np.ndarray, supported: np.ndarray) -> np.ndarray:
    """The `valid` pixels just before a hidden band that took their disparity from their
    neighbours, (rows, cols) bool: to be dropped.

    A hole in `valid` whose disparity falls by D > `OCCLUSION_DROP_PX` across it may start up to
    D px earlier than the masks say, so of the last ⌈D⌉ valid pixels before it the trailing run
    in which pixels without a correlation peak of their own (not `supported`) outnumber those
    with one is dropped. `disparity_px` (rows, cols) float, finite where `valid`."""
    return _unsupported_beside_occlusions(
        np.asarray(disparity_px, np.float64),
        np.asarray(valid, np.bool_),
        np.asarray(supported, np.bool_),
        OCCLUSION_DROP_PX,
    )


@numba.njit(nogil=True, cache=True, boundscheck=False)
def _unsupported_beside_occlusions(disparity_px, valid, supported, min_drop_px):  # pragma: no cover - compiled
    rows, cols = valid.shape
    dropped = np.zeros((rows, cols), np.bool_)
    for row in range(rows):
        col = 0
        while col < cols:
            if valid[row, col]:
                col += 1
                continue
            start = col  # a hole: [start, col)
            while col < cols and not valid[row, col]:
                col += 1
            if start == 0 or col == cols:
                continue
            drop_px = disparity_px[row, start - 1] - disparity_px[row, col]
            if not drop_px > min_drop_px or (col - start) < 0.5 * drop_px:
                continue
            first = start
            while first > 0 and start - first < np.ceil(drop_px) and valid[row, first - 1]:
                first -= 1
            # Keep [first, split), drop [split, start): the split that minimizes the kept
            # unsupported pixels plus half the dropped ones.
            cost = 0.5 * (start - first)
            best_cost, split = cost, first
            for index in range(first, start):
                cost += (0.0 if supported[row, index] else 1.0) - 0.5
                if cost < best_cost:
                    best_cost, split = cost, index + 1
            dropped[row, split:start] = True
    return dropped
