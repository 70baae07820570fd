"""The specimen verbs: `fracto reconstruct` (from a manifest), `list`, `profile`, `roughness`,
`zoom`, `tiles` (download) and `report`."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from fractoscope.cli.common import (
    PICTURE_SUFFIXES,
    SERVER_HELP,
    UNMEASURED,
    UsageError,
    add_unmeasured_argument,
    calibrated_tilts,
    connected,
    datum_sentence,
    err,
    existing_file,
    given_pixel_size_um,
    output_file,
    output_folder,
    print_json,
    progress_bar,
    recorded_pixel_size_um,
    region_argument,
    relief_sign_sentence,
)
from fractoscope.client.manifest import load_manifest
from fractoscope.numbers import measured, with_uncertainty
from fractoscope.rpc import wire

FORMS = tuple(wire.FORMS)


def add_parsers(commands) -> None:
    def specimen_command(name: str, help_text: str, run) -> argparse.ArgumentParser:
        command = commands.add_parser(name, help=help_text)
        command.add_argument("--server", help=SERVER_HELP)
        command.add_argument(
            "--data", default="./data", help="data directory of the in-process server (default ./data)"
        )
        command.add_argument("--json", action="store_true", help="print JSON instead of text")
        command.set_defaults(run=run)
        return command

    reconstruct = specimen_command(
        "reconstruct", "build a multi-scale specimen from a manifest; prints its id", command_reconstruct
    )
    reconstruct.add_argument("manifest", help="specimen manifest (JSON; image paths relative to it)")
    reconstruct.add_argument(
        "--request-id", help="repeat-safe id: a second request with it returns the first one's specimen"
    )
    add_unmeasured_argument(reconstruct)

    profile = specimen_command(
        "profile", "surface profile along a line and its ISO 21920 roughness parameters", command_profile
    )
    profile.add_argument("specimen")
    profile.add_argument(
        "--from", dest="start", type=_pair, required=True, metavar="X,Y", help="start, µm in the specimen frame"
    )
    profile.add_argument("--to", dest="end", type=_pair, required=True, metavar="X,Y", help="end, µm")
    profile.add_argument(
        "--magnification", type=float, default=0.0, help="sample at this magnification (default: finest data)"
    )
    profile.add_argument("--spacing-um", type=float, default=0.0, help="sample spacing (default: the pixel size used)")
    profile.add_argument(
        "--form", choices=FORMS, help="form removed before the filters (default plane: the least-squares line)"
    )
    profile.add_argument(
        "--s-filter-um", type=float, help="S-filter cut-off lambda_s, µm (default: ISO 21920-3 for the length; 0: none)"
    )
    profile.add_argument(
        "--l-filter-um", type=float, help="L-filter cut-off lambda_c, µm (default: ISO 21920-3 for the length; 0: none)"
    )
    profile.add_argument("-o", "--output", required=True, help="CSV with distance_um,z_um,source")
    profile.add_argument("--plot", help="also write a plot of the profile (.png, .pdf, .svg, ...)")

    rough = specimen_command(
        "roughness",
        "ISO 25178 roughness (form removal, S- and L-filters, parameters with uncertainties) and fracture metrics "
        "of a specimen's ROI or region, an npz height map (fracto height) or an X3P file",
        command_roughness,
    )
    rough.add_argument("source", metavar="SOURCE", help="specimen id, or a .npz height map, or a .x3p file")
    area = rough.add_mutually_exclusive_group()
    area.add_argument("--roi", help="ROI id (default: the overview; specimens only)")
    area.add_argument(
        "--region", type=region_argument, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm (specimens only)"
    )
    rough.add_argument("--form", choices=FORMS, help="form removed first (default plane)")
    rough.add_argument("--s-filter-um", type=float, help="S-filter cut-off lambda_s, µm (default: none)")
    rough.add_argument("--l-filter-um", type=float, help="L-filter cut-off lambda_c, µm (default: none)")
    rough.add_argument(
        "--direction-deg",
        type=float,
        help="direction of the 'along' Hurst exponents, degrees "
        "counter-clockwise from +x (default 0); 'across' is 90 more",
    )
    rough.add_argument(
        "--levelling-region",
        type=region_argument,
        metavar="X0,Y0,X1,Y1",
        help="fit the form on this region only, µm (specimen frame; for files x = column, y = row times the "
        "pixel size)",
    )
    rough.add_argument(
        "--window-px",
        type=float,
        help="matcher's smoothing width in pixels of the map (default: the matching "
        "window for specimens and npz maps, 1 for X3P files)",
    )
    rough.add_argument("--min-windows", type=float, help="the Hurst fit starts this many windows up (default 4)")
    rough.add_argument(
        "--robust-form",
        action="store_true",
        default=None,
        help="fit the form robustly, so that outliers (dust, spikes) do not pull it (default: least squares)",
    )
    rough.add_argument("--pixel-size-um", type=float, help="pixel size of the file, µm (default: the one it records)")

    zoom = specimen_command("zoom", "tiles that show a region at a magnification, optical or digital", command_zoom)
    zoom.add_argument("specimen")
    zoom.add_argument("--region", type=region_argument, required=True, metavar="X0,Y0,X1,Y1", help="region, µm")
    zoom.add_argument("--magnification", type=float, required=True)

    tiles = specimen_command("tiles", "download a specimen's tileset.json and tiles", command_tiles)
    tiles.add_argument("specimen")
    tiles.add_argument("-o", "--output", required=True, help="directory to write into")

    specimen_command("list", "the stored specimens and their ROIs", command_list)

    report = specimen_command(
        "report", "the measurement report of an ROI or region: HTML, and PDF with --pdf", command_report
    )
    report.add_argument("source", metavar="SOURCE", help="specimen id, or a .npz height map (fracto height)")
    area = report.add_mutually_exclusive_group()
    area.add_argument("--roi", help="ROI id (default: the overview; specimens only)")
    area.add_argument(
        "--region", type=region_argument, metavar="X0,Y0,X1,Y1", help="region of the fused surface, µm (specimens only)"
    )
    report.add_argument("-o", "--output", required=True, metavar="REPORT.html", help="the HTML report")
    report.add_argument("--pdf", metavar="REPORT.pdf", help="also the report as PDF")
    report.add_argument(
        "--pixel-size-um", type=float, help="pixel size of an npz map, µm (default: the one it records)"
    )


def command_reconstruct(args) -> int:
    specimen_id, rois = load_manifest(args.manifest)
    with (
        connected(args.server, args.data) as client,
        progress_bar("reconstructing", enabled=not args.json and err.is_terminal) as advance,
    ):
        summary = client.reconstruct_specimen(
            specimen_id,
            rois,
            request_id=args.request_id or "",
            on_progress=advance,
            unmeasured=UNMEASURED[args.unmeasured],
        )
    if args.json:
        print_json(summary)
        return 0
    print(summary["id"])
    for roi in summary["rois"]:
        region = roi["region"]
        err.print(
            f"  ROI {roi['id']}: {roi['pixel_size_um']:.4g} µm/px at x {region['min']['x_um']:.1f} to "
            f"{region['max']['x_um']:.1f}, y {region['min']['y_um']:.1f} to {region['max']['y_um']:.1f} µm"
            + (
                f", aligned to {roi['parent']} within {roi['alignment_residual_um']:.3f} µm RMS"
                if roi["parent"]
                else ""
            )
        )
        for line in (calibrated_tilts(roi["matching"]), relief_sign_sentence(roi["matching"])):
            if line:
                err.print(f"    {line}", markup=False, soft_wrap=True)
        if roi.get("datum"):
            err.print(f"    {datum_sentence(roi['datum'])}", markup=False, soft_wrap=True)
    return 0


def _pair(text: str) -> tuple[float, float]:
    try:
        x, y = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X,Y in µm, got {text!r}") from None
    return x, y


def command_profile(args) -> int:
    out = output_file(args.output, "-o", suffixes=(".csv",))
    picture = output_file(args.plot, "--plot", suffixes=PICTURE_SUFFIXES, inputs=(out,)) if args.plot else None
    with connected(args.server, args.data) as client:
        result = client.profile(
            args.specimen,
            [args.start, args.end],
            spacing_um=args.spacing_um,
            magnification=args.magnification,
            form=args.form,
            s_filter_um=args.s_filter_um,
            l_filter_um=args.l_filter_um,
        )
    with out.open("w") as csv:
        csv.write("distance_um,z_um,source\n")
        for d, z, source in zip(result.distance_um, result.z_um, result.source):
            csv.write(f"{d:.6g},{'' if np.isnan(z) else f'{z:.6g}'},{source}\n")
    if picture:
        plot_profile(result, picture, title=f"{args.specimen}: {args.start} to {args.end} µm")
    if args.json:
        print_json({"output": str(out), "samples": len(result.z_um), **result.parameters, "chain": result.chain})
    else:
        print(f"wrote {out}: {len(result.z_um)} samples; {profile_figures(result.parameters, result.chain)}")
    return 0


def profile_figures(parameters: dict, chain: dict | None) -> str:
    """A profile's ISO 21920-2 parameters with their units (three significant digits: the profile
    carries no uncertainty) and the chain that made its roughness profile: Ra and the others are
    of the profile after the λc filter, not of the primary profile's relief."""
    figures = ", ".join(f"{k} {measured(v, wire.profile_unit(k))}" for k, v in parameters.items() if v is not None)
    if not chain:
        return figures
    cutoffs = ", ".join(
        f"{name} {f'{chain[key]:g} µm' if chain[key] else 'none'}"
        for name, key in (("λs", "s_filter_um"), ("λc", "l_filter_um"))
    )
    return f"{figures} (roughness profile: form {chain['form']}, {cutoffs})"


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
    figure.savefig(path, dpi=120)
    plt.close(figure)


