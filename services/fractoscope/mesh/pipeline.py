"""From a height map to filtered, tiled, textured GLB levels of detail (the meshing service's work)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from fractoscope.mesh import glb, levels
from fractoscope.mesh.outline import DEFAULT_MIN_ISLAND_PX, Unmeasured, drop_islands
from fractoscope.progress import silent
from fractoscope.surface import filtering
from fractoscope.units import METRES_PER_UM


@dataclass(frozen=True)
class EncodedTile:
    """One tile of one level as GLB; level 0 is full resolution, larger is coarser. Its geometric
    error is at least its finer tiles' (as 3D Tiles wants); level_error_m is its own."""

    level: int
    tile_row: int
    tile_col: int
    glb: bytes
    geometric_error_m: float
    vertex_count: int
    triangle_count: int
    wall_triangle_count: int = 0
    level_error_m: float = 0.0


@dataclass(frozen=True)
class MeshingOptions:
    """Filtering and simplification settings (see surface.filtering and mesh.levels)."""

    outlier_threshold_sigma: float = filtering.OUTLIER_THRESHOLD_SIGMA
    max_fill_distance_px: int = filtering.MAX_FILL_DISTANCE_PX
    smoothing_um: float = 0.0
    method: levels.Simplification = levels.Simplification.VERTEX_CLUSTERING
    level_count: int | None = None
    plain_glb: bool = False  # float32 GLBs without extensions instead of quantized, meshopt-compressed ones
    max_slope: float | None = None  # steeper triangles are walls (mesh.walls); None: no walls
    unmeasured: Unmeasured = Unmeasured.ABSENT  # how areas without heights are drawn (mesh.outline)
    min_island_px: float = DEFAULT_MIN_ISLAND_PX  # smaller measured patches are dropped (mesh.outline); 0: none
    margin_cells: int = 0  # outer rows and columns that only shape the normals (one level only)
    max_sigma_um: float | None = None  # heights whose sigma exceeds it are not meshed; None: all are
    resolution_px: float = 1.0  # the heights' horizontal resolution: normals are shaded at it (mesh.levels)


@dataclass(frozen=True)
class MeshReport:
    """What meshing changed in the heights: the filter's counts, how many islands it dropped and how
    many heights it left out for their sigma."""

    filtered: filtering.FilterReport
    islands_dropped: int
    uncertain_dropped: int = 0


