"""Plain HTTP for standard 3D Tiles viewers and our web viewer.

- `/specimens/{id}/tileset.json` and the tiles it names, each under its one URI (a tile number
  zero-padded, in other digits or percent-encoded is a 404, not another cache entry; a tile of a
  build since replaced, `?v=OLD`, is 410 Gone, the current build's bytes never): CORS headers (viewers run on
  other origins), gzip when Accept-Encoding accepts it (q > 0), a strong ETag per representation
  (the gzip one has its own) and 304 when If-None-Match holds it (weak comparison, RFC 9110).
- `/livez` 200 while the process answers; `/healthz` 200, or 503 "degraded" while the object store
  is out of reach (a liveness probe asks the first: restarting cannot mend the store).
- `/viewer/` the web viewer (the installed clients/web package, see WEB_ROOT) and `/vendor/` the
  three.js and 3DTilesRendererJS modules it imports (that package's node_modules).
- `/api/` the HTTP/JSON API (http.api, described at `/api/openapi.json`), which the
  viewer uses too.
"""

from __future__ import annotations

import asyncio
import functools
import gzip
import hashlib
import json
import logging
import math
import os
import re
import resource
import sys
import threading
import time
import urllib.parse
from http import HTTPStatus
from pathlib import Path

from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from aiohttp.log import server_logger

from fractoscope.errors import FractoscopeError, NotFoundError, outcome_of
from fractoscope.http.api import JsonApi
from fractoscope.http.responses import json_error
from fractoscope.http.uploads import DEFAULT_MAX_UPLOAD_BYTES
from fractoscope.runtime.auth import TokenTable
from fractoscope.runtime.budget import Budget
from fractoscope.runtime.caches import BoundedCache
from fractoscope.runtime.process import CredentialFilter
from fractoscope.specimen.quadtree import TILE_URI
from fractoscope.store.base import StoredSpecimens

_ROUTE = re.compile(
    rf"/specimens/(?P<specimen>[A-Za-z0-9_-]{{1,64}})/(?P<path>tileset\.json|{TILE_URI.pattern})", re.ASCII
)
_TYPES = {
    ".json": "application/json",
    ".glb": "model/gltf-binary",
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript",
    ".css": "text/css",
    ".svg": "image/svg+xml",
}
# The web viewer's installed location, read once: FRACTO_WEB_ROOT, else the environment's data
# folder (`make install` links clients/web there; the container image copies it there).
WEB_ROOT = Path(os.environ.get("FRACTO_WEB_ROOT") or Path(sys.prefix, "share", "fractoscope", "web"))
VENDOR_ROOTS = {package: WEB_ROOT / "node_modules" / package for package in ("three", "3d-tiles-renderer")}
_STATIC = re.compile(r"/(?P<area>viewer|vendor)/(?P<path>[A-Za-z0-9_./-]*)")
# An entity tag in If-None-Match: its opaque part, weak or not.
_ENTITY_TAG = re.compile(r'(?:W/)?("[^"]*")')
# The longest request target (path and query) served; a longer one is refused as 414 in the
# API's JSON (plain text elsewhere). aiohttp's own parser, which answers in plain text before any
# handler runs, is let take lines and headers up to eight times as long, so that our answer is
# the one clients get.
MAX_TARGET_BYTES = 8190
_PARSER_LINE_BYTES = 8 * MAX_TARGET_BYTES


class _Body:
    """One response body with its gzip form and the strong ETag of each, computed once."""

    def __init__(self, raw: bytes):
        self.raw = raw
        self.gzipped = gzip.compress(raw, compresslevel=6)
        digest = hashlib.sha256(raw).hexdigest()[:32]
        self.etag, self.gzip_etag = f'"{digest}"', f'"{digest}-gzip"'


def body_cache(limit_bytes: int = 256 * 1024 * 1024) -> BoundedCache[_Body]:
    """Response bodies by key, bounded by their raw and gzip bytes together."""
    return BoundedCache(limit_bytes, size=lambda body: len(body.raw) + len(body.gzipped))


