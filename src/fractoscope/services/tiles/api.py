"""The HTTP/JSON API under /api/, described by the OpenAPI 3.1 document at /api/openapi.json
(`openapi.document`): specimens, reconstructions from uploads and their jobs, roughness,
profiles, zoom, exports and the measurement report.

Every error is JSON, {"error": message, "field": the input at fault or null}, with a 4xx status
for anything the caller can fix. Tokens and scopes are gRPC's (see auth): read tokens query,
write tokens compute (uploads and builds); they are checked before a request's body is read.
Builds run as ReconstructSpecimen calls on this server's own gRPC endpoint with the submitter's
token, so they follow the same path, limits and scopes as any gRPC build.
"""

from __future__ import annotations

import asyncio
import io
import json
import math
import os
import re
import shutil
import tempfile
import threading
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from http import HTTPStatus
from pathlib import Path

import numpy as np
from aiohttp import web
from aiohttp.http_exceptions import HttpProcessingError
from google.protobuf import json_format

from fractoscope import report
from fractoscope.errors import FractoscopeError, InvalidInputError, NotFoundError
from fractoscope.formats import strict_json
from fractoscope.formats.exports import MEDIA_TYPES
from fractoscope.rpc import wire
from fractoscope.rpc.channel import open_channel
from fractoscope.rpc.limits import MAX_REQUEST_ID_CHARS
from fractoscope.rpc.manifest import manifest_field, parse_manifest
from fractoscope.rpc.status import ClientError, raised_as_client_errors
from fractoscope.rpc.tiles import checked_rois, profile_response, roughness_response, specimen_message, tile_message
from fractoscope.services.auth import READ, WRITE, Grant, TokenTable
from fractoscope.services.tiles import openapi
from fractoscope.specimen import exports, quadtree, queries
from fractoscope.specimen.store import SpecimenStore, validate_id
from fractoscope.stereo.geometry import validate_pixel_size_um
from fractoscope.v1 import tiles_pb2, tiles_pb2_grpc

_JSON = "application/json"
_CORS = {"Access-Control-Allow-Origin": "*", "Access-Control-Expose-Headers": "ETag, Content-Encoding, Content-Disposition, Location"}
_FILE_NAME = re.compile(r"[A-Za-z0-9][A-Za-z0-9._-]{0,127}")
_CHUNK_BYTES = 1 << 20
DEFAULT_MAX_UPLOAD_BYTES = 512 * 1024 * 1024
# Analyses at once (CPU-bound: one per CPU) and waiting before 429.
DEFAULT_ANALYSIS_WORKERS = len(os.sched_getaffinity(0))
DEFAULT_QUEUED_ANALYSES = 16


class ApiError(Exception):
    """An answer other than success: its status, message, the field at fault and extra headers."""

    def __init__(self, status: HTTPStatus, message: str, field: str | None = None, **headers: str):
        super().__init__(message)
        self.status, self.message, self.field, self.headers = status, message, field, headers


@dataclass(frozen=True)
class _Route:
    method: str
    pattern: re.Pattern
    handler: str
    access: str  # READ or WRITE: the scope it needs


_ROUTES = [
    _Route("GET", re.compile(r"/api/openapi\.json"), "openapi", ""),
    _Route("GET", re.compile(r"/api/specimens"), "list_specimens", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)"), "get_specimen", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/roughness"), "roughness", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/profile"), "profile", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/heights"), "heights", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/zoom"), "zoom", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/export"), "export_area", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/report"), "report", READ),
    _Route("POST", re.compile(r"/api/exports"), "export_height_map", READ),
    _Route("POST", re.compile(r"/api/uploads"), "upload", WRITE),
    _Route("POST", re.compile(r"/api/jobs"), "submit_job", WRITE),
    _Route("GET", re.compile(r"/api/jobs/(?P<job_id>[^/]+)"), "get_job", READ),
]


