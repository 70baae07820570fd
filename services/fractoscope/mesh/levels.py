"""Tiled levels of detail of a 2.5D height map as triangle meshes.

Level 0 is the full-resolution grid mesh: one vertex per measured pixel, two triangles per quad of
measured pixels and one per quad with three (mesh.outline's chamfers). Level k clusters the pixels
into cells of 2**k x 2**k and keeps one vertex per cell, the centroid of its measured pixels (the
paper's hierarchical space decomposition); with the quadric method, each tile of level k >= 1 is
that grid further decimated to half its triangles by quadric error collapses (fast-simplification),
which spends triangles where the surface bends. Each level is cut into tiles of at most
LOD_TILE_MAX_CELLS x LOD_TILE_MAX_CELLS cells; neighbouring tiles share their border vertices
exactly (decimation keeps tile borders), so there are no cracks. A tile of level k+1 covers the
area of the four tiles of level k below it (to within half a cell).

Walls (see mesh.walls): with a `max_slope`, triangles that bridge a height jump steeper than the
measurement supports are flagged, kept apart from the surface and left out of geometric errors.
Tiles without a triangle (no quad with three measured corners) are not produced.

Pixel positions (row_px, col_px) count from the centre of the top-left pixel.
"""

from __future__ import annotations

import enum
import functools
from collections.abc import Iterator
from dataclasses import dataclass, replace

import fast_simplification
import meshoptimizer
import numpy as np

from fractoscope.mesh import deviation
from fractoscope.mesh.grid import cell_sums, quad_triangles
from fractoscope.mesh.outline import Unmeasured, chamfer_triangles, drop_islands, floor_triangles
from fractoscope.mesh.walls import (
    WALL_SIGMA_FACTOR,
    grid_wall_triangles,
    real_jumps,
    wall_triangles,
    wall_vertices,
    within_distance,
)
from fractoscope.surface.filtering import normalized_mean

LOD_TILE_MAX_CELLS = 254  # 255 x 255 vertices: indices fit 16 bits below the restart value 65535
COARSEST_TRIANGLES = 5_000


class Simplification(enum.Enum):
    """How coarser levels are made."""

    VERTEX_CLUSTERING = "vertex_clustering"
    QUADRIC = "quadric"


@dataclass(frozen=True)
class ClusterLevel:
    """The height map clustered into square cells of `cell_px` pixels, arrays (cells_r, cells_c).

    z_um, row_px, col_px: centroid of each cell's measured pixels (NaN where it has none).
    texture: mean grey value of each cell's pixels.
    complete: True where every pixel of the cell is measured (its centroid is its centre).
    sigma_um: mean local uncertainty of each cell's measured pixels (0 where none was given).
    shading_z_um: the heights the normals are taken from (`_shading_heights`; None: z_um).
    """

    cell_px: int
    z_um: np.ndarray
    row_px: np.ndarray
    col_px: np.ndarray
    texture: np.ndarray
    complete: np.ndarray
    sigma_um: np.ndarray
    shading_z_um: np.ndarray | None = None


@dataclass(frozen=True)
class LodTile:
    """One tile of one level: a triangle mesh in the height map's pixel frame.

    positions: (N, 3) (col_px, row_px, z_um); normals: (N, 3) unit vectors in glTF axes
    (X along columns, Y up, Z along rows); triangles: (M, 3) vertex indices, counter-clockwise
    seen from above; uvs: (N, 2) texture coordinates; texture: (h, w) uint8 grey image of the
    tile's area at the level's resolution; walls: (M,) bool, the triangles that are walls;
    floor: (F, 3) triangles of the flat floor at height zero that stands for the unmeasured area
    (mesh.outline; empty unless asked for), on vertices of their own. geometric_error_um leaves
    the walls out and is at least the finer level's tiles' errors; level_error_um is this tile's
    own.
    """

    level: int
    tile_row: int
    tile_col: int
    positions: np.ndarray
    normals: np.ndarray
    triangles: np.ndarray
    uvs: np.ndarray
    texture: np.ndarray
    geometric_error_um: float
    walls: np.ndarray
    floor: np.ndarray
    level_error_um: float


