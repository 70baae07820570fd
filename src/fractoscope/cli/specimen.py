"""The specimen verbs: `fracto reconstruct` (from a manifest), `list`, `profile`, `roughness`,
`zoom`, `tiles` (download) and `report`."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from fractoscope.cli.common import SERVER_HELP, UsageError, connected, err, progress_bar, region_argument
from fractoscope.client.manifest import load_manifest
from fractoscope.formats.tileset import content_uris


def add_parsers(commands) -> None:
    def specimen_command(name: str, help_text: str, run) -> argparse.ArgumentParser:
        command = commands.add_parser(name, help=help_text)
        command.add_argument("--server", help=SERVER_HELP)
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
    area.add_argument("--region", type=region_argument, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm")

    zoom = specimen_command("zoom", "tiles that show a region at a magnification, optical or digital", command_zoom)
    zoom.add_argument("specimen")
    zoom.add_argument("--region", type=region_argument, required=True, metavar="X0,Y0,X1,Y1", help="region, µm")
    zoom.add_argument("--magnification", type=float, required=True)

    tiles = specimen_command("tiles", "download a specimen's tileset.json and tiles", command_tiles)
    tiles.add_argument("specimen")
    tiles.add_argument("-o", "--output", required=True, help="directory to write into")

    specimen_command("list", "the stored specimens and their ROIs", command_list)

    report = specimen_command("report", "the measurement report of an ROI or region: HTML, and PDF with --pdf", command_report)
    report.add_argument("specimen")
    area = report.add_mutually_exclusive_group()
    area.add_argument("--roi", help="ROI id (default: the overview)")
    area.add_argument("--region", type=region_argument, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm")
    report.add_argument("-o", "--output", required=True, metavar="REPORT.html", help="the HTML report")
    report.add_argument("--pdf", metavar="REPORT.pdf", help="also the report as PDF")


def command_reconstruct(args) -> int:
    specimen_id, rois = load_manifest(args.manifest)
    with connected(args.server, args.data) as client, progress_bar("reconstructing", enabled=not args.json and err.is_terminal) as advance:
        summary = client.reconstruct_specimen(specimen_id, rois, request_id=args.request_id or "", on_progress=advance)
    if args.json:
        print(json.dumps(summary))
        return 0
    print(summary["id"])
    for roi in summary["rois"]:
        region = roi["region"]
        err.print(
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


def command_list(args) -> int:
    with connected(args.server, args.data) as client:
        specimens = client.list_specimens()
    if args.json:
        print(json.dumps({"specimens": specimens}))
        return 0
    for specimen in specimens:
        rois = ", ".join(f"{roi['id']} ({roi['pixel_size_um']:.4g} µm/px)" for roi in specimen["rois"])
        print(f"{specimen['id']}: {rois}")
    return 0


def command_report(args) -> int:
    outputs = [Path(args.output)] + ([Path(args.pdf)] if args.pdf else [])
    for path, suffix in zip(outputs, (".html", ".pdf")):
        if path.suffix.lower() != suffix:
            raise UsageError(f"{'-o' if suffix == '.html' else '--pdf'}: {path} must end in {suffix}")
        path.parent.mkdir(parents=True, exist_ok=True)
    with connected(args.server, args.data) as client:
        for path in outputs:
            client.report(args.specimen, path, roi=args.roi, region_um=args.region)
    if args.json:
        print(json.dumps({"outputs": [str(path) for path in outputs]}))
    else:
        print("wrote " + " and ".join(str(path) for path in outputs))
    return 0
