"""Plain HTTP for standard 3D Tiles viewers: `/specimens/{id}/tileset.json` and the tiles it names.

Responses carry CORS headers (viewers run on other origins), a strong ETag (answered with 304
when the client has it) and gzip when the client accepts it.
"""

from __future__ import annotations

import gzip
import hashlib
import logging
import re
import threading
from functools import partial
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from fractoscope.errors import FractoscopeError, NotFoundError
from fractoscope.specimen_store import SpecimenStore

_log = logging.getLogger("fractoscope.http")
_ROUTE = re.compile(r"^/specimens/(?P<specimen>[A-Za-z0-9_-]{1,64})/(?P<path>tileset\.json|tiles/\d{1,6}/\d{1,6}/\d{1,6}\.glb)$")
_TYPES = {".json": "application/json", ".glb": "model/gltf-binary"}


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

    def __init__(self, *args, store: SpecimenStore, cache: _BodyCache, **kwargs):
        self.store = store
        self.cache = cache
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
        path = self.path.split("?", 1)[0]
        if path == "/healthz":
            self._send_plain(HTTPStatus.OK, b"ok\n", with_body)
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
        self.send_header("Content-Type", _TYPES[relative[relative.rfind("."):]])
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


def create_http_server(store: SpecimenStore, host: str = "127.0.0.1", port: int = 0) -> ThreadingHTTPServer:
    """An HTTP server for the store's tilesets (not started: call serve_forever in a thread)."""
    server = ThreadingHTTPServer((host, port), partial(_TileHandler, store=store, cache=_BodyCache()))
    server.daemon_threads = True
    return server


def start_http_server(store: SpecimenStore, host: str = "127.0.0.1", port: int = 0) -> ThreadingHTTPServer:
    """Creates the HTTP server and serves it from a daemon thread; `server.server_port` is its port."""
    server = create_http_server(store, host, port)
    threading.Thread(target=server.serve_forever, name="fractoscope-http", daemon=True).start()
    return server
