"""The demo job behind `make run`: a deterministic synthetic multi-scale fracture specimen with
known truth, and the real pollen pair from the shared data when it is present."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from rich.console import Console
from rich.table import Table

from fractoscope.surface import roughness
from fractoscope.synthetic.examples import write_multiscale_specimen
from fractoscope.client import FractoscopeClient
from fractoscope.client.manifest import load_manifest

REAL_SERIES = "real/potamogeton-tilt-series"


def run_demo(client: FractoscopeClient, data_dir: Path, *, shared_data: Path, console: Console) -> list[str]:
    """Builds the demo specimens (the synthetic multi-scale fracture, and the pollen pair pot_02 /
    pot_04 when the shared data is present) and prints a summary; returns their ids."""
    inputs = data_dir / "demo-input"
    truth = write_multiscale_specimen(inputs / "synthetic")
    manifests = [inputs / "synthetic" / "manifest.json"]
    series = shared_data / REAL_SERIES
    if (series / "pot_02.tif").is_file():
        manifests.append(_write_pollen_manifest(series, inputs / "pollen"))
    else:
        console.print(f"[yellow]{series} not found: the real pollen specimen is skipped[/yellow]")

    table = Table(title="Fractoscope demo specimens")
    for column in ("specimen", "ROI", "µm/px", "placed at (x, y) µm", "height range µm", "Sa µm", "check"):
        table.add_column(column)
    built = []
    for manifest in manifests:
        specimen_id, rois = load_manifest(manifest)
        with console.status(f"reconstructing {specimen_id}"):
            summary = client.reconstruct_specimen(specimen_id, rois)
        built.append(specimen_id)
        for roi in summary["rois"]:
            values = client.roughness(specimen_id, roi=roi["id"])
            region = roi["region"]["min"]
            check = ""
            if specimen_id == "synthetic" and roi["parent"]:
                error_px = np.hypot(region["x_um"] - truth.roi_origin_px[0] * truth.overview_pixel_size_um,
                                    region["y_um"] - truth.roi_origin_px[1] * truth.overview_pixel_size_um) / truth.overview_pixel_size_um
                check = f"found {error_px:.2f} px from the truth; fit residual {roi['alignment_residual_um']:.2f} µm"
            elif specimen_id == "synthetic":
                check = f"true Sa {roughness.sa_um(truth.overview.z_seen_um):.3f}"
            table.add_row(
                specimen_id, roi["id"], f"{roi['pixel_size_um']:.4g}", f"{region['x_um']:.1f}, {region['y_um']:.1f}",
                f"{values['Sz']:.2f}", f"{values['Sa']:.3f}", check,
            )
    console.print(table)
    return built


def _write_pollen_manifest(series: Path, directory: Path) -> Path:
    """A one-ROI specimen of the real pollen pair at -3/+3 degrees (tilts and pixel size from the
    Zeiss metadata)."""
    import json

    directory.mkdir(parents=True, exist_ok=True)
    manifest = directory / "manifest.json"
    rois = [{"id": "pot-02-04", "left": str((series / "pot_02.tif").resolve()), "right": str((series / "pot_04.tif").resolve()),
             "magnification": 0}]
    manifest.write_text(json.dumps({"specimen": "pollen", "rois": rois}, indent=1))
    return manifest


def write_tiles(tiles, directory: Path) -> None:
    """GLB tiles as DIRECTORY/level_L/ROW_COL.glb."""
    for tile in tiles:
        path = directory / f"level_{tile.level}" / f"{tile.tile_row}_{tile.tile_col}.glb"
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(tile.glb)
