"""The demo job behind `make run`: a deterministic synthetic multi-scale fracture specimen with
known truth, and the real pollen pair from the shared data when it is present."""

from __future__ import annotations

import json
import signal
import threading
import time
from pathlib import Path

import numpy as np
from rich.console import Console

from fractoscope.cli.common import UsageError
from fractoscope.client import FractoscopeClient
from fractoscope.client.manifest import load_manifest

REAL_SERIES = "real/potamogeton-tilt-series"


def add_parsers(commands) -> None:
    demo = commands.add_parser("demo", help="serve the demo specimens with the web viewer (the main job of make run)")
    demo.add_argument("--data", default="./data", help="data directory (default ./data)")
    demo.add_argument("--shared-data", default="../shared/data", help="shared test data, used when present")
    demo.add_argument("--host", default="127.0.0.1", help="address to serve on (default loopback)")
    demo.add_argument("--port", type=int, default=50051, help="gRPC port (default 50051; 0 = any free port)")
    demo.add_argument(
        "--http-port", type=int, default=8080, help="HTTP port of tiles and viewer (default 8080; 0 = any)"
    )
    demo.add_argument("--exit", action="store_true", help="stop after building the specimens instead of serving")
    demo.set_defaults(run=command_demo)


def command_demo(args) -> int:
    from fractoscope.runtime.process import keep_freed_memory, settle_garbage_collector
    from fractoscope.server.main import embedded_server
    from fractoscope.specimen.store import SpecimenStore
    from fractoscope.tiles.http import start_http_server

    console = Console()
    data = Path(args.data)
    keep_freed_memory()
    store = SpecimenStore(data)  # one store, served over gRPC and HTTP
    try:
        http = start_http_server(store, args.host, args.http_port)
    except OSError as error:
        raise UsageError(
            f"cannot serve HTTP on {args.host}:{args.http_port}: {error.strerror}; choose another --http-port"
        ) from None
    try:
        with (
            embedded_server(host=args.host, port=args.port, store=store) as address,
            FractoscopeClient(address) as client,
        ):
            http.send_builds_to(address)
            specimens = run_demo(client, data, shared_data=Path(args.shared_data), console=console)
            stop = threading.Event()
            if not args.exit:  # before the URL is printed: whoever reads it may ask us to stop at once
                for signum in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(signum, lambda *_: stop.set())
            url = f"http://{args.host}:{http.server_port}/viewer/?specimen={specimens[0]}"
            console.print(f"viewer: [bold]{url}[/bold]", soft_wrap=True)
            console.print(
                f"gRPC:   {address}   (e.g. fracto roughness {specimens[0]} --server {address})", soft_wrap=True
            )
            console.print(f"data:   {data.resolve()}", soft_wrap=True)
            if not args.exit:
                settle_garbage_collector()
                console.print("serving until Ctrl-C")
                stop.wait()
                console.print("stopping")
    finally:
        http.shutdown()
    return 0


