"""The plain-HTTP endpoint's protocol details (methods, one URI per tile, gzip and conditional
requests per RFC 9110) and its body cache."""

import gzip
import http.client
import json
import urllib.parse

import pytest
from conftest import write_small_specimen

from fractoscope.http.server import MAX_TARGET_BYTES, _Body, accepts_gzip, body_cache, not_modified, start_http_server
from fractoscope.store.folder import SpecimenStore


@pytest.mark.server
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


@pytest.fixture()
def endpoint(tmp_path):
    """(host, port) of an HTTP endpoint serving one small stored specimen, `steel-1`."""
    store = SpecimenStore(tmp_path / "data")
    write_small_specimen(store, "steel-1", height_um=3.0)
    http = start_http_server(store)
    yield "127.0.0.1", http.server_port
    http.shutdown()


def _get(endpoint, path: str, **headers: str):
    connection = http.client.HTTPConnection(*endpoint, timeout=10)
    try:
        connection.request("GET", path, headers=headers)
        response = connection.getresponse()
        return response.status, response.headers, response.read()
    finally:
        connection.close()


def test_a_request_target_too_long_is_refused_as_414_in_the_apis_json_or_plain_text(endpoint):
    for length in (MAX_TARGET_BYTES + 1, 20_000, 60_000):  # aiohttp's own parser stops at 8190 bytes by default
        status, headers, body = _get(endpoint, "/api/specimens?roi=" + "a" * length)
        assert status == 414 and headers["Content-Type"].startswith("application/json"), length
        assert json.loads(body)["field"] == "url" and str(MAX_TARGET_BYTES) in json.loads(body)["error"]
        status, headers, body = _get(endpoint, "/specimens/steel-1/" + "a" * length)
        assert status == 414 and headers["Content-Type"].startswith("text/plain"), length
    assert _get(endpoint, "/api/specimens?x=" + "a" * (MAX_TARGET_BYTES - 20))[0] != 414


def test_a_tile_has_one_uri_and_its_aliases_are_not_found(endpoint):
    assert _get(endpoint, "/specimens/steel-1/tiles/0/0/0.glb")[::2] == (200, b"glTF\x03")
    for alias in (
        "tiles/00/0/0.glb",
        "tiles/0/000/0.glb",
        "tiles/\u0660/0/0.glb",
        "tiles/\uff10/0/0.glb",
        "tiles/0/0/0.glb%0A",
        "tiles/1234567/0/0.glb",
        "tiles/+0/0/0.glb",
        "tiles/0/0/0.GLB",
    ):
        assert _get(endpoint, "/specimens/steel-1/" + urllib.parse.quote(alias, safe="/%"))[0] == 404, alias


def test_gzip_is_sent_only_where_accept_encoding_weighs_it_above_zero(endpoint):
    for accept, gzipped in [
        ("gzip", True),
        ("gzip;q=0.5, identity", True),
        ("*", True),
        ("x-gzip", True),
        ("GZIP;Q=1", True),
        ("gzip;q=0", False),
        ("gzip;q=0.000", False),
        ("*;q=0", False),
        ("gzip;q=0, *", False),
        ("identity", False),
        ("br", False),
        ("", False),
        ("gzip;q=x", False),
    ]:
        status, headers, body = _get(endpoint, "/specimens/steel-1/tileset.json", **{"Accept-Encoding": accept})
        assert status == 200 and (headers.get("Content-Encoding") == "gzip") == gzipped, accept
        assert (gzip.decompress(body) if gzipped else body) == b"{}"
        assert headers["Vary"] == "Accept-Encoding"


def test_tiles_are_cached_for_good_only_under_their_build(endpoint, tmp_path):
    """tileset.json names each tile with its build; such a URL never changes its bytes, so it is
    immutable. After a rebuild the tileset names new URLs, and an old one is 410 Gone; a tile
    asked for without a build is the current one's, only briefly cached."""
    tileset = {"asset": {"version": "1.1"}, "root": {"content": {"uri": "tiles/0/0/0.glb"}, "children": []}}
    store = SpecimenStore(tmp_path / "data")
    (store.root / "steel-1" / "tileset.json").write_text(json.dumps(tileset))
    version = str(store.load("steel-1").version)
    status, headers, body = _get(endpoint, "/specimens/steel-1/tileset.json")
    assert status == 200 and headers["Cache-Control"] == "public, max-age=10"
    uri = json.loads(body)["root"]["content"]["uri"]
    assert uri == f"tiles/0/0/0.glb?v={urllib.parse.quote(version, safe='')}"
    status, headers, _ = _get(endpoint, f"/specimens/steel-1/{uri}")
    assert status == 200 and headers["Cache-Control"] == "public, max-age=31536000, immutable"
    for unnamed in ("tiles/0/0/0.glb", "tiles/0/0/0.glb?v="):
        status, headers, _ = _get(endpoint, f"/specimens/steel-1/{unnamed}")
        assert status == 200 and headers["Cache-Control"] == "public, max-age=10", unnamed
    status, headers, _ = _get(endpoint, "/specimens/steel-1/tiles/0/0/0.glb?v=1")
    assert status == 410 and headers["Cache-Control"] == "no-store"


def test_if_none_match_compares_entity_tags_weakly(endpoint):
    path = "/specimens/steel-1/tiles/0/0/0.glb"
    _, raw, _ = _get(endpoint, path)
    _, packed, _ = _get(endpoint, path, **{"Accept-Encoding": "gzip"})
    raw_tag, gzip_tag = raw["ETag"], packed["ETag"]
    assert raw_tag != gzip_tag and not raw_tag.startswith("W/")  # each representation its own strong tag
    for if_none_match in (raw_tag, f"W/{raw_tag}", f'"other", {raw_tag}', f'W/"other",W/{raw_tag}', "*"):
        status, headers, body = _get(endpoint, path, **{"If-None-Match": if_none_match})
        assert (status, body, headers["ETag"]) == (304, b"", raw_tag), if_none_match
        assert (
            headers["Vary"] == "Accept-Encoding" and headers["Cache-Control"] == "public, max-age=10"
        )  # asked for without its build: looked at again soon
    assert _get(endpoint, path, **{"If-None-Match": gzip_tag, "Accept-Encoding": "gzip"})[0] == 304
    for if_none_match in (
        gzip_tag,
        '"other"',
        raw_tag.strip('"'),
        f'{raw_tag[:-2]}"',
    ):  # gzip's tag does not validate the raw bytes
        assert _get(endpoint, path, **{"If-None-Match": if_none_match})[0] == 200, if_none_match


def test_accept_encoding_and_if_none_match_follow_rfc_9110():
    assert accepts_gzip("deflate, gzip;q=1.0, *;q=0.5") and not accepts_gzip("gzip;q=0, x-gzip;q=1")
    assert not_modified('W/"a", "b"', '"b"') and not_modified('"a,b"', '"a,b"') and not not_modified('"a,b"', '"a"')
    assert not not_modified("", '"a"') and not_modified(" * ", '"a"')