class _TileApp:
    """Request handling: one coroutine for every path, so the routing below reads top to bottom.
    Cached bodies are answered on the event loop; producing them (file reads, gzip) and the
    analysis queries run on the default executor so that they never stall it."""

    def __init__(self, store: StoredSpecimens, tokens: TokenTable, api: JsonApi):
        self.store = store
        self.cache = body_cache()
        self.tokens = tokens
        self.api = api
        self._check: asyncio.Future | None = None  # the object store's last health check (_store_problem)
        self._checked_s = -math.inf

    async def handle(self, request: web.Request) -> web.StreamResponse:
        if request.method == "OPTIONS":
            return web.Response(
                status=HTTPStatus.NO_CONTENT,
                headers={
                    **_CORS,
                    "Access-Control-Allow-Methods": "GET, HEAD, POST, DELETE, OPTIONS",
                    "Access-Control-Allow-Headers": "Authorization, Content-Type",  # `*` is not Authorization
                },
            )
        if len(request.raw_path) > MAX_TARGET_BYTES:
            message = f"the request target is {len(request.raw_path)} bytes long, at most {MAX_TARGET_BYTES} are served"
            if request.path.startswith("/api/"):
                return json_error(HTTPStatus.REQUEST_URI_TOO_LONG, message, "url")
            return _plain(HTTPStatus.REQUEST_URI_TOO_LONG, message + "\n")
        if request.path.startswith("/api/"):
            return await self.api.handle(request)  # its own JSON errors, scopes and methods
        if request.method not in ("GET", "HEAD"):
            return _plain(HTTPStatus.METHOD_NOT_ALLOWED, "only GET, HEAD and OPTIONS\n", Allow="GET, HEAD, OPTIONS")
        path = request.path
        if path == "/livez":  # the process answers: what a liveness probe asks, whatever the store's state
            return _plain(HTTPStatus.OK, "ok\n")
        if path == "/healthz":
            return await self._health()
        if path == "/":
            return web.Response(status=HTTPStatus.FOUND, headers={"Location": "/viewer/"})
        if self.tokens.enabled and not path.startswith(("/viewer/", "/vendor/")):
            offered = request.headers.get("Authorization") or "Bearer " + request.query.get("token", "")
            if self.tokens.grant(offered) is None:
                return _plain(HTTPStatus.UNAUTHORIZED, "a valid bearer token is required\n")
        if (static := _STATIC.fullmatch(path)) is not None:
            return await self._static(request, static["area"], static["path"] or "index.html")
        # Matched as sent: `tiles%2F0%2F0%2F0.glb` decodes to a tile's path but is not its URI.
        route = _ROUTE.fullmatch(request.raw_path.partition("?")[0])
        if route is None:
            return _plain(HTTPStatus.NOT_FOUND, "not found\n")
        return await self._tileset_file(request, route["specimen"], route["path"])

    async def _tileset_file(self, request: web.Request, specimen_id: str, relative: str) -> web.Response:
        """tileset.json or a tile it names (`relative`), of the build its `?v=` names (410 for one replaced)."""
        build = (request.query.get("v") or None) if relative != "tileset.json" else None
        try:
            specimen = await self._specimen(specimen_id, build)
            if build is not None and build != str(specimen.version):
                return _plain(
                    HTTPStatus.GONE,
                    f"build {build} of specimen {specimen.id!r} was replaced; load its tileset.json again\n",
                    **{"Cache-Control": "no-store"},
                )
            content = (
                (lambda: versioned_tileset(specimen.tileset_bytes, specimen.version))
                if relative == "tileset.json"
                else (lambda: specimen.tile_bytes(relative))
            )
            produce = lambda: _Body(content())  # noqa: E731 - runs on the executor below
            key = (specimen.id, specimen.version, relative)
            body = self.cache.cached(key) or await _off_loop(self.cache.get, key, produce)
        except (NotFoundError, FileNotFoundError):
            return _plain(HTTPStatus.NOT_FOUND, "not found\n")
        except FractoscopeError as error:  # the status the error table gives: 503 when the object store is out of reach
            status = HTTPStatus(outcome_of(error).http_status)
            retry = {"Retry-After": "5"} if status == HTTPStatus.SERVICE_UNAVAILABLE else {}
            return _plain(status, f"{error}\n", **retry)
        caching = _SHORT_CACHING if build is None else _TILE_CACHING
        return _body_response(request, body, _TYPES[relative[relative.rfind(".") :]], caching)

    async def _health(self) -> web.Response:
        """200 "ok", or 503 "degraded" saying why the store cannot serve now."""
        problem = await self._store_problem()
        if problem is not None:
            return _plain(HTTPStatus.SERVICE_UNAVAILABLE, f"degraded: {problem}\n", **{"Retry-After": "5"})
        return _plain(HTTPStatus.OK, "ok\n")

    async def _store_problem(self) -> str | None:
        """Why the store cannot serve now (None: it can): an object store held out of reach, or
        one that failed or did not answer within HEALTH_WAIT_S a check made at most every
        HEALTH_CHECK_EVERY_S (calls waiting meanwhile share it)."""
        objects = self.store.objects
        if objects is None:
            return None
        if objects.outage is not None:
            return objects.outage
        now_s = time.monotonic()
        if self._check is None or (self._check.done() and now_s - self._checked_s >= HEALTH_CHECK_EVERY_S):
            self._check, self._checked_s = asyncio.ensure_future(_off_loop(objects.check)), now_s
        try:
            await asyncio.wait_for(asyncio.shield(self._check), HEALTH_WAIT_S)
        except TimeoutError:
            return f"the object store {objects.url} did not answer within {HEALTH_WAIT_S:g} s"
        except FractoscopeError as error:
            return str(error)
        return None

    async def _specimen(self, specimen_id: str, build: str | None):
        """The stored specimen; when a tile of another build than the one known here is asked for,
        the store is asked again (a bucket's replica may not have seen a new build yet)."""
        if self.store.objects is None:  # a folder's: one stat
            return self.store.load(specimen_id)
        # A bucket's pointer may be read again, over the network: never on the event loop.
        specimen = await _off_loop(self.store.load, specimen_id)
        if build is not None and build != str(specimen.version):
            specimen = await _off_loop(functools.partial(self.store.load, specimen_id, fresh=True))
        return specimen

    async def _static(self, request: web.Request, area: str, relative: str) -> web.StreamResponse:
        if area == "viewer":
            root = WEB_ROOT
        else:
            package, _, relative = relative.partition("/")
            root = VENDOR_ROOTS.get(package)
        path = (root / relative).resolve() if root else None
        if path is None or not path.is_relative_to(root.resolve()) or not path.is_file() or path.suffix not in _TYPES:
            return _plain(HTTPStatus.NOT_FOUND, "not found\n")
        key = ("static", path.stat().st_mtime_ns, str(path))
        body = self.cache.cached(key) or await _off_loop(self.cache.get, key, lambda: _Body(path.read_bytes()))
        return _body_response(request, body, _TYPES[path.suffix])


