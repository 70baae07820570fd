"""No credential reaches the log, whichever layer logs (issue 49, item 8): an Authorization value
that is not UTF-8, sent over gRPC (HTTP/2 by curl, which sends any bytes), was logged whole by
gRPC's own _decode in an ERROR traceback; refused HTTP requests with tokens in them likewise."""

from __future__ import annotations

import subprocess

import requests
from probe_servers import READ_TOKEN, WRITE_TOKEN
from tools import required_tool

PROBE_SECRET = "probe-secret-7c1d"


def _grpc_with_authorization(address: str, value: bytes, method: str) -> subprocess.CompletedProcess:
    """A gRPC call of an empty request with `value` as its authorization header, sent as is."""
    curl = required_tool("curl", "/usr/bin/curl")
    header = b"authorization: " + value
    return subprocess.run(
        [curl, "-s", "-o", "/dev/null", "-w", "%{http_code}", "--http2-prior-knowledge", "-X", "POST",
         "-H", "content-type: application/grpc", "-H", "te: trailers", "-H", header,
         "--data-binary", "@-", f"http://{address}/{method}"],
        input=b"\x00\x00\x00\x00\x00",
        capture_output=True,
        timeout=60,
    )  # fmt: skip


def test_no_token_reaches_the_log_from_grpc_or_http(server_process):
    server = server_process()
    values = [
        b"Bearer " + WRITE_TOKEN.encode() + b"\xff",  # a good token spoilt by one byte
        b"Bearer " + PROBE_SECRET.encode() + b"\xfe\xff",
        PROBE_SECRET.encode() + b"\xc3\x28",  # no Bearer, bad UTF-8
        b"\xff" + READ_TOKEN.encode(),
    ]
    for method in ("fractoscope.v1.TileService/ListSpecimens", "fractoscope.v1.MatchingService/ComputeHeightMap"):
        for value in values:
            done = _grpc_with_authorization(server.grpc_address, value, method)
            # Answered (UNAUTHENTICATED in the trailers); curl's 92 when the refusal, which reads no
            # request, resets the stream while curl still sends it.
            assert done.stdout == b"200" or done.returncode == 92, done
    for headers in ({"Authorization": f"Bearer {PROBE_SECRET}"}, {"Authorization": f"{WRITE_TOKEN} x"}):
        assert requests.get(f"{server.http}/api/specimens", headers=headers, timeout=30).status_code == 401
    assert requests.get(f"{server.http}/api/specimens?token={PROBE_SECRET}", timeout=30).status_code == 401
    server.stop()
    log = server.log()
    assert "not UTF-8" in log  # the event is logged, its value not
    for secret in (WRITE_TOKEN, READ_TOKEN, PROBE_SECRET):
        assert secret not in log, [line for line in log.splitlines() if secret in line][:3]
