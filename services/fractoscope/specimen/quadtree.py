"""A specimen's fused surface as a quadtree of tiles (written as 3D Tiles by specimen.tileset).

The root tile spans the union of the ROIs (a square in the specimen frame); each level halves the
tile side, and every tile holds QUADTREE_TILE_CELLS x QUADTREE_TILE_CELLS cells. A tile is refined
(four children, REPLACE) while some ROI under it has pixels finer than its cells, so the tree goes
deep only where high-magnification data exists: children there are "optical", their siblings
outside the ROI are "digital" (coarser data upsampled). Tile URIs are
`tiles/{level}/{col}/{row}.glb`.

Walls (mesh.walls): each tile is meshed with the steepest slope its dominant ROI's pair could
measure, and its geometric error, measured against the finest data under it, leaves out wall
triangles and what lies within one of its cells of a wall, so that the rim of a grain does not
make every tile along it look coarser than it is.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field

import numpy as np

from fractoscope.mesh.outline import DEFAULT_MIN_ISLAND_PX, Unmeasured
from fractoscope.mesh.walls import (
    WALL_SIGMA_FACTOR,
    grid_wall_triangles,
    max_meshed_sigma_um,
    real_jumps,
    wall_vertices,
    within_distance,
)
from fractoscope.specimen.fusion import FusedSurface, PlacedRoi, overlaps
from fractoscope.stereo.matching import DEFAULT_WINDOW_PX

OPTICAL, DIGITAL = "optical", "digital"
# 64 x 64 cells keep a textured tile near 200 KB, small enough to stream many per second; the
# quadtree gets deeper instead.
QUADTREE_TILE_CELLS = 64
# Each tile is sampled this many cells beyond its border all round: the normals of its border
# vertices see its neighbours' heights, so tiles meshed apart shade their shared border alike, and
# an island (mesh.outline) that a tile border cuts is judged whole. A matching window's width: an
# island is smaller than one window's area, so no compact one reaches beyond it.
MESH_MARGIN_CELLS = DEFAULT_WINDOW_PX + 1
# A sampled tile's own vertices, without the margin.
_CORE = (slice(MESH_MARGIN_CELLS, -MESH_MARGIN_CELLS),) * 2
_REFINE_RATIO = math.sqrt(2)
# A tile with children stands for them while a cell of its texture is at most half its geometric
# error: viewers refine to an error of a few pixels on screen (the web viewer's 6 px), where a cell
# as large as the error shows the SEM image blurred (6 px texels, the demo's top view stopping at
# its 4 coarsest tiles), and where tiles of neighbouring levels meet, a blurred and a crisp texture
# side by side make a seam. Half, not less: the pollen overview's first view then still asks for
# at most 60 tiles (a third asked for 73).
TEXEL_ERROR_CELLS = 2.0
# A tile URI's one form: numbers of up to 6 ASCII digits without leading zeros.
_NUMBER = r"(0|[1-9][0-9]{0,5})"
TILE_URI = re.compile(rf"tiles/{_NUMBER}/{_NUMBER}/{_NUMBER}\.glb", re.ASCII)


@dataclass(frozen=True, order=True)
class TileKey:
    """A quadtree node: level 0 is the root; col and row count tiles from the top-left."""

    level: int
    col: int
    row: int

    @property
    def uri(self) -> str:
        return f"tiles/{self.level}/{self.col}/{self.row}.glb"

    def children(self) -> list[TileKey]:
        return [TileKey(self.level + 1, 2 * self.col + dc, 2 * self.row + dr) for dr in (0, 1) for dc in (0, 1)]

    @classmethod
    def from_uri(cls, uri: str) -> TileKey:
        """Parses `tiles/{level}/{col}/{row}.glb` in its one canonical form (ASCII digits, no
        leading zeros: `uri` equals the key's `uri`); ValueError for anything else, so that no two
        names reach one tile."""
        match = TILE_URI.fullmatch(uri)
        if match is None:
            raise ValueError(f"not a tile URI: {uri!r}")
        return cls(*(int(n) for n in match.groups()))


@dataclass(frozen=True)
class QuadtreeLayout:
    """The root square: its top-left corner (x, y) and side in the specimen frame, µm."""

    origin_um: tuple[float, float]
    size_um: float

    def cell_um(self, level: int) -> float:
        return self.size_um / (2**level * QUADTREE_TILE_CELLS)

    def bounds_um(self, key: TileKey) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of a tile's vertices, µm."""
        side = self.size_um / 2**key.level
        x0, y0 = self.origin_um[0] + key.col * side, self.origin_um[1] + key.row * side
        return x0, y0, x0 + side, y0 + side

    def vertex_grid_um(self, key: TileKey, margin: int = 0) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) of a tile's (QUADTREE_TILE_CELLS + 1)² vertices and `margin` more all round, µm,
        rows down."""
        x0, y0, x1, y1 = self.bounds_um(key)
        steps = np.arange(-margin, QUADTREE_TILE_CELLS + 1 + margin) * self.cell_um(key.level)
        return np.meshgrid(x0 + steps, y0 + steps)

    @classmethod
    def covering(cls, surface: FusedSurface) -> QuadtreeLayout:
        extents = np.array([roi.extent_um for roi in surface.rois])
        x0, y0 = extents[:, 0].min(), extents[:, 1].min()
        side = max(extents[:, 2].max() - x0, extents[:, 3].max() - y0, surface.finest_pixel_size_um)
        return cls((float(x0), float(y0)), float(side))


@dataclass
class TileRecord:
    """What the tileset says about one tile: the ROI that shows most of it, its magnification,
    optical or digital, the largest height deviation from the finest data below it (µm), the height
    range of it and its descendants (µm), and its children."""

    key: TileKey
    roi: str
    magnification: float
    zoom: str
    geometric_error_um: float
    z_min_um: float
    z_max_um: float
    children: list[TileKey] = field(default_factory=list)

    def to_json(self) -> dict:
        values = asdict(self)
        values["key"] = [self.key.level, self.key.col, self.key.row]
        values["children"] = [[c.level, c.col, c.row] for c in self.children]
        return values

    @classmethod
    def from_json(cls, values: dict) -> TileRecord:
        values = dict(values)
        values["key"] = TileKey(*values["key"])
        values["children"] = [TileKey(*c) for c in values["children"]]
        return cls(**values)


@dataclass(frozen=True)
class TileSamples:
    """What a tile is meshed from: heights (QUADTREE_TILE_CELLS + 1 + 2 MESH_MARGIN_CELLS)² µm
    (NaN unknown) and grey texture on its vertex grid and margin, the cell size µm, the position of
    the tile's vertex (0, 0) (x, y) µm, the wall settings of the ROI that shows most of it (see
    PlacedRoi), the least island area in cells (mesh.outline), how unmeasured areas are drawn, the
    heights' fused matching noise on the same grid (µm, NaN unknown; None: not known) and the
    largest a meshed height may have (mesh.walls.max_meshed_sigma_um of that ROI; 0: none), and the
    heights' horizontal resolution in cells (that ROI's matching window)."""

    z_um: np.ndarray
    texture: np.ndarray
    cell_um: float
    origin_um: tuple[float, float]
    max_slope: float | None
    noise_um: float
    min_island_cells: float = 0.0
    unmeasured: Unmeasured = Unmeasured.ABSENT
    sigma_um: np.ndarray | None = None
    max_sigma_um: float = 0.0
    resolution_cells: float = 1.0

    @property
    def core_z_um(self) -> np.ndarray:
        """The heights of the tile's own (QUADTREE_TILE_CELLS + 1)² vertices."""
        return self.z_um[_CORE]

    @property
    def grid_origin_um(self) -> tuple[float, float]:
        """The position of the sampled grid's first point, margin included, (x, y) µm."""
        shift = MESH_MARGIN_CELLS * self.cell_um
        return self.origin_um[0] - shift, self.origin_um[1] - shift


