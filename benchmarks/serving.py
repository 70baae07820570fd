"""`make load` (concurrency 50 for 60 s per query) and `make bench` (10 s): a `fracto-server`
process holding the multi-scale demo specimen, loaded with

- tiles over plain HTTP (what 3D Tiles viewers fetch), by wrk (Debian's package),
- tiles, zooms and profiles over gRPC, by ghz (built from the Go module proxy into .tools/bin),

each for a fixed time at a fixed number of concurrent requests, round-robin over every tile, 64
zoom regions and 256 profile lines. Reported per query: requests per second, p50/p99 latency,
errors, and the server's resident memory sampled every half second. Then the mixed phase:
`BUILDERS` clients reconstructing the demo specimen under new ids, one build after another (a
RESOURCE_EXHAUSTED answer, the documented refusal of a full build queue, is counted and retried
after its hint), while wrk reads tiles and ghz checks health 20 times a second, all for the same
time; reported: builds done and refused, other errors, the tiles' and health checks' latency,
and the server's peak memory. Last, the same GetTile load on a bare gRPC server returning one
cached tile-sized response (bare_grpc_server): the floor that gRPC Python sets on these CPUs,
whatever the tile service does.

With two or more CPUs the server runs on the first half and the load generator on the rest, so
that neither takes the other's CPU time; the figures are then the server's on its share.
Writes bench-results/NAME.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from pathlib import Path

import grpc
import numpy as np

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.client.manifest import load_manifest
from fractoscope.specimen.tileset import content_uris
from fractoscope.synthetic.examples import write_multiscale_specimen

ROOT = Path(__file__).resolve().parents[1]
GHZ = ROOT / ".tools" / "bin" / "ghz"
TILES_PROTO = "fractoscope/v1/tiles.proto"
# Clients building at once in the mixed phase: more than a one-CPU server's build worker and queue
# (1 + 8), so that some builds are refused.
BUILDERS = 12
HEALTH_CHECKS_PER_S = 20
# grpc.health.v1's Check, for ghz (grpcio-health-checking ships no .proto file).
HEALTH_PROTO = """syntax = "proto3";
package grpc.health.v1;
message HealthCheckRequest { string service = 1; }
message HealthCheckResponse {
  enum ServingStatus { UNKNOWN = 0; SERVING = 1; NOT_SERVING = 2; }
  ServingStatus status = 1;
}
service Health { rpc Check(HealthCheckRequest) returns (HealthCheckResponse); }
"""
# wrk's script: every connection walks the tile list; at the end one JSON line with the figures.
WRK_SCRIPT = """
local paths = {}
for line in io.lines("%(paths)s") do paths[#paths + 1] = line end
local counter = 0
request = function()
  counter = counter + 1
  return wrk.format("GET", paths[(counter %% #paths) + 1], {["Accept-Encoding"] = "gzip"})
end
done = function(summary, latency, requests)
  local e = summary.errors
  io.write(string.format('{"requests": %%d, "duration_us": %%d, "p50_us": %%d, "p99_us": %%d, "errors": %%d}\\n',
    summary.requests, summary.duration, latency:percentile(50), latency:percentile(99),
    e.connect + e.read + e.write + e.status + e.timeout))
end
"""


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def split_cpus() -> tuple[set[int] | None, set[int] | None]:
    """CPUs for the server and for the load generator: halves of this process's, or None (share)."""
    cpus = sorted(os.sched_getaffinity(0))
    if len(cpus) < 2:
        return None, None
    half = len(cpus) // 2
    return set(cpus[:half]), set(cpus[half:])


def pinned(cpus: set[int] | None):
    """A preexec_fn that pins a child process to `cpus` (None: no pinning)."""
    return None if cpus is None else (lambda: os.sched_setaffinity(0, cpus))


class MemorySampler:
    """Resident memory of a process (MB), sampled every `interval_s` while the block runs."""

    def __init__(self, pid: int, interval_s: float = 0.5):
        self.pid, self.interval_s, self.samples = pid, interval_s, []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(_status_mb(self.pid, "VmRSS"))
            self._stop.wait(self.interval_s)

    def __enter__(self) -> MemorySampler:
        self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()
        self._thread.join()
        self.samples.append(_status_mb(self.pid, "VmRSS"))

    def summary(self) -> dict:
        return {"first": self.samples[0], "min": min(self.samples), "max": max(self.samples), "last": self.samples[-1]}


def http_tiles(base_url: str, paths: list[str], *, concurrency: int, duration_s: float, cpus, scratch: Path) -> dict:
    (scratch / "paths.txt").write_text("".join(f"{path}\n" for path in paths))
    script = scratch / "tiles.lua"
    script.write_text(WRK_SCRIPT % {"paths": scratch / "paths.txt"})
    threads = max(1, min(len(cpus or [0]), concurrency))
    command = [
        "wrk",
        f"-t{threads}",
        f"-c{concurrency}",
        f"-d{duration_s:g}s",
        "--timeout",
        "10s",
        "-s",
        str(script),
        base_url,
    ]
    output = subprocess.run(command, capture_output=True, text=True, check=True, preexec_fn=pinned(cpus)).stdout
    figures = json.loads(output.strip().splitlines()[-1])
    return {
        "requests_per_s": figures["requests"] / (figures["duration_us"] / 1e6),
        "p50_ms": figures["p50_us"] / 1000,
        "p99_ms": figures["p99_us"] / 1000,
        "requests": figures["requests"],
        "errors": figures["errors"],
        "tool": "wrk",
    }


def grpc_calls(
    address: str, method: str, messages: list[dict], *, concurrency: int, duration_s: float, cpus, scratch: Path
) -> dict:
    data = scratch / f"{method}.json"
    data.write_text(json.dumps(messages))
    return _ghz(
        [
            "--import-paths",
            str(ROOT / "proto"),
            "--proto",
            TILES_PROTO,
            "--call",
            f"fractoscope.v1.TileService.{method}",
            "-D",
            str(data),
            "-c",
            str(concurrency),
            "-z",
            f"{duration_s:g}s",
            "--duration-stop",
            "wait",
            "--timeout",
            "10s",
            address,
        ],
        cpus,
    )


def health_checks(address: str, *, duration_s: float, cpus, scratch: Path) -> dict:
    """grpc.health.v1 Check at HEALTH_CHECKS_PER_S for `duration_s`, each with a deadline of
    10 s; ghz's figures, and its slowest check."""
    (scratch / "health.proto").write_text(HEALTH_PROTO)
    return _ghz(
        [
            "--import-paths",
            str(scratch),
            "--proto",
            "health.proto",
            "--call",
            "grpc.health.v1.Health.Check",
            "-d",
            "{}",
            "--rps",
            str(HEALTH_CHECKS_PER_S),
            "-c",
            "2",
            "-z",
            f"{duration_s:g}s",
            "--duration-stop",
            "wait",
            "--timeout",
            "10s",
            address,
        ],
        cpus,
    )


def _ghz(arguments: list[str], cpus) -> dict:
    command = [str(GHZ), "--insecure", "--format", "json", *arguments]
    if cpus is not None:
        command[1:1] = ["--cpus", str(len(cpus))]
    report = json.loads(
        subprocess.run(command, capture_output=True, text=True, check=True, preexec_fn=pinned(cpus)).stdout
    )
    latency = {entry["percentage"]: entry["latency"] / 1e6 for entry in report["latencyDistribution"] or []}
    ok = report.get("statusCodeDistribution", {}).get("OK", 0)
    return {
        "requests_per_s": report["rps"],
        "p50_ms": latency.get(50, float("nan")),
        "p99_ms": latency.get(99, float("nan")),
        "max_ms": report.get("slowest", float("nan")) / 1e6,
        "requests": report["count"],
        "errors": report["count"] - ok,
        "tool": "ghz",
    }


def measured(phase: Callable[[], dict]) -> dict:
    """A phase's figures, or {"failed": what went wrong} when it raised: one failed phase (a load
    tool that died, a server that stopped answering) is reported, never the end of the run."""
    try:
        return phase()
    except Exception as error:  # any failure of the phase is its result
        return {"failed": f"{type(error).__name__}: {error}"}


def mixed(address: str, base_url: str, tile_paths: list[str], rois: list, *, server_pid: int, load: dict) -> dict:
    """Builds, tile reads over HTTP and health checks together for `load["duration_s"]` (see the
    module's docstring); the figures of each and the server's memory."""
    duration_s = load["duration_s"]
    outcomes = {"built": 0, "refused": 0, "errors": []}
    lock = threading.Lock()
    stop_at = time.monotonic() + duration_s

    def builder(index: int) -> None:
        with FractoscopeClient(address, timeout_s=600) as client:
            count = 0
            while time.monotonic() < stop_at:
                try:
                    client.reconstruct_specimen(f"mixed-{index}-{count}", rois)
                    outcome = "built"
                except ClientError as error:
                    if error.code != grpc.StatusCode.RESOURCE_EXHAUSTED:
                        with lock:
                            outcomes["errors"].append(f"{error.code.name}: {error}")
                        continue
                    outcome = "refused"
                    time.sleep(min(error.retry_after_s or 1.0, max(stop_at - time.monotonic(), 0.0)))
                with lock:
                    outcomes[outcome] += 1
                count += 1

    builders = [threading.Thread(target=builder, args=(index,)) for index in range(BUILDERS)]
    figures = {}
    readers = [
        threading.Thread(
            target=lambda: figures.__setitem__(
                "http_get_tile", measured(lambda: http_tiles(base_url, tile_paths, **load))
            )
        ),
        threading.Thread(
            target=lambda: figures.__setitem__(
                "health",
                measured(
                    lambda: health_checks(address, duration_s=duration_s, cpus=load["cpus"], scratch=load["scratch"])
                ),
            )
        ),
    ]
    started = time.perf_counter()
    with MemorySampler(server_pid) as memory:
        for thread in builders + readers:
            thread.start()
        for thread in builders + readers:
            thread.join()
    return {
        **figures,
        "builders": BUILDERS,
        "builds": outcomes["built"],
        "builds_refused": outcomes["refused"],
        "build_errors": outcomes["errors"],
        "wall_s": time.perf_counter() - started,
        "server_rss_mb": memory.summary(),
        "server_peak_mb": _status_mb(server_pid, "VmHWM"),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--duration-s", type=float, default=10.0)
    parser.add_argument("--concurrency", type=int, default=50)
    parser.add_argument("--name", default="serving", help="results file name (without .json)")
    args = parser.parse_args()
    for tool, path in (("wrk", shutil.which("wrk")), ("ghz", GHZ if GHZ.exists() else None)):
        if path is None:
            sys.exit(f"{tool} is missing: `make load` and `make bench` install it")
    server_cpus, load_cpus = split_cpus()
    scratch = Path(tempfile.mkdtemp(prefix="fracto-load-"))
    write_multiscale_specimen(scratch / "input")
    grpc_port, http_port = free_port(), free_port()
    server = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "fractoscope.server.main",
            "--address",
            f"127.0.0.1:{grpc_port}",
            "--http-address",
            f"127.0.0.1:{http_port}",
            "--data",
            str(scratch / "data"),
            "--log-level",
            "WARNING",
        ],
        env={**os.environ, "GRPC_VERBOSITY": "ERROR"},
        preexec_fn=pinned(server_cpus),
    )
    address = f"127.0.0.1:{grpc_port}"
    try:
        with FractoscopeClient(address, timeout_s=600) as client:
            wait_until_serving(client)
            specimen_id, rois = load_manifest(scratch / "input" / "manifest.json")
            started = time.perf_counter()
            client.reconstruct_specimen(specimen_id, rois)
            reconstruct_s = time.perf_counter() - started
            uris = content_uris(client.get_tileset(specimen_id))
        rng = np.random.default_rng(0)
        corners = rng.uniform(0, 511, size=(64, 2))
        zooms = [
            {
                "specimen_id": specimen_id,
                "magnification": float(m),
                "region": {"min": {"x_um": x, "y_um": y}, "max": {"x_um": x + size, "y_um": y + size}},
            }
            for (x, y), size, m in zip(
                corners.tolist(), rng.uniform(16, 256, 64).tolist(), rng.choice([1.0, 2.0, 4.0, 8.0], 64)
            )
        ]
        profiles = [
            {"specimen_id": specimen_id, "points": [{"x_um": x0, "y_um": y0}, {"x_um": x1, "y_um": y1}]}
            for x0, y0, x1, y1 in rng.uniform(0, 511, size=(256, 4)).tolist()
        ]
        tiles = [{"specimen_id": specimen_id, "uri": uri} for uri in uris]
        load = {"concurrency": args.concurrency, "duration_s": args.duration_s, "cpus": load_cpus, "scratch": scratch}
        tile_paths = [f"/specimens/{specimen_id}/{uri}" for uri in uris]
        base_url = f"http://127.0.0.1:{http_port}"
        phases = {
            "http_get_tile": lambda: http_tiles(base_url, tile_paths, **load),
            "grpc_get_tile": lambda: grpc_calls(address, "GetTile", tiles, **load),
            "grpc_zoom": lambda: grpc_calls(address, "Zoom", zooms, **load),
            "grpc_profile": lambda: grpc_calls(address, "GetProfile", profiles, **load),
        }
        results = {
            "reconstruct_s": reconstruct_s,
            "tiles": len(uris),
            "cpu_count": os.cpu_count(),
            "server_cpus": sorted(server_cpus or []),
            "load_generator_cpus": sorted(load_cpus or []),
        }
        http_tiles(base_url, tile_paths, **{**load, "duration_s": 3})  # warms the endpoint's cache (gzip of every tile)
        for name, phase in phases.items():
            with MemorySampler(server.pid) as memory:
                results[name] = measured(phase)
            results[name]["server_rss_mb"] = memory.summary()
        results["mixed"] = mixed(address, base_url, tile_paths, rois, server_pid=server.pid, load=load)
        with FractoscopeClient(address, timeout_s=600) as client:
            tile_bytes = int(np.mean([len(client.get_tile(specimen_id, uri)) for uri in uris]))
    finally:
        server.terminate()
        server.wait(timeout=30)
    try:
        results["grpc_get_tile_bare_server"] = measured(lambda: _bare_server_floor(tile_bytes, load, server_cpus))
    finally:
        shutil.rmtree(scratch, ignore_errors=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / f"{args.name}.json").write_text(json.dumps(results, indent=1))
    print(f"specimen: {results['tiles']} tiles, reconstructed in {reconstruct_s:.1f} s")
    print(
        f"concurrency {args.concurrency}, {args.duration_s:g} s per query; server on CPUs "
        f"{results['server_cpus'] or 'all'}, load generator on {results['load_generator_cpus'] or 'all'}"
    )
    print(
        f"{'query':14} {'tool':>5} {'req/s':>8} {'p50 ms':>8} {'p99 ms':>8} {'errors':>7} "
        f"{'server MB first/max/last':>26}"
    )
    for name in [*phases, "grpc_get_tile_bare_server"]:
        row = results[name]
        if "failed" in row:
            print(f"{name:14} FAILED: {row['failed']}")
            continue
        memory = row["server_rss_mb"]
        print(
            f"{name:14} {row['tool']:>5} {row['requests_per_s']:8.0f} {row['p50_ms']:8.2f} {row['p99_ms']:8.2f} "
            f"{row['errors']:7d} {memory['first']:>10.0f} / {memory['max']:.0f} / {memory['last']:.0f}"
        )
    mixed_row = results["mixed"]
    tiles, health = mixed_row["http_get_tile"], mixed_row["health"]
    for name, row in (("tiles", tiles), ("health checks", health)):
        if "failed" in row:
            print(f"mixed, {name} FAILED: {row['failed']}")
    if "failed" not in tiles and "failed" not in health:
        _print_mixed(mixed_row, args.duration_s)
    print(f"written to {out / (args.name + '.json')}")


def _print_mixed(mixed_row: dict, duration_s: float) -> None:
    tiles, health = mixed_row["http_get_tile"], mixed_row["health"]
    print(
        f"mixed, {duration_s:g} s: {mixed_row['builds']} builds by {BUILDERS} clients, "
        f"{mixed_row['builds_refused']} refused (RESOURCE_EXHAUSTED), {len(mixed_row['build_errors'])} failed; tiles "
        f"{tiles['requests_per_s']:.0f}/s at p99 {tiles['p99_ms']:.1f} ms, {tiles['errors']} errors; health p99 "
        f"{health['p99_ms']:.1f} ms, slowest {health['max_ms']:.1f} ms, {health['errors']} errors; server memory max "
        f"{mixed_row['server_rss_mb']['max']:.0f} MB sampled, {mixed_row['server_peak_mb']:.0f} MB peak of the whole "
        "run"
    )


def _bare_server_floor(tile_bytes: int, load: dict, server_cpus) -> dict:
    """GetTile against a bare gRPC server returning a cached response of the mean tile size, on
    the same CPUs and under the same load: the floor of gRPC Python itself (bare_grpc_server)."""
    address = f"127.0.0.1:{free_port()}"
    bare = subprocess.Popen(
        [sys.executable, "-m", "benchmarks.bare_grpc_server", "--address", address, "--tile-bytes", str(tile_bytes)],
        env={**os.environ, "GRPC_VERBOSITY": "ERROR"},
        preexec_fn=pinned(server_cpus),
    )
    try:
        with grpc.insecure_channel(address) as channel:
            grpc.channel_ready_future(channel).result(timeout=60)
        with MemorySampler(bare.pid) as memory:
            figures = grpc_calls(address, "GetTile", [{"specimen_id": "bare", "uri": "tile.glb"}], **load)
        return {**figures, "tile_bytes": tile_bytes, "server_rss_mb": memory.summary()}
    finally:
        bare.terminate()
        bare.wait(timeout=30)


def wait_until_serving(client: FractoscopeClient, timeout_s: float = 60.0) -> None:
    """Returns once the server answers a call; raises its last error after `timeout_s`."""
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            client.list_specimens()
            return
        except Exception:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.2)


def _status_mb(pid: int, field: str) -> float:
    """A memory figure of /proc/PID/status (VmRSS, VmHWM: the peak so far), MB."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(f"{field}:"):
            return int(line.split()[1]) / 1024
    return float("nan")


if __name__ == "__main__":
    main()
