"""`fracto mesh`: GLB levels of detail of a height map (.npz of fracto height, whose calibration it
reads back), written as level_L/ROW_COL.glb."""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

from fractoscope.cli.common import (
    SERVER_HELP,
    UNMEASURED,
    UsageError,
    add_unmeasured_argument,
    connected,
    err,
    existing_file,
    output_folder,
    print_json,
    progress_bar,
)
from fractoscope.v1 import meshing_pb2

if TYPE_CHECKING:
    import numpy as np

_METHODS = {
    "vertex-clustering": meshing_pb2.SIMPLIFICATION_METHOD_VERTEX_CLUSTERING,
    "quadric": meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC,
}


def add_parsers(commands) -> None:
    mesh = commands.add_parser("mesh", help="GLB levels of detail of a height map")
    mesh.add_argument("heights", help=".npz as written by fracto height (its calibration is read back)")
    mesh.add_argument("--texture", help="the reference SEM image to texture the surface with")
    mesh.add_argument(
        "--pixel-size-um", type=float, help="pixel size of the height map, µm (default: the one the .npz records)"
    )
    mesh.add_argument("--method", choices=("vertex-clustering", "quadric"), default="vertex-clustering")
    mesh.add_argument("--levels", type=int, default=0, help="number of levels (default: down to one small tile)")
    mesh.add_argument("-o", "--output", required=True, help="directory for level_L/ROW_COL.glb")
    mesh.add_argument(
        "--plain-glb",
        action="store_true",
        help="float32 GLBs without extensions, for tools that cannot decode meshopt compression (about 5x larger)",
    )
    mesh.add_argument(
        "--no-walls",
        dest="walls",
        action="store_false",
        help="triangulate across height jumps steeper than the pair can measure too (default: such triangles "
        "are walls, a primitive of their own, left out of the geometric error)",
    )
    add_unmeasured_argument(mesh)
    mesh.add_argument(
        "--min-island-px",
        type=float,
        help="drop measured patches smaller than this many pixels (default 225: a 15 x 15 matching window; 0: none)",
    )
    mesh.add_argument("--server", help=SERVER_HELP)
    mesh.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    mesh.set_defaults(run=command_mesh)


def command_mesh(args) -> int:
    from fractoscope.formats.height_npz import read_height_npz

    out = output_folder(args.output, "-o")
    heights = read_height_npz(existing_file(args.heights), field=args.heights)
    pixel_size_um = args.pixel_size_um if args.pixel_size_um is not None else heights.pixel_size_um
    if pixel_size_um is None:
        raise UsageError(
            f"{args.heights} records no calibration (written before fracto height stored it): give --pixel-size-um P"
        )
    texture = _texture_of(args.texture, heights.z_um.shape) if args.texture else None
    max_slope = (heights.max_slope or 0.0) if args.walls else 0.0
    with (
        connected(args.server) as client,
        progress_bar("meshing", enabled=not args.json and err.is_terminal) as advance,
    ):
        tiles, report = client.build_mesh(
            heights.z_um,
            texture,
            pixel_size_um=pixel_size_um,
            method=_METHODS[args.method],
            level_count=args.levels,
            on_progress=advance,
            plain_glb=args.plain_glb,
            max_slope=max_slope,
            sigma_um=heights.local_sigma_um if max_slope else None,
            unmeasured=UNMEASURED[args.unmeasured],
            min_island_px=args.min_island_px,
            # The matching window: the heights resolve no finer relief, which the normals then shade.
            resolution_px=(heights.record.get("report", {}).get("parameters") or {}).get("window_px") or 0.0,
        )
    write_tiles(tiles, out)
    summary = {
        "output": args.output,
        "pixel_size_um": pixel_size_um,
        "max_slope": max_slope or None,
        "unmeasured": args.unmeasured,
        "filter": report,
        "levels": _level_rows(tiles),
    }
    if args.json:
        print_json(summary)
    else:
        _print_summary(summary, tile_count=len(tiles))
    return 0


def _texture_of(path: str, shape: tuple[int, ...]) -> np.ndarray:
    """The grey pixels of the SEM image at `path`, which must have the heights' `shape`."""
    from fractoscope.sem.image import read_sem_image

    texture = read_sem_image(existing_file(path).read_bytes(), field=path).pixels
    if texture.shape != shape:
        raise UsageError(f"texture {path} is {texture.shape[1]}x{texture.shape[0]}, heights are {shape[1]}x{shape[0]}")
    return texture


def _level_rows(tiles) -> list[dict]:
    """Per level of detail, finest first: its tiles, triangles, walls, its own largest error (the
    level's distance from the full-resolution surface) and the largest geometric error its tiles
    carry (at least the finer levels' own, as 3D Tiles wants)."""
    return [
        {
            "level": level,
            "tiles": sum(1 for t in tiles if t.level == level),
            "triangles": sum(t.triangle_count for t in tiles if t.level == level),
            "wall_triangles": sum(t.wall_triangle_count for t in tiles if t.level == level),
            "level_error_m": max(t.level_error_m for t in tiles if t.level == level),
            "geometric_error_m": max(t.geometric_error_m for t in tiles if t.level == level),
        }
        for level in sorted({tile.level for tile in tiles})
    ]


def _print_summary(summary: dict, *, tile_count: int) -> None:
    """The summary of `tile_count` tiles written, as text."""
    max_slope = summary["max_slope"]
    walls = (
        f"; walls: slopes steeper than {max_slope:.1f} µm per µm ({math.degrees(math.atan(max_slope)):.0f}°) set apart"
        if max_slope
        else ""
    )
    print(
        f"wrote {_count(tile_count, 'GLB tile')} in {_count(len(summary['levels']), 'level')} to {summary['output']} "
        f"({summary['pixel_size_um']:g} µm/px{walls}; unmeasured areas {summary['unmeasured']}; "
        f"{_count(summary['filter'].get('islands_dropped', 0), 'island')} dropped)"
    )
    for row in summary["levels"]:
        print(
            f"  level {row['level']}: {_count(row['tiles'], 'tile')}, {_count(row['triangles'], 'triangle')} "
            f"({row['wall_triangles']} walls), error {row['level_error_m'] * 1e6:.3f} µm "
            f"(geometric error {row['geometric_error_m'] * 1e6:.3f} µm with the finer levels')"
        )


def _count(number: int, noun: str) -> str:
    return f"{number} {noun}" + ("" if number == 1 else "s")


def write_tiles(tiles, directory: Path) -> None:
    """GLB tiles as DIRECTORY/level_L/ROW_COL.glb."""
    for tile in tiles:
        path = directory / f"level_{tile.level}" / f"{tile.tile_row}_{tile.tile_col}.glb"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(tile.glb)