# /healthz checks an object store at most this often, and waits at most this long for it, s.
HEALTH_CHECK_EVERY_S, HEALTH_WAIT_S = 5.0, 4.0
_CORS = {"Access-Control-Allow-Origin": "*", "Access-Control-Expose-Headers": "ETag, Content-Encoding"}
# A tile's bytes never change within a build: tileset.json names each tile with its build
# (`?v=`, see versioned_tileset), and a tile asked for under its current build is cached for good;
# under a build since replaced, it is 410 Gone (the viewer then loads the tileset again).
# tileset.json itself, and a tile asked for without a build, are looked at again soon.
_TILE_CACHING = "public, max-age=31536000, immutable"
_SHORT_CACHING = "public, max-age=10"


def versioned_tileset(tileset: bytes, version: int | str) -> bytes:
    """tileset.json with each content URI tagged with its build (`tiles/0/0/0.glb?v=VERSION`):
    a rebuild names other URLs, so no cache serves a tile of the last build under the new tileset."""
    document = json.loads(tileset)
    nodes = [document["root"]] if "root" in document else []
    tag = "?v=" + urllib.parse.quote(str(version), safe="")
    while nodes:
        node = nodes.pop()
        if "content" in node:
            node["content"]["uri"] += tag
        nodes += node.get("children", [])
    return json.dumps(document, separators=(",", ":")).encode()


async def _off_loop(function, *args):
    return await asyncio.get_running_loop().run_in_executor(None, function, *args)


def _body_response(
    request: web.Request, body: _Body, content_type: str, cache_control: str = "no-cache"
) -> web.Response:
    """The raw or gzip representation as Accept-Encoding chooses, or 304 when If-None-Match names
    its ETag; the 304 carries the headers a 200 would validate (RFC 9110, 15.4.5)."""
    gzipped = accepts_gzip(",".join(request.headers.getall("Accept-Encoding", [])))
    etag = body.gzip_etag if gzipped else body.etag
    headers = {**_CORS, "ETag": etag, "Cache-Control": cache_control, "Vary": "Accept-Encoding"}
    if not_modified(",".join(request.headers.getall("If-None-Match", [])), etag):
        return web.Response(status=HTTPStatus.NOT_MODIFIED, headers=headers)
    headers["Content-Type"] = content_type
    if gzipped:
        headers["Content-Encoding"] = "gzip"
        return web.Response(body=body.gzipped, headers=headers)
    return web.Response(body=body.raw, headers=headers)


