"""Where a grid mesh ends: its outline along the measured mask, islands too small to trust, and what
stands in for the unmeasured rest.

A grid mesh makes two triangles of each quad whose four corners are measured (mesh.grid). Its
outline then steps cell by cell. A quad with three measured corners also gets the one triangle of
those three, so that the outline runs diagonally across the cell instead of around it: a mask's
oblique edge becomes straight, not a staircase.

Islands: a measured patch smaller than a matching window cannot hold one measurement its
surroundings did not reject (the correlation window of stereo.matching, 15 x 15 px, is what one
height is measured from); such patches hang in the air as specks. `drop_islands` removes the
connected patches of complete quads below a given area.

Unmeasured areas are shown as absent (nothing drawn) or as a flat floor at height zero (the datum
when the heights were levelled on one): the grid's other triangles, with no relief of their own.

Quad (i, j) has the corners a = (i, j), b = (i, j + 1), c = (i + 1, j), d = (i + 1, j + 1) (row,
column); its usual triangles are (a, c, b) and (b, c, d), counter-clockwise seen from above.
"""

from __future__ import annotations

import enum

import cv2
import numpy as np

from fractoscope.stereo.matching import DEFAULT_WINDOW_PX

# One matching window's area: see the module docstring.
DEFAULT_MIN_ISLAND_PX = DEFAULT_WINDOW_PX**2


class Unmeasured(enum.Enum):
    """How areas without measured heights are drawn."""

    ABSENT = "absent"
    FLAT = "flat"  # a flat grey floor at height zero


def quad_corners(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """(a, b, c, d): the values at each quad's corners, (rows - 1, cols - 1) views each, of a (rows,
    cols) grid."""
    return values[:-1, :-1], values[:-1, 1:], values[1:, :-1], values[1:, 1:]


def chamfer_triangles(index: np.ndarray) -> np.ndarray:
    """(M, 3) vertex indices: one triangle per quad with exactly three corners that have a vertex
    index (`index` (rows, cols), -1 where none), of those three corners, counter-clockwise seen
    from above; quads in row-major order."""
    a, b, c, d = (values.ravel() for values in quad_corners(index))
    known = np.column_stack([a, b, c, d]) >= 0
    three = known.sum(axis=1) == 3
    a, b, c, d, known = a[three], b[three], c[three], d[three], known[three]
    # The missing corner decides the triangle: a -> (b, c, d), b -> (a, c, d), c -> (a, d, b), d -> (a, c, b).
    missing = [~known[:, k] for k in range(4)]
    choices = [np.column_stack(t) for t in ((b, c, d), (a, c, d), (a, d, b), (a, c, b))]
    return np.select([m[:, None] for m in missing], choices).astype(np.int64).reshape(-1, 3)


def floor_triangles(index: np.ndarray, known: np.ndarray) -> np.ndarray:
    """(M, 3) triangles of the grid `index` ((rows, cols) vertex indices of every grid point) that
    the surface of the `known` points ((rows, cols) bool) leaves uncovered: both triangles of a
    quad with at most two known corners, and the other half of a chamfered quad (three known)."""
    a, b, c, d = (values.ravel() for values in quad_corners(index))
    ka, kb, kc, kd = (values.ravel() for values in quad_corners(known))
    count = ka.astype(np.int8) + kb + kc + kd
    open_quad = count <= 2
    upper, lower = np.column_stack([a, c, b]), np.column_stack([b, c, d])
    left, right = np.column_stack([a, c, d]), np.column_stack([a, d, b])
    three = count == 3
    parts = [
        upper[open_quad | (three & ~ka)],
        lower[open_quad | (three & ~kd)],
        right[three & ~kc],
        left[three & ~kb],
    ]
    return np.concatenate(parts).astype(np.int64)


def drop_islands(z_um: np.ndarray, *, min_area_cells: float, keep_edge: bool = False) -> tuple[np.ndarray, int]:
    """`z_um` ((rows, cols) heights, NaN unknown) without its islands, and how many it dropped.

    An island is a patch of complete quads (four known corners) connected through shared corners
    with fewer than `min_area_cells` quads; its heights, and every known point that is no corner of
    a kept patch's quad (it would make at most a lone triangle), become NaN. With `keep_edge`, patches
    that reach the grid's edge are kept whatever their size (the grid is a piece of a larger surface
    they may go on in). The largest patch is never an island: a map too small for the threshold is
    kept whole rather than emptied, and so is a grid of one row or column (it has no quad)."""
    known = np.isfinite(z_um)
    complete = np.logical_and.reduce(quad_corners(known))
    if not known.any() or complete.size == 0:
        return z_um, 0
    count, labels, stats, _ = cv2.connectedComponentsWithStats(complete.astype(np.uint8), connectivity=8)
    small = stats[:, cv2.CC_STAT_AREA] < min_area_cells
    small[0] = False  # the background
    if count > 1:
        small[1 + np.argmax(stats[1:, cv2.CC_STAT_AREA])] = False
    if keep_edge:
        edge = np.unique(np.concatenate([labels[0], labels[-1], labels[:, 0], labels[:, -1]]))
        small[edge] = False
    kept_quads = complete & ~small[labels]
    kept = np.zeros_like(known)
    for rows, cols in ((slice(None, -1), slice(None, -1)), (slice(None, -1), slice(1, None))):
        kept[rows, cols] |= kept_quads
    for rows, cols in ((slice(1, None), slice(None, -1)), (slice(1, None), slice(1, None))):
        kept[rows, cols] |= kept_quads
    dropped = int(small.sum())
    if keep_edge:  # points of a patch that reaches the edge but has no complete quad yet may go on there too
        kept |= known & _on_edge(known.shape)
    if kept.sum() == known.sum():
        return z_um, dropped
    return np.where(kept, z_um, np.float32(np.nan)).astype(z_um.dtype, copy=False), dropped


def _on_edge(shape: tuple[int, int]) -> np.ndarray:
    edge = np.zeros(shape, bool)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    return edge
