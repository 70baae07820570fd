"""`make bench` (serving) and `make load`: tile requests over gRPC and over HTTP, and profile
queries, each at a fixed concurrency (32 for the bench, 50 for 60 s for the load test) on loopback
against a `fracto-server` process holding the multi-scale demo specimen, with the server's
resident memory before and after each phase.

Writes bench-results/NAME.json (serving or load) and prints a table. The load comes from Python threads in this
process (one channel or keep-alive connection per worker), so the figures are a floor set partly
by the load generator itself.
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from fractoscope.client import FractoscopeClient
from fractoscope.client.demo import write_multiscale_specimen
from fractoscope.client.manifest import load_manifest
from fractoscope.tileset import content_uris

CONCURRENCY = 32
DURATION_S = 10.0


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def load(worker: Callable[[int, int], None], *, concurrency: int, duration_s: float) -> dict:
    """Runs `worker(worker_index, request_index)` in a loop on `concurrency` threads for
    `duration_s`; returns requests per second, latency percentiles (ms) and the error count."""
    latencies: list[list[float]] = [[] for _ in range(concurrency)]
    errors = [0] * concurrency
    deadline = time.perf_counter() + duration_s

    def run(index: int) -> None:
        count = 0
        while time.perf_counter() < deadline:
            started = time.perf_counter()
            try:
                worker(index, count)
                latencies[index].append(time.perf_counter() - started)
            except Exception:
                errors[index] += 1
            count += 1

    threads = [threading.Thread(target=run, args=(i,)) for i in range(concurrency)]
    started = time.perf_counter()
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    elapsed = time.perf_counter() - started
    all_ms = np.concatenate([np.array(values) for values in latencies]) * 1000
    return {
        "requests_per_s": len(all_ms) / elapsed,
        "p50_ms": float(np.percentile(all_ms, 50)),
        "p99_ms": float(np.percentile(all_ms, 99)),
        "requests": int(len(all_ms)),
        "errors": int(sum(errors)),
        "concurrency": concurrency,
        "duration_s": elapsed,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--duration-s", type=float, default=DURATION_S)
    parser.add_argument("--concurrency", type=int, default=CONCURRENCY)
    parser.add_argument("--name", default="serving", help="results file name (without .json)")
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp(prefix="fracto-bench-"))
    write_multiscale_specimen(work / "input")
    grpc_port, http_port = free_port(), free_port()
    server = subprocess.Popen(
        [sys.executable, "-m", "fractoscope.services.server", "--address", f"127.0.0.1:{grpc_port}",
         "--http-address", f"127.0.0.1:{http_port}", "--data", str(work / "data"), "--log-level", "WARNING"],
        env={**os.environ, "GRPC_VERBOSITY": "ERROR"},
    )
    try:
        address = f"127.0.0.1:{grpc_port}"
        with FractoscopeClient(address, timeout_s=600) as client:
            _wait_until_serving(client)
            specimen_id, rois = load_manifest(work / "input" / "manifest.json")
            started = time.perf_counter()
            client.reconstruct_specimen(specimen_id, rois)
            reconstruct_s = time.perf_counter() - started
            tileset = client.get_tileset(specimen_id)
        uris = content_uris(tileset)
        clients = [FractoscopeClient(address, timeout_s=30) for _ in range(args.concurrency)]
        connections = [http.client.HTTPConnection("127.0.0.1", http_port, timeout=30) for _ in range(args.concurrency)]
        rng = np.random.default_rng(0)
        lines = [((float(x0), float(y0)), (float(x1), float(y1))) for x0, y0, x1, y1 in rng.uniform(0, 511, size=(256, 4))]

        def grpc_tile(worker: int, index: int) -> None:
            clients[worker].get_tile(specimen_id, uris[(worker * 7 + index) % len(uris)])

        def http_tile(worker: int, index: int) -> None:
            connection = connections[worker]
            connection.request("GET", f"/specimens/{specimen_id}/{uris[(worker * 7 + index) % len(uris)]}", headers={"Accept-Encoding": "gzip"})
            response = connection.getresponse()
            response.read()
            if response.status != 200:
                raise RuntimeError(response.status)

        def profile(worker: int, index: int) -> None:
            clients[worker].profile(specimen_id, list(lines[(worker * 11 + index) % len(lines)]))

        results = {"reconstruct_s": reconstruct_s, "tiles": len(uris), "cpu_count": os.cpu_count()}
        for name, worker in (("grpc_get_tile", grpc_tile), ("http_get_tile", http_tile), ("grpc_profile", profile)):
            before_mb = _rss_mb(server.pid)
            results[name] = load(worker, concurrency=args.concurrency, duration_s=args.duration_s)
            results[name].update(server_rss_before_mb=before_mb, server_rss_after_mb=_rss_mb(server.pid))
        for client in clients:
            client.close()
    finally:
        server.terminate()
        server.wait(timeout=30)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(results, indent=1))
    print(f"specimen: {results['tiles']} tiles, reconstructed in {reconstruct_s:.1f} s")
    print(f"concurrency {args.concurrency}, {args.duration_s:g} s per query")
    print(f"{'query':16} {'req/s':>8} {'p50 ms':>8} {'p99 ms':>8} {'errors':>7} {'server MB before/after':>24}")
    for name in ("grpc_get_tile", "http_get_tile", "grpc_profile"):
        row = results[name]
        memory = f"{row['server_rss_before_mb']:.0f} / {row['server_rss_after_mb']:.0f}"
        print(f"{name:16} {row['requests_per_s']:8.0f} {row['p50_ms']:8.2f} {row['p99_ms']:8.2f} {row['errors']:7d} {memory:>24}")


def _wait_until_serving(client: FractoscopeClient, timeout_s: float = 60.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            client.list_specimens()
            return
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _rss_mb(pid: int) -> float:
    """Resident memory of a process, MB (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")



if __name__ == "__main__":
    main()