class JsonApi:
    """The API's request handling. `grpc_address` is this server's gRPC endpoint, which builds go
    to (None: builds are refused with 503); uploads are kept under `uploads_root`."""

    def __init__(self, store: SpecimenStore, tokens: TokenTable, *, grpc_address: str | None, uploads_root: Path,
                 max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES, build_workers: int = 2, queued_builds: int = 8,
                 analysis_workers: int = DEFAULT_ANALYSIS_WORKERS, queued_analyses: int = DEFAULT_QUEUED_ANALYSES):
        self.store = store
        self.tokens = tokens
        self.uploads = Uploads(uploads_root, max_upload_bytes)
        self.jobs = BuildJobs(grpc_address, workers=build_workers, queue_limit=queued_builds)
        self.analyses = Analyses(workers=analysis_workers, queue_limit=queued_analyses)

    async def handle(self, request: web.Request) -> web.StreamResponse:
        try:
            route, match = _route(request)
            grant = self._authorize(request, route.access)
            return await getattr(self, route.handler)(request, match, grant)
        except ApiError as error:
            return json_error(error.status, error.message, error.field, **error.headers)
        except NotFoundError as error:
            return json_error(HTTPStatus.NOT_FOUND, str(error), error.field)
        except InvalidInputError as error:
            return json_error(HTTPStatus.BAD_REQUEST, str(error), error.field)
        except FractoscopeError as error:
            return json_error(HTTPStatus.BAD_REQUEST, str(error), None)

    def _authorize(self, request: web.Request, access: str) -> Grant | None:
        """The caller's grant, checked against the scope the route needs before anything is read."""
        if not self.tokens.enabled or not access:
            return None
        offered = request.headers.get("Authorization") or "Bearer " + request.query.get("token", "")
        grant = self.tokens.grant(offered)
        if grant is None:
            raise ApiError(HTTPStatus.UNAUTHORIZED, "a valid bearer token is required", "authorization", **{"WWW-Authenticate": "Bearer"})
        if access == WRITE and grant.access != WRITE:
            raise ApiError(HTTPStatus.FORBIDDEN, f"client {grant.client!r} may only read", "authorization")
        return grant

    async def openapi(self, request, match, grant):
        return _json(openapi.document())

    async def list_specimens(self, request, match, grant):
        _parameters(request, set())
        return _json(await _off_loop(lambda: [_summary(self.store.load(i)) for i in self.store.ids()]))

    async def get_specimen(self, request, match, grant):
        _parameters(request, set())
        return _json(await _off_loop(lambda: _summary(self._specimen(match))))

    async def roughness(self, request, match, grant):
        query = _parameters(request, {"roi", "region", *CHAIN_PARAMETERS})
        area, chain = _area(query), _chain(query)

        def answer():
            specimen = self._specimen(match)
            analysis = queries.roughness_of(specimen, roi=area["roi"] or None, region_um=area["region_um"], chain=chain)
            return wire.response_to_roughness(roughness_response(analysis, chain))

        return _json(await self.analyses.run(answer))

    async def profile(self, request, match, grant):
        query = _parameters(request, {"from", "to", "magnification", "spacing_um", *PROFILE_CHAIN_PARAMETERS})
        points = [_numbers(query, "from", 2), _numbers(query, "to", 2)]
        magnification = _number(query, "magnification", default=0.0, minimum=0.0)
        spacing_um = _number(query, "spacing_um", default=0.0, minimum=0.0)
        chain = _chain(query)

        def answer():
            found = queries.profile_along(self._specimen(match), points, spacing_um=spacing_um, magnification=magnification, chain=chain)
            names = found.sources + [""]
            response = profile_response(found)
            return {
                "distance_um": found.distance_um.tolist(), "z_um": found.z_um.tolist(),
                "source": [names[i] for i in found.source_index.tolist()],
                "parameters": wire.message_to_profile_parameters(response.parameters) if found.parameters else None,
                "roughness_um": found.r_um.tolist() if found.r_um is not None else None,
                "chain": {**wire.chain_to_dict(response.chain), "cutoffs_from_iso_table": response.cutoffs_from_iso_table,
                          "spacing_within_iso": response.spacing_within_iso} if found.roughness else None,
            }  # fmt: skip

        return _json(await self.analyses.run(answer))

    async def heights(self, request, match, grant):
        region = _numbers(_parameters(request, {"region"}), "region", 4)
        return _json(await self.analyses.run(lambda: queries.height_statistics(self._specimen(match), region)))

    async def zoom(self, request, match, grant):
        query = _parameters(request, {"region", "magnification"})
        region = queries.checked_region(_numbers(query, "region", 4))
        magnification = _number(query, "magnification")

        def answer():
            specimen = self._specimen(match)
            cell_um = specimen.pixel_size_at_magnification(queries.positive(magnification, "magnification"))
            chosen = quadtree.tiles_in_region(specimen.layout, specimen.tiles, region, cell_um=cell_um)
            return {"tiles": [_tile(tile_message(specimen, record, upsampled=upsampled)) for record, upsampled in chosen]}

        return _json(await _off_loop(answer))

    async def export_area(self, request, match, grant):
        query = _parameters(request, {"format", "roi", "region", "pixel_size_um", "solid", "units"})
        options = _export_options(query)
        area = _area(query)

        def write(directory: Path) -> tuple[Path, str]:
            exported = exports.export_area(self._specimen(match), directory, **area, **options)
            return exported.path, MEDIA_TYPES[exported.file_format]

        return await _file_response(request, self.analyses.run, write)

    async def export_height_map(self, request, match, grant):
        _parameters(request, set())
        form = await _small_form(request, files={"height_map"}, fields={"format", "map_pixel_size_um", "pixel_size_um", "solid", "units"},
                                 limit_bytes=self.uploads.max_bytes)
        options = _export_options(form)
        z_um, sigma_um, stored = _npz_height_map(form.get("height_map"))
        if stored is not None:
            map_pixel_size_um = validate_pixel_size_um(stored, field="height_map.pixel_size_um")
        else:
            map_pixel_size_um = validate_pixel_size_um(_number(form, "map_pixel_size_um"), field="map_pixel_size_um")
        export_pixel_size_um = options.pop("pixel_size_um")

        def write(directory: Path) -> tuple[Path, str]:
            exported = exports.export_height_map(directory, z_um, pixel_size_um=map_pixel_size_um, sigma_um=sigma_um,
                                                 export_pixel_size_um=export_pixel_size_um, **options)
            return exported.path, MEDIA_TYPES[exported.file_format]

        return await _file_response(request, self.analyses.run, write)

    async def report(self, request, match, grant):
        query = _parameters(request, {"format", "roi", "region"})
        file_format = _choice(query, "format", tuple(report.MEDIA_TYPES), default="html")
        area = _area(query)

        def write(directory: Path) -> tuple[Path, str]:
            path = report.write_report(self._specimen(match), directory, file_format=file_format, **area)
            return path, report.MEDIA_TYPES[file_format]

        return await _file_response(request, self.analyses.run, write)

    async def upload(self, request, match, grant):
        _parameters(request, set())
        upload_id, specimen_id, rois = await self.uploads.receive(request)
        return _json({"upload_id": upload_id, "specimen_id": specimen_id, "rois": [roi.id for roi in rois]}, status=HTTPStatus.CREATED,
                     Location=f"/api/uploads/{upload_id}")

    async def submit_job(self, request, match, grant):
        _parameters(request, set())
        if not self.jobs.enabled:
            raise ApiError(HTTPStatus.SERVICE_UNAVAILABLE, "this endpoint does not run builds (it has no gRPC endpoint to send them to)")
        if request.content_type == "multipart/form-data":
            upload_id, _, _ = await self.uploads.receive(request)
            request_id = self.uploads.field(upload_id, "request_id")
        elif request.content_type == _JSON:
            body = await _json_body(request, limit_bytes=64 * 1024)
            unknown = sorted(set(body) - {"upload_id", "request_id"})
            if unknown:
                raise InvalidInputError(unknown[0] or "body", f"{unknown[0]!r} is not a field of a job request (upload_id, request_id)")
            upload_id, request_id = body.get("upload_id"), body.get("request_id", "")
            if not isinstance(upload_id, str):
                raise InvalidInputError("upload_id", "is required (a string)")
            if not isinstance(request_id, str) or len(request_id) > MAX_REQUEST_ID_CHARS:
                raise InvalidInputError("request_id", f"must be a string of at most {MAX_REQUEST_ID_CHARS} characters")
        else:
            raise ApiError(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "send application/json ({\"upload_id\": ...}) or multipart/form-data "
                           "(manifest and images)", "content-type")
        specimen_id, rois = await _off_loop(self.uploads.load, upload_id)
        token = (request.headers.get("Authorization") or "").removeprefix("Bearer ").strip() or request.query.get("token") or None
        job = self.jobs.submit(specimen_id, rois, request_id=request_id or "", token=token, upload_id=upload_id)
        return _json(job.as_dict(), status=HTTPStatus.ACCEPTED, Location=f"/api/jobs/{job.id}")

    async def get_job(self, request, match, grant):
        _parameters(request, set())
        return _json(self.jobs.get(match["job_id"]).as_dict())

    def _specimen(self, match):
        return self.store.load(validate_id(match["specimen_id"], field="specimen_id"))


