"""The probe suite's servers (tests/hostile; fixtures of tests/conftest.py): what a hostile user
meets, on loopback. `live` is one process's gRPC and HTTP endpoints over a folder store, tokens
required (write and read); `ServerProcess` runs fracto-server as a process of its own, for what is
measured from outside it (memory, CPU, file descriptors, its log). Specimens are written straight
into a store (`write_map_specimen`), not built, so that each probe starts at once."""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
import requests
from s3_server import free_ports

from fractoscope import synthetic
from fractoscope.http.server import start_http_server
from fractoscope.runtime.auth import TokenTable
from fractoscope.runtime.budget import Budget
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.specimen.fusion import PlacedRoi
from fractoscope.specimen.model import RoiEntry, write_description, write_roi_arrays, write_roi_views
from fractoscope.specimen.quadtree import OPTICAL, QuadtreeLayout, TileKey, TileRecord
from fractoscope.store.folder import SpecimenStore

WRITE_TOKEN, READ_TOKEN = "w-9f3c1e2b7a-secret", "r-4d8a6b0c5e-secret"
TOKENS = f"writer:{WRITE_TOKEN}:write,reader:{READ_TOKEN}:read"
WRITE = {"Authorization": f"Bearer {WRITE_TOKEN}"}
READ = {"Authorization": f"Bearer {READ_TOKEN}"}
WRITE_METADATA = (("authorization", f"Bearer {WRITE_TOKEN}"),)
READ_METADATA = (("authorization", f"Bearer {READ_TOKEN}"),)


@dataclass(frozen=True)
class Live:
    """A running server: its gRPC address, HTTP base URL, store and data folder."""

    grpc_address: str
    http: str
    store: SpecimenStore
    data: Path


@pytest.fixture(scope="module")
def live(tmp_path_factory):
    data = tmp_path_factory.mktemp("hostile") / "data"
    store = SpecimenStore(data)
    tokens = TokenTable.from_text(TOKENS)
    budget = Budget.for_server(None, concurrent_requests=1, scratch_root=store.scratch_root)  # one for both
    server, port = create_server(ServerConfig(address="127.0.0.1:0"), store=store, tokens=tokens, budget=budget)
    server.start()
    endpoint = start_http_server(store, tokens=tokens, grpc_address=f"127.0.0.1:{port}", budget=budget)
    yield Live(f"127.0.0.1:{port}", f"http://127.0.0.1:{endpoint.server_port}", store, data)
    endpoint.shutdown()
    server.stop(grace=None)


def write_map_specimen(
    store: SpecimenStore,
    specimen_id: str,
    *,
    size_px: int = 256,
    pixel_size_um: float = 0.5,
    view_names: tuple[str, ...] = ("left.png", "right.png"),
    tile_bytes: bytes = b"glTF-tile",
) -> None:
    """A one-ROI specimen without building it: a self-affine map of `size_px`² at `pixel_size_um`,
    its sigma 0.05 µm, its texture from its heights, image files named `view_names` (PNG bytes of
    the texture) and one root tile, `tile_bytes` (not a GLB)."""
    z_um = synthetic.self_affine_surface((size_px, size_px), hurst=0.8, rms_um=1.0, seed=3).astype(np.float32)
    texture = np.clip((z_um - z_um.min()) / np.ptp(z_um) * 255, 0, 255).astype(np.uint8)
    roi = PlacedRoi("overview", 100.0, pixel_size_um, (0.0, 0.0), z_um, texture, np.full(z_um.shape, 0.05, np.float32))
    root = TileKey(0, 0, 0)
    record = TileRecord(root, roi.id, roi.magnification, OPTICAL, 0.0, float(z_um.min()), float(z_um.max()))
    png = cv2.imencode(".png", texture)[1].tobytes()
    with store.writing(specimen_id) as staging:
        (staging / root.uri).parent.mkdir(parents=True)
        (staging / root.uri).write_bytes(tile_bytes)
        (staging / "tileset.json").write_text(
            '{"asset": {"version": "1.1"}, "geometricError": 1, "root": {"geometricError": 0, '
            '"boundingVolume": {"box": [0,0,0,1,0,0,0,1,0,0,0,1]}, "content": {"uri": "tiles/0/0/0.glb"}}}'
        )
        write_roi_arrays(staging, roi)
        views = write_roi_views(staging, roi.id, [(name, png) for name in view_names])
        entry = RoiEntry(
            roi.id,
            "",
            roi.magnification,
            pixel_size_um,
            roi.origin_um,
            z_um.shape,
            matching={"valid_fraction": 1.0},
            views=views,
        )
        size_um = pixel_size_um * (size_px - 1)
        write_description(
            staging,
            specimen_id=specimen_id,
            request_id="",
            rois=[entry],
            layout=QuadtreeLayout((0.0, 0.0), size_um),
            tiles={root: record},
        )


