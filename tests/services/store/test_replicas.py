"""Two tile replicas (fracto-server processes) sharing nothing but one bucket on a real S3
server: a specimen built through A is served byte for byte by B over HTTP and gRPC, B lists A's
build while it runs, and B keeps serving the previous build, without an error, through a kill -9
of A in the middle of a rebuild, then reports A's lost build as failed, and builds it again once
A's lease has run out."""

import json
import os
import signal
import subprocess
import sys
import time
import uuid
from pathlib import Path

import grpc
import pytest
import requests
from s3_server import BUCKET, free_ports

from fractoscope.http.build_jobs import JOB_LOST_AFTER_S
from fractoscope.specimen.tileset import content_uris
from fractoscope.synthetic.examples import write_multiscale_specimen
from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc

READS = 10_000


class _Replica:
    """A fracto-server with every service, its gRPC and HTTP ports on loopback, its scratch
    folder its own, its specimens and jobs in `store`."""

    def __init__(self, store: str, data: Path):
        self.grpc_port, self.http_port = free_ports(2)
        self.base = f"http://127.0.0.1:{self.http_port}"
        arguments = [
            *(sys.executable, "-m", "fractoscope.server.main", "--store", store, "--data", str(data)),
            *("--address", f"127.0.0.1:{self.grpc_port}", "--http-address", f"127.0.0.1:{self.http_port}"),
            *("--build-workers", "1", "--workers", "4"),
        ]
        self.log = open(data.parent / f"{data.name}.log", "wb")
        self.process = subprocess.Popen(arguments, stdout=self.log, stderr=subprocess.STDOUT, env={**os.environ})
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            assert self.process.poll() is None, (data.parent / f"{data.name}.log").read_text()
            try:
                if requests.get(f"{self.base}/healthz", timeout=2).status_code == 200:
                    return
            except requests.ConnectionError:
                time.sleep(0.5)
        raise RuntimeError("the replica did not start within 120 s")

    def stop(self, signal_number: int = signal.SIGTERM) -> None:
        if self.process.poll() is None:
            self.process.send_signal(signal_number)
            self.process.wait(timeout=60)
        self.log.close()


@pytest.fixture(scope="module")
def replicas(s3_endpoint, tmp_path_factory):
    root = tmp_path_factory.mktemp("replicas")
    write_multiscale_specimen(root / "input")
    store = f"s3://{BUCKET}/replicas-{uuid.uuid4().hex}"
    a, b = _Replica(store, root / "a"), _Replica(store, root / "b")
    yield a, b, root / "input"
    for replica in (a, b):
        replica.stop()


def _submit(replica: _Replica, input_directory: Path, request_id: str) -> str:
    manifest = json.loads((input_directory / "manifest.json").read_text())
    manifest["specimen"] = "shared"
    parts = [("manifest", (None, json.dumps(manifest), "application/json")), ("request_id", (None, request_id))]
    parts += [("images", (path.name, path.read_bytes(), "image/png")) for path in sorted(input_directory.glob("*.png"))]
    answer = requests.post(f"{replica.base}/api/jobs", files=parts, timeout=120)
    assert answer.status_code == 202, answer.text
    return answer.json()["job_id"]


def _listed(replica: _Replica, job_id: str) -> dict | None:
    jobs = requests.get(f"{replica.base}/api/jobs", timeout=30).json()["jobs"]
    return next((job for job in jobs if job["job_id"] == job_id), None)


def _served(replica: _Replica) -> dict[str, bytes]:
    """tileset.json and every tile of the shared specimen, over HTTP."""
    base = f"{replica.base}/specimens/shared"
    tileset = requests.get(f"{base}/tileset.json", timeout=30)
    assert tileset.status_code == 200
    files = {"tileset.json": tileset.content}
    for uri in content_uris(tileset.json()):
        files[uri] = requests.get(f"{base}/{uri}", timeout=30).content
    return files


def test_a_build_through_one_replica_is_listed_and_served_whole_by_the_other(replicas):
    a, b, input_directory = replicas
    job_id = _submit(a, input_directory, "first")
    states = set()
    deadline = time.monotonic() + 400
    while (job := _listed(b, job_id)) is None or job["state"] not in ("succeeded", "failed"):
        assert time.monotonic() < deadline, job
        states.add(job and job["state"])
        time.sleep(0.3)
    assert job["state"] == "succeeded", job["error"]
    assert "running" in states  # B listed A's build while it ran
    served_by_a, served_by_b = _served(a), _served(b)
    assert served_by_b == served_by_a and len(served_by_b) > 2
    with grpc.insecure_channel(f"127.0.0.1:{b.grpc_port}") as channel:
        stub = tiles_pb2_grpc.TileServiceStub(channel)
        for uri, content in served_by_a.items():
            if uri != "tileset.json":  # over HTTP tagged with the build (?v=), over gRPC by its plain URI
                plain = uri.partition("?v=")[0]
                tile = stub.GetTile(tiles_pb2.GetTileRequest(specimen_id="shared", uri=plain), timeout=30).tile
                assert tile.glb == content
        tileset = stub.GetTileset(tiles_pb2.GetTilesetRequest(specimen_id="shared"), timeout=30).tileset_json
        over_http = content_uris(json.loads(served_by_a["tileset.json"]))
        assert content_uris(json.loads(tileset)) == [uri.partition("?v=")[0] for uri in over_http]


