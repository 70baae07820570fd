"""The demo job behind `make run`: a deterministic synthetic fracture pair with known truth, and
the real pollen tilt series from the shared data when it is present."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import tifffile
from rich.console import Console
from rich.table import Table

from fractoscope import roughness, synthetic
from fractoscope.client import FractoscopeClient

DEMO_PIXEL_SIZE_UM = 0.1
DEMO_TILTS_DEG = (-5.0, 5.0)
REAL_SERIES = "real/potamogeton-tilt-series"


def write_demo_pair(directory: Path, *, size_px: int = 640) -> tuple[Path, Path, np.ndarray]:
    """Renders the demo pair (self-affine fracture surface, H = 0.8) into `directory`; returns the
    two TIFF paths and the true heights on the first image's grid, µm."""
    directory.mkdir(parents=True, exist_ok=True)
    surface_um = synthetic.self_affine_surface((size_px + 64, size_px + 64), hurst=0.8, rms_um=2.5, seed=2026)
    pair = synthetic.render_stereo_pair(
        surface_um, pixel_size_um=DEMO_PIXEL_SIZE_UM, tilt_deg=DEMO_TILTS_DEG, output_shape=(size_px, size_px), seed=7
    )
    paths = directory / "demo_left.tif", directory / "demo_right.tif"
    for path, image in zip(paths, (pair.first, pair.second)):
        tifffile.imwrite(path, image, compression="zlib")
    np.save(directory / "demo_truth_z_um.npy", pair.z_seen_um.astype(np.float32))
    return paths[0], paths[1], pair.z_seen_um


MULTISCALE_MAGNIFICATIONS = (100.0, 400.0)


def write_multiscale_specimen(directory: Path, *, specimen_id: str = "synthetic") -> synthetic.MultiscaleSpecimen:
    """Renders the multi-scale demo specimen (an overview at 1 µm/px and a 4x ROI, placed
    automatically) as PNG pairs with `manifest.json` in `directory`; returns the truth."""
    import json

    import cv2

    spec = synthetic.render_multiscale_specimen()
    directory.mkdir(parents=True, exist_ok=True)
    rois = []
    for roi_id, pair, pixel_um, magnification in [
        ("overview", spec.overview, spec.overview_pixel_size_um, MULTISCALE_MAGNIFICATIONS[0]),
        ("zoom", spec.roi, spec.roi_pixel_size_um, MULTISCALE_MAGNIFICATIONS[1]),
    ]:
        cv2.imwrite(str(directory / f"{roi_id}_left.png"), pair.first)
        cv2.imwrite(str(directory / f"{roi_id}_right.png"), pair.second)
        rois.append({"id": roi_id, "left": f"{roi_id}_left.png", "right": f"{roi_id}_right.png", "tilt_deg": list(spec.tilt_deg),
                     "pixel_size_um": pixel_um, "magnification": magnification})
    rois[1].update(parent="overview", center_um="auto")
    (directory / "manifest.json").write_text(json.dumps({"specimen": specimen_id, "rois": rois}, indent=1))
    return spec


def run_demo(client: FractoscopeClient, data_dir: Path, *, shared_data: Path, console: Console) -> int:
    left, right, truth_um = write_demo_pair(data_dir / "demo")
    table = Table(title="Fractoscope demo: height maps")
    for column in ("pair", "tilts °", "valid %", "height range µm", "Sa µm", "check"):
        table.add_column(column)

    result = client.compute_height_map([left, right], tilt_deg=DEMO_TILTS_DEG, pixel_size_um=DEMO_PIXEL_SIZE_UM)
    np.savez_compressed(data_dir / "demo" / "demo_heights.npz", z_um=result.z_um, sigma_um=result.sigma_um)
    tiles, filter_report = client.build_mesh(result.z_um, result.texture, pixel_size_um=DEMO_PIXEL_SIZE_UM)
    write_tiles(tiles, data_dir / "demo" / "tiles")
    error = result.z_um - truth_um
    error -= np.nanmean(error)
    span = float(truth_um.max() - truth_um.min())
    rms_percent = 100 * float(np.sqrt(np.nanmean(error**2))) / span
    table.add_row(
        "synthetic fracture", "-5 / +5", f"{100 * result.report['valid_fraction']:.1f}",
        f"{np.nanmax(result.z_um) - np.nanmin(result.z_um):.2f}", f"{roughness.sa_um(result.z_um):.3f}",
        f"RMS error {rms_percent:.2f} % of range; true Sa {roughness.sa_um(truth_um):.3f}",
    )

    series = shared_data / REAL_SERIES
    if (series / "pot_02.tif").is_file():
        real = client.compute_height_map([series / "pot_02.tif", series / "pot_04.tif"])
        np.savez_compressed(data_dir / "demo" / "pollen_heights.npz", z_um=real.z_um, sigma_um=real.sigma_um)
        z = real.z_um
        table.add_row(
            "pollen pot_02/pot_04", "/".join(f"{t:+.0f}" for t in real.report["tilt_deg"]),
            f"{100 * real.report['valid_fraction']:.1f}",
            f"{np.nanpercentile(z, 99.5) - np.nanpercentile(z, 0.5):.2f}", f"{roughness.sa_um(z):.3f}",
            f"pixel {real.report['pixel_size_um'] * 1000:.2f} nm from metadata",
        )
    else:
        console.print(f"[yellow]{series} not found: real series skipped[/yellow]")
    console.print(table)
    levels = sorted({tile.level for tile in tiles})
    errors = ", ".join(f"{max(t.geometric_error_m for t in tiles if t.level == level) * 1e6:.3f}" for level in levels)
    console.print(
        f"demo mesh: {len(tiles)} GLB tiles in {len(levels)} levels (geometric error per level, µm: {errors}); "
        f"filter: {filter_report}"
    )
    console.print(f"height maps and tiles written under {data_dir / 'demo'}")
    return 0


def write_tiles(tiles, directory: Path) -> None:
    """GLB tiles as DIRECTORY/level_L/ROW_COL.glb."""
    for tile in tiles:
        path = directory / f"level_{tile.level}" / f"{tile.tile_row}_{tile.tile_col}.glb"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(tile.glb)
