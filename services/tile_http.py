"""Plain HTTP for standard 3D Tiles viewers and our web viewer.

- `/specimens/{id}/tileset.json` and the tiles it names: CORS headers (viewers run on other
  origins), a strong ETag (answered with 304 when the client has it), gzip when accepted.
- `/viewer/` the web viewer (clients/web) and `/vendor/` the three.js and 3DTilesRendererJS
  modules it imports (installed by `make install` into node_modules).
- `/api/specimens[/{id}[/profile|/roughness]]` JSON for the viewer: summaries, profiles
  (`?from=X,Y&to=X,Y[&magnification=M]`) and roughness (`?roi=ID` or `?region=X0,Y0,X1,Y1`), µm.
"""

from __future__ import annotations

import gzip
import hashlib
import json
import logging
import math
import os
import re
import threading
from functools import partial
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from pathlib import Path
from urllib.parse import parse_qs, urlsplit

from google.protobuf import json_format

from fractoscope import specimen_queries
from fractoscope.errors import FractoscopeError, InvalidInputError, NotFoundError
from fractoscope.services.auth import TokenTable
from fractoscope.services.tiles import specimen_message
from fractoscope.specimen_store import SpecimenStore

_log = logging.getLogger("fractoscope.http")
_ROUTE = re.compile(r"^/specimens/(?P<specimen>[A-Za-z0-9_-]{1,64})/(?P<path>tileset\.json|tiles/\d{1,6}/\d{1,6}/\d{1,6}\.glb)$")
_TYPES = {
    ".json": "application/json", ".glb": "model/gltf-binary", ".html": "text/html; charset=utf-8",
    ".js": "text/javascript", ".css": "text/css", ".svg": "image/svg+xml",
}
_REPOSITORY = Path(__file__).resolve().parents[1]
# From a checkout these are the repository's; an installed image says where via the environment.
WEB_ROOT = Path(os.environ.get("FRACTO_WEB_ROOT", _REPOSITORY / "clients" / "web"))
_VENDOR = Path(os.environ.get("FRACTO_VENDOR_ROOT", _REPOSITORY / "node_modules"))
VENDOR_ROOTS = {"three": _VENDOR / "three", "3d-tiles-renderer": _VENDOR / "3d-tiles-renderer"}
_STATIC = re.compile(r"^/(?P<area>viewer|vendor)/(?P<path>[A-Za-z0-9_./-]*)$")
_API = re.compile(r"^/api/specimens(?:/(?P<specimen>[A-Za-z0-9_-]{1,64})(?:/(?P<query>profile|roughness))?)?$")


class _Body:
    """One response body with its ETag and gzip form, computed once."""

    def __init__(self, raw: bytes):
        self.raw = raw
        self.etag = '"' + hashlib.sha256(raw).hexdigest()[:32] + '"'
        self.gzipped = gzip.compress(raw, compresslevel=6)


class _BodyCache:
    """Bodies by (specimen folder, path), dropped when the specimen is rebuilt."""

    def __init__(self, limit: int = 4096):
        self._bodies: dict[tuple[str, int, str], _Body] = {}
        self._lock = threading.Lock()
        self._limit = limit

    def get(self, key, produce) -> _Body:
        with self._lock:
            body = self._bodies.get(key)
        if body is None:
            body = _Body(produce())
            with self._lock:
                if len(self._bodies) >= self._limit:
                    self._bodies.clear()
                self._bodies[key] = body
        return body


