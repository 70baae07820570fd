"""A real S3 server for the tests: SeaweedFS (`weed mini`, built by `make .tools/bin/weed`) on
loopback ports of its own, its data in a temporary folder, started once per test session."""

from __future__ import annotations

import contextlib
import os
import socket
import subprocess
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import pytest
from tools import required_tool

from fractoscope.store.objects import S3Objects

REPOSITORY = Path(__file__).resolve().parents[1]
WEED = REPOSITORY / ".tools" / "bin" / "weed"
BUCKET = "fractoscope-tests"
CREDENTIALS = {"AWS_ACCESS_KEY_ID": "fractoscope-test", "AWS_SECRET_ACCESS_KEY": "fractoscope-test-secret"}
# The servers `weed mini` runs, each on a free port of its own (the defaults would collide with other tests).
_PORTS = (
    "master.port",
    "master.port.grpc",
    "volume.port",
    "volume.port.grpc",
    "filer.port",
    "filer.port.grpc",
    "s3.port",
    "s3.port.grpc",
    "s3.port.iceberg",
    "s3.port.lance",
    "admin.port",
    "admin.port.grpc",
    "webdav.port",
)


def _weed() -> str:
    """The weed binary (built by `make .tools/bin/weed`; the tests that need it skip without it)."""
    return required_tool(str(WEED.relative_to(REPOSITORY)), str(WEED.relative_to(REPOSITORY)))


def free_ports(count: int) -> list[int]:
    sockets = [socket.socket() for _ in range(count)]
    try:
        for each in sockets:
            each.bind(("127.0.0.1", 0))
        return [each.getsockname()[1] for each in sockets]
    finally:
        for each in sockets:
            each.close()


class SeaweedFs:
    """`weed mini` with its data in `directory` on loopback ports of its own, kept across restarts
    (`stop`, `start`), so that a restarted server holds what the stopped one stored."""

    def __init__(self, directory: Path):
        self.directory = directory
        self.ports = dict(zip(_PORTS, free_ports(len(_PORTS)), strict=True))
        self.endpoint = f"http://127.0.0.1:{self.ports['s3.port']}"
        self.environment = {**CREDENTIALS, "AWS_ENDPOINT_URL": self.endpoint, "AWS_REGION": "us-east-1"}
        self.process: subprocess.Popen | None = None

    def start(self) -> None:
        arguments = [
            str(_weed()),
            "mini",
            f"-dir={self.directory}",
            "-ip=127.0.0.1",
            "-ip.bind=127.0.0.1",
            "-admin.ui=false",
            "-admin.port.legacy=0",
            "-webdav=false",
            f"-bucket={BUCKET}",
            *(f"-{name}={port}" for name, port in self.ports.items()),
        ]
        with open(self.directory / "weed.log", "ab") as log:
            self.process = subprocess.Popen(
                arguments, env={**os.environ, **self.environment}, stdout=log, stderr=subprocess.STDOUT
            )
        _wait_for_bucket(self.process, self.directory / "weed.log", self.environment)

    def stop(self) -> None:
        self.process.terminate()
        self.process.wait(timeout=30)


@pytest.fixture(scope="session")
def s3_endpoint(tmp_path_factory) -> str:
    """The S3 endpoint URL of a SeaweedFS server with BUCKET, its keys and endpoint set in the
    environment (AWS_*) for this process and the servers it starts."""
    server = SeaweedFs(tmp_path_factory.mktemp("seaweedfs"))
    with environment(server.environment):
        server.start()
        try:
            yield server.endpoint
        finally:
            server.stop()


@contextlib.contextmanager
def environment(values: dict[str, str]) -> Iterator[None]:
    """os.environ with `values` set (boto3 reads the endpoint and keys when a client is made),
    as it was after."""
    with pytest.MonkeyPatch.context() as patch:
        for name, value in values.items():
            patch.setenv(name, value)
        yield


def _wait_for_bucket(server: subprocess.Popen, log: Path, settings: dict, timeout_s: float = 120.0) -> None:
    """Until the bucket takes a write (the S3 gateway answers once the filer and volumes are up)."""
    with environment(settings):
        objects = S3Objects(BUCKET, "startup")
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if server.poll() is not None:
            raise RuntimeError(f"weed mini exited with {server.returncode}: {log.read_text()[-2000:]}")
        try:
            objects.put("probe", b"")
            return
        except Exception:  # not up yet: connection refused, or the bucket not made yet
            time.sleep(0.5)
    raise RuntimeError(f"weed mini did not serve S3 within {timeout_s} s: {log.read_text()[-2000:]}")


@pytest.fixture
def s3_objects(s3_endpoint) -> S3Objects:
    """The objects under a new prefix of the test bucket, for one test."""
    return S3Objects(BUCKET, f"test-{uuid.uuid4().hex}")
