"""`make load`: the figures issue 49 asks of a hostile probe, each against fracto-server processes
of their own on loopback (the probe suite's, tests/probe_servers.py):

- `bomb`: a 1.1 MB zlib float32 16384² TIFF pair uploaded twice at once: each answer's status and
  seconds, and the server's peak resident memory above its resting one;
- `caps`: an STL export of a region, an STL of an uploaded 4000² npz and a report, each over a
  32 MiB file cap: status and seconds, and whether anything was written;
- `analyses`: twelve cylinder-form GetRoughness calls on a 1024² map with a 60 s deadline: their
  outcomes, GetTile + GetSpecimen's worst seconds while they run, and how long after the last
  caller went the CPU falls idle (under 0.1 CPU s per 0.5 s);
- `frozen_store`: SeaweedFS stopped by SIGSTOP under an object-store replica: each request's
  status and seconds, and /healthz's;
- `mixed`: DURATION_S of tiles (HTTP and gRPC), roughness, small and over-cap exports, uploads of
  bombs and of 20,000 tiny parts, idle sockets and builds over HTTP at once: statuses counted
  (5xx other than 503 must be none), the server's resident memory sampled, /healthz's worst
  seconds, and whether every build accepted was built.

Writes bench-results/hostile.json and prints it.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import signal
import socket
import sys
import tempfile
import threading
import time
import uuid
from collections import Counter
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import grpc
import numpy as np
import requests

TESTS = Path(__file__).resolve().parents[1] / "tests"
sys.path.insert(0, str(TESTS))  # the probe suite's servers and bombs: one home for them
sys.path.insert(0, str(TESTS / "hostile"))

from probe_servers import READ, READ_METADATA, WRITE, ServerProcess, write_map_specimen  # noqa: E402
from s3_server import BUCKET, SeaweedFs, environment  # noqa: E402
from test_probe_budget import zlib_float_tiff  # noqa: E402
from test_probe_multipart import multipart_body  # noqa: E402

from fractoscope.specimen.model import SpecimenStore  # noqa: E402
from fractoscope.store.objects import S3Objects  # noqa: E402
from fractoscope.store.s3 import ObjectSpecimenStore  # noqa: E402
from fractoscope.synthetic.examples import write_multiscale_specimen  # noqa: E402
from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc  # noqa: E402

MB = 1 << 20
DURATION_S = 60.0


def _timed(call) -> tuple[int, float]:
    started = time.monotonic()
    try:
        status = call()
    except requests.RequestException as error:
        status = f"no answer ({type(error).__name__})"
    return status, round(time.monotonic() - started, 3)


def _bomb_parts(bomb: bytes) -> list:
    manifest = {
        "specimen": f"bomb-{uuid.uuid4().hex[:6]}",
        "rois": [{"id": "o", "left": "a.tif", "right": "b.tif", "tilt_deg": [-5, 5], "pixel_size_um": 0.1}],
    }
    return [("manifest", (None, json.dumps(manifest)))] + [
        ("images", (n, bomb, "image/tiff")) for n in ("a.tif", "b.tif")
    ]


def bomb(root: Path) -> dict:
    server = ServerProcess(root / "data", environment={"FRACTO_MAX_REQUEST_MB": "4096"}).start()
    try:
        payload, resting = zlib_float_tiff(16384), server.rss_bytes()

        def post() -> int:
            answer = requests.post(f"{server.http}/api/uploads", files=_bomb_parts(payload), headers=WRITE, timeout=300)
            return answer.status_code

        with ThreadPoolExecutor(2) as pool:
            answers = list(pool.map(lambda _: _timed(post), range(2)))
        return {
            "tiff_bytes": len(payload),
            "answers": answers,
            "peak_rss_growth_mb": round((server.peak_rss_bytes() - resting) / MB, 1),
        }
    finally:
        server.stop()


def caps(root: Path) -> dict:
    write_map_specimen(SpecimenStore(root / "data"), "capped", size_px=256)
    server = ServerProcess(root / "data", environment={"FRACTO_MAX_FILE_MB": "32"}).start()
    npz = io.BytesIO()
    np.savez_compressed(npz, z_um=np.zeros((4000, 4000), np.float32), pixel_size_um=np.float64(0.1))
    base = f"{server.http}/api"
    try:
        result = {
            "region_stl": _timed(
                lambda: (
                    requests.get(
                        f"{base}/specimens/capped/export",
                        headers=READ,
                        timeout=300,
                        params={"format": "stl", "region": "0,0,127,127", "pixel_size_um": "0.05"},
                    ).status_code
                )
            ),  # fmt: skip
            "npz_stl": _timed(
                lambda: (
                    requests.post(
                        f"{base}/exports",
                        headers=READ,
                        timeout=300,
                        files=[("height_map", ("m.npz", npz.getvalue())), ("format", (None, "stl"))],
                    ).status_code
                )
            ),  # fmt: skip
            "report": _timed(
                lambda: requests.get(f"{base}/specimens/capped/report", headers=READ, timeout=300).status_code
            ),
        }
        scratch = server.data / "tmp"
        result["files_written"] = len([p for p in scratch.rglob("*") if p.is_file()]) if scratch.is_dir() else 0
        return result
    finally:
        server.stop()


def _idle_after(server: ServerProcess, limit_s: float = 120.0) -> float:
    """Seconds until the server spends under 0.1 CPU s in 0.5 s."""
    started = time.monotonic()
    while time.monotonic() - started < limit_s:
        before = server.cpu_s()
        time.sleep(0.5)
        if server.cpu_s() - before < 0.1:
            return round(time.monotonic() - started, 2)
    return float("inf")


def analyses(root: Path) -> dict:
    write_map_specimen(SpecimenStore(root / "data"), "slow", size_px=1024)
    server = ServerProcess(root / "data").start()
    try:
        with grpc.insecure_channel(server.grpc_address) as channel:
            stub = tiles_pb2_grpc.TileServiceStub(channel)
            chain = tiles_pb2.SurfaceChain(form=tiles_pb2.FORM_CYLINDER)
            request = tiles_pb2.GetRoughnessRequest(specimen_id="slow", chain=chain)
            calls = [stub.GetRoughness.future(request, metadata=READ_METADATA, timeout=60) for _ in range(12)]
            worst = 0.0
            while not all(call.done() for call in calls):
                started = time.monotonic()
                stub.GetTile(tiles_pb2.GetTileRequest(specimen_id="slow", uri="tiles/0/0/0.glb"),
                             metadata=READ_METADATA, timeout=60)  # fmt: skip
                stub.GetSpecimen(tiles_pb2.GetSpecimenRequest(specimen_id="slow"), metadata=READ_METADATA, timeout=60)
                worst = max(worst, time.monotonic() - started)
                time.sleep(0.5)
            outcomes = Counter(call.exception().code().name if call.exception() else "OK" for call in calls)
        return {
            "outcomes": dict(outcomes),
            "tile_and_specimen_worst_s": round(worst, 3),
            "idle_after_s": _idle_after(server),
        }
    finally:
        server.stop()


def frozen_store(root: Path) -> dict:
    seaweed = SeaweedFs(root / "seaweedfs")
    seaweed.directory.mkdir(parents=True)
    with environment(seaweed.environment):
        seaweed.start()
        prefix = f"bench-{uuid.uuid4().hex}"
        write_map_specimen(ObjectSpecimenStore(S3Objects(BUCKET, prefix), root / "writer"), "frozen", size_px=64)
        server = ServerProcess(
            root / "data", environment=seaweed.environment, arguments=("--store", f"s3://{BUCKET}/{prefix}")
        ).start()
    get = lambda path: lambda: requests.get(f"{server.http}{path}", headers=READ, timeout=300).status_code  # noqa: E731
    paths = {
        "tileset": "/specimens/frozen/tileset.json",
        "specimens": "/api/specimens",
        "specimen": "/api/specimens/frozen",
        "jobs": "/api/jobs",
        "job": f"/api/jobs/{uuid.uuid4().hex}",
        "healthz": "/healthz",
        "livez": "/livez",
    }
    try:
        os.kill(seaweed.process.pid, signal.SIGSTOP)
        time.sleep(1.5)
        answers = {name: _timed(get(path)) for name, path in paths.items()}
        with grpc.insecure_channel(server.grpc_address) as channel:
            stub = tiles_pb2_grpc.TileServiceStub(channel)
            started = time.monotonic()
            try:
                stub.ListSpecimens(tiles_pb2.ListSpecimensRequest(), metadata=READ_METADATA, timeout=300)
                code = "OK"
            except grpc.RpcError as error:
                code = error.code().name
            answers["ListSpecimens"] = (code, round(time.monotonic() - started, 3))
        answers["again_specimens"] = _timed(get("/api/specimens"))  # the store held out of reach: at once
        return answers
    finally:
        os.kill(seaweed.process.pid, signal.SIGCONT)
        server.stop()
        seaweed.stop()


def _rss_sampler(server: ServerProcess, samples: list[int], stop: threading.Event) -> None:
    while not stop.wait(0.5):
        samples.append(server.rss_bytes())


def mixed(root: Path) -> dict:
    write_map_specimen(SpecimenStore(root / "data"), "steady", size_px=512)
    server = ServerProcess(root / "data", environment={"FRACTO_HTTP_IDLE_TIMEOUT_S": "5"}).start()
    example = root / "example"
    write_multiscale_specimen(example)
    manifest = json.loads((example / "manifest.json").read_text())
    images = [("images", (p.name, p.read_bytes(), "image/png")) for p in sorted(example.glob("*.png"))]
    payload = zlib_float_tiff(16384)
    tiny, tiny_type = multipart_body(
        [({"Content-Disposition": 'form-data; name="manifest"'}, json.dumps(manifest).encode())]
        + [({"Content-Disposition": f'form-data; name="images"; filename="f{i}.png"'}, b"x") for i in range(20_000)]
    )
    statuses: Counter = Counter()
    jobs: list[str] = []
    opened: list[socket.socket] = []  # idle sockets, kept open: the server closes them
    stop, rss, health = threading.Event(), [], []
    base = server.http

    def record(name, call):
        try:
            statuses[(name, call())] += 1
        except (requests.RequestException, grpc.RpcError) as error:
            statuses[(name, type(error).__name__)] += 1

    def build():
        spec = {**manifest, "specimen": f"mixed-{uuid.uuid4().hex[:8]}"}
        answer = requests.post(f"{base}/api/jobs", files=[("manifest", (None, json.dumps(spec)))] + images,
                               headers=WRITE, timeout=120)  # fmt: skip
        if answer.status_code == 202:
            jobs.append(answer.json()["job_id"])
        return answer.status_code

    def grpc_tile():
        with grpc.insecure_channel(server.grpc_address) as channel:
            tiles_pb2_grpc.TileServiceStub(channel).GetTile(
                tiles_pb2.GetTileRequest(specimen_id="steady", uri="tiles/0/0/0.glb"),
                metadata=READ_METADATA,
                timeout=60,
            )
        return 200

    kinds = {
        "tile": lambda: requests.get(f"{base}/specimens/steady/tiles/0/0/0.glb", headers=READ, timeout=60).status_code,
        "grpc_tile": grpc_tile,
        "roughness": lambda: (
            requests.get(
                f"{base}/api/specimens/steady/roughness", headers=READ, timeout=120, params={"form": "cylinder"}
            ).status_code
        ),  # fmt: skip
        "export_x3p": lambda: (
            requests.get(
                f"{base}/api/specimens/steady/export", headers=READ, timeout=120, params={"format": "x3p"}
            ).status_code
        ),  # fmt: skip
        "export_huge": lambda: (
            requests.get(
                f"{base}/api/specimens/steady/export",
                headers=READ,
                timeout=120,
                params={"format": "stl", "region": "0,0,255,255", "pixel_size_um": "0.035"},
            ).status_code
        ),  # fmt: skip
        "bomb": lambda: (
            requests.post(f"{base}/api/uploads", files=_bomb_parts(payload), headers=WRITE, timeout=120).status_code
        ),  # fmt: skip
        "tiny_parts": lambda: (
            requests.post(
                f"{base}/api/uploads", data=tiny, timeout=120, headers={**WRITE, "Content-Type": tiny_type}
            ).status_code
        ),  # fmt: skip
        "idle_socket": lambda: opened.append(socket.create_connection(("127.0.0.1", server.http_port))) or 0,
        "build": build,
    }

    def loop(name, call, pause_s):
        while not stop.is_set():
            record(name, call)
            time.sleep(pause_s)

    def healthz():
        while not stop.wait(0.5):
            status, seconds = _timed(lambda: requests.get(f"{base}/healthz", timeout=60).status_code)
            health.append(seconds)
            statuses[("healthz", status)] += 1

    pauses = {"tile": 0.0, "grpc_tile": 0.0, "roughness": 1.0, "export_x3p": 1.0, "export_huge": 2.0, "bomb": 3.0,
              "tiny_parts": 3.0, "idle_socket": 0.05, "build": 10.0}  # fmt: skip
    resting = server.rss_bytes()
    threads = [threading.Thread(target=loop, args=(name, call, pauses[name])) for name, call in kinds.items()]
    threads += [threading.Thread(target=healthz), threading.Thread(target=_rss_sampler, args=(server, rss, stop))]
    for thread in threads:
        thread.start()
    time.sleep(DURATION_S)
    stop.set()
    for thread in threads:
        thread.join(timeout=180)
    states = Counter()
    deadline = time.monotonic() + 600
    while jobs and time.monotonic() < deadline:
        states = Counter(
            requests.get(f"{base}/api/jobs/{job}", headers=READ, timeout=60).json()["state"] for job in jobs
        )
        if not states.keys() & {"queued", "running"}:
            break
        time.sleep(2)
    listed = {entry["id"] for entry in requests.get(f"{base}/api/specimens", headers=READ, timeout=60).json()}
    server.stop()
    five_hundreds = {f"{n} {s}": c for (n, s), c in statuses.items() if isinstance(s, int) and s >= 500 and s != 503}
    return {
        "duration_s": DURATION_S,
        "statuses": {f"{name} {status}": count for (name, status), count in sorted(statuses.items(), key=str)},
        "5xx_other_than_503": five_hundreds,
        "rss_resting_mb": round(resting / MB),
        "rss_max_mb": round(max(rss, default=resting) / MB),
        "healthz_worst_s": round(max(health, default=0.0), 3),
        "builds_accepted": len(jobs),
        "build_states": dict(states),
        "builds_listed": len([job for job in listed if job.startswith("mixed-")]),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--only", nargs="*", help="phases to run (default: all)")
    args = parser.parse_args()
    phases = {"bomb": bomb, "caps": caps, "analyses": analyses, "frozen_store": frozen_store, "mixed": mixed}
    results = {}
    with tempfile.TemporaryDirectory(prefix="fracto-hostile-") as scratch:
        for name, phase in phases.items():
            if not args.only or name in args.only:
                root = Path(scratch) / name
                root.mkdir()
                results[name] = phase(root)
                print(name, json.dumps(results[name]), flush=True)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "hostile.json").write_text(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
