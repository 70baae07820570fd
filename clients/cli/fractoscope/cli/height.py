"""`fracto height`: height maps of stereo pairs and tilt series, as .npz (and a picture), with the
calibration they were computed with (formats.height_npz)."""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fractoscope.cli.common import (
    PICTURE_SUFFIXES,
    SERVER_HELP,
    UsageError,
    calibrated_tilts,
    connected,
    datum_sentence,
    err,
    existing_file,
    output_file,
    print_json,
    progress_bar,
    relief_sign_sentence,
)
from fractoscope.client import FractoscopeClient, HeightMap
from fractoscope.numbers import uncertainty_text, value_text
from fractoscope.rpc import wire

if TYPE_CHECKING:
    from fractoscope.surface.measurement import Measurement


def add_parsers(commands) -> None:
    height = commands.add_parser("height", help="height map of a stereo pair or a tilt series")
    height.add_argument(
        "images",
        nargs="+",
        metavar="IMAGE",
        help="the reference image (TIFF or PNG; heights use its pixel grid), then the other views",
    )
    height.add_argument(
        "--tilt", nargs="+", type=float, metavar="T", help="stage tilts in degrees, one per image (default: metadata)"
    )
    height.add_argument(
        "--calibrate-tilt",
        action="store_true",
        help="estimate the tilts from three or more images (the given or metadata tilts are the start)",
    )
    height.add_argument(
        "--local-contrast",
        action=argparse.BooleanOptionalAction,
        help="take tilt-dependent shading out before matching (default: on; --no-local-contrast for flat, "
        "weakly textured areas)",
    )
    height.add_argument(
        "--method",
        choices=[name.replace("_", "-") for name in wire.method_names()],
        default="tgv-zncc",
        help="matching method: tgv-zncc (default: the window correlation refined by TGV², most accurate), "
        "window-zncc (the paper's window correlation, about ten times faster) or "
        "fast (optical flow refined by window correlation: about StereoSGBM's time at 0.2-0.7 times its error)",
    )
    height.add_argument(
        "--relief-sign",
        choices=wire.relief_sign_names(),
        default="auto",
        help="which way up the heights are: auto (default: as the images show it where occlusion, or the lighting "
        "of a detector whose place is known, tells it; else as the tilts say, with a warning), nominal (as the "
        "tilts as given say) or inverted",
    )
    height.add_argument(
        "--detector-from-tilt-axis-deg",
        type=float,
        help="where the side (Everhart-Thornley) detector lies, degrees counter-clockwise from the tilt axis as "
        "displayed (0: the side the axis points to); default: not known, no place assumed (an instrument profile, "
        "see fracto instrument learn, may give it)",
    )
    height.add_argument(
        "--propagate-at-full-resolution",
        action="store_true",
        help="let pixels try their neighbours' disparities at full resolution too: for steps (cleavage); "
        "about 1.5x slower",
    )
    height.add_argument("--pixel-size-um", type=float, help="pixel size in µm (default: metadata)")
    height.add_argument(
        "--tilt-axis-deg", type=float, help="tilt axis direction in the image, degrees (default 90: vertical)"
    )
    height.add_argument(
        "--level",
        type=level_choice,
        metavar="DATUM",
        help="where height zero is: plane (a plane through all heights), substrate (a plane through the "
        "lowest extensive level, e.g. what a grain lies on) or X0,Y0,X1,Y1 (a plane through that region, µm from "
        "the image's top-left); default: as measured (arbitrary offset). A substrate that is not measured "
        "over an extensive, flat area gives the plane datum with a warning",
    )
    height.add_argument(
        "--strict-level",
        action="store_true",
        help="fail instead when --level substrate finds no measured substrate (nothing is written)",
    )
    height.add_argument(
        "-o", "--output", required=True, help="output .npz with z_um, sigma_um, confidence and the calibration"
    )
    height.add_argument("--server", help=SERVER_HELP)
    height.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    height.add_argument("--png", help="also write a picture: height colour map with hillshade and colour bar in µm")
    height.set_defaults(run=command_height)


def level_choice(text: str) -> str | tuple[float, float, float, float]:
    """--level's value: a datum name or a region X0,Y0,X1,Y1 in µm."""
    from fractoscope.surface import datum

    if text in datum.LEVELS:
        return text
    try:
        region = tuple(float(v) for v in text.split(","))
    except ValueError:
        region = ()
    if len(region) != 4:
        raise argparse.ArgumentTypeError(f"expected {' or '.join(datum.LEVELS)} or X0,Y0,X1,Y1 in µm, got {text!r}")
    return region