class ServerProcess:
    """fracto-server in a process of its own on free loopback ports, its data in `data`, its log
    (JSON lines) in `data/../server.log`; `environment` adds to or overrides the inherited one;
    `open_files` sets its limit of file descriptors (RLIMIT_NOFILE)."""

    def __init__(
        self,
        data: Path,
        *,
        environment: dict[str, str] | None = None,
        arguments: tuple[str, ...] = (),
        open_files: int | None = None,
    ):
        self.data = data
        self.open_files = open_files
        self.grpc_port, self.http_port = free_ports(2)
        self.log_path = data.parent / f"server-{self.grpc_port}.log"
        self.environment = {"FRACTO_TOKENS": TOKENS, "FRACTO_TOKEN": WRITE_TOKEN, **(environment or {})}
        self.arguments = arguments
        self.process: subprocess.Popen | None = None

    @property
    def http(self) -> str:
        return f"http://127.0.0.1:{self.http_port}"

    @property
    def grpc_address(self) -> str:
        return f"127.0.0.1:{self.grpc_port}"

    def start(self, timeout_s: float = 120.0) -> ServerProcess:
        command = [
            sys.executable,
            "-m",
            "fractoscope.server.main",
            "--address",
            self.grpc_address,
            "--http-address",
            f"127.0.0.1:{self.http_port}",
            "--data",
            str(self.data),
            *self.arguments,
        ]
        with open(self.log_path, "ab") as log:
            self.process = subprocess.Popen(
                command,
                env={**os.environ, **self.environment},
                stdout=log,
                stderr=subprocess.STDOUT,
                preexec_fn=self._limits if self.open_files else None,
            )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if self.process.poll() is not None:
                raise RuntimeError(f"fracto-server exited with {self.process.returncode}: {self.log()[-2000:]}")
            try:
                if requests.get(f"{self.http}/healthz", timeout=2).status_code in (200, 503):
                    return self
            except requests.RequestException:
                time.sleep(0.3)
        raise RuntimeError(f"fracto-server did not answer within {timeout_s} s: {self.log()[-2000:]}")

    def _limits(self) -> None:
        resource.setrlimit(resource.RLIMIT_NOFILE, (self.open_files, self.open_files))

    def stop(self) -> None:
        if self.process is not None and self.process.poll() is None:
            self.process.send_signal(signal.SIGKILL)
            self.process.wait(timeout=30)

    def log(self) -> str:
        return self.log_path.read_text(errors="replace") if self.log_path.exists() else ""

    def rss_bytes(self) -> int:
        """The process's resident memory now."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) * 1024
        raise RuntimeError("no VmRSS")

    def peak_rss_bytes(self) -> int:
        """The most resident memory the process has had (VmHWM)."""
        for line in Path(f"/proc/{self.process.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) * 1024
        raise RuntimeError("no VmHWM")

    def cpu_s(self) -> float:
        """User and system CPU seconds of all its threads so far."""
        fields = Path(f"/proc/{self.process.pid}/stat").read_text().rpartition(")")[2].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@pytest.fixture
def server_process(tmp_path):
    """A factory of started ServerProcesses over `tmp_path/data`, all killed after the test."""
    started: list[ServerProcess] = []

    def start(**options) -> ServerProcess:
        server = ServerProcess(options.pop("data", tmp_path / "data"), **options)
        started.append(server)
        return server.start()

    yield start
    for server in started:
        server.stop()
