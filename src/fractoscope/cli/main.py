"""`fracto`: the command line of Fractoscope.

Exit codes: 0 success, 1 unexpected failure, 2 bad input, 3 server unavailable, 4 not found.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import signal
import sys
import threading
from collections.abc import Iterator
from pathlib import Path

import grpc
import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from fractoscope.client import ClientError, FractoscopeClient, HeightMap, embedded_server, server_address
from fractoscope.errors import InvalidInputError
from fractoscope.formats.tileset import content_uris

EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_UNAVAILABLE, EXIT_NOT_FOUND = 1, 2, 3, 4
_EXIT_CODES = {
    grpc.StatusCode.INVALID_ARGUMENT: EXIT_BAD_INPUT,
    grpc.StatusCode.FAILED_PRECONDITION: EXIT_BAD_INPUT,
    grpc.StatusCode.UNAVAILABLE: EXIT_UNAVAILABLE,
    grpc.StatusCode.DEADLINE_EXCEEDED: EXIT_UNAVAILABLE,
    grpc.StatusCode.NOT_FOUND: EXIT_NOT_FOUND,
}
_err = Console(stderr=True)


class UsageError(Exception):
    """A problem with the command line itself (missing file, bad value)."""


@contextlib.contextmanager
def connected(server: str | None, data_dir: str = "./data") -> Iterator[FractoscopeClient]:
    """A client to `server`, FRACTO_SERVER, or services started in-process for this command (with
    specimens kept in `data_dir`)."""
    address = server_address(server)
    if address:
        with FractoscopeClient(address) as client:
            yield client
        return
    from fractoscope.services.server import keep_freed_memory

    keep_freed_memory()  # as fracto-server does: the services run in this process
    with embedded_server(data_dir) as local, FractoscopeClient(local) as client:
        yield client


@contextlib.contextmanager
def progress_bar(description: str, enabled: bool):
    """A progress bar on stderr; yields the callback that advances it."""
    if not enabled:
        yield lambda fraction, message: None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn())
    with Progress(*columns, console=_err, transient=True) as bar:
        task = bar.add_task(description, total=1.0)
        yield lambda fraction, message: bar.update(task, completed=fraction, description=f"{description}: {message}")


def _existing_file(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        raise UsageError(f"cannot read {text}: no such file")
    return path


def compute_height(client: FractoscopeClient, args, quiet: bool) -> HeightMap:
    if len(args.images) < 2:
        raise UsageError("give at least two images (a stereo pair or a tilt series)")
    if args.tilt is not None and len(args.tilt) != len(args.images):
        raise UsageError(f"--tilt needs one angle per image: {len(args.images)} images, {len(args.tilt)} tilts")
    if args.calibrate_tilt and len(args.images) < 3:
        raise UsageError("--calibrate-tilt needs three or more images")
    paths = [_existing_file(image) for image in args.images]
    with progress_bar("matching", enabled=not quiet and _err.is_terminal) as advance:
        return client.compute_height_map(
            paths,
            tilt_deg=args.tilt,
            pixel_size_um=args.pixel_size_um,
            tilt_axis_deg=args.tilt_axis_deg,
            calibrate_tilt=args.calibrate_tilt,
            normalize_local_contrast=args.local_contrast,
            propagate_at_full_resolution=args.propagate_at_full_resolution,
            on_progress=advance,
        )


def command_height(args) -> int:
    with connected(args.server) as client:
        result = compute_height(client, args, quiet=args.json)
    for warning in result.report.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    arrays = {"z_um": result.z_um, "sigma_um": result.sigma_um, "confidence": result.confidence}
    if args.calibrate_tilt:
        arrays["tilt_deg_estimated"] = np.array(result.report["tilt_deg"])
    np.savez_compressed(out, **arrays)
    summary = {"output": str(out), **height_summary(result)}
    if args.png:
        plot_height_map(result, Path(args.png))
        summary["png"] = args.png
    if args.json:
        print(json.dumps(summary))
    else:
        print(
            f"wrote {out}: {result.z_um.shape[1]}x{result.z_um.shape[0]} px, "
            f"heights {summary['z_min_um']:.3f} to {summary['z_max_um']:.3f} µm, "
            f"{100 * summary['valid_fraction']:.1f} % valid, median sigma {summary['median_sigma_um']:.3f} µm"
        )
        if args.calibrate_tilt:
            report = result.report
            estimated = ", ".join(f"{t:+.3f} ± {s:.3f}" for t, s in zip(report["tilt_deg"], report["tilt_sigma_deg"]))
            nominal = ", ".join(f"{t:+.2f}" for t in report["tilt_deg_nominal"])
            print(f"tilts estimated {estimated} ° (nominal {nominal}; residual {report['tilt_residual_px']:.3f} px)")
    return 0


def plot_height_map(result: HeightMap, path: Path) -> None:
    """Heights as a colour map shaded by a hillshade, with a colour bar in µm and axes in µm."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.colors import LightSource, Normalize

    z = np.ma.masked_invalid(result.z_um)
    low, high = np.nanpercentile(result.z_um, [0.5, 99.5]) if z.count() else (0.0, 1.0)
    norm = Normalize(low, high)
    rows, cols = z.shape
    extent = (0, cols * result.pixel_size_um, rows * result.pixel_size_um, 0)
    shaded = LightSource(azdeg=315, altdeg=45).shade(
        z.filled(np.nanmedian(result.z_um) if z.count() else 0), cmap=plt.get_cmap("viridis"), norm=norm,
        blend_mode="soft", vert_exag=1.0 / result.pixel_size_um, dx=1, dy=1,
    )
    shaded[np.ma.getmaskarray(z)] = (0.5, 0.5, 0.5, 1.0)
    figure, axes = plt.subplots(figsize=(7, 6), layout="constrained")
    axes.imshow(shaded, extent=extent)
    axes.set_xlabel("x (µm)")
    axes.set_ylabel("y (µm)")
    bar = figure.colorbar(plt.cm.ScalarMappable(norm=norm, cmap="viridis"), ax=axes, shrink=0.8)
    bar.set_label("height (µm)")
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=110)
    plt.close(figure)


