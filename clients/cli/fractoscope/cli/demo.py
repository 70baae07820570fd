"""The demo job behind `make run`: a deterministic synthetic multi-scale fracture specimen with
known truth, and the real pollen pair from the shared data when it is present. The servers and
the viewer's URL come first; the specimens are built in the background, with their progress."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import sys
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from fractoscope.cli.common import UsageError
from fractoscope.client import FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.progress import ProgressCallback

REAL_SERIES = "real/potamogeton-tilt-series"
FIRST_SPECIMEN = "synthetic"  # the one the viewer's URL opens, built first


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
    from fractoscope.http.server import start_http_server
    from fractoscope.runtime.process import keep_freed_memory
    from fractoscope.server.main import embedded_server
    from fractoscope.store.folder import SpecimenStore

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
            viewer = f"http://{args.host}:{http.server_port}/viewer/"
            builds = _Builds(
                lambda: run_demo(client, data, shared_data=Path(args.shared_data), console=console, viewer=viewer),
                stop_when_built=args.exit,
            )
            if not args.exit:  # before the URL is printed: whoever reads it may ask us to stop at once
                for signum in (signal.SIGINT, signal.SIGTERM):
                    signal.signal(signum, lambda *_: builds.interrupt())
            console.print(f"viewer: [bold]{viewer}?specimen={FIRST_SPECIMEN}[/bold]", soft_wrap=True)
            console.print(
                f"gRPC:   {address}   (e.g. fracto roughness {FIRST_SPECIMEN} --server {address})", soft_wrap=True
            )
            console.print(f"data:   {data.resolve()}", soft_wrap=True)
            console.print("building the demo specimens; the viewer lists each one once it is built", soft_wrap=True)
            builds.start()
            if not args.exit:
                console.print("serving until Ctrl-C")
            builds.wait()
            if not args.exit:
                console.print("stopping")
    finally:
        http.shutdown()
    if builds.interrupted:
        # A build stopped mid-way may still run on a job thread inside native code, which the
        # interpreter's exit would tear down (abort, status -6); the process ends here, as
        # fracto-server's does (the store recovers from an unfinished build at its next start).
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(0)
    return 0


class _Builds:
    """The demo's builds on a thread of their own while the main thread serves. `wait` returns
    when interrupted (Ctrl-C, SIGTERM), and with `stop_when_built` once the builds are done; it
    raises the builds' error, if any, in the main thread, where the command's errors are told."""

    def __init__(self, build: Callable[[], object], *, stop_when_built: bool):
        self._build, self._stop_when_built = build, stop_when_built
        self._stop, self._interrupted = threading.Event(), threading.Event()
        self._failure: Exception | None = None
        self._thread = threading.Thread(target=self._run, name="demo-builds", daemon=True)

    def start(self) -> None:
        self._thread.start()

    @property
    def interrupted(self) -> bool:
        return self._interrupted.is_set()

    def interrupt(self) -> None:
        self._interrupted.set()
        self._stop.set()

    def wait(self) -> None:
        self._stop.wait()
        if self._failure is not None and not self._interrupted.is_set():
            raise self._failure

    def _run(self) -> None:
        from fractoscope.runtime.process import settle_garbage_collector

        try:
            self._build()
        except Exception as error:  # told by `wait`; after an interrupt, only the stopped server's doing
            self._failure = error
            self._stop.set()
            return
        settle_garbage_collector()  # start-up is over: what the builds left is frozen (see process)
        if self._stop_when_built:
            self._stop.set()


def run_demo(
    client: FractoscopeClient, data_dir: Path, *, shared_data: Path, console: Console, viewer: str
) -> list[str]:
    """Builds the demo specimens (the synthetic multi-scale fracture, and the pollen pair pot_02 /
    pot_04 when the shared data is present), showing their progress (see _progress) and each
    one's link under `viewer` as it is built, then a summary no wider than 80 columns; returns
    their ids."""
    inputs = data_dir / "demo-input"
    truth = _write_synthetic(inputs / FIRST_SPECIMEN)
    manifests = [inputs / FIRST_SPECIMEN / "manifest.json"]
    series = shared_data / REAL_SERIES
    if (series / "pot_02.tif").is_file():
        manifests.append(_write_pollen_manifest(series, inputs / "pollen"))
    else:
        console.print(f"{series} not found: the real pollen specimen is skipped", style="yellow", soft_wrap=True)
    rows, checks, built = [], [], []
    with _progress(console) as progress_of:
        for manifest in manifests:
            specimen_id, rois = load_manifest(manifest)
            started = time.monotonic()
            summary = client.reconstruct_specimen(specimen_id, rois, on_progress=progress_of(specimen_id))
            console.print(
                f"{specimen_id}: built in {time.monotonic() - started:.0f} s: {viewer}?specimen={specimen_id}",
                soft_wrap=True,
                highlight=False,
            )
            built.append(specimen_id)
            for roi in summary["rois"]:
                # Seconds per ROI (the Hurst fits, Spd): said, so that a log is never silent meanwhile.
                console.print(f"{specimen_id}: roughness of ROI {roi['id']} ...", soft_wrap=True, highlight=False)
                values = client.roughness(specimen_id, roi=roi["id"])
                rows.append(_summary_row(specimen_id, roi, values))
                checks.extend(_checks(specimen_id, roi, values, truth))
    console.print(summary_table(rows, checks), soft_wrap=True, highlight=False)
    return built


def _write_synthetic(directory: Path):
    """The synthetic specimen's images and manifest in `directory`; returns its truth
    (synthetic.examples.MultiscaleSpecimen)."""
    from fractoscope.synthetic.examples import write_multiscale_specimen

    return write_multiscale_specimen(directory, specimen_id=FIRST_SPECIMEN)


def _summary_row(specimen_id: str, roi: dict, values: dict) -> tuple[str, ...]:
    """One ROI's line of the summary table (SUMMARY_COLUMNS) from its summary and roughness."""
    region = roi["region"]["min"]
    return (
        specimen_id,
        roi["id"],
        f"{roi['magnification']:g}x" if roi["magnification"] else "-",
        f"{roi['pixel_size_um']:.4g}",
        f"{region['x_um']:.1f}, {region['y_um']:.1f}",
        f"{values['Sz']:.2f}",
        f"{values['Sa']:.3f}",
    )