def check_calibration(paths: list[Path], args) -> None:
    """Every calibration value that neither the command line nor the files' metadata gives, named
    at once (UsageError), before any matching starts."""
    if args.tilt is not None and args.pixel_size_um is not None:
        return
    from fractoscope.sem.image import read_sem_image

    images = [read_sem_image(path.read_bytes(), field=str(path)) for path in paths]
    missing = []
    if args.tilt is None:
        untilted = [path.name for path, image in zip(paths, images) if image.tilt_deg is None]
        if untilted:
            missing.append(
                f"--tilt {' '.join(f'T{i + 1}' for i in range(len(paths)))} (no stage tilt in the metadata of "
                f"{', '.join(untilted)})"
            )
    if args.pixel_size_um is None and images[0].pixel_size_um is None:
        missing.append(f"--pixel-size-um P (no pixel size in the metadata of {paths[0].name})")
    if missing:
        raise UsageError("give " + " and ".join(missing))


def compute_height(client: FractoscopeClient, args, quiet: bool) -> HeightMap:
    if len(args.images) < 2:
        raise UsageError("give at least two images (a stereo pair or a tilt series)")
    if args.tilt is not None and len(args.tilt) != len(args.images):
        raise UsageError(f"--tilt needs one angle per image: {len(args.images)} images, {len(args.tilt)} tilts")
    if args.calibrate_tilt and len(args.images) < 3:
        raise UsageError("--calibrate-tilt needs three or more images")
    paths = [existing_file(image) for image in args.images]
    check_calibration(paths, args)
    with progress_bar("matching", enabled=not quiet and err.is_terminal) as advance:
        return client.compute_height_map(
            paths,
            tilt_deg=args.tilt,
            pixel_size_um=args.pixel_size_um,
            tilt_axis_deg=args.tilt_axis_deg,
            calibrate_tilt=args.calibrate_tilt,
            normalize_local_contrast=args.local_contrast,
            propagate_at_full_resolution=args.propagate_at_full_resolution,
            method=args.method.replace("-", "_"),
            relief_sign=args.relief_sign,
            detector_from_tilt_axis_deg=args.detector_from_tilt_axis_deg,
            on_progress=advance,
        )


def command_height(args) -> int:
    from fractoscope.formats.calibration import Calibration
    from fractoscope.formats.height_npz import write_height_npz
    from fractoscope.stereo import geometry

    inputs = tuple(Path(image) for image in args.images if Path(image).is_file())
    out = output_file(args.output, "-o", suffixes=(".npz",), inputs=inputs)
    picture = output_file(args.png, "--png", suffixes=PICTURE_SUFFIXES, inputs=(*inputs, out)) if args.png else None
    with connected(args.server) as client:
        result = compute_height(client, args, quiet=args.json)
    for warning in result.report.get("warnings", []):
        print(f"warning: {warning}", file=sys.stderr)
    report = result.report
    kept = _kept(result, args.level, strict=args.strict_level)
    write_height_npz(
        out,
        z_um=kept.z_um,
        sigma_um=kept.sigma_um,
        confidence=result.confidence,
        views_used=result.views_used,
        local_sigma_um=kept.local_sigma_um,
        filled=kept.filled,
        calibration=Calibration.from_report(report),
        record={
            "tilt_axis_deg": report["tilt_axis_deg"],
            "max_slope": geometry.max_measurable_slope(report["tilt_deg"]),
            "method": report.get("method", ""),
            "parameters": matching_parameters(args),
            "report": report,
            "datum": kept.datum.to_dict() if kept.datum else None,
        },
        tilt_deg_estimated=np.array(report["tilt_deg"]) if args.calibrate_tilt else None,
    )
    result = dataclasses.replace(result, z_um=kept.z_um, sigma_um=kept.sigma_um)
    summary = {"output": str(out), **height_summary(result, kept)}
    if kept.datum:
        summary["datum"] = kept.datum.to_dict()
    if picture:
        plot_height_map(result, picture)
        summary["png"] = str(picture)
    if args.json:
        print_json(summary)
    else:
        _print_summary(summary, result.z_um.shape, with_tilts=args.calibrate_tilt)
    return 0