def height_summary(result: HeightMap) -> dict:
    """Figures worth printing about a height map (µm where dimensional)."""
    valid = np.isfinite(result.z_um)
    z = result.z_um[valid]
    return {
        "z_min_um": float(z.min()) if z.size else float("nan"),
        "z_max_um": float(z.max()) if z.size else float("nan"),
        "valid_fraction": float(valid.mean()),
        "median_sigma_um": float(np.median(result.sigma_um[valid])) if z.size else float("nan"),
        "report": result.report,
    }


def command_mesh(args) -> int:
    from fractoscope.cli.demo import write_tiles
    from fractoscope.sem.image import read_sem_image
    from fractoscope.v1 import meshing_pb2

    heights = _existing_file(args.heights)
    try:
        with np.load(heights) as arrays:
            z_um = arrays["z_um"]
    except (OSError, ValueError, KeyError) as error:
        raise UsageError(f"cannot read z_um from {heights}: {error}") from None
    texture = None
    if args.texture:
        image = read_sem_image(_existing_file(args.texture).read_bytes(), field="texture")
        texture = image.pixels
        if texture.shape != z_um.shape:
            raise UsageError(f"texture {args.texture} is {texture.shape[1]}x{texture.shape[0]}, heights are {z_um.shape[1]}x{z_um.shape[0]}")
    method = meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC if args.method == "quadric" else meshing_pb2.SIMPLIFICATION_METHOD_VERTEX_CLUSTERING
    with connected(args.server) as client, progress_bar("meshing", enabled=not args.json and _err.is_terminal) as advance:
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