def cluster_levels(
    z_um: np.ndarray, texture: np.ndarray, *, count: int, sigma_um: np.ndarray | None = None
) -> list[ClusterLevel]:
    """`count` levels of grid vertex clustering, cells of 1, 2, 4, ... pixels. z_um, texture and
    the local uncertainty sigma_um (optional, µm) are (rows, cols) of one shape; z_um is NaN
    where unknown."""
    measured = np.isfinite(z_um)
    rows = np.broadcast_to(np.arange(z_um.shape[0], dtype=np.float64)[:, None], z_um.shape)
    cols = np.broadcast_to(np.arange(z_um.shape[1], dtype=np.float64)[None, :], z_um.shape)
    sigma = (
        np.zeros(z_um.shape, np.float32)
        if sigma_um is None
        else np.where(measured, np.nan_to_num(sigma_um), 0.0).astype(np.float32)
    )
    levels = [ClusterLevel(1, z_um.astype(np.float32), rows, cols, texture.astype(np.float32), measured, sigma)]
    if count == 1:
        return levels
    # Sums per cell, aggregated 2x2 from level to level: heights, row and column positions,
    # measured pixels (exact in float32 up to 2**24), grey values, all pixels, sigmas.
    sums = [
        cell_sums(np.where(measured, z_um, 0.0).astype(np.float64), factor=2, partial=True),
        cell_sums(np.where(measured, rows, 0.0), factor=2, partial=True),
        cell_sums(np.where(measured, cols, 0.0), factor=2, partial=True),
        cell_sums(measured.astype(np.float32), factor=2, partial=True),
        cell_sums(texture.astype(np.float32), factor=2, partial=True),
        cell_sums(np.ones(z_um.shape, np.float32), factor=2, partial=True),
        cell_sums(sigma, factor=2, partial=True),
    ]
    for level in range(1, count):
        z_sum, row_sum, col_sum, weight, texture_sum, area, sigma_sum = sums
        with np.errstate(invalid="ignore", divide="ignore"):
            has = weight > 0
            levels.append(
                ClusterLevel(
                    cell_px=2**level,
                    z_um=np.where(has, z_sum / weight, np.nan),
                    row_px=np.where(has, row_sum / weight, np.nan),
                    col_px=np.where(has, col_sum / weight, np.nan),
                    texture=texture_sum / area,
                    complete=weight == 4**level,
                    sigma_um=np.where(has, sigma_sum / weight, 0.0),
                )
            )
        sums = [cell_sums(values, factor=2, partial=True) for values in sums]
    return levels


def level_count_for(shape: tuple[int, int]) -> int:
    """Levels until the whole map is one tile of at most COARSEST_TRIANGLES triangles."""
    count = 1
    cells = max(shape)
    while cells > LOD_TILE_MAX_CELLS or 2 * (cells - 1) ** 2 > COARSEST_TRIANGLES:
        cells = (cells + 1) // 2
        count += 1
    return count