def _kept(result: HeightMap, level: str | tuple[float, float, float, float] | None, *, strict: bool) -> Measurement:
    """The heights as every route keeps them (surface.measurement: cleaned, their matching noise
    apart, levelled on `level`, see level_choice; None: as measured), the datum's warning, if any,
    printed. `strict`: a substrate that is not found fails (UsageError)."""
    from fractoscope.surface.measurement import measurement

    flag = "" if level is None else f"--level {level if isinstance(level, str) else ','.join(f'{v:g}' for v in level)}"
    try:
        kept = measurement(
            result.z_um,
            result.sigma_um,
            pixel_size_um=result.pixel_size_um,
            tilt_deg=result.report["tilt_deg"],
            tilt_uncertainty_deg=result.report["tilt_uncertainty_deg"],
            level=level,
            strict_level=strict,
        )
    except ValueError as error:
        raise UsageError(f"{flag}: {error}") from None
    if kept.datum and kept.datum.warning:
        print(f"warning: {flag}: {kept.datum.warning}", file=sys.stderr)
    return kept


def _print_summary(summary: dict, shape: tuple[int, ...], *, with_tilts: bool) -> None:
    """The summary of a height map of `shape` written, as text, with the estimated tilts when asked."""
    sigma = summary["median_sigma_um"]
    covered = summary["coverage"]
    print(
        f"wrote {summary['output']}: {shape[1]} × {shape[0]} px (width × height), heights "
        f"{value_text(summary['z_min_um'], sigma)} to {value_text(summary['z_max_um'], sigma)} µm, "
        f"{100 * summary['valid_fraction']:.1f} % matched, {100 * covered['filled_fraction']:.1f} % filled, "
        f"median sigma {uncertainty_text(sigma)} µm"
    )
    if len(summary["report"].get("tilt_deg", ())) > 2 and "all_views_fraction" in summary:
        print(f"{100 * summary['all_views_fraction']:.1f} % of the heights rest on all the views")
    if relief := relief_sign_sentence(summary["report"]):
        print(relief)
    if with_tilts:
        print(calibrated_tilts(summary["report"]))
    if summary.get("datum"):
        print(datum_sentence(summary["datum"]))


def matching_parameters(args) -> dict:
    """The matching settings the command asked for (None: the server's default)."""
    return {
        "method": args.method.replace("-", "_"),
        "calibrate_tilt": args.calibrate_tilt,
        "normalize_local_contrast": args.local_contrast,
        "propagate_at_full_resolution": args.propagate_at_full_resolution,
        "tilt_axis_deg": args.tilt_axis_deg,
        "relief_sign": args.relief_sign,
        "detector_from_tilt_axis_deg": args.detector_from_tilt_axis_deg,
    }


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
        z.filled(np.nanmedian(result.z_um) if z.count() else 0),
        cmap=plt.get_cmap("viridis"),
        norm=norm,
        blend_mode="soft",
        vert_exag=1.0 / result.pixel_size_um,
        dx=1,
        dy=1,
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


def height_summary(result: HeightMap, kept: Measurement) -> dict:
    """Figures worth printing about a height map as kept (µm where dimensional): its extremes,
    the share the matching measured (`valid_fraction`, as its report has it), the coverage
    (surface.measurement.coverage: filled points apart, rejected outliers unknown) and the
    median sigma."""
    from fractoscope.surface.measurement import coverage

    valid = np.isfinite(result.z_um)
    z = result.z_um[valid]
    covered = coverage(result.z_um, kept.filled)
    return {
        "z_min_um": float(z.min()) if z.size else float("nan"),
        "z_max_um": float(z.max()) if z.size else float("nan"),
        "valid_fraction": result.report.get("valid_fraction", covered.measured),
        "coverage": covered.to_dict(),
        "median_sigma_um": float(np.median(result.sigma_um[valid])) if z.size else float("nan"),
        "report": result.report,
    } | _views_summary(result, valid)


def _views_summary(result: HeightMap, valid: np.ndarray) -> dict:
    """The share of the heights that rest on every view of the series (none from servers that do
    not count them)."""
    if result.views_used is None or not valid.any():
        return {}
    views = len(result.report.get("tilt_deg", ()))
    return {"all_views_fraction": float(np.mean(result.views_used[valid] >= views))}
