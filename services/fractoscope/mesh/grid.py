"""The regular grid that height-map meshes are built on, shared by the levels of detail
(mesh.levels) and the exported meshes (formats.mesh_export): its quad triangulation, and sums and
area averages over coarser cells.

Grid point (row r, column c) of a (rows, cols) grid is numbered r·cols + c.
"""

from __future__ import annotations

import cv2
import numpy as np


def quad_triangles(complete: np.ndarray, cols: int) -> np.ndarray:
    """(M, 3) int32: two triangles per True quad of `complete` ((rows - 1, cols - 1) bool, quad
    (i, j) between points (i, j) and (i + 1, j + 1)), row by row, a quad's two triangles together.

    Seen from above (+z up, rows down the image) a quad's (top-left, bottom-left, top-right) and
    (top-right, bottom-left, bottom-right) turn counter-clockwise. The row order with a quad's two
    triangles together is the order meshoptimizer's index codec compresses best (half the bytes of
    its own vertex-cache order on these grids)."""
    complete = np.asarray(complete, bool)
    corner = np.arange(complete.shape[0], dtype=np.int32)[:, None] * cols + np.arange(complete.shape[1], dtype=np.int32)
    corner = corner.reshape(-1) if complete.all() else corner[complete]
    offsets = np.array([0, cols, 1, 1, cols, cols + 1], dtype=np.int32)  # from each quad's top-left point
    faces = np.empty((len(corner), 6), dtype=np.int32)
    np.add(corner[:, None], offsets, out=faces)
    return faces.reshape(-1, 3)


def cell_sums(values: np.ndarray, *, factor: float, partial: bool = False) -> np.ndarray:
    """Integrals of `values` ((rows, cols), one unit per pixel) over square cells of `factor`
    pixels (any real factor >= 1): cell (i, j) spans pixels [i·factor, (i + 1)·factor) along rows
    and likewise along columns, and a pixel a cell covers in part counts with the part covered.

    Output (floor(rows / factor), floor(cols / factor)), or with `partial` (ceil(...)): the last
    cells cover what is left, as if the grid were padded with zeros. Whole factors on float32 or
    float64 keep the dtype; the rest integrates in float64."""
    values = np.asarray(values)
    if not (np.isfinite(factor) and factor >= 1):
        raise ValueError(f"factor: must be at least 1, got {factor}")
    shape = tuple(int(np.ceil(n / factor)) if partial else int(n // factor) for n in values.shape)
    if min(shape) < 1:
        raise ValueError(f"factor: {factor} leaves no cell of a {values.shape} map")
    if float(factor).is_integer() and values.dtype in (np.float32, np.float64):
        # OpenCV's area resize of a whole factor is the block mean, several times numpy's block sum.
        step = int(factor)
        rows, cols = shape[0] * step, shape[1] * step
        kept = values[: min(rows, values.shape[0]), : min(cols, values.shape[1])]
        if kept.shape != (rows, cols):
            kept = cv2.copyMakeBorder(
                kept, 0, rows - kept.shape[0], 0, cols - kept.shape[1], cv2.BORDER_CONSTANT, value=0
            )
        return float(step * step) * cv2.resize(kept, shape[::-1], interpolation=cv2.INTER_AREA)
    sums = values.astype(np.float64)
    for axis, size in enumerate(shape):
        edges = np.minimum(np.arange(size + 1) * float(factor), values.shape[axis])
        sums = _integrate_between(sums, edges, axis)
    return sums


def area_average(z_um: np.ndarray, *, factor: float) -> np.ndarray:
    """Heights on a grid `factor` (>= 1, any real) times coarser: each output cell is the mean of
    the measured heights it covers, weighted by the area covered (exact for fractional overlaps).

    z_um: (rows, cols) heights, µm, NaN where unknown. Output: (floor(rows / factor),
    floor(cols / factor)) float32, NaN where a cell covers no measured point; cells as in
    `cell_sums`."""
    z_um = np.asarray(z_um)
    valid = np.isfinite(z_um)
    heights = np.zeros(z_um.shape)  # float64: running sums of thousands
    np.copyto(heights, z_um, where=valid)
    sums = cell_sums(heights, factor=factor)
    counts = cell_sums(valid.astype(np.float64), factor=factor)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 1e-6, sums / counts, np.nan).astype(np.float32)


def _integrate_between(values: np.ndarray, edges: np.ndarray, axis: int) -> np.ndarray:
    """Integrals of the piecewise-constant `values` (unit cells along `axis`) between consecutive
    `edges`: differences of their running integral, which is linear within each cell."""
    values = np.moveaxis(values, axis, -1)
    running = np.concatenate([np.zeros(values.shape[:-1] + (1,)), np.cumsum(values, axis=-1)], axis=-1)
    cell = np.minimum(edges.astype(np.int64), values.shape[-1] - 1)
    at_edges = running[..., cell] + (edges - cell) * values[..., cell]
    return np.moveaxis(np.diff(at_edges, axis=-1), -1, axis)