def mesh_height_map(
    z_um: np.ndarray,
    texture: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    options: MeshingOptions = MeshingOptions(),
    sigma_um: np.ndarray | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[list[EncodedTile], MeshReport]:
    """Filters `z_um` ((rows, cols) µm, NaN unknown), builds the levels with `texture` (grey, same
    shape) and encodes every tile with pixel (0, 0) at `origin_um` (x, y); tiles come finest level
    first, tiles without a measured quad left out. `sigma_um` (same shape, optional) is each
    height's local uncertainty, which widens what `options.max_slope` lets pass as surface.
    Islands below `options.min_island_px` are dropped after filtering (those that reach the edge
    kept when the map has a margin: it is a piece of a larger surface). Heights whose sigma exceeds
    `options.max_sigma_um` are left out first, and filled from their neighbours where near enough
    (what the mesh shows there is an interpolation, never the uncertain height)."""
    report = progress or silent
    z_um, cleaning = _cleaned(z_um, sigma_um, options, pixel_size_um)
    report(0.1, "filtered")

    total = levels.tile_count(z_um.shape, options.level_count, options.margin_cells)
    tiles = levels.iter_tiles(
        z_um,
        texture,
        pixel_size_um=pixel_size_um,
        method=options.method,
        level_count=options.level_count,
        max_slope=options.max_slope,
        sigma_um=sigma_um,
        margin_cells=options.margin_cells,
        min_island_px=options.min_island_px,
        unmeasured=options.unmeasured,
        resolution_px=options.resolution_px,
    )
    floor = options.unmeasured is Unmeasured.FLAT
    grid = (
        None
        if options.plain_glb
        else _position_grid(z_um, pixel_size_um=pixel_size_um, origin_um=origin_um, with_zero=floor)
    )
    encoded = []
    # Tiles are built (numpy, mostly outside the GIL) in a worker thread while this thread encodes
    # the previous ones, so both cores work.
    with ThreadPoolExecutor(max_workers=1) as builder:
        pending = builder.submit(next, tiles, None)
        while (tile := pending.result()) is not None:
            pending = builder.submit(next, tiles, None)
            encoded.append(_encoded_tile(tile, pixel_size_um=pixel_size_um, grid=grid, origin_um=origin_um))
            report(0.1 + 0.9 * len(encoded) / total, f"level {tile.level}: {len(encoded)} of at most {total} tiles")
    return encoded, cleaning


def _cleaned(z_um: np.ndarray, sigma_um, options: MeshingOptions, pixel_size_um: float):
    """The heights as meshed and the MeshReport of what that changed: uncertain heights out,
    filtered (surface.filtering), islands dropped (see mesh_height_map)."""
    z_um, uncertain = _without_uncertain(z_um, sigma_um, options.max_sigma_um)
    filtered = filtering.filter_heights(
        z_um,
        outlier_threshold_sigma=options.outlier_threshold_sigma,
        max_fill_distance_px=options.max_fill_distance_px,
        smoothing_um=options.smoothing_um,
        sigma_um=sigma_um,
        max_slope=options.max_slope,
        pixel_size_um=pixel_size_um,
    )
    z_um, islands = filtered.z_um, 0
    if options.min_island_px > 0:
        z_um, islands = drop_islands(z_um, min_area_cells=options.min_island_px, keep_edge=options.margin_cells > 0)
    return z_um, MeshReport(filtered.report, islands, uncertain)


def _without_uncertain(z_um: np.ndarray, sigma_um: np.ndarray | None, max_sigma_um: float | None):
    """The heights with those whose sigma exceeds `max_sigma_um` unknown, and their count."""
    if sigma_um is None or not max_sigma_um:
        return z_um, 0
    with np.errstate(invalid="ignore"):
        uncertain = np.isfinite(z_um) & (np.asarray(sigma_um) > max_sigma_um)
    if not uncertain.any():
        return z_um, 0
    return np.where(uncertain, np.float32(np.nan), z_um).astype(np.float32), int(uncertain.sum())


def _position_grid(
    z_um: np.ndarray, *, pixel_size_um: float, origin_um: tuple[float, float], with_zero: bool
) -> glb.PositionGrid:
    """The quantization grid spanning the whole height map (rows, cols) µm, NaN unknown (and
    height zero `with_zero`, for a floor there), in glTF metres with pixel (0, 0) at `origin_um`
    (x, y): one grid for all its tiles."""
    rows, cols = z_um.shape
    low, high = (np.nanmin(z_um), np.nanmax(z_um)) if np.isfinite(z_um).any() else (0.0, 0.0)
    if with_zero:
        low, high = min(low, 0.0), max(high, 0.0)
    corners = np.array([[0.0, 0.0, low], [cols - 1.0, rows - 1.0, high]])
    return glb.PositionGrid.spanning(
        *glb.to_gltf_positions_m(corners, pixel_size_um=pixel_size_um, origin_um=origin_um)
    )


def _encoded_tile(
    tile: levels.LodTile, *, pixel_size_um: float, grid: glb.PositionGrid | None, origin_um: tuple[float, float]
) -> EncodedTile:
    """A tile as GLB on `grid` (None: plain float32), its level and place in the node's extras."""
    extras = {"level": tile.level, "tile_row": tile.tile_row, "tile_col": tile.tile_col}
    return EncodedTile(
        level=tile.level,
        tile_row=tile.tile_row,
        tile_col=tile.tile_col,
        glb=glb.tile_glb(tile, pixel_size_um=pixel_size_um, grid=grid, origin_um=origin_um, extras=extras),
        geometric_error_m=tile.geometric_error_um * METRES_PER_UM,
        vertex_count=len(tile.positions),
        triangle_count=len(tile.triangles),
        wall_triangle_count=int(tile.walls.sum()),
        level_error_m=tile.level_error_um * METRES_PER_UM,
    )
