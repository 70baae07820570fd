"""`fracto height`: height maps of stereo pairs and tilt series, as .npz (and a picture)."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from fractoscope.cli.common import SERVER_HELP, UsageError, connected, err, existing_file, progress_bar
from fractoscope.client import FractoscopeClient, HeightMap


def add_parsers(commands) -> None:
    height = commands.add_parser("height", help="height map of a stereo pair or a tilt series")
    height.add_argument("images", nargs="+", metavar="IMAGE",
                        help="the reference image (TIFF or PNG; heights use its pixel grid), then the other views")
    height.add_argument("--tilt", nargs="+", type=float, metavar="T", help="stage tilts in degrees, one per image (default: metadata)")
    height.add_argument("--calibrate-tilt", action="store_true",
                        help="estimate the tilts from three or more images (the given or metadata tilts are the start)")
    height.add_argument("--local-contrast", action=argparse.BooleanOptionalAction,
                        help="take tilt-dependent shading out before matching (default: on; --no-local-contrast for flat, "
                             "weakly textured areas)")
    height.add_argument("--method", choices=("tgv-zncc", "window-zncc"), default="tgv-zncc",
                        help="matching method: tgv-zncc (default: the window correlation refined by TGV², most accurate) or "
                             "window-zncc (the paper's window correlation, about ten times faster)")
    height.add_argument("--propagate-at-full-resolution", action="store_true",
                        help="let pixels try their neighbours' disparities at full resolution too: for steps (cleavage); "
                             "about 1.5x slower")
    height.add_argument("--pixel-size-um", type=float, help="pixel size in µm (default: metadata)")
    height.add_argument("--tilt-axis-deg", type=float, help="tilt axis direction in the image, degrees (default 90: vertical)")
    height.add_argument("-o", "--output", required=True, help="output .npz with z_um, sigma_um, confidence")
    height.add_argument("--server", help=SERVER_HELP)
    height.add_argument("--json", action="store_true", help="print a JSON summary instead of text")
    height.add_argument("--png", help="also write a picture: height colour map with hillshade and colour bar in µm")
    height.set_defaults(run=command_height)


def compute_height(client: FractoscopeClient, args, quiet: bool) -> HeightMap:
    if len(args.images) < 2:
        raise UsageError("give at least two images (a stereo pair or a tilt series)")
    if args.tilt is not None and len(args.tilt) != len(args.images):
        raise UsageError(f"--tilt needs one angle per image: {len(args.images)} images, {len(args.tilt)} tilts")
    if args.calibrate_tilt and len(args.images) < 3:
        raise UsageError("--calibrate-tilt needs three or more images")
    paths = [existing_file(image) for image in args.images]
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
