"""The HTTP/JSON API under /api/, described by the OpenAPI 3.1 document at /api/openapi.json
(`openapi.document`): specimens, reconstructions from uploads and their jobs, roughness,
profiles, zoom, exports and the measurement report.

Every error is JSON, {"error": message, "field": the input at fault or null}, with a 4xx status
for anything the caller can fix, 507 when the disk is full, and 500 naming only the exception's
class for what was not foreseen (its traceback goes to the log). Tokens and scopes are gRPC's
(see auth): read tokens query, write tokens also upload, build and delete (uploads and
specimens); they are checked before a request's body is read.
Builds run as ReconstructSpecimen calls on this server's own gRPC endpoint with the submitter's
token, so they follow the same path, limits and scopes as any gRPC build.
"""

from __future__ import annotations

import functools
import logging
import re
from dataclasses import dataclass
from http import HTTPStatus
from pathlib import Path

import cv2
from aiohttp import web
from google.protobuf import json_format

from fractoscope import report
from fractoscope.errors import FractoscopeError, InvalidInputError
from fractoscope.formats.exports import EXPORT_FORMATS
from fractoscope.http import openapi
from fractoscope.http.build_jobs import Analyses, BuildJobs, FolderRecords
from fractoscope.http.inputs import (
    CHAIN_PARAMETERS,
    NPZ_BYTES_PER_POINT,
    PROFILE_CHAIN_PARAMETERS,
    area_of,
    chain_request,
    choice,
    export_options,
    json_body,
    npz_height_map,
    npz_shape,
    number,
    numbers,
    query_parameters,
    small_form,
)
from fractoscope.http.responses import (
    CORS_HEADERS,
    JSON_TYPE,
    ApiError,
    failure_response,
    file_response,
    json_error,
    json_response,
    no_content,
    off_loop,
    unexpected_response,
)
from fractoscope.http.uploads import DEFAULT_MAX_UPLOAD_BYTES, Uploads
from fractoscope.rpc import wire
from fractoscope.rpc.limits import MAX_REQUEST_ID_CHARS
from fractoscope.runtime.auth import READ, WRITE, Grant, TokenTable
from fractoscope.runtime.budget import Budget, Cost
from fractoscope.specimen import exports, quadtree, queries
from fractoscope.specimen.model import validate_id
from fractoscope.stereo.geometry import validate_pixel_size_um
from fractoscope.store.base import StoredSpecimens
from fractoscope.tiles import admission
from fractoscope.tiles.messages import (
    profile_response,
    request_digest,
    roughness_response,
    specimen_message,
    tile_message,
)
from fractoscope.v1 import tiles_pb2

_log = logging.getLogger(__name__)
# The specimen list's pictures: the overview's SEM image this wide, px.
THUMBNAIL_WIDTH_PX = 160


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
    _Route("DELETE", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)"), "delete_specimen", WRITE),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/roughness"), "roughness", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/profile"), "profile", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/heights"), "heights", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/zoom"), "zoom", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/export"), "export_area", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/report"), "report", READ),
    _Route("GET", re.compile(r"/api/specimens/(?P<specimen_id>[^/]+)/thumbnail"), "thumbnail", READ),
    _Route("POST", re.compile(r"/api/exports"), "export_height_map", READ),
    _Route("POST", re.compile(r"/api/uploads"), "upload", WRITE),
    _Route("DELETE", re.compile(r"/api/uploads/(?P<upload_id>[^/]+)"), "delete_upload", WRITE),
    _Route("GET", re.compile(r"/api/jobs"), "list_jobs", READ),
    _Route("POST", re.compile(r"/api/jobs"), "submit_job", WRITE),
    _Route("GET", re.compile(r"/api/jobs/(?P<job_id>[^/]+)"), "get_job", READ),
]


