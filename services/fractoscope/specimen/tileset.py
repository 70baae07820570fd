"""3D Tiles 1.1: a specimen's quadtree as tileset.json, and the tile URIs a tileset names."""

from __future__ import annotations

from fractoscope.specimen.quadtree import QuadtreeLayout, TileKey, TileRecord
from fractoscope.units import METRES_PER_UM


def tileset_json(layout: QuadtreeLayout, records: dict[TileKey, TileRecord]) -> dict:
    """The 3D Tiles 1.1 tileset: glTF content is Y-up, so boxes are in the Z-up tileset frame with
    x = specimen x, y = -specimen y, z = height, all in metres; tile metadata names the ROI, its
    magnification and optical or digital zoom."""
    root = records[TileKey(0, 0, 0)]
    height_range_um = root.z_max_um - root.z_min_um
    return {
        "asset": {"version": "1.1", "generator": "fractoscope"},
        "schema": _metadata_schema(),
        "geometricError": max(2 * root.geometric_error_um, height_range_um, 1e-3) * METRES_PER_UM,
        "root": _tile_json(layout, records, root.key),
    }


def _tile_json(layout: QuadtreeLayout, records: dict[TileKey, TileRecord], key: TileKey) -> dict:
    """The tileset node of tile `key` and, depth first, of its descendants."""
    record = records[key]
    entry = {
        "boundingVolume": {"box": _bounding_box_m(layout.bounds_um(key), record)},
        "geometricError": record.geometric_error_um * METRES_PER_UM,
        "refine": "REPLACE",
        "content": {"uri": key.uri},
        "metadata": {
            "class": "tile",
            "properties": {
                "roi": record.roi,
                "magnification": record.magnification,
                "zoom": record.zoom.upper(),
                "cellSizeUm": layout.cell_um(key.level),
            },
        },
    }
    if record.children:
        entry["children"] = [_tile_json(layout, records, child) for child in record.children]
    return entry


def _bounding_box_m(bounds_um: tuple[float, float, float, float], record: TileRecord) -> list[float]:
    """The 3D Tiles box (centre, then the three half-axes) of a tile whose vertices span
    `bounds_um` (x_min, y_min, x_max, y_max) and the record's heights, in the Z-up tileset frame,
    metres; the half-height at least 1 nm."""
    x0, y0, x1, y1 = bounds_um
    centre = [(x0 + x1) / 2, -(y0 + y1) / 2, (record.z_min_um + record.z_max_um) / 2]
    half = [(x1 - x0) / 2, (y1 - y0) / 2, max((record.z_max_um - record.z_min_um) / 2, 1e-3)]
    return [c * METRES_PER_UM for c in centre] + [
        half[0] * METRES_PER_UM,
        0,
        0,
        0,
        half[1] * METRES_PER_UM,
        0,
        0,
        0,
        half[2] * METRES_PER_UM,
    ]


def _metadata_schema() -> dict:
    """The tileset's metadata schema: class "tile", whose properties say where a tile's data comes
    from."""
    return {
        "id": "fractoscope",
        "classes": {
            "tile": {
                "description": "Where a tile's data comes from.",
                "properties": {
                    "roi": {"type": "STRING", "description": "Id of the ROI that shows most of the tile."},
                    "magnification": {
                        "type": "SCALAR",
                        "componentType": "FLOAT64",
                        "description": "That ROI's magnification.",
                    },
                    "zoom": {
                        "type": "ENUM",
                        "enumType": "zoomKind",
                        "description": "OPTICAL: measured at this resolution; DIGITAL: coarser data upsampled.",
                    },
                    "cellSizeUm": {
                        "type": "SCALAR",
                        "componentType": "FLOAT64",
                        "description": "Vertex spacing, micrometres.",
                    },
                },
            }
        },
        "enums": {"zoomKind": {"values": [{"name": "OPTICAL", "value": 1}, {"name": "DIGITAL", "value": 2}]}},
    }


def content_uris(tileset: dict) -> list[str]:
    """Every tile content URI a tileset.json (parsed) names, root first, depth first."""
    uris, nodes = [], [tileset["root"]]
    while nodes:
        node = nodes.pop()
        uris.append(node["content"]["uri"])
        nodes += reversed(node.get("children", []))
    return uris