def command_demo(args) -> int:
    from fractoscope.cli.demo import run_demo
    from fractoscope.services.server import keep_freed_memory, settle_garbage_collector
    from fractoscope.services.tiles.http import start_http_server
    from fractoscope.specimen.store import SpecimenStore

    console = Console()
    data = Path(args.data)
    keep_freed_memory()
    try:
        http = start_http_server(SpecimenStore(data), args.host, args.http_port)
    except OSError as error:
        raise UsageError(f"cannot serve HTTP on {args.host}:{args.http_port}: {error.strerror}; choose another --http-port") from None
    try:
        with embedded_server(data, host=args.host, port=args.port) as address, FractoscopeClient(address) as client:
            specimens = run_demo(client, data, shared_data=Path(args.shared_data), console=console)
            url = f"http://{args.host}:{http.server_port}/viewer/?specimen={specimens[0]}"
            console.print(f"viewer: [bold]{url}[/bold]", soft_wrap=True)
            console.print(f"gRPC:   {address}   (e.g. fracto roughness {specimens[0]} --server {address})", soft_wrap=True)
            console.print(f"data:   {data.resolve()}", soft_wrap=True)
            if not args.exit:
                settle_garbage_collector()
                console.print("serving until Ctrl-C")
                stop = threading.Event()
                for signum in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(signum, lambda *_: stop.set())
                stop.wait()
                console.print("stopping")
    finally:
        http.shutdown()
    return 0


def command_reconstruct(args) -> int:
    from fractoscope.client.manifest import load_manifest

    specimen_id, rois = load_manifest(args.manifest)
    with connected(args.server, args.data) as client, progress_bar("reconstructing", enabled=not args.json and _err.is_terminal) as advance:
        summary = client.reconstruct_specimen(specimen_id, rois, request_id=args.request_id or "", on_progress=advance)
    if args.json:
        print(json.dumps(summary))
        return 0
    print(summary["id"])
    for roi in summary["rois"]:
        region = roi["region"]
        _err.print(
            f"  ROI {roi['id']}: {roi['pixel_size_um']:.4g} µm/px at x {region['min']['x_um']:.1f} to {region['max']['x_um']:.1f}, "
            f"y {region['min']['y_um']:.1f} to {region['max']['y_um']:.1f} µm"
            + (f", aligned to {roi['parent']} within {roi['alignment_residual_um']:.3f} µm RMS" if roi["parent"] else "")
        )
    return 0