# Requests ##########################################################################################


def _route(request: web.Request) -> tuple[_Route, re.Match]:
    allowed = []
    for route in _ROUTES:
        match = route.pattern.fullmatch(request.path)
        if match is None:
            continue
        if route.method == request.method or (route.method == "GET" and request.method == "HEAD"):
            return route, match
        allowed.append(route.method)
    if allowed:
        raise ApiError(HTTPStatus.METHOD_NOT_ALLOWED, f"{request.method} is not allowed here; use {', '.join(allowed)}", "method",
                       Allow=", ".join(allowed))
    raise ApiError(HTTPStatus.NOT_FOUND, f"no API resource {request.path}", "path")


def _parameters(request: web.Request, known: set[str]) -> dict[str, str]:
    """The query's parameters (`token` aside), each given once and known."""
    values = {}
    for name in request.query.keys():
        if name == "token":
            continue
        if name not in known:
            raise InvalidInputError(name or "query", f"{'an unnamed parameter ' if not name else ''}is not a parameter here{'; known: ' + ', '.join(sorted(known)) if known else ''}")
        given = request.query.getall(name)
        if len(given) > 1:
            raise InvalidInputError(name, "is given more than once")
        values[name] = given[0]
    return values


def _numbers(values: dict, name: str, count: int) -> list[float]:
    """`name=a,b,...` as `count` finite numbers."""
    if name not in values:
        raise InvalidInputError(name, "is required")
    try:
        numbers = [float(v) for v in values[name].split(",")]
    except (ValueError, AttributeError):
        numbers = []
    if len(numbers) != count or not all(math.isfinite(v) for v in numbers):
        raise InvalidInputError(name, f"must be {count} comma-separated finite numbers")
    return numbers