TileSink = Callable[[TileKey, TileSamples], None]


def build_tiles(
    surface: FusedSurface,
    layout: QuadtreeLayout,
    emit: TileSink,
    *,
    progress: Callable[[str], None] | None = None,
    unmeasured: Unmeasured = Unmeasured.ABSENT,
) -> dict[TileKey, TileRecord]:
    """Walks the quadtree depth first, samples each tile's heights and texture from the fused
    surface and hands them to `emit(key, TileSamples)` (the mesher); returns the records. Tiles
    without four neighbouring measured vertices are left out. A tile's geometric error is the
    larger of its measured height error (`_deviation_um`) and TEXEL_ERROR_CELLS of its cell size
    (the detail of the SEM image it shows), and above its children's; leaves have none. Each tile drops islands smaller
    than mesh.outline's least area in its dominant ROI's pixels, and leaves out the heights whose
    sigma exceeds that ROI's mesh.walls.max_meshed_sigma_um; `unmeasured` is handed on."""
    records: dict[TileKey, TileRecord] = {}
    announce = progress or (lambda message: None)

    def visit(key: TileKey) -> bool:
        bounds = layout.bounds_um(key)
        below = surface.rois_intersecting(bounds)
        if not below:
            return False
        cell_um = layout.cell_um(key.level)
        shown, tile = _tile_samples(surface, layout, key, below, unmeasured)
        if not _has_a_quad(tile.core_z_um):
            return False
        emit(key, tile)
        announce(f"tile {key.uri}")
        record = records[key] = _leaf_record(key, shown, tile)
        finest_um = min(roi.pixel_size_um for roi in below)
        if finest_um * _REFINE_RATIO < cell_um:
            for child in key.children():
                if visit(child):
                    record.children.append(child)
                    record.z_min_um = min(record.z_min_um, records[child].z_min_um)
                    record.z_max_um = max(record.z_max_um, records[child].z_max_um)
        if record.children:
            record.geometric_error_um = _refined_error_um(surface, layout, tile, record, records, finest_um=finest_um)
        return True

    visit(TileKey(0, 0, 0))
    return records


