"""How far a coarser level's mesh lies from the full-resolution heights (mesh.levels' geometric
errors), and the height of a level's grid mesh at any point; `cluster` is a
mesh.levels.ClusterLevel."""

from __future__ import annotations

import cv2
import numpy as np


def grid_height_at(cluster, col_px: np.ndarray, row_px: np.ndarray) -> np.ndarray:
    """Height of the level's grid mesh (its triangles through the cell centroids) at points."""
    size = cluster.cell_px
    centre = (size - 1) / 2.0
    quad_rows = np.clip(np.floor((row_px - centre) / size).astype(np.int64), 0, cluster.z_um.shape[0] - 2)
    quad_cols = np.clip(np.floor((col_px - centre) / size).astype(np.int64), 0, cluster.z_um.shape[1] - 2)

    def corner(row_step, col_step):
        index = (quad_rows + row_step, quad_cols + col_step)
        return cluster.col_px[index], cluster.row_px[index], cluster.z_um[index]

    a, b, c, d = corner(0, 0), corner(0, 1), corner(1, 0), corner(1, 1)
    first, in_first = _barycentric_height(col_px, row_px, a, c, b)
    second, _ = _barycentric_height(col_px, row_px, b, c, d)
    return np.where(in_first, first, second)


def grid_deviation(cluster, z_full: np.ndarray, walls: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """|grid mesh - full-resolution heights| at every full-resolution pixel (NaN where the mesh
    has no triangle, a wall triangle (`walls`: (upper, lower) per quad), or the pixel is
    unknown), for a level of even cell size.

    Quads run between cell centres, so the pixels inside quad (i, j) form the block that starts
    at (i s + s/2, j s + s/2), and all quads are evaluated at once. Quads with an incomplete corner cell (map edges,
    holes), whose vertices are
    centroids away from the regular layout, are evaluated with their actual vertex positions."""
    size, half = cluster.cell_px, cluster.cell_px // 2
    quads_r, quads_c = cluster.z_um.shape[0] - 1, cluster.z_um.shape[1] - 1
    deviation = np.full(z_full.shape, np.nan, np.float32)
    if quads_r < 1 or quads_c < 1:
        return deviation
    padded = np.full((half + quads_r * size, half + quads_c * size), np.nan, np.float32)
    rows, cols = min(padded.shape[0], z_full.shape[0]), min(padded.shape[1], z_full.shape[1])
    padded[:rows, :cols] = z_full[:rows, :cols]
    blocks = padded[half:, half:].reshape(quads_r, size, quads_c, size)

    # The triangle pair equals the bilinear patch minus the quad's twist (a - b - c + d) times
    # u v in the upper triangle and (1 - u)(1 - v) in the lower one. OpenCV's linear resize puts
    # output pixel x at input coordinate (x - (s - 1) / 2) / s: the cell-centre convention.
    z = cluster.z_um.astype(np.float32)
    bilinear = cv2.resize(z, (z.shape[1] * size, z.shape[0] * size), interpolation=cv2.INTER_LINEAR)
    bilinear_blocks = bilinear[half : half + quads_r * size, half : half + quads_c * size].reshape(
        quads_r, size, quads_c, size
    )
    offset = (np.arange(size, dtype=np.float32) + 0.5) / size
    u, v = offset[None, None, None, :], offset[None, :, None, None]
    twist_weight = np.where(u + v <= 1.0, u * v, (1.0 - u) * (1.0 - v)).astype(np.float32)
    twist = (z[:-1, :-1] - z[:-1, 1:] - z[1:, :-1] + z[1:, 1:])[:, None, :, None]
    difference = np.subtract(blocks, bilinear_blocks)
    difference += twist * twist_weight
    np.abs(difference, out=difference)

    complete = cluster.complete
    regular = complete[:-1, :-1] & complete[:-1, 1:] & complete[1:, :-1] & complete[1:, 1:]
    measured = np.isfinite(z)
    irregular = ~regular & measured[:-1, :-1] & measured[:-1, 1:] & measured[1:, :-1] & measured[1:, 1:]
    if irregular.any():
        difference[np.nonzero(irregular)[0], :, np.nonzero(irregular)[1], :] = _irregular_quad_deviation(
            cluster, blocks, np.nonzero(irregular)
        )
    upper_walls, lower_walls = walls
    if upper_walls.any() or lower_walls.any():
        in_wall = np.where(u + v <= 1.0, upper_walls[:, None, :, None], lower_walls[:, None, :, None])
        difference[in_wall] = np.nan
    flat = difference.reshape(quads_r * size, quads_c * size)
    deviation[half : half + flat.shape[0], half : half + flat.shape[1]] = flat[
        : z_full.shape[0] - half, : z_full.shape[1] - half
    ]
    return deviation


def _irregular_quad_deviation(cluster, blocks, quads) -> np.ndarray:
    """(n, s, s) deviations of the pixels of quads (i, j) whose vertices sit at their centroids."""
    size, half = cluster.cell_px, cluster.cell_px // 2
    quad_rows, quad_cols = quads
    pixel_rows = (quad_rows * size + half)[:, None, None] + np.arange(size)[None, :, None]
    pixel_cols = (quad_cols * size + half)[:, None, None] + np.arange(size)[None, None, :]
    surface = grid_height_at(cluster, pixel_cols.astype(np.float64), pixel_rows.astype(np.float64))
    return np.abs(blocks[quad_rows, :, quad_cols, :] - surface)


def _barycentric_height(x, y, p, q, r):
    """Height of the plane through triangle (p, q, r) at (x, y), and whether (x, y) lies inside
    (up to rounding). Each corner is (x, y, z) arrays."""
    (x1, y1, z1), (x2, y2, z2), (x3, y3, z3) = p, q, r
    tolerance = -1e-4
    with np.errstate(invalid="ignore", divide="ignore"):  # degenerate triangles give NaN: outside
        determinant = (y2 - y3) * (x1 - x3) + (x3 - x2) * (y1 - y3)
        w1 = ((y2 - y3) * (x - x3) + (x3 - x2) * (y - y3)) / determinant
        w2 = ((y3 - y1) * (x - x3) + (x1 - x3) * (y - y3)) / determinant
        w3 = 1.0 - w1 - w2
        return w1 * z1 + w2 * z2 + w3 * z3, (w1 >= tolerance) & (w2 >= tolerance) & (w3 >= tolerance)


def nanmax(values: np.ndarray) -> float:
    """The largest finite value, at least 0."""
    finite = values[np.isfinite(values)]
    return max(float(finite.max()), 0.0) if finite.size else 0.0


def mesh_deviation(positions, triangles, z_um, footprint, *, tolerance_um=None, chunk_pixels: int = 4_000_000) -> float:
    """Largest vertical distance between an irregular (decimated) mesh and the full-resolution
    heights over the footprint, less `tolerance_um` (rows, cols) at each pixel: every pixel inside
    a triangle's bounding box is tested with barycentric coordinates, in chunks of about
    `chunk_pixels` candidate pixels."""
    corners = positions[triangles]  # (T, 3 corners, 3 coordinates)
    low = np.floor(corners[:, :, :2].min(axis=1)).astype(np.int64)
    high = np.ceil(corners[:, :, :2].max(axis=1)).astype(np.int64)
    low = np.maximum(low, [footprint[1].start, footprint[0].start])
    high = np.minimum(high, [footprint[1].stop - 1, footprint[0].stop - 1])
    widths, heights = np.maximum(high - low + 1, 0).T
    counts = widths * heights
    ends = np.cumsum(counts)  # candidate pixels up to and including each triangle
    worst = 0.0
    start = 0
    while start < len(triangles):
        done = ends[start - 1] if start else 0
        stop = max(int(np.searchsorted(ends, done + chunk_pixels, side="right")), start + 1)
        ids = np.repeat(np.arange(start, stop), counts[start:stop])
        offsets = np.arange(len(ids)) - np.repeat(ends[start:stop] - counts[start:stop] - done, counts[start:stop])
        x = low[ids, 0] + offsets % widths[ids]
        y = low[ids, 1] + offsets // widths[ids]
        p, q, r = (tuple(corners[ids, k, axis] for axis in range(3)) for k in range(3))
        height, inside = _barycentric_height(x.astype(np.float64), y.astype(np.float64), p, q, r)
        difference = (
            np.abs(height - z_um[y, x]) if tolerance_um is None else np.abs(height - z_um[y, x]) - tolerance_um[y, x]
        )
        difference = difference[inside]
        difference = difference[np.isfinite(difference)]
        if difference.size:
            worst = max(worst, float(difference.max()))
        start = stop
    return worst