def _number(values: dict, name: str, *, default: float | None = None, minimum: float | None = None) -> float | None:
    if name not in values:
        if default is None:
            raise InvalidInputError(name, "is required")
        return default
    value = _numbers(values, name, 1)[0]
    if minimum is not None and value < minimum:
        raise InvalidInputError(name, f"must be at least {minimum:g}")
    return value


def _choice(values: dict, name: str, choices: tuple[str, ...], *, default: str | None = None) -> str:
    value = values.get(name, default)
    if value not in choices:
        raise InvalidInputError(name, f"must be one of {', '.join(choices)}" if name in values or default is None else "is required")
    return value


def _flag(values: dict, name: str) -> bool:
    return _choice(values, name, ("true", "false"), default="false") == "true"


# The surface texture chain's query parameters (see queries.ChainRequest); profiles take the first three.
PROFILE_CHAIN_PARAMETERS = ("form", "s_filter_um", "l_filter_um")
CHAIN_PARAMETERS = (*PROFILE_CHAIN_PARAMETERS, "direction_deg", "levelling_region", "window_px", "min_windows", "robust_form")


def _chain(values: dict) -> queries.ChainRequest:
    """The chain's settings among the query's parameters; absent ones stay at their defaults."""

    def number(name: str) -> float | None:
        return _numbers(values, name, 1)[0] if name in values else None

    form = _choice(values, "form", tuple(wire.FORMS)) if "form" in values else None
    return queries.ChainRequest(
        form=form, s_filter_um=number("s_filter_um"), l_filter_um=number("l_filter_um"), direction_deg=number("direction_deg"),
        levelling_region_um=tuple(_numbers(values, "levelling_region", 4)) if "levelling_region" in values else None,
        window_px=number("window_px"), min_windows=number("min_windows"),
        robust_form=_flag(values, "robust_form") if "robust_form" in values else None,
    )  # fmt: skip


