"""`fracto export`: a specimen's ROI or region, or an npz height map, as X3P, TIFF, CSV, STL, PLY
or OBJ (the format follows the output's extension)."""

from __future__ import annotations

from fractoscope.cli.common import (
    SERVER_HELP,
    UsageError,
    connected,
    existing_file,
    given_pixel_size_um,
    output_file,
    print_json,
    recorded_pixel_size_um,
    region_argument,
)
from fractoscope.rpc import wire


def add_parsers(commands) -> None:
    export = commands.add_parser(
        "export", help="a surface as X3P, TIFF, CSV, STL, PLY or OBJ (by the output's extension)"
    )
    export.add_argument("source", metavar="SOURCE", help="a specimen id, or an .npz height map from `fracto height`")
    area = export.add_mutually_exclusive_group()
    area.add_argument("--roi", help="ROI id (default: the overview)")
    area.add_argument("--region", type=region_argument, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm")
    export.add_argument(
        "--pixel-size-um",
        type=float,
        metavar="P",
        help="grid step of the export, µm (default: the source's own); for an npz without a stored pixel size, "
        "its pixel size",
    )
    export.add_argument("-o", "--output", required=True, metavar="OUT", help="OUT.x3p, .tif, .csv, .stl, .ply or .obj")
    export.add_argument(
        "--solid", action="store_true", help="meshes: close into a watertight block (sides and a flat base)"
    )
    export.add_argument("--units", choices=("um", "mm"), default="um", help="meshes: coordinate unit (default um)")
    export.add_argument("--server", help=SERVER_HELP)
    export.add_argument("--data", default="./data", help="data directory of the in-process server (default ./data)")
    export.add_argument("--json", action="store_true", help="print JSON instead of text")
    export.set_defaults(run=command_export)


def command_export(args) -> int:
    from fractoscope.formats.height_npz import read_height_npz

    out = output_file(
        args.output, "-o", suffixes=(*(f".{name}" for name in wire.EXPORT_FORMATS), ".tiff")
    )  # never the .npz source
    options = {"solid": args.solid, "units": args.units}
    given_pixel_size_um(args.pixel_size_um)
    if args.source.lower().endswith(".npz"):
        if args.roi or args.region:
            raise UsageError("--roi and --region select an area of a specimen, not of an npz height map")
        stored = read_height_npz(existing_file(args.source))
        pixel_size_um = (
            args.pixel_size_um
            if stored.pixel_size_um is None
            else recorded_pixel_size_um(args.source, stored.pixel_size_um)
        )
        if pixel_size_um is None:
            raise UsageError(f"--pixel-size-um: {args.source} stores no pixel size; give it")
        with connected(args.server, args.data) as client:
            grid = client.export_height_map(
                stored.z_um,
                out,
                pixel_size_um=pixel_size_um,
                sigma_um=stored.sigma_um,
                report=stored.calibration.to_report() if stored.calibration else None,
                export_pixel_size_um=args.pixel_size_um if args.pixel_size_um != pixel_size_um else None,
                **options,
            )
    else:
        with connected(args.server, args.data) as client:
            grid = client.export_area(
                args.source, out, roi=args.roi, region_um=args.region, pixel_size_um=args.pixel_size_um, **options
            )
    summary = {"output": str(out), "bytes": out.stat().st_size, **grid}
    if args.json:
        print_json(summary)
    else:
        print(
            f"wrote {out}: {grid['cols']}x{grid['rows']} points at {grid['pixel_size_um']:.4g} µm, "
            f"{summary['bytes']} bytes"
        )
    return 0