class JsonApi:
    """The API's request handling. `grpc_address` is this server's gRPC endpoint, which builds go
    to (None: builds are refused with 503); uploads are kept under `uploads_root`; analyses,
    exports, reports and the checks of uploads are admitted by `budget` (shared with gRPC)."""

    def __init__(
        self,
        store: StoredSpecimens,
        tokens: TokenTable,
        *,
        grpc_address: str | None,
        uploads_root: Path,
        max_upload_bytes: int = DEFAULT_MAX_UPLOAD_BYTES,
        build_workers: int = 2,
        queued_builds: int = 8,
        budget: Budget,
    ):
        self.store = store
        self.tokens = tokens
        self.budget = budget
        self.analyses = Analyses(budget)
        self.uploads = Uploads(uploads_root, max_upload_bytes, analyses=self.analyses, objects=store.objects)
        records = store.objects or FolderRecords(uploads_root.parent)  # a folder store's: beside its uploads
        self.jobs = BuildJobs(grpc_address, workers=build_workers, queue_limit=queued_builds, objects=records)

    async def handle(self, request: web.Request) -> web.StreamResponse:
        try:
            route, match = _route(request)
            grant = self._authorize(request, route.access)
            return await getattr(self, route.handler)(request, match, grant)
        except ApiError as error:
            return json_error(error.status, error.message, error.field, **error.headers)
        except FractoscopeError as error:
            return failure_response(error)
        except Exception as error:  # not raised on purpose: JSON all the same, the traceback in our log only
            if request.writer.output_size:  # a file half sent: aiohttp's closing the connection tells the client
                raise
            _log.error("%s %r failed", request.method, request.path, exc_info=error)
            return unexpected_response(error)

    def _authorize(self, request: web.Request, access: str) -> Grant | None:
        """The caller's grant, checked against the scope the route needs before anything is read."""
        if not self.tokens.enabled or not access:
            return None
        offered = request.headers.get("Authorization") or "Bearer " + request.query.get("token", "")
        grant = self.tokens.grant(offered)
        if grant is None:
            raise ApiError(
                HTTPStatus.UNAUTHORIZED,
                "a valid bearer token is required",
                "authorization",
                **{"WWW-Authenticate": "Bearer"},
            )
        if access == WRITE and grant.access != WRITE:
            raise ApiError(HTTPStatus.FORBIDDEN, f"client {grant.client!r} may only read", "authorization")
        return grant

    async def openapi(self, request, match, grant):
        return json_response(openapi.document())

    async def list_specimens(self, request, match, grant):
        query_parameters(request, set())
        return json_response(await off_loop(lambda: [_summary(self.store.load(i)) for i in self.store.ids()]))

    async def get_specimen(self, request, match, grant):
        query_parameters(request, set())
        return json_response(await off_loop(lambda: _summary(self._specimen(match))))

    async def delete_specimen(self, request, match, grant):
        query_parameters(request, set())
        await off_loop(self.store.delete, match["specimen_id"])
        return no_content()

    async def roughness(self, request, match, grant):
        query = query_parameters(request, {"roi", "region", *CHAIN_PARAMETERS})
        area, chain = area_of(query), chain_request(query)
        area["roi"] = area["roi"] or None
        specimen = await off_loop(self._specimen, match)

        def answer():
            analysis = queries.roughness_of(specimen, **area, chain=chain)
            return wire.response_to_roughness(roughness_response(analysis, chain))

        cost = await off_loop(lambda: admission.roughness_cost(specimen, **area))
        return json_response(await self.analyses.run(request, cost, answer))

    async def profile(self, request, match, grant):
        query = query_parameters(request, {"from", "to", "magnification", "spacing_um", *PROFILE_CHAIN_PARAMETERS})
        points = [numbers(query, "from", 2), numbers(query, "to", 2)]
        magnification = number(query, "magnification", default=0.0, minimum=0.0)
        spacing_um = number(query, "spacing_um", default=0.0, minimum=0.0)
        chain = chain_request(query)

        def answer():
            try:
                found = queries.profile_along(
                    self._specimen(match), points, spacing_um=spacing_um, magnification=magnification, chain=chain
                )
            except InvalidInputError as error:  # the line's points are the query's from and to
                if error.field.split("[")[0] != "points":
                    raise
                raise InvalidInputError("to" if error.field == "points[1]" else "from", error.message) from None
            names = found.sources + [""]
            response = profile_response(found)
            return {
                "distance_um": found.distance_um.tolist(),
                "z_um": found.z_um.tolist(),
                "source": [names[i] for i in found.source_index.tolist()],
                "parameters": wire.message_to_profile_parameters(response.parameters) if found.parameters else None,
                "roughness_um": found.r_um.tolist() if found.r_um is not None else None,
                "chain": {
                    **wire.chain_to_dict(response.chain),
                    "cutoffs_from_iso_table": response.cutoffs_from_iso_table,
                    "spacing_within_iso": response.spacing_within_iso,
                }
                if found.roughness
                else None,
            }

        return json_response(await self.analyses.run(request, admission.profile_cost(), answer))

    async def heights(self, request, match, grant):
        region = numbers(query_parameters(request, {"region"}), "region", 4)
        specimen = await off_loop(self._specimen, match)
        cost = await off_loop(admission.heights_cost, specimen, region)
        return json_response(await self.analyses.run(request, cost, queries.height_statistics, specimen, region))

    async def zoom(self, request, match, grant):
        query = query_parameters(request, {"region", "magnification"})
        region = queries.checked_region(numbers(query, "region", 4))
        magnification = number(query, "magnification")

        def answer():
            specimen = self._specimen(match)
            cell_um = specimen.pixel_size_at_magnification(queries.positive_input(magnification, "magnification"))
            chosen = quadtree.tiles_in_region(specimen.layout, specimen.tiles, region, cell_um=cell_um)
            return {
                "tiles": [_tile(tile_message(specimen, record, upsampled=upsampled)) for record, upsampled in chosen]
            }

        return json_response(await off_loop(answer))

    async def export_area(self, request, match, grant):
        query = query_parameters(request, {"format", "roi", "region", "pixel_size_um", "solid", "units"})
        options = export_options(query)
        area = area_of(query)
        specimen = await off_loop(self._specimen, match)

        def write(directory: Path) -> tuple[Path, str]:
            exported = exports.export_area(specimen, directory, **area, **options)
            return exported.path, EXPORT_FORMATS[exported.file_format].media_type

        cost = await off_loop(
            lambda: admission.area_export_cost(
                specimen, **area, **{key: options[key] for key in ("pixel_size_um", "file_format", "solid")}
            )
        )
        return await self._file(request, cost, write)

    async def export_height_map(self, request, match, grant):
        query_parameters(request, set())
        form = await small_form(
            request,
            files={"height_map"},
            fields={"format", "map_pixel_size_um", "pixel_size_um", "solid", "units"},
            limit_bytes=self.uploads.max_bytes,
        )
        options = export_options(form)
        export_pixel_size_um = options.pop("pixel_size_um")
        shape = await off_loop(npz_shape, form.get("height_map"))  # from its headers: nothing decoded yet
        cost = admission.map_export_cost(
            shape,
            file_format=options["file_format"],
            solid=options["solid"],
            source_bytes_per_point=NPZ_BYTES_PER_POINT,
        )

        def write(directory: Path) -> tuple[Path, str]:
            # Decoded here, on the analysis threads: a map near the pixel limit takes seconds and
            # gigabytes, which neither the event loop nor requests queued behind it should wait on or hold.
            z_um, sigma_um, stored = npz_height_map(form.get("height_map"))
            if stored is not None:
                map_pixel_size_um = validate_pixel_size_um(stored, field="height_map.pixel_size_um")
            else:
                map_pixel_size_um = validate_pixel_size_um(number(form, "map_pixel_size_um"), field="map_pixel_size_um")
            exported = exports.export_height_map(
                directory,
                z_um,
                pixel_size_um=map_pixel_size_um,
                sigma_um=sigma_um,
                export_pixel_size_um=export_pixel_size_um,
                **options,
            )
            return exported.path, EXPORT_FORMATS[exported.file_format].media_type

        return await self._file(request, cost, write)

    async def report(self, request, match, grant):
        query = query_parameters(request, {"format", "roi", "region"})
        file_format = choice(query, "format", tuple(report.MEDIA_TYPES), default="html")
        area = area_of(query)
        specimen = await off_loop(self._specimen, match)

        def write(directory: Path) -> tuple[Path, str]:
            path = report.write_report(specimen, directory, file_format=file_format, **area)
            return path, report.MEDIA_TYPES[file_format]

        return await self._file(request, await off_loop(lambda: admission.report_cost(specimen, **area)), write)

    async def _file(self, request: web.Request, cost: Cost, write) -> web.StreamResponse:
        """`write`'s file (see file_response), admitted as `cost`: its disk held until it is sent."""
        with self.budget.scratch(cost):
            run = functools.partial(self.analyses.run, request, cost)
            return await file_response(request, run, write, scratch_root=self.store.scratch_root)

    async def upload(self, request, match, grant):
        query_parameters(request, set())
        upload_id, specimen_id, rois = await self.uploads.receive(request)
        return json_response(
            {"upload_id": upload_id, "specimen_id": specimen_id, "rois": [roi.id for roi in rois]},
            status=HTTPStatus.CREATED,
            Location=f"/api/uploads/{upload_id}",
        )

    async def delete_upload(self, request, match, grant):
        query_parameters(request, set())
        await off_loop(self.uploads.delete, match["upload_id"])
        return no_content()

    async def submit_job(self, request, match, grant):
        query_parameters(request, set())
        if not self.jobs.enabled:
            raise ApiError(
                HTTPStatus.SERVICE_UNAVAILABLE,
                "this endpoint does not run builds (it has no gRPC endpoint to send them to)",
            )
        if request.content_type == "multipart/form-data":
            upload_id, specimen_id, rois = await self.uploads.receive(request)
            request_id = self.uploads.field(upload_id, "request_id")
        elif request.content_type == JSON_TYPE:
            body = await json_body(request, limit_bytes=64 * 1024)
            unknown = sorted(set(body) - {"upload_id", "request_id"})
            if unknown:
                raise InvalidInputError(
                    unknown[0] or "body", f"{unknown[0]!r} is not a field of a job request (upload_id, request_id)"
                )
            upload_id, request_id = body.get("upload_id"), body.get("request_id", "")
            if not isinstance(upload_id, str):
                raise InvalidInputError("upload_id", "is required (a string)")
            if not isinstance(request_id, str) or len(request_id) > MAX_REQUEST_ID_CHARS:
                raise InvalidInputError("request_id", f"must be a string of at most {MAX_REQUEST_ID_CHARS} characters")
            specimen_id, rois = await off_loop(self.uploads.load, upload_id)
        else:
            raise ApiError(
                HTTPStatus.UNSUPPORTED_MEDIA_TYPE,
                'send application/json ({"upload_id": ...}) or multipart/form-data (manifest and images)',
                "content-type",
            )
        if request_id:  # a reused id is refused now, not in a job that fails later
            build = tiles_pb2.ReconstructSpecimenRequest(specimen_id=specimen_id, rois=rois)
            await off_loop(self.store.built_by, specimen_id, request_id, request_digest(build))
        token = (
            (request.headers.get("Authorization") or "").removeprefix("Bearer ").strip()
            or request.query.get("token")
            or None
        )
        job = self.jobs.submit(specimen_id, rois, request_id=request_id or "", token=token, upload_id=upload_id)
        return json_response(job.as_dict(), status=HTTPStatus.ACCEPTED, Location=f"/api/jobs/{job.id}")

    async def list_jobs(self, request, match, grant):
        query_parameters(request, set())
        return json_response({"jobs": [job.as_dict() for job in await off_loop(self.jobs.listed)]})

    async def thumbnail(self, request, match, grant):
        query_parameters(request, set())
        png = await off_loop(lambda: _thumbnail_png(self._specimen(match)))
        headers = {"Content-Type": "image/png", "Cache-Control": "no-cache"}
        disposition = f'inline; filename="{match["specimen_id"]}-thumbnail.png"'
        return web.Response(body=png, headers={**CORS_HEADERS, **headers, "Content-Disposition": disposition})

    async def get_job(self, request, match, grant):
        query_parameters(request, set())
        return json_response(self.jobs.get(match["job_id"]).as_dict())

    def _specimen(self, match):
        return self.store.load(validate_id(match["specimen_id"], field="specimen_id"))


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
        raise ApiError(
            HTTPStatus.METHOD_NOT_ALLOWED,
            f"{request.method} is not allowed here; use {', '.join(allowed)}",
            "method",
            Allow=", ".join(allowed),
        )
    raise ApiError(HTTPStatus.NOT_FOUND, f"no API resource {request.path}", "path")


def _summary(specimen) -> dict:
    return json_format.MessageToDict(
        specimen_message(specimen), preserving_proto_field_name=True, always_print_fields_with_no_presence=True
    )


def _thumbnail_png(specimen, width_px: int = THUMBNAIL_WIDTH_PX) -> bytes:
    """The overview's SEM image `width_px` wide (area-averaged, aspect kept) as a PNG."""
    texture = specimen.heights(specimen.rois[0].id).texture
    rows, cols = texture.shape
    size = (min(width_px, cols), max(1, round(rows * min(width_px, cols) / cols)))
    _, encoded = cv2.imencode(".png", cv2.resize(texture, size, interpolation=cv2.INTER_AREA))
    return encoded.tobytes()


def _tile(message: tiles_pb2.Tile) -> dict:
    return {
        "uri": message.uri,
        "roi": message.roi,
        "magnification": message.magnification,
        "zoom": wire.zoom_name(message.zoom),
        "geometric_error_m": message.geometric_error_m,
    }