def _area(values: dict) -> dict:
    """roi= or region= (not both); neither: the overview."""
    if "roi" in values and "region" in values:
        raise InvalidInputError("region", "give roi or region, not both")
    region = queries.checked_region(_numbers(values, "region", 4)) if "region" in values else None
    return {"roi": values.get("roi"), "region_um": region}


def _export_options(values: dict) -> dict:
    pixel_size_um = _number(values, "pixel_size_um", default=0.0, minimum=0.0) or None
    return {"file_format": _choice(values, "format", tuple(MEDIA_TYPES)), "pixel_size_um": pixel_size_um,
            "solid": _flag(values, "solid"), "units": _choice(values, "units", tuple(wire.LENGTH_UNITS), default="um")}


async def _json_body(request: web.Request, *, limit_bytes: int) -> dict:
    raw = await request.content.read(limit_bytes + 1)
    if len(raw) > limit_bytes:
        raise ApiError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a JSON body of at most {limit_bytes} bytes", "body")
    try:
        body = json.loads(raw)
    except (json.JSONDecodeError, UnicodeDecodeError, RecursionError) as error:
        raise InvalidInputError("body", f"is not JSON: {error}") from None
    if not isinstance(body, dict):
        raise InvalidInputError("body", "must be a JSON object")
    return body


async def _small_form(request: web.Request, *, files: set[str], fields: set[str], limit_bytes: int) -> dict:
    """A multipart form held in memory: the `fields` as str, the `files` parts as bytes."""
    form, total = {}, 0
    async for part in _parts(await _multipart(request, limit_bytes=limit_bytes)):
        name = part.name or ""
        if name not in files | fields:
            raise InvalidInputError(name or "body", f"is not a part of this form ({', '.join(sorted(files | fields))})")
        if name in form:
            raise InvalidInputError(name, "is given more than once")
        content = bytearray()
        while chunk := await _chunk(part):
            total += len(chunk)
            if total > limit_bytes:
                raise ApiError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the request exceeds {limit_bytes} bytes", name)
            content += chunk
        if name in files:
            form[name] = bytes(content)
        else:
            try:
                form[name] = content.decode("utf-8")
            except UnicodeDecodeError:
                raise InvalidInputError(name, "must be UTF-8 text") from None
    return form


async def _parts(reader):
    """The parts of a multipart body; a malformed one is the caller's error, not ours."""
    while True:
        try:
            part = await reader.next()
        except (HttpProcessingError, ValueError, AssertionError, LookupError) as error:
            raise InvalidInputError("body", f"is not valid multipart/form-data: {_first_line(error)}") from None
        if part is None:
            return
        yield part


async def _chunk(part) -> bytes:
    try:
        return await part.read_chunk(_CHUNK_BYTES)
    except (HttpProcessingError, ValueError, AssertionError, LookupError) as error:
        raise InvalidInputError(part.name or "body", f"is not valid multipart/form-data: {_first_line(error)}") from None


def _first_line(error: Exception) -> str:
    return (str(error).strip().splitlines() or [type(error).__name__])[0][:200]


# What a multipart body may carry besides its parts' contents: boundaries and part headers.
_MULTIPART_FRAMING_BYTES = 1024 * 1024


async def _multipart(request: web.Request, *, limit_bytes: int):
    """The reader of a multipart body whose parts may hold `limit_bytes` in all: a Content-Length
    beyond that is refused (413) before anything is read."""
    if request.content_type != "multipart/form-data":
        raise ApiError(HTTPStatus.UNSUPPORTED_MEDIA_TYPE, "send multipart/form-data", "content-type")
    if (request.content_length or 0) > limit_bytes + _MULTIPART_FRAMING_BYTES:
        raise ApiError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"a body of {request.content_length} bytes exceeds the {limit_bytes} allowed", "body",
                       Connection="close")  # the body is not read
    try:
        return await request.multipart()
    except (ValueError, AssertionError, KeyError) as error:
        raise InvalidInputError("body", f"is not multipart/form-data: {error}") from None