def _tile_samples(
    surface: FusedSurface, layout: QuadtreeLayout, key: TileKey, below: list[PlacedRoi], unmeasured: Unmeasured
) -> tuple[PlacedRoi, TileSamples]:
    """The ROI that shows most of a tile and what the tile is meshed from (see build_tiles)."""
    cell_um = layout.cell_um(key.level)
    samples = surface.sample(*layout.vertex_grid_um(key, MESH_MARGIN_CELLS), cell_um=cell_um)
    shown = surface.rois[_dominant_source(samples.source[_CORE], below, surface)]
    max_sigma_um = (
        max_meshed_sigma_um(max_slope=shown.max_slope, pixel_size_um=shown.pixel_size_um) if shown.max_slope else 0.0
    )
    x0, y0, _, _ = layout.bounds_um(key)
    return shown, TileSamples(
        _certain(samples.z_um, samples.sigma_um, max_sigma_um),
        np.clip(samples.texture, 0, 255).astype(np.uint8),
        cell_um,
        (x0, y0),
        shown.max_slope,
        shown.noise_um,
        DEFAULT_MIN_ISLAND_PX * min(shown.pixel_size_um / cell_um, 1.0) ** 2,
        unmeasured,
        samples.sigma_um if np.isfinite(samples.sigma_um).any() else None,
        max_sigma_um,
        DEFAULT_WINDOW_PX * shown.pixel_size_um / cell_um,
    )


_ABOVE_CHILDREN = 1.01
# A tile's error is measured on the surface sampled up to 2**_ERROR_LEVELS times finer than its
# cells (at most (64 * 16 + 1)² points): the finest data below a tile of a deep tree.
_ERROR_LEVELS = 4


