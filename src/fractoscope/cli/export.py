"""`fracto export`: a specimen's ROI or region, or an npz height map, as X3P, TIFF, CSV, STL, PLY
or OBJ (the format follows the output's extension)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from fractoscope.cli.common import SERVER_HELP, UsageError, connected, given_pixel_size_um, print_json, region_argument


def add_parsers(commands) -> None:
    export = commands.add_parser("export", help="a surface as X3P, TIFF, CSV, STL, PLY or OBJ (by the output's extension)")
    export.add_argument("source", metavar="SOURCE", help="a specimen id, or an .npz height map from `fracto height`")
    area = export.add_mutually_exclusive_group()
    area.add_argument("--roi", help="ROI id (default: the overview)")
    area.add_argument("--region", type=region_argument, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm")
    export.add_argument("--pixel-size-um", type=float, metavar="P",
                        help="grid step of the export, µm (default: the source's own); for an npz without a stored pixel size, "
                             "its pixel size")
    export.add_argument("-o", "--output", required=True, metavar="OUT", help="OUT.x3p, .tif, .csv, .stl, .ply or .obj")
    export.add_argument("--solid", action="store_true", help="meshes: close into a watertight block (sides and a flat base)")
    export.add_argument("--units", choices=("um", "mm"), default="um", help="meshes: coordinate unit (default um)")
    export.add_argument("--server", help=SERVER_HELP)
    export.add_argument("--data", default="./data", help="data directory of the in-process server (default ./data)")
    export.add_argument("--json", action="store_true", help="print JSON instead of text")
    export.set_defaults(run=command_export)


def command_export(args) -> int:
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    options = {"solid": args.solid, "units": args.units}
    given_pixel_size_um(args.pixel_size_um)
    with connected(args.server, args.data) as client:
        if args.source.lower().endswith(".npz"):
            if args.roi or args.region:
                raise UsageError("--roi and --region select an area of a specimen, not of an npz height map")
            z_um, sigma_um, pixel_size_um = _height_map(Path(args.source), args.pixel_size_um)
            export_pixel_size_um = args.pixel_size_um if args.pixel_size_um != pixel_size_um else None
            grid = client.export_height_map(z_um, out, pixel_size_um=pixel_size_um, sigma_um=sigma_um,
                                            export_pixel_size_um=export_pixel_size_um, **options)
        else:
            grid = client.export_area(args.source, out, roi=args.roi, region_um=args.region, pixel_size_um=args.pixel_size_um, **options)
    summary = {"output": str(out), "bytes": out.stat().st_size, **grid}
    if args.json:
        print_json(summary)
    else:
        print(f"wrote {out}: {grid['cols']}x{grid['rows']} points at {grid['pixel_size_um']:.4g} µm, {summary['bytes']} bytes")
    return 0


def _height_map(path: Path, pixel_size_um: float | None) -> tuple[np.ndarray, np.ndarray | None, float]:
    """z_um and sigma_um of an npz, with its pixel size: the stored one (`pixel_size_um`) or, for
    an npz without one, `--pixel-size-um`."""
    if not path.is_file():
        raise UsageError(f"cannot read {path}: no such file")
    try:
        with np.load(path) as arrays:
            z_um = arrays["z_um"]
            sigma_um = arrays["sigma_um"] if "sigma_um" in arrays.files else None
            stored = float(arrays["pixel_size_um"]) if "pixel_size_um" in arrays.files else None
    except (OSError, ValueError, KeyError) as error:
        raise UsageError(f"cannot read z_um from {path}: {error}") from None
    if stored is None and pixel_size_um is None:
        raise UsageError(f"--pixel-size-um: {path} stores no pixel size; give it")
    return z_um, sigma_um, stored if stored is not None else pixel_size_um