def _npz_height_map(content: bytes | None) -> tuple[np.ndarray, np.ndarray | None, float | None]:
    """z_um (and sigma_um, pixel_size_um if stored) of an uploaded npz, as `fracto height` writes it."""
    if not content:
        raise InvalidInputError("height_map", "is required: an .npz with z_um (as fracto height writes it)")
    if not content.startswith(b"PK"):  # npz files are zip archives; np.load would try a pickle
        raise InvalidInputError("height_map", "is not an npz file (a zip archive with z_um, as fracto height writes it)")
    try:
        with np.load(io.BytesIO(content), allow_pickle=False) as arrays:
            z_um = np.asarray(arrays["z_um"])
            sigma_um = np.asarray(arrays["sigma_um"]) if "sigma_um" in arrays.files else None
            stored = float(arrays["pixel_size_um"]) if "pixel_size_um" in arrays.files else None
    except (OSError, ValueError, KeyError, TypeError, EOFError) as error:
        raise InvalidInputError("height_map", f"is not an npz with z_um: {error}") from None
    if z_um.dtype.kind not in "fiu" or (sigma_um is not None and sigma_um.dtype.kind not in "fiu"):
        raise InvalidInputError("height_map", "z_um and sigma_um must be real numbers")
    return z_um, sigma_um, stored


# Responses #########################################################################################


async def _off_loop(function, *args):
    return await asyncio.get_running_loop().run_in_executor(None, function, *args)


def _json(value, *, status: HTTPStatus = HTTPStatus.OK, **headers: str) -> web.Response:
    body = strict_json.dumps(value).encode()
    return web.Response(status=status, body=body, headers={**_CORS, "Content-Type": _JSON, "Cache-Control": "no-store", **headers})


def json_error(status: HTTPStatus, message: str, field: str | None, **headers: str) -> web.Response:
    """An error in the API's format: {"error": message, "field": the request field it names or null}."""
    return _json({"error": message, "field": field}, status=status, **headers)


async def _file_response(request: web.Request, run, write: Callable[[Path], tuple[Path, str]]) -> web.StreamResponse:
    """A file written by `write(directory)` (on threads by `await run(function, *args)`, into a
    temporary folder) and streamed out in chunks, so memory stays bounded; the folder goes once it
    is sent."""
    directory = Path(tempfile.mkdtemp(prefix="fractoscope-http-"))
    try:
        path, media_type = await run(write, directory)
        response = web.StreamResponse(headers={
            **_CORS, "Content-Type": media_type, "Content-Length": str(path.stat().st_size), "Cache-Control": "no-store",
            "Content-Disposition": f'attachment; filename="{path.name}"',
        })
        await response.prepare(request)
        if request.method != "HEAD":
            with open(path, "rb") as source:
                while chunk := source.read(_CHUNK_BYTES):
                    await response.write(chunk)
        await response.write_eof()
        return response
    finally:
        shutil.rmtree(directory, ignore_errors=True)


def _summary(specimen) -> dict:
    return json_format.MessageToDict(specimen_message(specimen), preserving_proto_field_name=True, always_print_fields_with_no_presence=True)


def _tile(message: tiles_pb2.Tile) -> dict:
    return {"uri": message.uri, "roi": message.roi, "magnification": message.magnification, "zoom": wire.zoom_name(message.zoom),
            "geometric_error_m": message.geometric_error_m}


# Uploads ###########################################################################################