def iter_tiles(
    z_um: np.ndarray,
    texture: np.ndarray,
    *,
    pixel_size_um: float,
    method: Simplification = Simplification.VERTEX_CLUSTERING,
    level_count: int | None = None,
    max_slope: float | None = None,
    sigma_um: np.ndarray | None = None,
    margin_cells: int = 0,
    min_island_px: float = 0.0,
    unmeasured: Unmeasured = Unmeasured.ABSENT,
    resolution_px: float = 1.0,
) -> Iterator[LodTile]:
    """The tiles of every level, finest level first, as they are built. Each tile carries its
    measured geometric error: the largest vertical distance between its surface and the
    full-resolution grid surface, µm. With `max_slope` (see mesh.walls) triangles steeper than the
    measurement supports are walls; `sigma_um` (rows, cols), each height's local uncertainty µm,
    widens what it supports. The error then leaves out walls and the full-resolution pixels
    within one cell of a full-resolution wall (a level places a cliff only to within its cell,
    and that sideways error would read as a vertical one of the cliff's whole height), and counts
    at each pixel only what exceeds three of its sigmas (within which the full-resolution data
    does not know its own surface better), and is at least the errors of the finer level's tiles
    under it (those leave out less around walls; a viewer that refines a tile must not find its
    children worse). Tiles without triangles are skipped. The outer `margin_cells` (one level only)
    shape normals but get no vertex; see `_meshed_level` for `min_island_px` and `resolution_px`."""
    if z_um.shape != texture.shape or z_um.ndim != 2:
        raise ValueError(f"z_um and texture must be 2D of one shape, got {z_um.shape} and {texture.shape}")
    count = level_count or level_count_for(z_um.shape)
    tolerance_um = None if sigma_um is None else WALL_SIGMA_FACTOR * np.nan_to_num(sigma_um).astype(np.float32)
    finer_errors: dict[tuple[int, int], float] = {}  # the finer level's tiles' errors by (row, col)
    for level, cluster in enumerate(cluster_levels(z_um, texture, count=count, sigma_um=sigma_um)):
        errors: dict[tuple[int, int], float] = {}
        cluster = _meshed_level(cluster, level, min_island_px, resolution_px)
        grid_walls = _level_walls(cluster, pixel_size_um=pixel_size_um, max_slope=max_slope)
        if level == 0:
            full_resolution_walls = grid_walls
        surface_um = _away_from_walls(*full_resolution_walls, z_um, cluster.cell_px) if level > 0 else z_um
        decimated = level > 0 and method is not Simplification.VERTEX_CLUSTERING
        grid_error = deviation.grid_deviation(cluster, surface_um, grid_walls) if level > 0 and not decimated else None
        meshed = functools.partial(
            _tile_mesh, grid_walls=grid_walls, decimated=decimated, pixel_size_um=pixel_size_um, max_slope=max_slope
        )
        margin = margin_cells if level == 0 else 0
        for tile_row, row_cells in enumerate(_tile_spans(cluster.z_um.shape[0], margin)):
            for tile_col, col_cells in enumerate(_tile_spans(cluster.z_um.shape[1], margin)):
                if len((mesh := meshed(cluster, row_cells, col_cells)).triangles) == 0:
                    continue
                footprint = _footprint(cluster.cell_px, row_cells, col_cells, z_um.shape)
                own = level and _measured_error_um(
                    mesh, footprint, grid_error=grid_error, surface_um=surface_um, tolerance_um=tolerance_um
                )
                children = [finer_errors.get((2 * tile_row + i, 2 * tile_col + j), 0.0) for i in (0, 1) for j in (0, 1)]
                errors[(tile_row, tile_col)] = max(float(own), *children)
                key = (level, tile_row, tile_col)
                floor = _floor(cluster, row_cells, col_cells) if unmeasured is Unmeasured.FLAT else None
                yield _lod_tile(
                    mesh, cluster, row_cells, col_cells, key=key, errors_um=(errors[key[1:]], float(own)), floor=floor
                )
        finer_errors = errors


