"""A specimen's fused surface as a quadtree of tiles (written as 3D Tiles by formats.tileset).

The root tile spans the union of the ROIs (a square in the specimen frame); each level halves the
tile side, and every tile holds QUADTREE_TILE_CELLS x QUADTREE_TILE_CELLS cells. A tile is refined
(four children, REPLACE) while some ROI under it has pixels finer than its cells, so the tree goes
deep only where high-magnification data exists: children there are "optical", their siblings
outside the ROI are "digital" (coarser data upsampled). Tile URIs are
`tiles/{level}/{col}/{row}.glb`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable, Iterator
from dataclasses import asdict, dataclass, field

import cv2
import numpy as np

from fractoscope.specimen.fusion import FusedSurface, overlaps

OPTICAL, DIGITAL = "optical", "digital"
# 64 x 64 cells keep a textured tile near 200 KB, small enough to stream many per second; the
# quadtree gets deeper instead.
QUADTREE_TILE_CELLS = 64
_REFINE_RATIO = math.sqrt(2)
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

    def vertex_grid_um(self, key: TileKey) -> tuple[np.ndarray, np.ndarray]:
        """(x, y) of a tile's (QUADTREE_TILE_CELLS + 1)² vertices, µm, rows down."""
        x0, y0, x1, y1 = self.bounds_um(key)
        steps = np.arange(QUADTREE_TILE_CELLS + 1) * self.cell_um(key.level)
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


TileSink = Callable[[TileKey, np.ndarray, np.ndarray, float, tuple[float, float]], None]


def build_tiles(
    surface: FusedSurface, layout: QuadtreeLayout, emit: TileSink, *, progress: Callable[[str], None] | None = None
) -> dict[TileKey, TileRecord]:
    """Walks the quadtree depth first, samples each tile's heights and texture from the fused surface
    and hands them to `emit(key, z_um, texture, cell_um, origin_um)` (the mesher); returns the records.
    Geometric errors are measured: a tile's largest deviation (bilinear between its vertices) from
    its children's vertices, plus the largest error among the children; leaves have none."""
    records: dict[TileKey, TileRecord] = {}
    announce = progress or (lambda message: None)

    def visit(key: TileKey) -> np.ndarray | None:
        bounds = layout.bounds_um(key)
        below = surface.rois_intersecting(bounds)
        if not below:
            return None
        cell_um = layout.cell_um(key.level)
        x_um, y_um = layout.vertex_grid_um(key)
        samples = surface.sample(x_um, y_um, cell_um=cell_um)
        if not np.isfinite(samples.z_um).any():
            return None
        emit(key, samples.z_um, np.clip(samples.texture, 0, 255).astype(np.uint8), cell_um, (bounds[0], bounds[1]))
        announce(f"tile {key.uri}")
        shown = surface.rois[_dominant_source(samples.source, below, surface)]
        record = TileRecord(
            key=key,
            roi=shown.id,
            magnification=shown.magnification,
            zoom=OPTICAL if shown.pixel_size_um <= cell_um * _REFINE_RATIO else DIGITAL,
            geometric_error_um=0.0,
            z_min_um=float(np.nanmin(samples.z_um)),
            z_max_um=float(np.nanmax(samples.z_um)),
        )
        records[key] = record
        if min(roi.pixel_size_um for roi in below) * _REFINE_RATIO < cell_um:
            deviation, child_error = 0.0, 0.0
            for child in key.children():
                child_z = visit(child)
                if child_z is None:
                    continue
                record.children.append(child)
                child_record = records[child]
                deviation = max(deviation, _deviation_from_child(samples.z_um, child_z, child))
                child_error = max(child_error, child_record.geometric_error_um)
                record.z_min_um = min(record.z_min_um, child_record.z_min_um)
                record.z_max_um = max(record.z_max_um, child_record.z_max_um)
            record.geometric_error_um = deviation + child_error if record.children else 0.0
        return samples.z_um

    visit(TileKey(0, 0, 0))
    return records


def _dominant_source(source: np.ndarray, below, surface: FusedSurface) -> int:
    counts = np.bincount(source[source >= 0].ravel(), minlength=len(surface.rois))
    if counts.sum() == 0:
        return surface.rois.index(below[0])
    return int(np.argmax(counts))


def _deviation_from_child(parent_z: np.ndarray, child_z: np.ndarray, child: TileKey) -> float:
    """Largest |parent (bilinear) - child| at the child's vertices, µm (unknown points ignored)."""
    half = QUADTREE_TILE_CELLS // 2
    steps = np.arange(QUADTREE_TILE_CELLS + 1, dtype=np.float32) / 2
    map_x, map_y = np.meshgrid((child.col % 2) * half + steps, (child.row % 2) * half + steps)
    parent_there = cv2.remap(parent_z.astype(np.float32), map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    difference = np.abs(parent_there - child_z)
    return float(np.nanmax(difference)) if np.isfinite(difference).any() else 0.0


def tiles_in_region(
    layout: QuadtreeLayout, records: dict[TileKey, TileRecord], region_um: tuple[float, float, float, float], *, cell_um: float
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
    layout: QuadtreeLayout, records: dict[TileKey, TileRecord], region_um: tuple[float, float, float, float], *, viewport_px: int
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
