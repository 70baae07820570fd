"""Optional bearer tokens (write and read-only) on gRPC and HTTP, checked before any work, and
optional TLS."""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
import urllib.error
import urllib.request
from http.client import HTTPConnection

import grpc
import numpy as np
import pytest
from conftest import fracture_pair, tiff_bytes
from test_budget import _serve, _status_kb

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.http.server import start_http_server
from fractoscope.runtime.auth import TokenTable
from fractoscope.server.config import ServerConfig
from fractoscope.server.main import create_server
from fractoscope.stereo.disparity import StripTask
from fractoscope.store.folder import SpecimenStore
from fractoscope.v1 import matching_pb2, matching_pb2_grpc, tiles_pb2

TOKENS = TokenTable.from_text("lims:write-secret:write,viewer:read-secret:read")


@pytest.fixture()
def guarded(tmp_path):
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data"), tokens=TOKENS)
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
    with grpc.insecure_channel(guarded) as channel:  # matching a strip computes too
        from fractoscope.matching.messages import strip_request

        strip = np.zeros((64, 64), np.float32)
        request = strip_request(StripTask(strip, strip, 15, 8, 0.3, 1.0))
        with pytest.raises(grpc.RpcError) as denied:
            matching_pb2_grpc.MatchingServiceStub(channel).MatchStrip(
                request, metadata=[("authorization", "Bearer read-secret")], timeout=30
            )
        assert denied.value.code() == grpc.StatusCode.PERMISSION_DENIED
    assert (
        subprocess.run([sys.executable, "-m", "fractoscope.server.healthcheck", guarded]).returncode == 0
    )  # probes stay open


@pytest.mark.server
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
        for offered in (
            "Bearer r\u00e9ad-secret".encode(),
            b"Bearer \xff\xfe",
            "Bearer \u8aad".encode(),
        ):  # any bytes: 401, never 500
            connection = HTTPConnection("127.0.0.1", http.server_port, timeout=10)
            connection.putrequest("GET", "/api/specimens")
            connection.putheader("Authorization", offered)
            connection.endheaders()
            assert connection.getresponse().status == 401
            connection.close()
        with pytest.raises(urllib.error.HTTPError) as refused:
            urllib.request.urlopen(f"{base}/api/specimens?token=%C3%A9%FF")
        assert refused.value.code == 401
    finally:
        http.shutdown()


def test_tokens_of_any_characters_are_compared_safely():
    table = TokenTable.from_text("lims:s\u00e9cret:write")
    assert table.grant("Bearer s\u00e9cret").client == "lims"
    for offered in ("Bearer s\u00e9cre", "Bearer \udcff\udcfe", "Bearer \u8aad\u307f", "Bearer ", "Basic x", None):
        assert table.grant(offered) is None


@pytest.mark.server
@pytest.mark.timeout(300)
def test_refused_calls_are_answered_before_their_message_is_read(tmp_path):
    """A 200 MiB ComputeHeightMap without a token, and one with a read token: each refused, and
    the server's peak memory grows by far less than the message (it grew by 1.6 GB for 400 MiB
    when the refusal read the message first)."""
    process, address = _serve(
        tmp_path,
        env={"FRACTO_TOKENS": "lims:write-secret:write,viewer:read-secret:read", "FRACTO_TOKEN": "write-secret"},
    )
    request = matching_pb2.ComputeHeightMapRequest()
    for _ in range(2):
        request.images.add().image.content = b"\x01" * (100 * 2**20)
    try:
        options = [("grpc.max_send_message_length", 512 * 2**20)]
        with grpc.insecure_channel(address, options=options) as channel:
            stub = matching_pb2_grpc.MatchingServiceStub(channel)
            before_kb = _status_kb(process.pid, "VmHWM")
            for metadata, code in (
                ([], grpc.StatusCode.UNAUTHENTICATED),
                ([("authorization", "Bearer read-secret")], grpc.StatusCode.PERMISSION_DENIED),
            ):
                with pytest.raises(grpc.RpcError) as refused:
                    list(stub.ComputeHeightMap(request, metadata=metadata, timeout=120))
                assert refused.value.code() == code
            grown_mb = (_status_kb(process.pid, "VmHWM") - before_kb) / 1024
    finally:
        process.terminate()
        process.wait(timeout=60)
    print(f"server peak grew by {grown_mb:.0f} MB for two refused 200 MiB calls")
    assert grown_mb < 50


@pytest.mark.server
@pytest.mark.timeout(300)
def test_a_server_that_cannot_authenticate_to_its_peers_warns_at_start_and_fails_builds_clearly(
    tmp_path, monkeypatch, caplog
):
    """The tile service on its own, calling matching and meshing on a guarded server: without
    FRACTO_TOKEN a warning at start and UNAUTHENTICATED builds that say why; with it, builds."""
    peers, peer_port = create_server(
        ServerConfig(address="127.0.0.1:0", services=("matching", "meshing")), tokens=TOKENS
    )
    peers.start()
    peer = f"127.0.0.1:{peer_port}"
    pair = fracture_pair(size_px=128, seed=9)
    spec = tiles_pb2.RoiSpec(id="overview", pixel_size_um=0.1)
    for image, tilt_deg in ((pair.first, -5.0), (pair.second, 5.0)):
        spec.images.add(tilt_deg=tilt_deg).image.content = tiff_bytes(image)
    monkeypatch.delenv("FRACTO_TOKEN", raising=False)
    try:
        with caplog.at_level(logging.WARNING, logger="fractoscope.server"):
            tiles, port = create_server(
                ServerConfig(
                    address="127.0.0.1:0",
                    services=("tiles",),
                    data_dir=tmp_path / "data",
                    matching_address=peer,
                    meshing_address=peer,
                ),
                tokens=TOKENS,
            )
        assert "FRACTO_TOKEN is not" in caplog.text and peer in caplog.text
        tiles.start()
        with FractoscopeClient(f"127.0.0.1:{port}", token="write-secret", timeout_s=120) as client:
            with pytest.raises(ClientError) as refused:
                client.reconstruct_specimen("steel-1", [spec])
            assert refused.value.code == grpc.StatusCode.UNAUTHENTICATED
            assert "could not authenticate to the matching service" in str(refused.value) and "FRACTO_TOKEN" in str(
                refused.value
            )
            monkeypatch.setenv("FRACTO_TOKEN", "write-secret")  # read when a build opens its channels
            assert client.reconstruct_specimen("steel-1", [spec])["id"] == "steel-1"
        tiles.stop(grace=None)
    finally:
        peers.stop(grace=None)


@pytest.mark.server
@pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl is needed to make a test certificate")
def test_tls(tmp_path):
    key, cert = tmp_path / "key.pem", tmp_path / "cert.pem"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "rsa:2048",
            "-nodes",
            "-keyout",
            key,
            "-out",
            cert,
            "-days",
            "1",
            "-subj",
            "/CN=localhost",
            "-addext",
            "subjectAltName=DNS:localhost",
        ],
        check=True,
        capture_output=True,
    )
    server, port = create_server(
        ServerConfig(address="localhost:0", data_dir=tmp_path / "data", tls_cert_path=str(cert), tls_key_path=str(key))
    )
    server.start()
    try:
        with FractoscopeClient(f"localhost:{port}", tls_ca_path=str(cert)) as client:
            assert client.list_specimens() == []
        with FractoscopeClient(f"localhost:{port}", timeout_s=5) as plain, pytest.raises(ClientError) as refused:
            plain.list_specimens()
        assert refused.value.code == grpc.StatusCode.UNAVAILABLE
    finally:
        server.stop(grace=None)