class Uploads:
    """Uploaded manifests and their images under `root/{upload_id}/`, each written in a staging
    folder and renamed into place once complete and valid: never half of one."""

    def __init__(self, root: Path, max_bytes: int):
        self.root = Path(root)
        self.max_bytes = max_bytes
        self.root.mkdir(parents=True, exist_ok=True)
        for leftover in self.root.glob(".staging-*"):
            shutil.rmtree(leftover, ignore_errors=True)

    async def receive(self, request: web.Request) -> tuple[str, str, list[tiles_pb2.RoiSpec]]:
        """Stores a multipart upload (a `manifest` part, `images` parts with the file names the
        manifest gives, optionally `request_id`); returns its id and the manifest's specimen id
        and ROIs."""
        reader = await _multipart(request, limit_bytes=self.max_bytes)
        upload_id = uuid.uuid4().hex
        staging = self.root / f".staging-{upload_id}"
        staging.mkdir()
        try:
            await self._receive_parts(reader, staging)
            specimen_id, rois = await _off_loop(self._parse, staging)
            staging.rename(self.root / upload_id)
        finally:
            shutil.rmtree(staging, ignore_errors=True)
        return upload_id, specimen_id, rois

    async def _receive_parts(self, reader, staging: Path) -> None:
        total, fields = 0, {}
        async for part in _parts(reader):
            name = part.name or ""
            if name in ("manifest", "request_id"):
                target, label = staging / f"{name}.field", name
            elif name == "images":
                if not _FILE_NAME.fullmatch(part.filename or ""):
                    raise InvalidInputError(f"images[{part.filename!r}]", "file names are 1 to 128 of A-Z a-z 0-9 . _ -, not starting with . _ -")
                target, label = staging / "images" / part.filename, f"images[{part.filename!r}]"
                target.parent.mkdir(exist_ok=True)
            else:
                raise InvalidInputError(name or "body", "is not a part of an upload (manifest, request_id, images)")
            if target.exists():
                raise InvalidInputError(label, "is given more than once")
            with open(target, "wb") as out:
                while chunk := await _chunk(part):
                    total += len(chunk)
                    if total > self.max_bytes:
                        raise ApiError(HTTPStatus.REQUEST_ENTITY_TOO_LARGE, f"the upload exceeds {self.max_bytes} bytes", label)
                    out.write(chunk)
            fields[name] = True
        if "manifest" not in fields:
            raise InvalidInputError("manifest", "is required: the specimen manifest (JSON)")

    def _parse(self, directory: Path) -> tuple[str, list[tiles_pb2.RoiSpec]]:
        def read_image(name: str, field_name: str) -> bytes:
            path = directory / "images" / name
            if not _FILE_NAME.fullmatch(name) or not path.is_file():
                raise InvalidInputError(field_name, f"{name!r} was not uploaded (send each image as a file part named as in the manifest)")
            return path.read_bytes()

        specimen_id, rois = parse_manifest((directory / "manifest.field").read_bytes(), read_image, source="the uploaded manifest")
        validate_id(specimen_id, field="manifest.specimen")
        try:  # what the build would refuse, refused before a job is accepted
            checked_rois(rois)
        except InvalidInputError as error:  # named as the manifest names it
            raise InvalidInputError(manifest_field(error.field), error.message) from None
        return specimen_id, rois

    def load(self, upload_id: str) -> tuple[str, list[tiles_pb2.RoiSpec]]:
        if not re.fullmatch(r"[0-9a-f]{32}", upload_id or ""):
            raise InvalidInputError("upload_id", "is not an upload id (32 hexadecimal digits)")
        directory = self.root / upload_id
        if not directory.is_dir():
            raise NotFoundError(f"no upload {upload_id!r}", field="upload_id")
        return self._parse(directory)

    def field(self, upload_id: str, name: str) -> str:
        path = self.root / upload_id / f"{name}.field"
        return path.read_text(errors="replace")[:128] if path.is_file() else ""


# Jobs ##############################################################################################


@dataclass
class Job:
    """A reconstruction submitted over HTTP and what became of it."""

    id: str
    specimen_id: str
    request_id: str
    upload_id: str
    state: str = "queued"  # queued, running, succeeded, failed
    fraction: float = 0.0
    message: str = ""
    created_s: float = field(default_factory=time.time)
    finished_s: float | None = None
    specimen: dict | None = None
    error: dict | None = None

    def as_dict(self) -> dict:
        return {
            "job_id": self.id, "specimen_id": self.specimen_id, "request_id": self.request_id, "upload_id": self.upload_id,
            "state": self.state, "progress": {"fraction": self.fraction, "message": self.message},
            "created": _iso(self.created_s), "finished": _iso(self.finished_s) if self.finished_s else None,
            "specimen": self.specimen, "error": self.error,
        }


