"""Walls: triangles of a 2.5D mesh that bridge a height jump no measurement supports.

Where the surface drops by more than a stereo pair can see (the rim of a grain, the edge of a hole,
a cliff), a grid mesh stretches a "curtain" from the top to the bottom. A matcher measures
neighbouring points only while their disparities differ by less than their distance (the
disparity gradient limit, `stereo.geometry.max_measurable_slope`); beyond it one view sees what
the other cannot. So an edge whose ends, a horizontal distance L apart, differ in height by more
than `max_slope` L plus WALL_SIGMA_FACTOR times their combined local uncertainty is no measured
surface: each triangle with such an edge is a wall. Walls are kept apart from the surface (a
separate primitive in the GLB, shown differently) and left out of geometric errors, which they
would otherwise dominate.
"""

from __future__ import annotations

import cv2
import numpy as np

WALL_SIGMA_FACTOR = 3.0
# A height whose matching sigma exceeds the height this many pixels of disparity make is no
# measurement (the matcher did not locate its correlation peak) and is not meshed: 1.07 µm on the
# ±3° pollen pair, where 15 % of the heights (the substrate's speckle, up to 9 µm) lie beyond it.
MAX_MESHED_SIGMA_DISPARITY_PX = 2.0
# A real jump runs along a cliff or a rim: its wall quads connect into a chain of at least this many;
# fewer are steps between noisy neighbours (a substrate measured to ±1 µm at 0.06 µm/px), no jump.
MIN_WALL_QUADS = 8


def max_meshed_sigma_um(*, max_slope: float, pixel_size_um: float) -> float:
    """The largest local sigma a meshed height may have, µm: MAX_MESHED_SIGMA_DISPARITY_PX pixels of
    disparity (one pixel of disparity is `max_slope` pixels of height for the widest pair)."""
    return MAX_MESHED_SIGMA_DISPARITY_PX * max_slope * pixel_size_um


def unsupported(dz_um: np.ndarray, length_um: np.ndarray, sigma_a_um, sigma_b_um, *, max_slope: float) -> np.ndarray:
    """Whether height differences `dz_um` over horizontal distances `length_um` (arrays of one
    shape; sigmas broadcast) are steeper than the measurement supports."""
    with np.errstate(invalid="ignore"):
        allowed = max_slope * np.asarray(length_um) + WALL_SIGMA_FACTOR * np.hypot(sigma_a_um, sigma_b_um)
        return np.abs(dz_um) > allowed


def wall_triangles(
    xy_um: np.ndarray,
    z_um: np.ndarray,
    triangles: np.ndarray,
    *,
    max_slope: float | None,
    sigma_um: np.ndarray | float = 0.0,
) -> np.ndarray:
    """(M,) bool: the triangles (M, 3) of vertices at `xy_um` (N, 2) with heights `z_um` (N,) and
    local one-sigma uncertainties `sigma_um` ((N,) or one value), µm, that have an edge steeper
    than `max_slope` allows (none when it is None)."""
    if max_slope is None or len(triangles) == 0:
        return np.zeros(len(triangles), bool)
    sigma = np.broadcast_to(np.asarray(sigma_um, np.float64), z_um.shape)
    walls = np.zeros(len(triangles), bool)
    for first, second in ((0, 1), (1, 2), (2, 0)):
        a, b = triangles[:, first], triangles[:, second]
        length = np.hypot(*(xy_um[a] - xy_um[b]).T)
        walls |= unsupported(z_um[a] - z_um[b], length, sigma[a], sigma[b], max_slope=max_slope)
    return walls


def grid_wall_triangles(
    x_um: np.ndarray, y_um: np.ndarray, z_um: np.ndarray, *, max_slope: float | None, sigma_um: np.ndarray | float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """Walls of a grid of vertices (rows, cols) at (x_um, y_um) with heights z_um (NaN unknown)
    and local sigmas, µm, triangulated as the meshes are: each quad (a b / c d) as (a, c, b) and
    (b, c, d). Returns whether each quad's upper-left (a, c, b) and lower-right (b, c, d) triangle
    is a wall, (rows - 1, cols - 1) bool each; none when `max_slope` is None."""
    rows, cols = z_um.shape
    shape = (max(rows - 1, 0), max(cols - 1, 0))
    if max_slope is None or 0 in shape:
        return np.zeros(shape, bool), np.zeros(shape, bool)
    sigma = np.broadcast_to(np.asarray(sigma_um, np.float64), z_um.shape)
    corners = {
        name: (slice(r, rows - 1 + r), slice(c, cols - 1 + c))
        for name, (r, c) in {"a": (0, 0), "b": (0, 1), "c": (1, 0), "d": (1, 1)}.items()
    }

    def edge(first: str, second: str) -> np.ndarray:
        p, q = corners[first], corners[second]
        length = np.hypot(x_um[p] - x_um[q], y_um[p] - y_um[q])
        return unsupported(z_um[p] - z_um[q], length, sigma[p], sigma[q], max_slope=max_slope)

    diagonal = edge("b", "c")
    return edge("a", "b") | edge("a", "c") | diagonal, diagonal | edge("b", "d") | edge("c", "d")


def real_jumps(upper: np.ndarray, lower: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`grid_wall_triangles`' (upper, lower) masks without the walls of quads that connect
    (8-connected) into fewer than MIN_WALL_QUADS: a curtain is drawn only where a jump runs
    between two measured sides, not between two noisy neighbours."""
    quads = (upper | lower).astype(np.uint8)
    if not quads.any():
        return upper, lower
    _, labels, stats, _ = cv2.connectedComponentsWithStats(quads, connectivity=8)
    short = stats[:, cv2.CC_STAT_AREA] < MIN_WALL_QUADS
    short[0] = False
    kept = ~short[labels]
    return upper & kept, lower & kept


def wall_vertices(upper: np.ndarray, lower: np.ndarray) -> np.ndarray:
    """(rows, cols) bool: the vertices of a grid that are a corner of a wall triangle, from
    `grid_wall_triangles`' (rows - 1, cols - 1) masks."""
    quads = upper | lower
    corners = np.zeros((quads.shape[0] + 1, quads.shape[1] + 1), bool)
    for rows, cols in (
        (slice(None, -1), slice(None, -1)),
        (slice(None, -1), slice(1, None)),
        (slice(1, None), slice(None, -1)),
        (slice(1, None), slice(1, None)),
    ):
        corners[rows, cols] |= quads
    return corners


def within_distance(mask: np.ndarray, distance_px: int) -> np.ndarray:
    """(rows, cols) bool: the points within `distance_px` (in rows and columns) of a True one."""
    if not mask.any():
        return np.zeros(mask.shape, bool)
    kernel = np.ones((2 * distance_px + 1, 2 * distance_px + 1), np.uint8)
    return cv2.dilate(mask.astype(np.uint8), kernel).astype(bool)