def _leaf_record(key: TileKey, shown: PlacedRoi, tile: TileSamples) -> TileRecord:
    """The record of a tile meshed from `tile` and shown by the ROI `shown`, as if it had no
    children: no geometric error, the height range of its own vertices (and zero, with a floor)."""
    floor = tile.unmeasured is Unmeasured.FLAT
    return TileRecord(
        key=key,
        roi=shown.id,
        magnification=shown.magnification,
        zoom=OPTICAL if shown.pixel_size_um <= tile.cell_um * _REFINE_RATIO else DIGITAL,
        geometric_error_um=0.0,
        z_min_um=float(min(np.nanmin(tile.core_z_um), 0.0 if floor else np.inf)),
        z_max_um=float(max(np.nanmax(tile.core_z_um), 0.0 if floor else -np.inf)),
    )


def _refined_error_um(
    surface: FusedSurface,
    layout: QuadtreeLayout,
    tile: TileSamples,
    record: TileRecord,
    records: dict[TileKey, TileRecord],
    *,
    finest_um: float,
) -> float:
    """The geometric error of a tile with children (`record`, its children's records in
    `records`), µm: its height error against the data below it, whose finest pixels are
    `finest_um`, at least its cell size and above its children's errors."""
    key, cell_um = record.key, tile.cell_um
    levels_below = math.ceil(math.log2(cell_um / (finest_um * _REFINE_RATIO)) - 1e-9)
    error_um = _deviation_um(surface, layout, key, tile, levels_below=min(levels_below, _ERROR_LEVELS))
    if levels_below > _ERROR_LEVELS:  # what the tiles _ERROR_LEVELS below leave, by the triangle inequality
        error_um += max(
            (
                r.geometric_error_um
                for k, r in records.items()
                if k.level == key.level + _ERROR_LEVELS and _within(k, key)
            ),
            default=0.0,
        )
    # The image shown loses detail finer than a cell as the surface loses height detail, and is
    # seen in every view where heights are not (from above): TEXEL_ERROR_CELLS cells; and viewers
    # refine a tile whose error is not below its parent's without showing it.
    return max(
        error_um,
        TEXEL_ERROR_CELLS * cell_um,
        _ABOVE_CHILDREN * max(records[child].geometric_error_um for child in record.children),
    )


def _deviation_um(
    surface: FusedSurface, layout: QuadtreeLayout, key: TileKey, tile: TileSamples, *, levels_below: int
) -> float:
    """The largest vertical distance between a tile's triangles and the fused surface sampled
    2**levels_below times finer (the finest data under it), µm, as mesh.levels measures a level:
    wall triangles and the points within one tile cell of a wall of the fine surface left out,
    and less three of the ROI's local sigmas, within which the finest data does not know its own
    surface better."""
    factor = 2**levels_below
    cells = QUADTREE_TILE_CELLS * factor
    fine_cell_um = tile.cell_um / factor
    steps = np.arange(cells + 1) * fine_cell_um
    fine_x, fine_y = np.meshgrid(tile.origin_um[0] + steps, tile.origin_um[1] + steps)
    fine_z = surface.sample(fine_x, fine_y, cell_um=fine_cell_um).z_um
    # The tile's triangles (a, c, b) and (b, c, d) of each quad, at the fine points.
    position = np.arange(cells + 1) / factor
    quad = np.minimum(position.astype(np.int64), QUADTREE_TILE_CELLS - 1)
    offset = position - quad
    rows, cols = np.meshgrid(quad, quad, indexing="ij")
    v, u = np.meshgrid(offset, offset, indexing="ij")
    z = tile.core_z_um
    a, b, c, d = z[rows, cols], z[rows, cols + 1], z[rows + 1, cols], z[rows + 1, cols + 1]
    in_upper = u + v <= 1.0
    coarse = np.where(in_upper, a + u * (b - a) + v * (c - a), d + (1 - u) * (c - d) + (1 - v) * (b - d))
    x_um, y_um = layout.vertex_grid_um(key)
    upper, lower = real_jumps(*grid_wall_triangles(x_um, y_um, z, max_slope=tile.max_slope, sigma_um=tile.noise_um))
    fine_walls = wall_vertices(
        *real_jumps(*grid_wall_triangles(fine_x, fine_y, fine_z, max_slope=tile.max_slope, sigma_um=tile.noise_um))
    )
    left_out = np.where(in_upper, upper[rows, cols], lower[rows, cols]) | within_distance(fine_walls, factor)
    deviation = np.abs(coarse - fine_z)[~left_out] - WALL_SIGMA_FACTOR * tile.noise_um
    deviation = deviation[np.isfinite(deviation)]
    return float(max(deviation.max(), 0.0)) if deviation.size else 0.0