def run_demo(client: FractoscopeClient, data_dir: Path, *, shared_data: Path, console: Console) -> list[str]:
    """Builds the demo specimens (the synthetic multi-scale fracture, and the pollen pair pot_02 /
    pot_04 when the shared data is present), printing progress as they are built and then a
    summary no wider than 80 columns; returns their ids."""
    from fractoscope.surface import roughness
    from fractoscope.synthetic.examples import write_multiscale_specimen

    inputs = data_dir / "demo-input"
    truth = write_multiscale_specimen(inputs / "synthetic")
    manifests = [inputs / "synthetic" / "manifest.json"]
    series = shared_data / REAL_SERIES
    if (series / "pot_02.tif").is_file():
        manifests.append(_write_pollen_manifest(series, inputs / "pollen"))
    else:
        console.print(f"{series} not found: the real pollen specimen is skipped", style="yellow", soft_wrap=True)

    rows, checks, built = [], [], []
    for manifest in manifests:
        specimen_id, rois = load_manifest(manifest)
        started = time.monotonic()
        summary = client.reconstruct_specimen(
            specimen_id, rois, on_progress=_progress_lines(console, specimen_id, started)
        )
        console.print(f"{specimen_id}: built in {time.monotonic() - started:.0f} s", soft_wrap=True)
        built.append(specimen_id)
        for roi in summary["rois"]:
            values = client.roughness(specimen_id, roi=roi["id"])
            region = roi["region"]["min"]
            if specimen_id == "synthetic" and roi["parent"]:
                error_px = (
                    np.hypot(
                        region["x_um"] - truth.roi_origin_px[0] * truth.overview_pixel_size_um,
                        region["y_um"] - truth.roi_origin_px[1] * truth.overview_pixel_size_um,
                    )
                    / truth.overview_pixel_size_um
                )
                checks.append(
                    f"{specimen_id}/{roi['id']}: found {error_px:.2f} px from the truth; fit residual "
                    f"{roi['alignment_residual_um']:.2f} µm"
                )
            elif specimen_id == "synthetic":
                checks.append(
                    f"{specimen_id}/{roi['id']}: Sa {values['Sa']:.3f} µm, true Sa "
                    f"{roughness.height_parameters_after_plane(truth.overview.z_seen_um)['Sa']:.3f} µm"
                )
            if roi["level"]:
                checks.append(f"{specimen_id}/{roi['id']}: heights from the {roi['level']} (zero there)")
            rows.append(
                (
                    specimen_id,
                    roi["id"],
                    f"{roi['magnification']:g}x" if roi["magnification"] else "-",
                    f"{roi['pixel_size_um']:.4g}",
                    f"{region['x_um']:.1f}, {region['y_um']:.1f}",
                    f"{values['Sz']:.2f}",
                    f"{values['Sa']:.3f}",
                )
            )
    console.print(summary_table(rows, checks), soft_wrap=True, highlight=False)
    return built


SUMMARY_COLUMNS = ("specimen", "ROI", "mag.", "µm/px", "at x, y µm", "Sz µm", "Sa µm")


def summary_table(rows: list[tuple[str, ...]], checks: list[str]) -> str:
    """The demo's summary as plain text: one line per ROI (no wider than 80 columns for ids of up
    to 12 characters, so it stays readable in a log), then the checks, one per line."""
    widths = [max(len(column), *(len(row[k]) for row in rows)) for k, column in enumerate(SUMMARY_COLUMNS)]

    def line(cells) -> str:
        return "  ".join(
            cell.ljust(width) if k < 2 else cell.rjust(width) for k, (cell, width) in enumerate(zip(cells, widths))
        ).rstrip()

    rule = "-" * len(line(SUMMARY_COLUMNS))
    return "\n".join(["Fractoscope demo specimens", line(SUMMARY_COLUMNS), rule, *map(line, rows), rule, *checks])


def _progress_lines(console: Console, specimen_id: str, started: float):
    """A progress callback that prints a line whenever the stage changes or another tenth is
    done: a log shows what the demo is doing while it builds."""
    last = {"stage": None, "tenth": -1}

    def report(fraction: float, message: str) -> None:
        stage, tenth = message.split(" ", 1)[0], int(fraction * 10)
        if stage == last["stage"] and tenth == last["tenth"]:
            return
        last.update(stage=stage, tenth=tenth)
        console.print(
            f"{specimen_id}: {100 * fraction:3.0f} % {message} ({time.monotonic() - started:.0f} s)",
            soft_wrap=True,
            highlight=False,
        )

    return report


def _write_pollen_manifest(series: Path, directory: Path) -> Path:
    """A one-ROI specimen of the real pollen pair at -3/+3 degrees (tilts, pixel size and
    magnification from the Zeiss metadata), its heights from the substrate it lies on."""
    directory.mkdir(parents=True, exist_ok=True)
    manifest = directory / "manifest.json"
    rois = [
        {
            "id": "pot-02-04",
            "left": str((series / "pot_02.tif").resolve()),
            "right": str((series / "pot_04.tif").resolve()),
            "level": "substrate",
        }
    ]
    manifest.write_text(json.dumps({"specimen": "pollen", "rois": rois}, indent=1))
    return manifest
