"""The plain-HTTP endpoint's protocol details and its body cache."""

import http.client

from fractoscope.services.tiles.http import _Body, body_cache, start_http_server
from fractoscope.specimen.store import SpecimenStore


def test_http_endpoint_answers_head_options_and_refuses_other_methods(tmp_path):
    endpoint = start_http_server(SpecimenStore(tmp_path / "data"))
    try:
        connection = http.client.HTTPConnection("127.0.0.1", endpoint.server_port, timeout=10)
        answers = {}
        for method in ("GET", "HEAD", "OPTIONS", "POST", "DELETE"):
            connection.request(method, "/healthz")
            response = connection.getresponse()
            answers[method] = (response.status, response.read(), response.headers)
        assert answers["GET"][:2] == (200, b"ok\n")
        assert answers["HEAD"][:2] == (200, b"") and answers["HEAD"][2]["Content-Length"] == "3"
        assert answers["OPTIONS"][0] == 204 and "GET" in answers["OPTIONS"][2]["Access-Control-Allow-Methods"]
        assert answers["POST"][0] == 405 and answers["DELETE"][0] == 405
        assert all(headers["Access-Control-Allow-Origin"] == "*" for _, _, headers in answers.values())
    finally:
        endpoint.shutdown()


def test_body_cache_keeps_at_most_its_byte_limit_and_reuses_bodies():
    cache = body_cache(limit_bytes=100_000)
    produced = []

    def produce(index):
        produced.append(index)
        return bytes([index % 251]) * 40_000 + bytes(range(256)) * 4  # compressible, ~41 kB raw

    first = cache.get(("a", 0), lambda: _Body(produce(0)))
    assert cache.get(("a", 0), lambda: _Body(produce(0))) is first and produced == [0]
    for index in range(1, 6):
        cache.get(("a", index), lambda index=index: _Body(produce(index)))
    assert cache.total_bytes <= 100_000
    assert cache.cached(("a", 0)) is None and cache.cached(("a", 5)) is not None