class _TileHandler(BaseHTTPRequestHandler):
    server_version = "fractoscope"
    protocol_version = "HTTP/1.1"

    def __init__(self, *args, store: SpecimenStore, cache: _BodyCache, tokens: TokenTable, **kwargs):
        self.store = store
        self.cache = cache
        self.tokens = tokens
        super().__init__(*args, **kwargs)

    def log_message(self, format, *args):
        _log.debug(format % args)

    def do_OPTIONS(self):
        self.send_response(HTTPStatus.NO_CONTENT)
        self._cors()
        self.send_header("Access-Control-Allow-Methods", "GET, HEAD, OPTIONS")
        self.send_header("Access-Control-Allow-Headers", "*")
        self.send_header("Content-Length", "0")
        self.end_headers()

    def do_HEAD(self):
        self._serve(with_body=False)

    def do_GET(self):
        self._serve(with_body=True)

    def _serve(self, *, with_body: bool) -> None:
        url = urlsplit(self.path)
        path = url.path
        if path == "/healthz":
            self._send_plain(HTTPStatus.OK, b"ok\n", with_body)
            return
        if path == "/":
            self.send_response(HTTPStatus.FOUND)
            self.send_header("Location", "/viewer/")
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        if self.tokens.enabled and not path.startswith(("/viewer/", "/vendor/")):
            offered = self.headers.get("Authorization") or ("Bearer " + parse_qs(url.query).get("token", [""])[0])
            if self.tokens.grant(offered) is None:
                self._send_plain(HTTPStatus.UNAUTHORIZED, b"a valid bearer token is required\n", with_body)
                return
        if (api := _API.match(path)) is not None:
            self._serve_api(api["specimen"], api["query"], parse_qs(url.query), with_body)
            return
        if (static := _STATIC.match(path)) is not None:
            self._serve_static(static["area"], static["path"] or "index.html", with_body)
            return
        route = _ROUTE.match(path)
        if route is None:
            self._send_plain(HTTPStatus.NOT_FOUND, b"not found\n", with_body)
            return
        try:
            specimen = self.store.load(route["specimen"])
            relative = route["path"]
            produce = (lambda: specimen.tileset_bytes) if relative == "tileset.json" else (lambda: specimen.tile_bytes(relative))
            stamp = (specimen.directory / "specimen.json").stat().st_mtime_ns
            body = self.cache.get((str(specimen.directory), stamp, relative), produce)
        except (NotFoundError, FileNotFoundError):
            self._send_plain(HTTPStatus.NOT_FOUND, b"not found\n", with_body)
            return
        except FractoscopeError as error:
            self._send_plain(HTTPStatus.BAD_REQUEST, f"{error}\n".encode(), with_body)
            return
        self._send_body(body, _TYPES[relative[relative.rfind("."):]], with_body)

    def _serve_static(self, area: str, relative: str, with_body: bool) -> None:
        if area == "viewer":
            root = WEB_ROOT
        else:
            package, _, relative = relative.partition("/")
            root = VENDOR_ROOTS.get(package)
        path = (root / relative).resolve() if root else None
        if path is None or not path.is_relative_to(root.resolve()) or not path.is_file() or path.suffix not in _TYPES:
            self._send_plain(HTTPStatus.NOT_FOUND, b"not found\n", with_body)
            return
        body = self.cache.get(("static", path.stat().st_mtime_ns, str(path)), path.read_bytes)
        self._send_body(body, _TYPES[path.suffix], with_body)

    def _serve_api(self, specimen_id: str | None, query: str | None, arguments: dict, with_body: bool) -> None:
        try:
            if specimen_id is None:
                answer = [_summary(self.store.load(i)) for i in self.store.ids()]
            elif query is None:
                answer = _summary(self.store.load(specimen_id))
            elif query == "profile":
                found = specimen_queries.profile_along(
                    self.store.load(specimen_id), [_numbers(arguments, "from", 2), _numbers(arguments, "to", 2)],
                    magnification=_numbers(arguments, "magnification", 1, default=[0.0])[0],
                )
                names = found.sources + [""]
                answer = {
                    "distance_um": found.distance_um.tolist(),
                    "z_um": [None if math.isnan(z) else z for z in found.z_um.tolist()],
                    "source": [names[i] for i in found.source_index.tolist()],
                    "parameters": found.parameters,
                }
            else:
                region = _numbers(arguments, "region", 4) if "region" in arguments else None
                roi = arguments.get("roi", [None])[0]
                specimen = self.store.load(specimen_id)
                answer = specimen_queries.roughness_of(specimen, roi=roi or (None if region else specimen.rois[0].id), region_um=region)
        except NotFoundError as error:
            self._send_json(HTTPStatus.NOT_FOUND, {"error": str(error)}, with_body)
            return
        except FractoscopeError as error:
            field = getattr(error, "field", None)
            self._send_json(HTTPStatus.BAD_REQUEST, {"error": str(error), "field": field}, with_body)
            return
        self._send_json(HTTPStatus.OK, answer, with_body)

    def _send_json(self, status: HTTPStatus, answer, with_body: bool) -> None:
        payload = json.dumps(answer, allow_nan=False).encode()
        self.send_response(status)
        self._cors()
        self.send_header("Content-Type", "application/json")
        self.send_header("Cache-Control", "no-store")
        self.send_header("Content-Length", str(len(payload)))
        self.end_headers()
        if with_body:
            self.wfile.write(payload)

    def _send_body(self, body: _Body, content_type: str, with_body: bool) -> None:
        if self.headers.get("If-None-Match") == body.etag:
            self.send_response(HTTPStatus.NOT_MODIFIED)
            self._cors()
            self.send_header("ETag", body.etag)
            self.send_header("Content-Length", "0")
            self.end_headers()
            return
        compressed = "gzip" in self.headers.get("Accept-Encoding", "")
        payload = body.gzipped if compressed else body.raw
        self.send_response(HTTPStatus.OK)
        self._cors()
        self.send_header("Content-Type", content_type)
        self.send_header("ETag", body.etag)
        self.send_header("Cache-Control", "no-cache")
        self.send_header("Vary", "Accept-Encoding")
        if compressed:
            self.send_header("Content-Encoding", "gzip")
        self.send_header("Content-Length", str(len(payload)))
        self.end_headers()
        if with_body:
            self.wfile.write(payload)

    def _send_plain(self, status: HTTPStatus, text: bytes, with_body: bool) -> None:
        self.send_response(status)
        self._cors()
        self.send_header("Content-Type", "text/plain; charset=utf-8")
        self.send_header("Content-Length", str(len(text)))
        self.end_headers()
        if with_body:
            self.wfile.write(text)

    def _cors(self) -> None:
        self.send_header("Access-Control-Allow-Origin", "*")
        self.send_header("Access-Control-Expose-Headers", "ETag, Content-Encoding")


