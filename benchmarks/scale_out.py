"""`make bench`: scale-out of matching. One large synthetic pair is sent to a matching process
that matches everything itself, then to one that farms the strips of its dense matching out to
1, 2, ... matching processes on loopback (round-robin over their addresses), one strip in flight
per peer. Reports wall times, the speed-up over the single process and whether the stitched
height maps are identical.

With `--one-cpu-per-replica` every process is pinned to one CPU (replicas with a CPU limit of 1,
as on a cluster), the peers spread over this machine's CPUs; otherwise all share every CPU.

Writes bench-results/scale_out.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import tifffile

from benchmarks.matching import PIXEL_SIZE_UM, TILTS_DEG, make_pair
from benchmarks.serving import free_port
from fractoscope.client import FractoscopeClient
from fractoscope.stereo.matching import DEFAULT_STRIP_PIXELS

REPEATS = 2


def _server(port: int, *args: str, cpu: int | None = None) -> subprocess.Popen:
    return subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fractoscope.server.main",
            "--address",
            f"127.0.0.1:{port}",
            "--services",
            "matching",
            "--http-address",
            "",
            *args,
        ],
        env={**os.environ, "GRPC_VERBOSITY": "ERROR"},
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
        preexec_fn=None if cpu is None else (lambda: os.sched_setaffinity(0, {cpu})),
    )


def _wait_healthy(ports: list[int]) -> None:
    deadline = time.monotonic() + 60
    for port in ports:
        while (
            subprocess.run(
                [sys.executable, "-m", "fractoscope.server.healthcheck", f"127.0.0.1:{port}"], capture_output=True
            ).returncode
            != 0
        ):
            if time.monotonic() > deadline:
                raise RuntimeError(f"matching on port {port} did not start")
            time.sleep(0.3)


def time_configuration(files: list[Path], peer_count: int, strip_pixels: int, pinned: bool) -> tuple[dict, np.ndarray]:
    """Best wall time of REPEATS height maps through a matching process with `peer_count` strip
    peers (0: it matches alone); returns the figures and the last height map. `pinned`: one CPU
    per process, the coordinator on the first, the peers from the second on, wrapping around."""
    cpus = sorted(os.sched_getaffinity(0))
    peer_ports = [free_port() for _ in range(peer_count)]
    coordinator_port = free_port()
    peer_args = ["--strip-peers", "ipv4:" + ",".join(f"127.0.0.1:{p}" for p in peer_ports)] if peer_ports else []
    processes = [
        _server(port, cpu=cpus[(index + 1) % len(cpus)] if pinned else None) for index, port in enumerate(peer_ports)
    ]
    processes.append(
        _server(
            coordinator_port,
            "--strip-pixels",
            str(strip_pixels),
            "--strip-in-flight",
            str(max(peer_count, 1)),
            *peer_args,
            cpu=cpus[0] if pinned else None,
        )
    )
    try:
        _wait_healthy([*peer_ports, coordinator_port])
        with FractoscopeClient(f"127.0.0.1:{coordinator_port}", timeout_s=1800) as client:
            seconds, result = [], None
            for _ in range(REPEATS + (1 if peer_ports else 0)):  # a first call connects to the peers
                started = time.perf_counter()
                result = client.compute_height_map(files, tilt_deg=TILTS_DEG, pixel_size_um=PIXEL_SIZE_UM)
                seconds.append(time.perf_counter() - started)
            if peer_ports:
                seconds = seconds[1:]
    finally:
        for process in processes:
            process.terminate()
            process.wait(timeout=60)
    figures = {
        "peers": peer_count,
        "seconds": min(seconds),
        "strip_count": result.report["strip_count"],
        "strip_workers": len(result.report["strip_workers"]),
    }
    return figures, result.z_um


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--size-px", type=int, default=4096)
    parser.add_argument("--peers", type=int, nargs="+", default=[1, 2, 4])
    parser.add_argument("--strip-pixels", type=int, default=DEFAULT_STRIP_PIXELS)
    parser.add_argument("--one-cpu-per-replica", action="store_true")
    parser.add_argument("--name", default="scale_out")
    args = parser.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as scratch:
        pair_path = Path(scratch) / "pair.npz"
        make_pair(args.size_px, pair_path)
        with np.load(pair_path) as arrays:
            files = [Path(scratch) / f"view{index}.tif" for index in range(2)]
            for path, key in zip(files, ("first", "second")):
                tifffile.imwrite(path, arrays[key])
        single, reference = time_configuration(files, 0, args.strip_pixels, args.one_cpu_per_replica)
        rows = [single]
        for peer_count in args.peers:
            figures, z_um = time_configuration(files, peer_count, args.strip_pixels, args.one_cpu_per_replica)
            figures["speed_up"] = single["seconds"] / figures["seconds"]
            figures["identical_to_single_process"] = bool(np.array_equal(z_um, reference, equal_nan=True))
            rows.append(figures)
    results = {
        "size_px": args.size_px,
        "cpu_count": os.cpu_count(),
        "one_cpu_per_replica": args.one_cpu_per_replica,
        "strip_pixels": args.strip_pixels,
        "runs": rows,
    }
    (out / f"{args.name}.json").write_text(json.dumps(results, indent=2))
    placement = "one CPU per replica" if args.one_cpu_per_replica else "all processes share every CPU"
    print(f"{args.size_px}² pair, {os.cpu_count()} CPUs ({placement}), strips of {args.strip_pixels} px")
    print(f"{'peers':>6}{'seconds':>10}{'speed-up':>10}{'strips':>8}{'workers':>9}{'identical':>11}")
    for row in rows:
        print(
            f"{row['peers']:>6}{row['seconds']:>10.2f}{row.get('speed_up', 1.0):>10.2f}{row['strip_count']:>8}"
            f"{row['strip_workers']:>9}{str(row.get('identical_to_single_process', '-')):>11}"
        )
    print(f"written to {out / (args.name + '.json')}")


if __name__ == "__main__":
    main()
