"""A frozen object store (issue 49, item 6): with the S3 server stopped by SIGSTOP (it accepts
connections and never answers), tileset, tile, list and job requests got no answer in 90 s and
/api/specimens a 500 after 241 s, while /healthz said 200. Now every request is answered, 503 or
UNAVAILABLE unless this replica holds the answer already, /healthz says degraded (503) and
/livez stays 200; once the store answers again, so does everything."""

from __future__ import annotations

import json
import os
import signal
import time
import uuid

import grpc
import pytest
import requests
from probe_servers import READ, READ_METADATA, WRITE, ServerProcess, write_map_specimen
from s3_server import BUCKET, SeaweedFs, environment

from fractoscope.store.objects import S3Objects
from fractoscope.store.s3 import ObjectSpecimenStore
from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc

# A hang bound, not the target (10 s; `make load` measures it): far above the bounded waits.
HANG_S = 60


@pytest.fixture(scope="module")
def seaweed(tmp_path_factory):
    server = SeaweedFs(tmp_path_factory.mktemp("frozen-seaweedfs"))
    with environment(server.environment):
        server.start()
        try:
            yield server
        finally:
            os.kill(server.process.pid, signal.SIGCONT)
            server.stop()


@pytest.fixture
def replica(seaweed, tmp_path):
    prefix = f"frozen-{uuid.uuid4().hex}"
    with environment(seaweed.environment):
        store = ObjectSpecimenStore(S3Objects(BUCKET, prefix), tmp_path / "writer")
        write_map_specimen(store, "frozen", size_px=64)
    server = ServerProcess(
        tmp_path / "data", environment=seaweed.environment, arguments=("--store", f"s3://{BUCKET}/{prefix}")
    )
    yield server.start()
    server.stop()


def _answers(replica: ServerProcess, tile: str) -> dict[str, int]:
    """The status of each kind of request, HTTP and gRPC (as its HTTP equivalent)."""
    answers = {}
    for name, path in {
        "tileset": "/specimens/frozen/tileset.json",
        "tile": f"/specimens/frozen/{tile}",
        "specimens": "/api/specimens",
        "specimen": "/api/specimens/frozen",
        "jobs": "/api/jobs",
        "job": f"/api/jobs/{uuid.uuid4().hex}",
        "roughness": "/api/specimens/frozen/roughness",
        "health": "/healthz",
        "live": "/livez",
    }.items():
        answers[name] = requests.get(f"{replica.http}{path}", headers=READ, timeout=HANG_S).status_code
    manifest = {"specimen": "x", "rois": [{"id": "o", "left": "l.png", "right": "r.png"}]}
    answers["upload"] = requests.post(
        f"{replica.http}/api/uploads", files=[("manifest", (None, json.dumps(manifest)))], headers=WRITE, timeout=HANG_S
    ).status_code
    with grpc.insecure_channel(replica.grpc_address) as channel:
        stub = tiles_pb2_grpc.TileServiceStub(channel)
        for name, call in {
            "GetSpecimen": lambda: stub.GetSpecimen(tiles_pb2.GetSpecimenRequest(specimen_id="frozen"), **options),
            "ListSpecimens": lambda: stub.ListSpecimens(tiles_pb2.ListSpecimensRequest(), **options),
            "GetTile": lambda: stub.GetTile(
                tiles_pb2.GetTileRequest(specimen_id="frozen", uri=tile.partition("?")[0]), **options
            ),
        }.items():
            try:
                call()
                answers[name] = 200
            except grpc.RpcError as error:
                answers[name] = {grpc.StatusCode.UNAVAILABLE: 503}.get(error.code(), 500)
    return answers


options = {"metadata": READ_METADATA, "timeout": HANG_S}


@pytest.mark.server
def test_a_frozen_object_store_gets_503_not_a_hang_and_health_says_degraded(seaweed, replica):
    tileset = requests.get(f"{replica.http}/specimens/frozen/tileset.json", headers=READ, timeout=HANG_S)
    tile = json.loads(tileset.content)["root"]["content"]["uri"]
    assert set(_answers(replica, tile).values()) <= {200, 400, 404}  # served (the upload lacks images, the job is none)
    os.kill(seaweed.process.pid, signal.SIGSTOP)
    try:
        time.sleep(1.5)  # past the replica's pointer cache
        frozen = _answers(replica, tile)
    finally:
        os.kill(seaweed.process.pid, signal.SIGCONT)
    assert frozen["health"] == 503 and frozen["live"] == 200, frozen
    served_from_memory = {"tile", "GetTile"}  # bytes this replica holds: better served than refused
    for name, status in frozen.items():
        if name not in ("health", "live"):
            assert status == 503 or (name in served_from_memory and status == 200), (name, frozen)
    deadline = time.monotonic() + HANG_S
    while (recovered := _answers(replica, tile))["health"] != 200:
        assert time.monotonic() < deadline, recovered
        time.sleep(1)
    assert recovered["specimens"] == 200 and recovered["ListSpecimens"] == 200, recovered