def _pair(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in µm, got {text!r}") from None
    return x, y


def _region(text: str) -> tuple[float, float, float, float]:
    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X0,Y0,X1,Y1 in µm, got {text!r}") from None
    return x0, y0, x1, y1


def command_profile(args) -> int:
    with connected(args.server, args.data) as client:
        result = client.profile(args.specimen, [args.start, args.end], spacing_um=args.spacing_um, magnification=args.magnification)
    out = Path(args.output)
    out.parent.mkdir(parents=True, exist_ok=True)
    with out.open("w") as csv:
        csv.write("distance_um,z_um,source\n")
        for d, z, source in zip(result.distance_um, result.z_um, result.source):
            csv.write(f"{d:.6g},{'' if np.isnan(z) else f'{z:.6g}'},{source}\n")
    if args.plot:
        plot_profile(result, Path(args.plot), title=f"{args.specimen}: {args.start} to {args.end} µm")
    if args.json:
        print(json.dumps({"output": str(out), "samples": len(result.z_um), **result.parameters}))
    else:
        figures = ", ".join(f"{k} {v:.4g}" for k, v in result.parameters.items())
        print(f"wrote {out}: {len(result.z_um)} samples; {figures}")
    return 0


def plot_profile(result, path: Path, *, title: str) -> None:
    """The profile as a line plot (matplotlib, no display needed), coloured by source ROI."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figure, axes = plt.subplots(figsize=(8, 3), layout="constrained")
    sources = np.array(result.source)
    for name in dict.fromkeys(result.source):
        shown = np.where(sources == name, result.z_um, np.nan)
        axes.plot(result.distance_um, shown, label=name or "no data")
    axes.set_xlabel("distance (µm)")
    axes.set_ylabel("height (µm)")
    axes.set_title(title)
    axes.legend(title="ROI")
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path, dpi=120)
    plt.close(figure)


def command_roughness(args) -> int:
    with connected(args.server, args.data) as client:
        values = client.roughness(args.specimen, roi=args.roi, region_um=args.region)
    if args.json:
        print(json.dumps(values))
    else:
        for key in ("Sa", "Sq", "Sp", "Sv", "Sz"):
            print(f"{key:4} {values[key]:.4g} µm")
        print(f"Ssk  {values['Ssk']:.4g}\nSku  {values['Sku']:.4g}\nSdq  {values['Sdq']:.4g}\nSdr  {values['Sdr']:.4g} %")
        print(f"Hurst exponent {values['hurst_exponent']:.3f} (fit {values['hurst_fit_min_um']:.3g} to "
              f"{values['hurst_fit_max_um']:.3g} µm), fractal dimension {values['fractal_dimension']:.3f}")
    return 0


def command_zoom(args) -> int:
    with connected(args.server, args.data) as client:
        tiles = client.zoom(args.specimen, args.region, magnification=args.magnification)
    if args.json:
        print(json.dumps({"tiles": tiles}))
    else:
        for tile in tiles:
            print(f"{tile['uri']}  {tile['zoom']:8} ROI {tile['roi']} ({tile['magnification']:g}x)")
    return 0


def command_tiles(args) -> int:
    out = Path(args.output)
    with connected(args.server, args.data) as client:
        tileset = client.get_tileset(args.specimen)
        uris = content_uris(tileset)
        out.mkdir(parents=True, exist_ok=True)
        (out / "tileset.json").write_text(json.dumps(tileset))
        for uri in uris:
            path = out / uri
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(client.get_tile(args.specimen, uri))
    print(json.dumps({"output": str(out), "tiles": len(uris)}) if args.json else f"wrote tileset.json and {len(uris)} tiles to {out}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="fracto", description="Calibrated 3D fracture surfaces from SEM stereo pairs.")
    commands = parser.add_subparsers(dest="command", required=True)

    height = commands.add_parser("height", help="height map of a stereo pair or a tilt series")
    height.add_argument("images", nargs="+", metavar="IMAGE",
                        help="the reference image (TIFF or PNG; heights use its pixel grid), then the other views")
    height.add_argument("--tilt", nargs="+", type=float, metavar="T", help="stage tilts in degrees, one per image (default: metadata)")
    height.add_argument("--calibrate-tilt", action="store_true",
                        help="estimate the tilts from three or more images (the given or metadata tilts are the start)")
    height.add_argument("--local-contrast", action=argparse.BooleanOptionalAction,
                        help="take tilt-dependent shading out before matching (default: on; --no-local-contrast for flat, "
                             "weakly textured areas)")
    height.add_argument("--propagate-at-full-resolution", action="store_true",
                        help="let pixels try their neighbours' disparities at full resolution too: for steps (cleavage); "
                             "about 1.5x slower")
    height.add_argument("--pixel-size-um", type=float, help="pixel size in µm (default: metadata)")
    height.add_argument("--tilt-axis-deg", type=float, help="tilt axis direction in the image, degrees (default 90: vertical)")
    height.add_argument("-o", "--output", required=True, help="output .npz with z_um, sigma_um, confidence")
    height.add_argument("--server", help="HOST:PORT of a Fractoscope server (default: FRACTO_SERVER, else in-process)")
    height.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    height.add_argument("--png", help="also write a picture: height colour map with hillshade and colour bar in µm")
    height.set_defaults(run=command_height)

    mesh = commands.add_parser("mesh", help="GLB levels of detail of a height map")
    mesh.add_argument("heights", help=".npz with z_um (as written by fracto height)")
    mesh.add_argument("--texture", help="the reference SEM image to texture the surface with")
    mesh.add_argument("--pixel-size-um", type=float, required=True, help="pixel size of the height map, µm")
    mesh.add_argument("--method", choices=("vertex-clustering", "quadric"), default="vertex-clustering")
    mesh.add_argument("--levels", type=int, default=0, help="number of levels (default: down to one small tile)")
    mesh.add_argument("-o", "--output", required=True, help="directory for level_L/ROW_COL.glb")
    mesh.add_argument("--plain-glb", action="store_true",
                      help="float32 GLBs without extensions, for tools that cannot decode meshopt compression (about 5x larger)")
    mesh.add_argument("--server", help="HOST:PORT of a Fractoscope server (default: FRACTO_SERVER, else in-process)")
    mesh.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    mesh.set_defaults(run=command_mesh)

    def specimen_command(name: str, help_text: str, run) -> argparse.ArgumentParser:
        command = commands.add_parser(name, help=help_text)
        command.add_argument("--server", help="HOST:PORT of a Fractoscope server (default: FRACTO_SERVER, else in-process)")
        command.add_argument("--data", default="./data", help="data directory of the in-process server (default ./data)")
        command.add_argument("--json", action="store_true", help="print JSON instead of text")
        command.set_defaults(run=run)
        return command

    reconstruct = specimen_command("reconstruct", "build a multi-scale specimen from a manifest; prints its id", command_reconstruct)
    reconstruct.add_argument("manifest", help="specimen manifest (JSON; image paths relative to it)")
    reconstruct.add_argument("--request-id", help="repeat-safe id: a second request with it returns the first one's specimen")

    profile = specimen_command("profile", "surface profile along a line, with Ra/Rq/Rz/Rsk/Rku", command_profile)
    profile.add_argument("specimen")
    profile.add_argument("--from", dest="start", type=_pair, required=True, metavar="X,Y", help="start, µm in the specimen frame")
    profile.add_argument("--to", dest="end", type=_pair, required=True, metavar="X,Y", help="end, µm")
    profile.add_argument("--magnification", type=float, default=0.0, help="sample at this magnification (default: finest data)")
    profile.add_argument("--spacing-um", type=float, default=0.0, help="sample spacing (default: the pixel size used)")
    profile.add_argument("-o", "--output", required=True, help="CSV with distance_um,z_um,source")
    profile.add_argument("--plot", help="also write a PNG plot of the profile")

    rough = specimen_command("roughness", "ISO 25178 roughness and fracture metrics of an ROI or region", command_roughness)
    rough.add_argument("specimen")
    area = rough.add_mutually_exclusive_group()
    area.add_argument("--roi", help="ROI id (default: the overview)")
    area.add_argument("--region", type=_region, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm")

    zoom = specimen_command("zoom", "tiles that show a region at a magnification, optical or digital", command_zoom)
    zoom.add_argument("specimen")
    zoom.add_argument("--region", type=_region, required=True, metavar="X0,Y0,X1,Y1", help="region, µm")
    zoom.add_argument("--magnification", type=float, required=True)

    tiles = specimen_command("tiles", "download a specimen's tileset.json and tiles", command_tiles)
    tiles.add_argument("specimen")
    tiles.add_argument("-o", "--output", required=True, help="directory to write into")

    demo = commands.add_parser("demo", help="serve the demo specimens with the web viewer (the main job of make run)")
    demo.add_argument("--data", default="./data", help="data directory (default ./data)")
    demo.add_argument("--shared-data", default="../shared/data", help="shared test data, used when present")
    demo.add_argument("--host", default="127.0.0.1", help="address to serve on (default loopback)")
    demo.add_argument("--port", type=int, default=50051, help="gRPC port (default 50051; 0 = any free port)")
    demo.add_argument("--http-port", type=int, default=8080, help="HTTP port of tiles and viewer (default 8080; 0 = any)")
    demo.add_argument("--exit", action="store_true", help="stop after building the specimens instead of serving")
    demo.set_defaults(run=command_demo)
    return parser


def main(argv: list[str] | None = None) -> None:
    args = build_parser().parse_args(argv)
    try:
        code = args.run(args)
    except (UsageError, InvalidInputError) as error:
        print(f"error: {error}", file=sys.stderr)
        code = EXIT_BAD_INPUT
    except ClientError as error:
        print(f"error: {error}", file=sys.stderr)
        code = _EXIT_CODES.get(error.code, EXIT_FAILURE)
    except (OSError, RuntimeError) as error:  # e.g. a port in use: one line, not a traceback
        print(f"error: {error}", file=sys.stderr)
        code = EXIT_FAILURE
    except KeyboardInterrupt:
        code = 130
    sys.exit(code)