def not_modified(if_none_match: str, etag: str) -> bool:
    """Whether If-None-Match fails for a representation with `etag`, so a GET gets 304 (RFC 9110,
    13.1.2): the header is `*` or lists an entity tag weakly equal to it (the opaque parts equal,
    `W/` or not). An empty header never does."""
    return if_none_match.strip() == "*" or etag.removeprefix("W/") in _ENTITY_TAG.findall(if_none_match)


def accepts_gzip(accept_encoding: str) -> bool:
    """Whether Accept-Encoding admits gzip (RFC 9110, 12.5.3): `gzip` (or `x-gzip`) with a
    weight above 0, or else `*` with one; a malformed weight counts as 0."""
    weights = {}
    for element in accept_encoding.split(","):
        coding, *parameters = (part.strip() for part in element.split(";"))
        weight = 1.0
        for parameter in parameters:
            name, _, value = parameter.partition("=")
            if name.strip().lower() == "q":
                try:
                    weight = float(value)
                except ValueError:
                    weight = 0.0
        if coding:
            weights[coding.lower()] = weight
    weight = weights.get("gzip", weights.get("x-gzip", weights.get("*", 0.0)))
    return weight > 0


def _plain(status: HTTPStatus, text: str, **headers: str) -> web.Response:
    return web.Response(
        status=status, body=text.encode(), headers={**_CORS, "Content-Type": "text/plain; charset=utf-8", **headers}
    )


class _CredentialFilter(CredentialFilter):
    """aiohttp's server log without credentials: a request its parser refuses (anyone's input) is
    logged at DEBUG without a traceback, not at ERROR with one whose message quotes the refused line,
    Authorization header and all; every record is redacted (CredentialFilter)."""

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, HttpProcessingError):
            record.msg, record.args = f"{record.getMessage()}: {error.message}", None
            record.levelno, record.levelname, record.exc_info, record.exc_text = logging.DEBUG, "DEBUG", None, None
        super().filter(record)
        # The logger's level was checked at the record's first level; a downgraded one is checked again.
        return record.levelno > logging.DEBUG or server_logger.isEnabledFor(logging.DEBUG)


_CREDENTIAL_FILTER = _CredentialFilter()


# How long a connection may go without a whole request, its first one's headers included, s:
# an idle socket costs a file descriptor, and a slow client's headers hold one open.
IDLE_TIMEOUT_S = float(os.environ.get("FRACTO_HTTP_IDLE_TIMEOUT_S", "15"))
# Connections kept open at most (FRACTO_HTTP_MAX_CONNECTIONS, and never more than half the file
# descriptors the process may open): a new one beyond closes the oldest idle one.
DEFAULT_MAX_CONNECTIONS = 1000