def tile_count(shape: tuple[int, int], level_count: int | None = None, margin_cells: int = 0) -> int:
    """How many tiles `iter_tiles` yields at most for a height map of `shape` (all of them when
    every tile has a triangle)."""
    count = level_count or level_count_for(shape)
    total = 0
    for level in range(count):
        cells = [-(-size // 2**level) for size in shape]
        margin = margin_cells if level == 0 else 0
        total += len(_tile_spans(cells[0], margin)) * len(_tile_spans(cells[1], margin))
    return total


def _tile_spans(cells: int, margin: int = 0) -> list[tuple[int, int]]:
    """Inclusive (first, last) vertex index of each tile along one axis, the outer `margin` cells
    left out; neighbours share one."""
    first, last = margin, cells - 1 - margin
    if last <= first:
        return [(first, first)]
    return [(start, min(start + LOD_TILE_MAX_CELLS, last)) for start in range(first, last, LOD_TILE_MAX_CELLS)]


def _footprint(cell_px: int, row_cells, col_cells, shape) -> tuple[slice, slice]:
    """Full-resolution pixels between the tile's first and last vertex (cell centres)."""
    centre = (cell_px - 1) / 2.0

    def span(first, last, size):
        return slice(int(np.ceil(first * cell_px + centre)), min(int(np.floor(last * cell_px + centre)) + 1, size))

    return span(*row_cells, shape[0]), span(*col_cells, shape[1])


def _level_walls(
    cluster: ClusterLevel, *, pixel_size_um: float, max_slope: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """(upper, lower) wall flags of the level's grid quads (see mesh.walls), real jumps only."""
    x_um, y_um = cluster.col_px * pixel_size_um, cluster.row_px * pixel_size_um
    return real_jumps(*grid_wall_triangles(x_um, y_um, cluster.z_um, max_slope=max_slope, sigma_um=cluster.sigma_um))


@dataclass(frozen=True)
class _TileMesh:
    """A tile's triangle mesh: positions (N, 3) (col_px, row_px, z_um), triangles (M, 3), walls
    (M,) bool, normals (N, 3) unit vectors in glTF axes."""

    positions: np.ndarray
    triangles: np.ndarray
    walls: np.ndarray
    normals: np.ndarray


def _tile_mesh(
    cluster: ClusterLevel, row_cells, col_cells, *, grid_walls, decimated: bool, pixel_size_um: float, max_slope
) -> _TileMesh:
    """The tile's grid mesh of the level, its walls taken from the level's (upper, lower)
    `grid_walls`; or, `decimated`, its quadric decimation, whose walls are found anew."""
    if not decimated:
        positions, triangles = _grid_mesh(cluster, row_cells, col_cells)
        walls = _grid_tile_walls(grid_walls, cluster, row_cells, col_cells)
        chamfers = triangles[len(walls) :]  # (mesh.outline) after the quads' triangles
        walls = np.concatenate(
            [walls, _walls(cluster, row_cells, col_cells, positions, chamfers, pixel_size_um, max_slope)]
        )
        normals = _grid_normals(cluster, row_cells, col_cells, pixel_size_um)
    else:
        positions, triangles = _decimated_mesh(cluster, row_cells, col_cells)
        walls = _walls(cluster, row_cells, col_cells, positions, triangles, pixel_size_um, max_slope)
        normals = _decimated_normals(cluster, row_cells, col_cells, positions, pixel_size_um)
    return _TileMesh(positions, triangles, walls, normals)


def _walls(cluster: ClusterLevel, row_cells, col_cells, positions, triangles, pixel_size_um, max_slope) -> np.ndarray:
    """(M,) bool: which of a tile's `triangles` are walls (mesh.walls), with the sigma of each
    vertex's nearest cell."""
    if max_slope is None or not len(triangles):  # no walls: the sigmas need not be looked up
        return np.zeros(len(triangles), bool)
    return wall_triangles(
        positions[:, :2] * pixel_size_um,
        positions[:, 2],
        triangles,
        max_slope=max_slope,
        sigma_um=_nearest_cell(cluster, row_cells, col_cells, positions, cluster.sigma_um),
    )


def _measured_error_um(mesh: _TileMesh, footprint, *, grid_error, surface_um, tolerance_um) -> float:
    """Largest vertical distance, µm, between a coarser level's tile and the full-resolution
    `surface_um` over its footprint, less `tolerance_um` (None: nothing): read off the level's
    `grid_error` (vertex clustering), or else measured on the tile's triangles, walls left out."""
    if grid_error is not None:
        return deviation.nanmax(
            grid_error[footprint] if tolerance_um is None else grid_error[footprint] - tolerance_um[footprint]
        )
    return deviation.mesh_deviation(
        mesh.positions, mesh.triangles[~mesh.walls], surface_um, footprint, tolerance_um=tolerance_um
    )


def _lod_tile(
    mesh: _TileMesh,
    cluster: ClusterLevel,
    row_cells,
    col_cells,
    *,
    key: tuple[int, int, int],
    errors_um: tuple[float, float],
    floor: tuple[np.ndarray, np.ndarray] | None,
) -> LodTile:
    """The tile `key` (level, tile_row, tile_col) with its texture coordinates, its block of the
    level's texture as uint8, its (geometric, own) `errors_um` and the `floor` (positions (F, 3),
    triangles into them) appended to its vertices."""
    level, tile_row, tile_col = key
    block = cluster.texture[row_cells[0] : row_cells[1] + 1, col_cells[0] : col_cells[1] + 1]
    positions, normals, floor_triangles_ = mesh.positions, mesh.normals, np.zeros((0, 3), np.int64)
    if floor is not None and len(floor[1]):
        floor_positions, floor_triangles_ = floor[0], floor[1] + len(positions)
        positions = np.concatenate([positions, floor_positions])
        normals = np.concatenate([normals, np.tile(np.float32([0.0, 1.0, 0.0]), (len(floor_positions), 1))])
    return LodTile(
        level=level,
        tile_row=tile_row,
        tile_col=tile_col,
        positions=positions,
        normals=normals,
        triangles=mesh.triangles,
        uvs=_uvs(positions, cluster.cell_px, row_cells, col_cells),
        texture=np.clip(np.round(block), 0, 255).astype(np.uint8),
        geometric_error_um=errors_um[0],
        walls=mesh.walls,
        floor=floor_triangles_,
        level_error_um=errors_um[1],
    )


def _floor(cluster: ClusterLevel, row_cells, col_cells) -> tuple[np.ndarray, np.ndarray]:
    """The flat floor at height zero of the block's unmeasured area (mesh.outline): (N, 3)
    positions (col_px, row_px, 0) at the cell centres and (M, 3) triangles into them."""
    block = (slice(row_cells[0], row_cells[1] + 1), slice(col_cells[0], col_cells[1] + 1))
    known = np.isfinite(cluster.z_um[block])
    centre = (cluster.cell_px - 1) / 2.0
    rows = (np.arange(row_cells[0], row_cells[1] + 1) * cluster.cell_px + centre).astype(np.float32)
    cols = (np.arange(col_cells[0], col_cells[1] + 1) * cluster.cell_px + centre).astype(np.float32)
    grid_rows, grid_cols = np.meshgrid(rows, cols, indexing="ij")
    positions = np.column_stack([grid_cols.ravel(), grid_rows.ravel(), np.zeros(grid_rows.size, np.float32)])
    triangles = floor_triangles(np.arange(known.size).reshape(known.shape), known)
    used, triangles = np.unique(triangles, return_inverse=True)
    return positions[used], triangles.reshape(-1, 3)


def _grid_mesh(cluster: ClusterLevel, row_cells, col_cells) -> tuple[np.ndarray, np.ndarray]:
    """Vertices of the measured cells of the block, two triangles per fully measured quad and then
    one per quad with three measured corners (mesh.outline's chamfers)."""
    block = (slice(row_cells[0], row_cells[1] + 1), slice(col_cells[0], col_cells[1] + 1))
    z = cluster.z_um[block]
    measured = np.isfinite(z)
    positions = np.empty((int(measured.sum()), 3), np.float32)  # float32, as the GLB stores them
    if measured.all():
        for axis, values in enumerate((cluster.col_px[block], cluster.row_px[block], z)):
            positions[:, axis] = values.ravel()
        return positions, _complete_grid_triangles(z.shape)
    index = np.full(z.shape, -1, np.int64)
    index[measured] = np.arange(len(positions))
    for axis, values in enumerate((cluster.col_px[block], cluster.row_px[block], z)):
        positions[:, axis] = values[measured]
    return positions, np.concatenate([_quad_triangles(index), chamfer_triangles(index)])


def _away_from_walls(upper: np.ndarray, lower: np.ndarray, z_um: np.ndarray, cell_px: int) -> np.ndarray:
    """The full-resolution heights with those within `cell_px` pixels of a full-resolution wall
    ((upper, lower) wall triangles of level 0) unknown."""
    if not (upper.any() or lower.any()):
        return z_um
    return np.where(within_distance(wall_vertices(upper, lower), cell_px), np.float32(np.nan), z_um)


def _grid_tile_walls(
    grid_walls: tuple[np.ndarray, np.ndarray], cluster: ClusterLevel, row_cells, col_cells
) -> np.ndarray:
    """The wall flags of a grid tile's triangles, in `_quad_triangles`' order, from the level's
    (upper, lower) wall triangles."""
    quads = (slice(row_cells[0], row_cells[1]), slice(col_cells[0], col_cells[1]))
    measured = np.isfinite(cluster.z_um[row_cells[0] : row_cells[1] + 1, col_cells[0] : col_cells[1] + 1])
    complete = measured[:-1, :-1] & measured[:-1, 1:] & measured[1:, :-1] & measured[1:, 1:]
    upper, lower = (walls[quads][complete] for walls in grid_walls)
    return np.column_stack([upper, lower]).ravel()


@functools.lru_cache(maxsize=16)
def _complete_grid_triangles(shape: tuple[int, int]) -> np.ndarray:
    """Triangles of a fully measured grid block (shared by every such block of one shape)."""
    triangles = quad_triangles(np.ones((shape[0] - 1, shape[1] - 1), bool), shape[1])
    triangles.setflags(write=False)
    return triangles


def _quad_triangles(index: np.ndarray) -> np.ndarray:
    """Two triangles per quad whose four corners have a vertex index (>= 0), in those indices."""
    known = index >= 0
    complete = known[:-1, :-1] & known[:-1, 1:] & known[1:, :-1] & known[1:, 1:]
    return index.reshape(-1)[quad_triangles(complete, index.shape[1])]


def _decimated_mesh(cluster: ClusterLevel, row_cells, col_cells):
    """The level's grid mesh of the tile decimated to half its triangles by quadric error
    collapses (heights in cell units for the quadrics), tile borders kept, vertices on the
    level's surface."""
    positions, triangles = _grid_mesh(cluster, row_cells, col_cells)
    if len(triangles) < 8:
        return positions, triangles
    scale = np.array([1.0, 1.0, 1.0 / cluster.cell_px])  # heights in units of the cell size
    simplified, faces = fast_simplification.simplify(
        positions * scale, np.array(triangles, np.int64), target_reduction=0.5, preserve_border=True
    )
    used, faces = np.unique(faces, return_inverse=True)  # drop vertices no triangle uses
    simplified = simplified[used] / scale
    # Quadric placement is ill-conditioned on flat patches; keep every vertex on the level's
    # surface. Vertices on hole rims (kept, being borders) may fall in an open quad: unchanged.
    on_surface = deviation.grid_height_at(cluster, simplified[:, 0], simplified[:, 1])
    simplified[:, 2] = np.where(np.isfinite(on_surface), on_surface, simplified[:, 2])
    return _in_vertex_cache_order(simplified, faces.reshape(-1, 3))


def _in_vertex_cache_order(positions: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Triangles in vertex-cache order and vertices in the order they are first used
    (meshoptimizer): quicker to draw, and it takes a decimated tile's compressed indices to about a
    third. (Grid meshes keep their row order, which compresses better still.)"""
    indices = np.ascontiguousarray(triangles, np.uint32).ravel()
    cached = np.empty_like(indices)
    meshoptimizer.optimize_vertex_cache(cached, indices, len(indices), len(positions))
    new_index = np.empty(len(positions), np.uint32)
    meshoptimizer.optimize_vertex_fetch_remap(new_index, cached, len(cached), len(positions))
    reordered = np.empty_like(positions)
    reordered[new_index] = positions
    return reordered, new_index[cached].astype(np.int64).reshape(-1, 3)


def _uvs(positions, cell_px, row_cells, col_cells) -> np.ndarray:
    """Texture coordinates: the tile texture's texel (i, j) covers cell (row_cells[0] + i, ...)."""
    centre = (cell_px - 1) / 2.0
    u = ((positions[:, 0] - centre) / cell_px - col_cells[0] + 0.5) / (col_cells[1] - col_cells[0] + 1)
    v = ((positions[:, 1] - centre) / cell_px - row_cells[0] + 0.5) / (row_cells[1] - row_cells[0] + 1)
    return np.column_stack([u, v])


def _normal_field(cluster: ClusterLevel, row_cells, col_cells, pixel_size_um: float) -> np.ndarray:
    """(rows, cols, 3) upward unit normals (-dh/dX, 1, -dh/dZ) / norm in glTF axes over a block
    of cells, from central differences over the actual centroid spacing (cells at the map's edge
    are partial); (0, 1, 0) where a neighbour is unknown. The differences reach one cell beyond
    the block where the level has it, so that tiles sharing a border give its vertices one normal
    (else each would shade them by its own one-sided difference: a seam)."""
    rows, cols = cluster.z_um.shape
    first_row, first_col = max(row_cells[0] - 1, 0), max(col_cells[0] - 1, 0)
    block = (slice(first_row, min(row_cells[1] + 2, rows)), slice(first_col, min(col_cells[1] + 2, cols)))
    inner = (
        slice(row_cells[0] - first_row, row_cells[1] + 1 - first_row),
        slice(col_cells[0] - first_col, col_cells[1] + 1 - first_col),
    )
    z = (cluster.z_um if cluster.shading_z_um is None else cluster.shading_z_um)[block].astype(np.float32)
    if min(z.shape) < 2:
        slope_rows = slope_cols = np.zeros_like(z)
    else:
        with np.errstate(invalid="ignore", divide="ignore"):
            slope_rows = np.gradient(z, axis=0) / (np.gradient(cluster.row_px[block], axis=0) * pixel_size_um)
            slope_cols = np.gradient(z, axis=1) / (np.gradient(cluster.col_px[block], axis=1) * pixel_size_um)
    slope_rows, slope_cols = np.nan_to_num(slope_rows), np.nan_to_num(slope_cols)
    slope_rows, slope_cols = slope_rows[inner], slope_cols[inner]
    inverse_norm = 1.0 / np.sqrt(1.0 + slope_rows**2 + slope_cols**2)
    return np.stack([-slope_cols * inverse_norm, inverse_norm, -slope_rows * inverse_norm], axis=-1)


def _meshed_level(cluster: ClusterLevel, level: int, min_island_px: float, resolution_px: float) -> ClusterLevel:
    """A level as meshed: above the finest, without islands below `min_island_px` (full-resolution
    pixels); the heights its normals come from set (`_shading_heights`)."""
    if level > 0 and min_island_px > 0:
        cluster = replace(cluster, z_um=drop_islands(cluster.z_um, min_area_cells=min_island_px / 4**level)[0])
    return replace(cluster, shading_z_um=_shading_heights(cluster, resolution_px))


def _shading_heights(cluster: ClusterLevel, resolution_px: float) -> np.ndarray | None:
    """The level's heights smoothed to the map's horizontal resolution (a Gaussian of a quarter of
    `resolution_px`, in its cells; unknown cells stay unknown): the pair measures no relief finer
    than its matching window, so finer shading is noise, which coarser levels average out and the
    finest would show as speckle beside them. None where the cells are that coarse already."""
    width_cells = resolution_px / 4.0 / cluster.cell_px
    if width_cells < 0.5:
        return None
    known = np.isfinite(cluster.z_um)
    smoothed = normalized_mean(cluster.z_um, known, width_cells)
    return np.where(known, smoothed, np.nan).astype(np.float32)


def _grid_normals(cluster: ClusterLevel, row_cells, col_cells, pixel_size_um: float) -> np.ndarray:
    """Normals of the measured vertices of a grid block, in `_grid_mesh`'s order."""
    field = _normal_field(cluster, row_cells, col_cells, pixel_size_um)
    block = (slice(row_cells[0], row_cells[1] + 1), slice(col_cells[0], col_cells[1] + 1))
    return field[np.isfinite(cluster.z_um[block])]


def _decimated_normals(cluster: ClusterLevel, row_cells, col_cells, positions, pixel_size_um: float) -> np.ndarray:
    """Normals of decimated vertices (which lie on the level's surface): the surface normal of the
    nearest cell."""
    return _nearest_cell(
        cluster, row_cells, col_cells, positions, _normal_field(cluster, row_cells, col_cells, pixel_size_um)
    )


def _nearest_cell(cluster: ClusterLevel, row_cells, col_cells, positions, values: np.ndarray) -> np.ndarray:
    """`values` of a tile's block of cells ((rows, cols, ...), or the level's whole grid) at the
    cell nearest each vertex (col_px, row_px, ...)."""
    if values.shape[:2] == cluster.z_um.shape:
        values = values[row_cells[0] : row_cells[1] + 1, col_cells[0] : col_cells[1] + 1]
    centre = (cluster.cell_px - 1) / 2.0
    rows = np.clip(
        np.round((positions[:, 1] - centre) / cluster.cell_px).astype(np.int64) - row_cells[0], 0, values.shape[0] - 1
    )
    cols = np.clip(
        np.round((positions[:, 0] - centre) / cluster.cell_px).astype(np.int64) - col_cells[0], 0, values.shape[1] - 1
    )
    return values[rows, cols]