def test_an_upload_received_by_one_replica_is_built_by_the_other_and_deleted_for_both(replicas):
    """POST /api/uploads on A, the job on B: B builds from the upload in the bucket. Deleted
    through A, the upload is gone for B too, though B kept a copy for its build."""
    a, b, input_directory = replicas
    manifest = json.loads((input_directory / "manifest.json").read_text())
    manifest["specimen"], manifest["rois"] = "uploaded", manifest["rois"][:1]
    parts = [("manifest", (None, json.dumps(manifest), "application/json"))]
    parts += [("images", (name, (input_directory / name).read_bytes(), "image/png")) for name in _images(manifest)]
    answer = requests.post(f"{a.base}/api/uploads", files=parts, timeout=120)
    assert answer.status_code == 201, answer.text
    upload = {"upload_id": answer.json()["upload_id"], "request_id": "from-an-upload"}
    answer = requests.post(f"{b.base}/api/jobs", json=upload, timeout=120)
    assert answer.status_code == 202, answer.text
    job_id, deadline = answer.json()["job_id"], time.monotonic() + 400
    while (job := _listed(b, job_id))["state"] not in ("succeeded", "failed"):
        assert time.monotonic() < deadline, job
        time.sleep(0.5)
    assert job["state"] == "succeeded", job["error"]
    assert requests.get(f"{a.base}/specimens/uploaded/tileset.json", timeout=30).status_code == 200
    assert requests.delete(f"{a.base}/api/uploads/{upload['upload_id']}", timeout=30).status_code == 204
    gone = requests.post(f"{b.base}/api/jobs", json={**upload, "request_id": "again"}, timeout=120)
    assert gone.status_code == 404 and gone.json()["field"] == "upload_id", gone.text


def _images(manifest: dict) -> list[str]:
    return [roi[side] for roi in manifest["rois"] for side in ("left", "right")]


def test_a_replica_killed_mid_rebuild_leaves_the_other_serving_the_previous_build(replicas):
    a, b, input_directory = replicas
    previous = _served(b)
    job_id = _submit(a, input_directory, "second")
    deadline = time.monotonic() + 300
    while (job := _listed(b, job_id)) is None or job["state"] != "running" or job["progress"]["fraction"] <= 0:
        assert time.monotonic() < deadline and (job is None or job["state"] != "failed"), job
        time.sleep(0.2)
    a.stop(signal.SIGKILL)
    uris = sorted(previous)
    errors = 0
    with requests.Session() as session:
        for index in range(READS):
            uri = uris[index % len(uris)]
            answer = session.get(f"{b.base}/specimens/shared/{uri}", timeout=30)
            errors += answer.status_code != 200 or answer.content != previous[uri]
    assert errors == 0
    deadline = time.monotonic() + JOB_LOST_AFTER_S + 60  # A's record goes stale: B reports the job failed
    while (job := _listed(b, job_id))["state"] == "running":
        assert time.monotonic() < deadline, job
        time.sleep(1)
    assert job["state"] == "failed" and job["error"]["code"] == "UNAVAILABLE", job
    retried, refused = _built_on(b, input_directory, "second-retry")  # while A's lease runs: refused
    assert retried["state"] == "succeeded", (retried, refused)
    assert requests.get(f"{b.base}/specimens/shared/tileset.json", timeout=30).status_code == 200


def _built_on(replica: _Replica, input_directory: Path, request_id: str) -> tuple[dict, int]:
    """Submits the build to `replica` until it is not refused for another replica's lease
    (RESOURCE_EXHAUSTED, the build of a replica that died holds it until it runs out); its last
    job, and how many times it was refused."""
    deadline, refused = time.monotonic() + 400, 0
    while True:
        job_id = _submit(replica, input_directory, f"{request_id}-{refused}")
        while (job := _listed(replica, job_id)) is None or job["state"] not in ("succeeded", "failed"):
            assert time.monotonic() < deadline, job
            time.sleep(0.5)
        if job["state"] == "succeeded" or job["error"]["code"] != "RESOURCE_EXHAUSTED":
            return job, refused
        refused += 1
        time.sleep(2)