def max_connections() -> int:
    """FRACTO_HTTP_MAX_CONNECTIONS (default DEFAULT_MAX_CONNECTIONS), at most half RLIMIT_NOFILE's
    soft limit, leaving the rest to files, gRPC and the object store."""
    wanted = int(os.environ.get("FRACTO_HTTP_MAX_CONNECTIONS", DEFAULT_MAX_CONNECTIONS))
    return max(8, min(wanted, resource.getrlimit(resource.RLIMIT_NOFILE)[0] // 2))


class _CappedSite(web.TCPSite):
    """A TCP site that keeps at most `max_connections` open: each new connection beyond closes the
    oldest idle ones (those without a request in a handler: `busy`, see _track_busy), so that
    idle or slow clients cannot take every descriptor from those that send requests. Sockets are
    accepted a quarter of the cap at a time at most (the listen backlog), so that a burst cannot
    overshoot it by much before the cap acts."""

    def __init__(self, runner: web.AppRunner, host: str, port: int, *, max_connections: int, busy: set, **options):
        super().__init__(runner, host, port, backlog=max(1, min(128, max_connections // 4)), **options)
        self._max_connections, self._busy = max_connections, busy

    async def start(self) -> None:
        await web.BaseSite.start(self)  # registers the site; TCPSite.start would bind its own factory
        server = self._runner.server

        def protocol():
            handlers = server.connections
            excess = len(handlers) + 1 - self._max_connections
            for idle in [handler for handler in handlers if handler not in self._busy][: max(0, excess)]:
                idle.force_close()  # waits for nothing: close() would leave an idle one's socket open
            return server()

        self._server = await asyncio.get_running_loop().create_server(
            protocol, self._host, self._port, reuse_address=self._reuse_address, backlog=self._backlog
        )
        self._bound_port = self._server.sockets[0].getsockname()[1]


def _track_busy(busy: set):
    """A middleware that keeps in `busy` the connections (request.protocol) whose request a
    handler is answering."""

    @web.middleware
    async def tracked(request: web.Request, handler):
        busy.add(request.protocol)
        try:
            return await handler(request)
        finally:
            busy.discard(request.protocol)

    return tracked


class _AcceptErrors:
    """The HTTP loop's handler of exceptions no task catches: asyncio's report that accept() ran
    out of descriptors (EMFILE, which it retries every second, each time with a traceback) is
    logged at most once every ACCEPT_ERROR_EVERY_S without one, counting the ones left out;
    everything else goes to asyncio's default handler."""

    def __init__(self):
        self._last_s, self._left_out = -math.inf, 0

    def __call__(self, loop: asyncio.AbstractEventLoop, context: dict) -> None:
        if not context.get("message", "").startswith("socket.accept() out of system resource"):
            loop.default_exception_handler(context)
            return
        now_s = time.monotonic()
        if now_s - self._last_s < ACCEPT_ERROR_EVERY_S:
            self._left_out += 1
            return
        _log.error(
            f"{context['message']}: {context.get('exception')!r} (file descriptors run out; "
            f"{self._left_out} more such reports left out since the last)"
        )
        self._last_s, self._left_out = now_s, 0


ACCEPT_ERROR_EVERY_S = 10.0
_log = logging.getLogger("fractoscope.http")


class HttpTileServer:
    """The HTTP endpoint, served by aiohttp from an event loop on its own daemon thread."""

    def __init__(self, store: StoredSpecimens, host: str, port: int, tokens: TokenTable, api: JsonApi):
        server_logger.addFilter(_CREDENTIAL_FILTER)  # once per process: the same filter is not added twice
        self._loop = asyncio.new_event_loop()
        self._api = api
        app = _TileApp(store, tokens, api)
        busy: set = set()
        application = web.Application(middlewares=[_track_busy(busy)])
        application.router.add_route("*", r"/{tail:[\s\S]*}", app.handle)  # any path, new lines too
        self._runner = web.AppRunner(
            application,
            access_log=None,
            handle_signals=False,
            max_line_size=_PARSER_LINE_BYTES,
            max_field_size=_PARSER_LINE_BYTES,
            keepalive_timeout=IDLE_TIMEOUT_S,  # from the connection's start too: a header timeout
        )
        self._loop.set_exception_handler(_AcceptErrors())
        self._loop.run_until_complete(self._runner.setup())
        site = _CappedSite(self._runner, host, port, max_connections=max_connections(), busy=busy, reuse_address=True)
        self._loop.run_until_complete(site.start())
        self.server_port: int = self._runner.addresses[0][1]
        self._thread = threading.Thread(target=self._loop.run_forever, name="fractoscope-http", daemon=True)
        self._thread.start()

    def send_builds_to(self, grpc_address: str) -> None:
        """Builds submitted to the API go to this gRPC endpoint from now on."""
        self._api.jobs.address = grpc_address

    def shutdown(self) -> None:
        """Stops serving: open connections are closed, the loop and its thread end."""
        asyncio.run_coroutine_threadsafe(self._runner.cleanup(), self._loop).result(timeout=30)
        self._api.jobs.close()
        self._api.analyses.close()
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=30)
        self._loop.close()


def start_http_server(
    store: StoredSpecimens,
    host: str = "127.0.0.1",
    port: int = 0,
    *,
    tokens: TokenTable | None = None,
    grpc_address: str | None = None,
    max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES,
    budget: Budget | None = None,
) -> HttpTileServer:
    """Serves the store's tilesets, the viewer and the JSON API over HTTP from a daemon thread;
    `server_port` is the bound port. With `tokens`, everything but the viewer's static files and
    the OpenAPI document needs a bearer token, and the API's builds a write token. Builds go to the
    gRPC endpoint at `grpc_address` (None: the API refuses them); uploads are kept next to the
    specimens (DATA/uploads), at most `max_upload_bytes` each. Analyses, exports, reports and the
    checks of uploads are admitted by `budget`: pass the one this process's gRPC server has (see
    runtime.budget); by default one of the endpoint's own."""
    tokens = tokens or TokenTable({})
    api = JsonApi(
        store,
        tokens,
        grpc_address=grpc_address,
        uploads_root=store.scratch_root.parent / "uploads",
        max_upload_bytes=max_upload_bytes,
        budget=budget or Budget.for_server(None, concurrent_requests=1, scratch_root=store.scratch_root),
    )
    return HttpTileServer(store, host, port, tokens, api)