def command_roughness(args) -> int:
    # The chain's flags are SurfaceChain's fields (tests/test_registries.py), as ChainRequest names them.
    chain = {name: getattr(args, name) for name in wire.CHAIN_FIELDS if name != "levelling_region"}
    chain["levelling_region_um"] = args.levelling_region
    pixel_size_um = given_pixel_size_um(args.pixel_size_um)
    if Path(args.source).suffix.lower() in (".npz", ".x3p"):
        if args.roi or args.region:
            raise UsageError("--roi and --region are for specimens; a file is analysed whole")
        from fractoscope.reconstruction.height_files import read_height_file, roughness_of_file
        from fractoscope.specimen.queries import ChainRequest
        from fractoscope.tiles.messages import roughness_response

        height_file = read_height_file(existing_file(args.source))
        request = ChainRequest(**chain)
        pixel_um = _pixel_size_um(Path(args.source), height_file, pixel_size_um)
        values = wire.response_to_roughness(
            roughness_response(roughness_of_file(height_file, request, pixel_size_um=pixel_um), request)
        )
    else:
        with connected(args.server, args.data) as client:
            values = client.roughness(args.source, roi=args.roi, region_um=args.region, **chain)
    if args.json:
        print_json(values)
        return 0
    print_roughness(values)
    return 0