def _summary(specimen) -> dict:
    return json_format.MessageToDict(specimen_message(specimen), preserving_proto_field_name=True, always_print_fields_with_no_presence=True)


def _numbers(arguments: dict, name: str, count: int, default: list[float] | None = None) -> list[float]:
    """`name=a,b,...` from a query string as `count` finite numbers."""
    if name not in arguments:
        if default is not None:
            return default
        raise InvalidInputError(name, "is required")
    try:
        values = [float(v) for v in arguments[name][0].split(",")]
    except ValueError:
        values = []
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise InvalidInputError(name, f"must be {count} comma-separated numbers")
    return values


def create_http_server(store: SpecimenStore, host: str = "127.0.0.1", port: int = 0, *, tokens: TokenTable | None = None) -> ThreadingHTTPServer:
    """An HTTP server for the store's tilesets (not started: call serve_forever in a thread); with
    `tokens`, everything but the viewer's static files needs a bearer token (any access)."""
    server = ThreadingHTTPServer((host, port), partial(_TileHandler, store=store, cache=_BodyCache(), tokens=tokens or TokenTable({})))
    server.daemon_threads = True
    return server


def start_http_server(store: SpecimenStore, host: str = "127.0.0.1", port: int = 0, *, tokens: TokenTable | None = None) -> ThreadingHTTPServer:
    """Creates the HTTP server and serves it from a daemon thread; `server.server_port` is its port."""
    server = create_http_server(store, host, port, tokens=tokens)
    threading.Thread(target=server.serve_forever, name="fractoscope-http", daemon=True).start()
    return server