def _within(key: TileKey, ancestor: TileKey) -> bool:
    shift = key.level - ancestor.level
    return shift >= 0 and (key.col >> shift, key.row >> shift) == (ancestor.col, ancestor.row)


def _certain(z_um: np.ndarray, sigma_um: np.ndarray, max_sigma_um: float) -> np.ndarray:
    """The heights with those whose matching sigma exceeds `max_sigma_um` (0: none) unknown: they
    are not meshed, and a tile of nothing else is not made."""
    if not max_sigma_um:
        return z_um
    with np.errstate(invalid="ignore"):
        return np.where(sigma_um > max_sigma_um, np.float32(np.nan), z_um)


def _has_a_quad(z_um: np.ndarray) -> bool:
    """Whether any four neighbouring vertices are measured (the mesher makes a triangle of them)."""
    known = np.isfinite(z_um)
    return bool((known[:-1, :-1] & known[:-1, 1:] & known[1:, :-1] & known[1:, 1:]).any())


def _dominant_source(source: np.ndarray, below, surface: FusedSurface) -> int:
    counts = np.bincount(source[source >= 0].ravel(), minlength=len(surface.rois))
    if counts.sum() == 0:
        return surface.rois.index(below[0])
    return int(np.argmax(counts))


def tiles_in_region(
    layout: QuadtreeLayout,
    records: dict[TileKey, TileRecord],
    region_um: tuple[float, float, float, float],
    *,
    cell_um: float,
) -> list[tuple[TileRecord, bool]]:
    """The tiles that show a region (x_min, y_min, x_max, y_max) with cells of about `cell_um`: the
    tiles of the level nearest that cell size, or where the tree stops earlier (no finer data), the
    deepest tile there. Each comes with True when it is shown coarser than asked (digital zoom)."""
    wanted_level = max(int(round(math.log2(layout.cell_um(0) / cell_um))), 0)
    chosen: dict[TileKey, bool] = {}

    def descend(key: TileKey) -> None:
        record = records.get(key)
        if record is None or not overlaps(layout.bounds_um(key), region_um):
            return
        if key.level == wanted_level or not record.children:
            chosen[key] = key.level < wanted_level
            return
        for child in record.children:
            descend(child)

    descend(TileKey(0, 0, 0))
    return [(records[key], upsampled) for key, upsampled in sorted(chosen.items())]


def tiles_for_view(
    layout: QuadtreeLayout,
    records: dict[TileKey, TileRecord],
    region_um: tuple[float, float, float, float],
    *,
    viewport_px: int,
) -> Iterator[TileRecord]:
    """Tiles that show a region on a screen `viewport_px` wide, coarse to fine: each level until its
    cells are smaller than a screen pixel or the tree ends."""
    pixel_um = (region_um[2] - region_um[0]) / max(viewport_px, 1)
    level = [TileKey(0, 0, 0)] if TileKey(0, 0, 0) in records else []
    while level:
        next_level = []
        for key in level:
            if not overlaps(layout.bounds_um(key), region_um):
                continue
            yield records[key]
            if layout.cell_um(key.level) > pixel_um:
                next_level += records[key].children
        level = next_level
