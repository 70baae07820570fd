"""`make bench` and `make load`: tile replicas side by side. The demo specimen is built once into
one folder; one `fracto-server` serves it, then two (both reading that folder, as replicas read
one bucket), each pinned to a CPU of its own, while the load generators read tiles over HTTP
(wrk) and over gRPC (ghz GetTile): against the one replica with the whole concurrency, then
against both at once with half each, as a round-robin balancer in front of them splits it.
Reports requests per second for one and for two replicas, and their ratio.

The load generators run on the CPUs no replica has. With fewer than four CPUs they share the
replicas' (the `load_cpus` field is then empty), and the ratio says more about this machine than
about the replicas: measure it where each replica and the load have CPUs of their own.
Writes bench-results/replicas.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

from benchmarks.serving import free_port, grpc_calls, http_tiles, measured, pinned, wait_until_serving
from fractoscope.client import FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.specimen.tileset import content_uris
from fractoscope.synthetic.examples import write_multiscale_specimen


class _Replica:
    """A fracto-server on loopback serving the folder `data`, pinned to `cpus` (None: any)."""

    def __init__(self, data: Path, cpus: set[int] | None):
        self.grpc_port, self.http_port = free_port(), free_port()
        self.address, self.base_url = f"127.0.0.1:{self.grpc_port}", f"http://127.0.0.1:{self.http_port}"
        arguments = [
            *(sys.executable, "-m", "fractoscope.server.main", "--data", str(data), "--log-level", "WARNING"),
            *("--address", self.address, "--http-address", f"127.0.0.1:{self.http_port}"),
        ]
        self.process = subprocess.Popen(
            arguments, env={**os.environ, "GRPC_VERBOSITY": "ERROR"}, preexec_fn=pinned(cpus)
        )
        with FractoscopeClient(self.address, timeout_s=60) as client:
            wait_until_serving(client)

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=60)


def cpu_plan() -> tuple[list[set[int] | None], set[int] | None]:
    """One CPU for each of two replicas and the rest for the load; with fewer than four CPUs the
    load shares them (None), with one CPU everything does."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return [None, None], None
    return [{cpus[0]}, {cpus[1]}], set(cpus[2:]) if len(cpus) >= 4 else None


def _together(replicas: list[_Replica], phase, *, concurrency: int, scratch: Path) -> dict:
    """`phase(replica, concurrency, scratch)` on every replica at once, concurrency split evenly;
    the summed requests per second, and each replica's figures."""
    share = max(1, concurrency // len(replicas))
    folders = [scratch / f"replica-{index}" for index in range(len(replicas))]
    for folder in folders:
        folder.mkdir(exist_ok=True)
    with ThreadPoolExecutor(len(replicas)) as pool:
        rows = list(
            pool.map(lambda pair: measured(lambda: phase(pair[0], share, pair[1])), zip(replicas, folders, strict=True))
        )
    failed = [row["failed"] for row in rows if "failed" in row]
    if failed:
        return {"failed": "; ".join(failed), "replicas": rows}
    return {
        "requests_per_s": sum(row["requests_per_s"] for row in rows),
        "errors": sum(row["errors"] for row in rows),
        "replicas": rows,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--duration-s", type=float, default=10.0)
    parser.add_argument("--concurrency", type=int, default=50)
    args = parser.parse_args()
    replica_cpus, load_cpus = cpu_plan()
    scratch = Path(tempfile.mkdtemp(prefix="fracto-replicas-"))
    write_multiscale_specimen(scratch / "input")
    first = _Replica(scratch / "data", replica_cpus[0])
    replicas = [first]
    try:
        with FractoscopeClient(first.address, timeout_s=600) as client:
            specimen_id, rois = load_manifest(scratch / "input" / "manifest.json")
            client.reconstruct_specimen(specimen_id, rois)
            uris = content_uris(client.get_tileset(specimen_id))
        paths = [f"/specimens/{specimen_id}/{uri}" for uri in uris]
        messages = [{"specimen_id": specimen_id, "uri": uri} for uri in uris]
        load = {"duration_s": args.duration_s, "cpus": load_cpus}
        phases = {
            "http_get_tile": lambda replica, concurrency, folder: http_tiles(
                replica.base_url, paths, concurrency=concurrency, scratch=folder, **load
            ),
            "grpc_get_tile": lambda replica, concurrency, folder: grpc_calls(
                replica.address, "GetTile", messages, concurrency=concurrency, scratch=folder, **load
            ),
        }
        results = {
            "tiles": len(uris),
            "cpu_count": os.cpu_count(),
            "replica_cpus": [sorted(cpus or []) for cpus in replica_cpus],
            "load_cpus": sorted(load_cpus or []),
            "concurrency": args.concurrency,
            "duration_s": args.duration_s,
        }
        for count in (1, 2):
            if count == 2:
                replicas.append(_Replica(scratch / "data", replica_cpus[1]))
            for replica in replicas:  # warm each replica's body cache (gzip of every tile)
                measured(
                    lambda replica=replica: http_tiles(
                        replica.base_url, paths, concurrency=4, scratch=scratch, duration_s=2, cpus=load_cpus
                    )
                )
            for name, phase in phases.items():
                results[f"{name}_{count}"] = _together(replicas, phase, concurrency=args.concurrency, scratch=scratch)
    finally:
        for replica in replicas:
            replica.stop()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "replicas.json").write_text(json.dumps(results, indent=1))
    print(f"tile replicas: {results['tiles']} tiles, load on CPUs {results['load_cpus'] or 'shared'}")
    print(f"{'query':14} {'1 replica/s':>12} {'2 replicas/s':>13} {'ratio':>6}")
    for name in phases:
        one, two = results[f"{name}_1"], results[f"{name}_2"]
        if "failed" in one or "failed" in two:
            print(f"{name:14} FAILED: {one.get('failed') or two.get('failed')}")
            continue
        ratio = two["requests_per_s"] / one["requests_per_s"]
        print(f"{name:14} {one['requests_per_s']:12.0f} {two['requests_per_s']:13.0f} {ratio:6.2f}")


if __name__ == "__main__":
    main()
