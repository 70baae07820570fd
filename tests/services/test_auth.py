"""Optional bearer tokens (write and read-only) on gRPC and HTTP, and optional TLS."""

from __future__ import annotations

import shutil
import subprocess
import sys
import urllib.error
import urllib.request

import grpc
import numpy as np
import pytest

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.services.auth import TokenTable
from fractoscope.services.server import create_server
from fractoscope.services.tiles.http import start_http_server
from fractoscope.specimen.store import SpecimenStore

TOKENS = TokenTable.from_text("lims:write-secret:write,viewer:read-secret:read")


@pytest.fixture()
def guarded(tmp_path):
    server, port = create_server("127.0.0.1:0", data_dir=tmp_path / "data", tokens=TOKENS)
    server.start()
    yield f"127.0.0.1:{port}"
    server.stop(grace=None)


def test_token_table_rejects_malformed_entries():
    with pytest.raises(ValueError, match="client:token:write|read"):
        TokenTable.from_text("lims:secret:admin")
    assert not TokenTable.from_text("").enabled


def test_calls_need_a_token_and_read_tokens_cannot_write(guarded):
    with FractoscopeClient(guarded) as anonymous, pytest.raises(ClientError) as refused:
        anonymous.list_specimens()
    assert refused.value.code == grpc.StatusCode.UNAUTHENTICATED
    with FractoscopeClient(guarded, token="wrong") as stranger, pytest.raises(ClientError) as refused:
        stranger.list_specimens()
    assert refused.value.code == grpc.StatusCode.UNAUTHENTICATED
    with FractoscopeClient(guarded) as anonymous, pytest.raises(ClientError) as refused:
        anonymous.get_tile("s", "tiles/0/0/0.glb")  # the cached path of GetTile checks tokens too
    assert refused.value.code == grpc.StatusCode.UNAUTHENTICATED
    with FractoscopeClient(guarded, token="read-secret") as viewer:
        assert viewer.list_specimens() == []
        with pytest.raises(ClientError) as missing:
            viewer.get_tile("s", "tiles/0/0/0.glb")
        assert missing.value.code == grpc.StatusCode.NOT_FOUND
        with pytest.raises(ClientError) as denied:
            viewer.build_mesh(np.zeros((8, 8), np.float32), None, pixel_size_um=1.0)
        assert denied.value.code == grpc.StatusCode.PERMISSION_DENIED
        with pytest.raises(ClientError) as denied:
            viewer.reconstruct_specimen("s", [])
        assert denied.value.code == grpc.StatusCode.PERMISSION_DENIED
    with FractoscopeClient(guarded, token="write-secret") as lims:
        tiles, _ = lims.build_mesh(np.zeros((8, 8), np.float32), None, pixel_size_um=1.0)
        assert tiles
    assert subprocess.run([sys.executable, "-m", "fractoscope.services.healthcheck", guarded]).returncode == 0  # probes stay open


def test_http_endpoint_honours_the_same_tokens(tmp_path):
    http = start_http_server(SpecimenStore(tmp_path / "data"), tokens=TOKENS)
    base = f"http://127.0.0.1:{http.server_port}"
    try:
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"{base}/api/specimens")
        assert refused.value.code == 401
        request = urllib.request.Request(f"{base}/api/specimens", headers={"Authorization": "Bearer read-secret"})
        with urllib.request.urlopen(request) as response:
            assert response.read() == b"[]"
        with urllib.request.urlopen(f"{base}/api/specimens?token=read-secret") as response:
            assert response.status == 200
        with urllib.request.urlopen(f"{base}/viewer/") as response:  # the page itself is public
            assert response.status == 200
    finally:
        http.shutdown()


@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is needed to make a test certificate")
def test_tls(tmp_path):
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(
        ["openssl", "req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", key, "-out", cert, "-days", "1",
         "-subj", "/CN=localhost", "-addext", "subjectAltName=DNS:localhost"],
        check=True, capture_output=True,
    )
    server, port = create_server("localhost:0", data_dir=tmp_path / "data", tls_cert_path=str(cert), tls_key_path=str(key))
    server.start()
    try:
        with FractoscopeClient(f"localhost:{port}", tls_ca_path=str(cert)) as client:
            assert client.list_specimens() == []
        with FractoscopeClient(f"localhost:{port}", timeout_s=5) as plain, pytest.raises(ClientError) as refused:
            plain.list_specimens()
        assert refused.value.code == grpc.StatusCode.UNAVAILABLE
    finally:
        server.stop(grace=None)

