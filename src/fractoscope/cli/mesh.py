"""`fracto mesh`: GLB levels of detail of a height map, written as level_L/ROW_COL.glb."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from fractoscope.cli.common import SERVER_HELP, UsageError, connected, err, existing_file, progress_bar
from fractoscope.sem.image import read_sem_image
from fractoscope.v1 import meshing_pb2


def add_parsers(commands) -> None:
    mesh = commands.add_parser("mesh", help="GLB levels of detail of a height map")
    mesh.add_argument("heights", help=".npz with z_um (as written by fracto height)")
    mesh.add_argument("--texture", help="the reference SEM image to texture the surface with")
    mesh.add_argument("--pixel-size-um", type=float, required=True, help="pixel size of the height map, µm")
    mesh.add_argument("--method", choices=("vertex-clustering", "quadric"), default="vertex-clustering")
    mesh.add_argument("--levels", type=int, default=0, help="number of levels (default: down to one small tile)")
    mesh.add_argument("-o", "--output", required=True, help="directory for level_L/ROW_COL.glb")
    mesh.add_argument("--plain-glb", action="store_true",
                      help="float32 GLBs without extensions, for tools that cannot decode meshopt compression (about 5x larger)")
    mesh.add_argument("--server", help=SERVER_HELP)
    mesh.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    mesh.set_defaults(run=command_mesh)


def command_mesh(args) -> int:
    heights = existing_file(args.heights)
    try:
        with np.load(heights) as arrays:
            z_um = arrays["z_um"]
    except (OSError, ValueError, KeyError) as error:
        raise UsageError(f"cannot read z_um from {heights}: {error}") from None
    texture = None
    if args.texture:
        image = read_sem_image(existing_file(args.texture).read_bytes(), field="texture")
        texture = image.pixels
        if texture.shape != z_um.shape:
            raise UsageError(f"texture {args.texture} is {texture.shape[1]}x{texture.shape[0]}, heights are {z_um.shape[1]}x{z_um.shape[0]}")
    method = meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC if args.method == "quadric" else meshing_pb2.SIMPLIFICATION_METHOD_VERTEX_CLUSTERING
    with connected(args.server) as client, progress_bar("meshing", enabled=not args.json and err.is_terminal) as advance:
        tiles, report = client.build_mesh(
            z_um, texture, pixel_size_um=args.pixel_size_um, method=method, level_count=args.levels, on_progress=advance,
            plain_glb=args.plain_glb,
        )
    write_tiles(tiles, Path(args.output))
    levels = sorted({tile.level for tile in tiles})
    summary = {
        "output": args.output,
        "filter": report,
        "levels": [
            {
                "level": level,
                "tiles": sum(1 for t in tiles if t.level == level),
                "triangles": sum(t.triangle_count for t in tiles if t.level == level),
                "geometric_error_m": max(t.geometric_error_m for t in tiles if t.level == level),
            }
            for level in levels
        ],
    }
    if args.json:
        print(json.dumps(summary))
    else:
        print(f"wrote {len(tiles)} GLB tiles in {len(levels)} levels to {args.output}")
        for row in summary["levels"]:
            print(f"  level {row['level']}: {row['tiles']} tiles, {row['triangles']} triangles, "
                  f"geometric error {row['geometric_error_m'] * 1e6:.3f} µm")
    return 0


def write_tiles(tiles, directory: Path) -> None:
    """GLB tiles as DIRECTORY/level_L/ROW_COL.glb."""
    for tile in tiles:
        path = directory / f"level_{tile.level}" / f"{tile.tile_row}_{tile.tile_col}.glb"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(tile.glb)
