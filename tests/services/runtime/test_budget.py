"""The memory budget: estimates against a measured peak, and requests over the limit refused
before any work, with a message naming the size."""

from __future__ import annotations

import os
import subprocess
import sys

import grpc
import numpy as np
import pytest
from conftest import fracture_pair, tiff_bytes

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.runtime import budget
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.v1 import tiles_pb2


def _status_kb(pid: int, field: str) -> int:
    for line in open(f"/proc/{pid}/status"):
        if line.startswith(f"{field}:"):
            return int(line.split()[1])
    raise LookupError(field)


def _serve(tmp_path, *flags: str, env: dict | None = None) -> tuple[subprocess.Popen, str]:
    """A fracto-server process on a free loopback port (as deployed: its own process, glibc
    keeping freed memory), once it answers."""
    import socket

    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    process = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fractoscope.server.main",
            "--address",
            f"127.0.0.1:{port}",
            "--http-address",
            "",
            "--data",
            str(tmp_path / "data"),
            "--log-level",
            "WARNING",
            *flags,
        ],
        env={**os.environ, **(env or {})},
    )
    address = f"127.0.0.1:{port}"
    with grpc.insecure_channel(address) as channel:
        grpc.channel_ready_future(channel).result(timeout=60)
    return process, address


@pytest.mark.timeout(300)
@pytest.mark.parametrize(
    "size_px, strip_pixels", [(1024, 300_000), pytest.param(2048, 2_000_000, marks=pytest.mark.slow)]
)
@pytest.mark.server
def test_the_estimate_covers_the_measured_peak_of_a_height_map(tmp_path, size_px, strip_pixels):
    """ComputeHeightMap on a server process: its peak memory above what the server held before
    (VmHWM after, VmRSS before) is within the estimate, and the estimate is not wildly above it."""
    pair = fracture_pair(size_px=size_px, seed=2)
    files = [tiff_bytes(pair.first), tiff_bytes(pair.second)]
    process, address = _serve(tmp_path, "--strip-pixels", str(strip_pixels))
    try:
        with FractoscopeClient(address, timeout_s=280) as client:
            before_kb = _status_kb(process.pid, "VmRSS")
            result = client.compute_height_map(files, tilt_deg=(-5, 5), pixel_size_um=0.1)
            peak_kb = _status_kb(process.pid, "VmHWM")
    finally:
        process.terminate()
        process.wait(timeout=60)
    assert result.report["strip_count"] > 1  # the strip term counts
    measured = (peak_kb - before_kb) * 1024
    estimate = budget.height_map_bytes((size_px, size_px), 2, strip_pixels=strip_pixels)
    print(f"{size_px}²: measured {measured / 2**20:.0f} MiB, estimated {estimate / 2**20:.0f} MiB")
    assert measured <= estimate <= 2.5 * measured


@pytest.mark.server
def test_a_request_over_the_memory_budget_is_refused_before_any_work_naming_its_size(tmp_path):
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data", max_request_mb=300))
    server.start()
    noise = np.random.default_rng(0).integers(0, 256, (1024, 1024), dtype=np.uint8)  # refused before it is decoded
    files = [tiff_bytes(noise), tiff_bytes(noise)]
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=60) as client:
            progress = []
            with pytest.raises(ClientError) as refused:
                client.compute_height_map(
                    files, tilt_deg=(-5, 5), pixel_size_um=0.1, on_progress=lambda *report: progress.append(report)
                )
            assert refused.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and progress == []
            message = str(refused.value)
            assert "1024 x 1024 pixels" in message and "300 MiB" in message and "FRACTO_MAX_REQUEST_MB" in message
            assert refused.value.retry_after_s is None  # retrying will not help

            spec = tiles_pb2.RoiSpec(id="overview", pixel_size_um=0.1)
            for content, tilt_deg in zip(files, (-5.0, 5.0)):
                spec.images.add(tilt_deg=tilt_deg).image.content = content
            with pytest.raises(ClientError) as refused:
                client.reconstruct_specimen("steel-1", [spec])
            assert refused.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED and "1024 x 1024 pixels" in str(
                refused.value
            )
            small = fracture_pair(size_px=256, seed=2)  # within the limit
            result = client.compute_height_map(
                [tiff_bytes(small.first), tiff_bytes(small.second)], tilt_deg=(-5, 5), pixel_size_um=0.1
            )
            assert result.z_um.shape == (256, 256)
    finally:
        server.stop(grace=None)


def test_the_default_limit_shares_the_servers_memory_among_its_build_workers():
    memory = budget.server_memory_bytes()
    assert 0 < memory <= os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    assert budget.Budget.for_server(None, concurrent_requests=2).limit_bytes == int(budget.REQUEST_SHARE * memory / 2)
    assert budget.Budget.for_server(300, concurrent_requests=2).limit_bytes == 300 * 2**20


def test_estimates_grow_with_the_views_the_rotated_canvas_and_the_strips():
    pair = budget.height_map_bytes((4096, 4096), 2)
    assert budget.height_map_bytes((4096, 4096), 3) > pair  # another matched view's full-image arrays
    # the canvas that turns a 45° axis vertical holds twice the pixels (its strips are no larger)
    assert (
        budget.height_map_bytes((4096, 4096), 2, tilt_axis_deg=45.0)
        > pair + budget.HEIGHT_MAP_BYTES_PER_PIXEL * 4096**2 // 2
    )
    assert budget.height_map_bytes((4096, 4096), 2, strip_pixels=8_000_000) > pair
    assert budget.height_map_bytes((16384, 16384), 2) > 13e9  # that pair took a server past 13 GB, still aligning