def print_roughness(values: dict) -> None:
    """GetRoughness's answer (wire.response_to_roughness) as text: the chain with its cut-offs,
    the coverage, each parameter with its uncertainty's digits and its unit (fractoscope.numbers),
    the caveats, the noise bias and each Hurst fit once, with its reason where it determines no H."""
    used = values["chain"]
    filters = ", ".join(
        f"{name} {f'{used[key]:g} µm' if used[key] else 'none'}"
        for name, key in (("λs", "s_filter_um"), ("λc", "l_filter_um"))
    )
    print(
        f"chain: form {used['form']}{' (levelled on a region)' if used['levelling_region_um'] else ''}, {filters}; "
        f"grid {values['pixel_size_um']:.4g} µm"
    )
    if covered := values.get("coverage"):
        print(
            f"on the matched heights: {100 * covered['measured_fraction']:.1f} % of the points "
            f"({100 * covered['filled_fraction']:.1f} % filled and {100 * covered['unknown_fraction']:.1f} % unknown "
            "left out)"
        )
    for name, unit in values["units"].items():
        print(f"{name:5} {with_uncertainty(values[name], values['uncertainty'][name]['u_total'], unit)}")
    for caveat in values.get("caveats", []):
        print(f"caveat: {caveat}")
    bias = values["noise_bias"]
    if bias["Sq"] is not None:
        print(
            f"matching noise inflates Sa by {measured(bias['Sa'], 'µm', digits=2)} and Sq by "
            f"{measured(bias['Sq'], 'µm', digits=2)}"
        )
    for fit in values["hurst"]:
        shown = fit["not_determinable"] or (
            f"{with_uncertainty(fit['hurst'], fit['hurst_stderr'], '1')} "
            f"(fit {measured(fit['fit_min_um'], 'µm')} to {measured(fit['fit_max_um'], 'µm')})"
        )
        print(f"Hurst {fit['method']} {fit['side']:6} ({fit['direction_deg']:g}°): {shown}")
    if values["hurst_note"]:
        print(f"Hurst: {values['hurst_note']}")