def _checks(specimen_id: str, roi: dict, values: dict, truth) -> list[str]:
    """What the summary says of an ROI against the truth: the synthetic zoom's placement, the
    synthetic overview's Sa, and where any ROI's height zero is."""
    from fractoscope.surface import roughness

    checks = []
    if specimen_id == FIRST_SPECIMEN and roi["parent"]:
        region = roi["region"]["min"]
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
    elif specimen_id == FIRST_SPECIMEN:
        true_sa_um = roughness.height_parameters_after_plane(truth.overview.z_seen_um)["Sa"]
        checks.append(f"{specimen_id}/{roi['id']}: Sa {values['Sa']:.3f} µm, true Sa {true_sa_um:.3f} µm")
    if roi["level"]:
        checks.append(f"{specimen_id}/{roi['id']}: heights from the {roi['level']} (zero there)")
    return checks


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


@contextlib.contextmanager
def _progress(console: Console) -> Iterator[Callable[[str], ProgressCallback]]:
    """Yields, for a specimen id, the progress callback of its build: on a terminal a live bar
    per specimen, elsewhere (a log, a pipe) plain lines (see _progress_lines)."""
    if not console.is_terminal:
        yield lambda specimen_id: _progress_lines(console, specimen_id, time.monotonic())
        return
    columns = (
        TextColumn("{task.fields[specimen]}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f} %"),
        TimeElapsedColumn(),
        TextColumn("{task.description}"),
    )
    with Progress(*columns, console=console) as bars:

        def progress_of(specimen_id: str) -> ProgressCallback:
            task = bars.add_task("starting", total=1.0, specimen=specimen_id)
            return lambda fraction, message: bars.update(task, completed=fraction, description=message)

        yield progress_of


def _progress_lines(console: Console, specimen_id: str, started: float) -> ProgressCallback:
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
