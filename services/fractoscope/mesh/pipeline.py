"""From a height map to filtered, tiled, textured GLB levels of detail (the meshing service's work)."""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import numpy as np

from fractoscope.mesh import glb, levels
from fractoscope.progress import silent
from fractoscope.surface import filtering
from fractoscope.units import METRES_PER_UM


@dataclass(frozen=True)
class EncodedTile:
    """One tile of one level as GLB; level 0 is full resolution, larger is coarser."""

    level: int
    tile_row: int
    tile_col: int
    glb: bytes
    geometric_error_m: float
    vertex_count: int
    triangle_count: int
    wall_triangle_count: int = 0


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


def mesh_height_map(
    z_um: np.ndarray,
    texture: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    options: MeshingOptions = MeshingOptions(),
    sigma_um: np.ndarray | None = None,
    progress: Callable[[float, str], None] | None = None,
) -> tuple[list[EncodedTile], filtering.FilterReport]:
    """Filters `z_um` ((rows, cols) µm, NaN unknown), builds the levels with `texture` (grey, same
    shape) and encodes every tile with pixel (0, 0) at `origin_um` (x, y); tiles come finest level
    first, tiles without a measured quad left out. `sigma_um` (same shape, optional) is each
    height's local uncertainty, which widens what `options.max_slope` lets pass as surface."""
    report = progress or silent
    filtered = filtering.filter_heights(
        z_um,
        outlier_threshold_sigma=options.outlier_threshold_sigma,
        max_fill_distance_px=options.max_fill_distance_px,
        smoothing_um=options.smoothing_um,
    )
    report(0.1, "filtered")

    total = levels.tile_count(z_um.shape, options.level_count)
    tiles = levels.iter_tiles(
        filtered.z_um,
        texture,
        pixel_size_um=pixel_size_um,
        method=options.method,
        level_count=options.level_count,
        max_slope=options.max_slope,
        sigma_um=sigma_um,
    )
    grid = (
        None if options.plain_glb else _position_grid(filtered.z_um, pixel_size_um=pixel_size_um, origin_um=origin_um)
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
    return encoded, filtered.report


def _position_grid(z_um: np.ndarray, *, pixel_size_um: float, origin_um: tuple[float, float]) -> glb.PositionGrid:
    """The quantization grid spanning the whole height map (rows, cols) µm, NaN unknown, in glTF
    metres with pixel (0, 0) at `origin_um` (x, y): one grid for all its tiles."""
    rows, cols = z_um.shape
    corners = np.array([[0.0, 0.0, np.nanmin(z_um)], [cols - 1.0, rows - 1.0, np.nanmax(z_um)]])
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
    )