class Analyses:
    """The API's analyses (roughness, profiles, height statistics, exports, reports) on `workers`
    threads of their own, so lookups, jobs and the viewer's tiles never wait behind them (twelve
    roughness queries at once once held a specimen lookup for 77 s); more than `queue_limit`
    waiting get 429. Used from the event loop's thread only."""

    def __init__(self, *, workers: int, queue_limit: int):
        self.limit = workers + queue_limit
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fractoscope-http-analysis")
        self._under_way = 0

    async def run(self, function, *args):
        """`function(*args)` on the analysis threads, or 429 when `limit` are under way."""
        if self._under_way >= self.limit:
            raise ApiError(HTTPStatus.TOO_MANY_REQUESTS, f"{self._under_way} analyses are running or waiting; retry later", None,
                           **{"Retry-After": "5"})
        self._under_way += 1
        try:
            return await asyncio.get_running_loop().run_in_executor(self._pool, function, *args)
        finally:
            self._under_way -= 1

    def close(self) -> None:
        """Waiting analyses never start; returns once running ones end."""
        self._pool.shutdown(wait=True, cancel_futures=True)


class BuildJobs:
    """Builds submitted over HTTP, each a ReconstructSpecimen call on `address` (this server's gRPC
    endpoint) with the submitter's token, at most `workers` at once and `queue_limit` waiting
    (more get 429); the last `keep` jobs stay queryable."""

    def __init__(self, address: str | None, *, workers: int, queue_limit: int, keep: int = 1000, timeout_s: float = 3600.0):
        self.address = address
        self.queue_limit = queue_limit
        self.timeout_s = timeout_s
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="fractoscope-http-build")
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._keep = keep
        self._lock = threading.Lock()
        self._calls: set = set()  # the ReconstructSpecimen calls under way, cancelled by close()

    @property
    def enabled(self) -> bool:
        return self.address is not None

    def submit(self, specimen_id: str, rois, *, request_id: str, token: str | None, upload_id: str) -> Job:
        with self._lock:
            waiting = sum(job.state == "queued" for job in self._jobs.values())
            if waiting >= self.queue_limit:
                raise ApiError(HTTPStatus.TOO_MANY_REQUESTS, f"{waiting} builds are waiting; retry later", None, **{"Retry-After": "30"})
            job = Job(uuid.uuid4().hex, specimen_id, request_id, upload_id)
            self._jobs[job.id] = job
            while len(self._jobs) > self._keep:
                self._jobs.popitem(last=False)
        self._pool.submit(self._run, job, rois, token)
        return job

    def get(self, job_id: str) -> Job:
        if not re.fullmatch(r"[0-9a-f]{32}", job_id):
            raise InvalidInputError("job_id", "is not a job id (32 hexadecimal digits)")
        with self._lock:
            job = self._jobs.get(job_id)
        if job is None:
            raise NotFoundError(f"no job {job_id!r}", field="job_id")
        return job

    def close(self) -> None:
        """Queued jobs never start; running ones are cancelled; returns once their threads end."""
        self._pool.shutdown(wait=False, cancel_futures=True)
        with self._lock:
            calls = list(self._calls)
        for call in calls:
            call.cancel()
        self._pool.shutdown(wait=True)

    def _run(self, job: Job, rois, token: str | None) -> None:
        job.state = "running"
        request = tiles_pb2.ReconstructSpecimenRequest(specimen_id=job.specimen_id, rois=rois, request_id=job.request_id)
        call = None
        try:
            with open_channel(self.address, token=token) as channel, raised_as_client_errors():
                call = tiles_pb2_grpc.TileServiceStub(channel).ReconstructSpecimen(request, timeout=self.timeout_s)
                with self._lock:
                    self._calls.add(call)
                for response in call:
                    if response.HasField("progress"):
                        job.fraction, job.message = response.progress.fraction, response.progress.message
                    else:
                        job.specimen = json_format.MessageToDict(response.specimen, preserving_proto_field_name=True,
                                                                 always_print_fields_with_no_presence=True)
            job.state, job.fraction = ("succeeded", 1.0) if job.specimen is not None else ("failed", job.fraction)
            if job.specimen is None:
                job.error = {"error": "the build ended without a specimen", "field": None, "code": "INTERNAL"}
        except ClientError as error:
            job.state = "failed"
            job.error = {"error": str(error), "field": error.field, "code": error.code.name}
        finally:
            job.finished_s = time.time()
            with self._lock:
                self._calls.discard(call)


def _iso(seconds: float) -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime(seconds))