def _pixel_size_um(path: Path, height_file, given_um: float | None) -> float:
    """--pixel-size-um if given, else the one the height map file records (checked alike)."""
    return given_um if given_um is not None else recorded_pixel_size_um(path, height_file.recorded_pixel_size_um)


def command_zoom(args) -> int:
    with connected(args.server, args.data) as client:
        tiles = client.zoom(args.specimen, args.region, magnification=args.magnification)
    if args.json:
        print_json({"tiles": tiles})
    else:
        for tile in tiles:
            print(f"{tile['uri']}  {tile['zoom']:8} ROI {tile['roi']} ({tile['magnification']:g}x)")
    return 0


def command_tiles(args) -> int:
    from fractoscope.specimen.tileset import content_uris

    out = output_folder(args.output, "-o")
    with connected(args.server, args.data) as client:
        tileset = client.get_tileset(args.specimen)
        uris = content_uris(tileset)
        out.mkdir(parents=True, exist_ok=True)
        (out / "tileset.json").write_text(json.dumps(tileset))
        for uri in uris:
            path = out / uri
            path.parent.mkdir(parents=True, exist_ok=True)
            path.write_bytes(client.get_tile(args.specimen, uri))
    if args.json:
        print_json({"output": str(out), "tiles": len(uris)})
    else:
        print(f"wrote tileset.json and {len(uris)} tiles to {out}")
    return 0


def command_list(args) -> int:
    with connected(args.server, args.data) as client:
        specimens = client.list_specimens()
    if args.json:
        print_json({"specimens": specimens})
        return 0
    for specimen in specimens:
        rois = ", ".join(f"{roi['id']} ({roi['pixel_size_um']:.4g} µm/px)" for roi in specimen["rois"])
        print(f"{specimen['id']}: {rois}")
    return 0


def command_report(args) -> int:
    outputs = [output_file(args.output, "-o", suffixes=(".html",))]
    if args.pdf:
        outputs.append(output_file(args.pdf, "--pdf", suffixes=(".pdf",)))
    source = Path(args.source)
    if source.suffix.lower() == ".npz":
        if args.roi or args.region:
            raise UsageError("--roi and --region are for specimens; a height map is reported whole")
        from fractoscope.reconstruction.height_files import read_height_file, report_of_file

        height_file = read_height_file(existing_file(args.source))
        pixel_um = _pixel_size_um(source, height_file, given_pixel_size_um(args.pixel_size_um))
        report_of_file(height_file, outputs, name=source.name, pixel_size_um=pixel_um)
    elif source.is_file() or source.suffix:
        raise UsageError(f"{args.source}: give a specimen id or an .npz height map of fracto height")
    else:
        if args.pixel_size_um is not None:
            raise UsageError("--pixel-size-um is for an npz height map; a specimen keeps its pixel sizes")
        with connected(args.server, args.data) as client:
            for path in outputs:
                client.report(args.source, path, roi=args.roi, region_um=args.region)
    if args.json:
        print_json({"outputs": [str(path) for path in outputs]})
    else:
        print("wrote " + " and ".join(str(path) for path in outputs))
    return 0
