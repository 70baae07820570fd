"""TileService: multi-scale specimens built on the matching and meshing services, and queries."""

from __future__ import annotations

import contextlib
import functools
import logging
import threading
from collections.abc import Callable, Iterator
from typing import Protocol

import grpc
import numpy as np

from fractoscope import report
from fractoscope.errors import (
    AlreadyExistsError,
    InvalidInputError,
    error_of_code,
)
from fractoscope.formats.exports import EXPORT_FORMATS
from fractoscope.mesh.pipeline import EncodedTile, MeshReport
from fractoscope.meshing import messages as rpc_meshing
from fractoscope.progress import ProgressCallback, silent
from fractoscope.reconstruction.build import MeasuredHeights, RoiRequest, reconstruct_specimen
from fractoscope.rpc import calls, wire
from fractoscope.rpc.channel import open_channel
from fractoscope.rpc.status import ClientError, abort_on_error, raised_as_client_errors
from fractoscope.runtime import budget
from fractoscope.runtime.caches import BoundedCache
from fractoscope.runtime.jobs import Job, JobRunner
from fractoscope.specimen import quadtree
from fractoscope.specimen import queries as specimen_queries
from fractoscope.specimen.model import Specimen, validate_id
from fractoscope.specimen.quadtree import MESH_MARGIN_CELLS, TileSamples
from fractoscope.stereo.pipeline import HeightMapResult
from fractoscope.store.base import StoredSpecimens
from fractoscope.store.scratch import scratch_folder
from fractoscope.tiles import admission
from fractoscope.tiles import messages as rpc_tiles
from fractoscope.v1 import (
    common_pb2,
    matching_pb2,
    matching_pb2_grpc,
    meshing_pb2,
    meshing_pb2_grpc,
    tiles_pb2,
    tiles_pb2_grpc,
)

_log = logging.getLogger("fractoscope.tiles")
GET_TILE_METHOD = "/fractoscope.v1.TileService/GetTile"


class LocalMatching(Protocol):
    """The matching service of this process, called in-process (see MatchingServicer)."""

    def peak_bytes(self, request: matching_pb2.ComputeHeightMapRequest) -> int: ...

    def height_map(
        self, request: matching_pb2.ComputeHeightMapRequest, job: Job, progress: ProgressCallback
    ) -> tuple[HeightMapResult, np.ndarray]: ...


class LocalMeshing(Protocol):
    """The meshing service of this process, called in-process (see MeshingServicer)."""

    def mesh(
        self, request: meshing_pb2.BuildMeshRequest, progress: ProgressCallback
    ) -> tuple[list[EncodedTile], MeshReport]: ...


# One ROI's heights for a build: its ComputeHeightMap request, the build's job, the progress callback.
MeasureHeights = Callable[[matching_pb2.ComputeHeightMapRequest, Job, ProgressCallback], MeasuredHeights]
# One tile's GLB for a build: its BuildMesh request (one level), the build's job.
MeshTile = Callable[[meshing_pb2.BuildMeshRequest, Job], bytes]


class BuildMatching(Protocol):
    """How builds match their ROIs, chosen at start-up: in this process or on a matching service."""

    def peak_bytes_here(self, request: matching_pb2.ComputeHeightMapRequest) -> int:
        """The estimated peak memory of matching `request` in this process (0: it is matched elsewhere)."""

    def connected(self) -> contextlib.AbstractContextManager[MeasureHeights]:
        """Matching for the length of one build."""


class BuildMeshing(Protocol):
    """How builds mesh their tiles, chosen at start-up: in this process or on a meshing service."""

    def connected(self) -> contextlib.AbstractContextManager[MeshTile]:
        """Meshing for the length of one build."""


class _InProcessMatching:
    """The matching service of this process."""

    def __init__(self, local: LocalMatching):
        self._local = local

    def peak_bytes_here(self, request: matching_pb2.ComputeHeightMapRequest) -> int:
        return self._local.peak_bytes(request)

    def connected(self) -> contextlib.AbstractContextManager[MeasureHeights]:
        return contextlib.nullcontext(self._measure)

    def _measure(
        self, request: matching_pb2.ComputeHeightMapRequest, job: Job, progress: ProgressCallback
    ) -> MeasuredHeights:
        result, texture = self._local.height_map(request, job, progress)
        return MeasuredHeights(result.z_um, texture, result.report["pixel_size_um"], result.report, result.sigma_um)


class _RemoteMatching:
    """The matching service at `address`, over a channel opened for each build (which reads
    FRACTO_TOKEN then); each call gets the deadline the build's callers still wait, at most
    `call_timeout_s`, and is cancelled with the build."""

    def __init__(self, address: str, call_timeout_s: float):
        self._address, self._call_timeout_s = address, call_timeout_s

    def peak_bytes_here(self, request: matching_pb2.ComputeHeightMapRequest) -> int:
        return 0

    @contextlib.contextmanager
    def connected(self) -> Iterator[MeasureHeights]:
        with open_channel(self._address) as channel:
            yield functools.partial(self._measure, matching_pb2_grpc.MatchingServiceStub(channel))

    def _measure(
        self,
        matching: matching_pb2_grpc.MatchingServiceStub,
        request: matching_pb2.ComputeHeightMapRequest,
        job: Job,
        progress: ProgressCallback,
    ) -> MeasuredHeights:
        with _calling("matching", self._address):
            call = matching.ComputeHeightMap(request, timeout=job.time_remaining_s(at_most_s=self._call_timeout_s))
            job.on_cancel(call.cancel)
            heights = calls.read_height_map(call, progress)
        return MeasuredHeights(heights.z_um, heights.texture, heights.pixel_size_um, heights.report, heights.sigma_um)


class _InProcessMeshing:
    """The meshing service of this process."""

    def __init__(self, local: LocalMeshing):
        self._local = local

    def connected(self) -> contextlib.AbstractContextManager[MeshTile]:
        return contextlib.nullcontext(self._mesh)

    def _mesh(self, request: meshing_pb2.BuildMeshRequest, job: Job) -> bytes:
        tiles, _ = self._local.mesh(request, silent)
        return tiles[0].glb


class _RemoteMeshing:
    """The meshing service at `address`, over a channel per build (as _RemoteMatching); each call
    gets the deadline the build's callers still wait, at most `call_timeout_s`."""

    def __init__(self, address: str, call_timeout_s: float):
        self._address, self._call_timeout_s = address, call_timeout_s

    @contextlib.contextmanager
    def connected(self) -> Iterator[MeshTile]:
        with open_channel(self._address) as channel:
            yield functools.partial(self._mesh, meshing_pb2_grpc.MeshingServiceStub(channel))

    def _mesh(
        self, meshing: meshing_pb2_grpc.MeshingServiceStub, request: meshing_pb2.BuildMeshRequest, job: Job
    ) -> bytes:
        with _calling("meshing", self._address):
            tiles, _ = calls.read_mesh(
                meshing.BuildMesh(request, timeout=job.time_remaining_s(at_most_s=self._call_timeout_s)), None
            )
        return tiles[0].glb


class _BuildClaims:
    """The content (request_digest) each request id of a specimen is being built from, claimed
    while calls follow its build or its work runs: a concurrent request with that id and other
    content is refused instead of joining the build. A request without an id claims nothing."""

    def __init__(self):
        self._lock = threading.Lock()
        self._held: dict[tuple[str, str], tuple[str, int]] = {}  # (specimen_id, request_id): (digest, claims)

    @contextlib.contextmanager
    def claimed(self, specimen_id: str, request_id: str, digest: str) -> Iterator[None]:
        if not request_id:
            yield
            return
        key = (specimen_id, request_id)
        with self._lock:
            held, count = self._held.get(key, (digest, 0))
            if held != digest:
                raise AlreadyExistsError(
                    f"request_id {request_id!r} names a build of specimen {specimen_id!r} under way with other "
                    "content; give this request a new request_id",
                    field="request_id",
                )
            self._held[key] = (digest, count + 1)
        try:
            yield
        finally:
            with self._lock:
                held, count = self._held.pop(key)
                if count > 1:
                    self._held[key] = (held, count - 1)


class TileServicer(tiles_pb2_grpc.TileServiceServicer):
    """Thin wrappers over reconstruction, the specimen store and the analysis modules.

    Reconstructions are `builds` jobs (see jobs), checked against the memory budget first.
    Concurrent calls with one request id follow one job; a request id already used for other
    content (request_digest), stored or under way, is refused (AlreadyExistsError). Matching and
    meshing run in this process when it serves them (`local_matching`, `local_meshing`), else on the services at
    `matching_address` and `meshing_address` (gRPC targets; a `dns:///` name of several replicas
    is balanced round-robin), each call with the deadline the build's callers still wait, at most
    `call_timeout_s`, and cancelled with the build.

    GetTile is answered by `get_tile_serialized`, which the server routes there (SerializedGetTile);
    up to `tile_response_cache_bytes` of serialized tile responses are kept."""

    def __init__(
        self,
        store: StoredSpecimens,
        *,
        builds: JobRunner,
        budget: budget.Budget,
        local_matching: LocalMatching | None = None,
        local_meshing: LocalMeshing | None = None,
        matching_address: str | None = None,
        meshing_address: str | None = None,
        call_timeout_s: float = 1800.0,
        tile_response_cache_bytes: int = 256 * 1024 * 1024,
    ):
        if (local_matching is None) == (matching_address is None) or (local_meshing is None) == (
            meshing_address is None
        ):
            raise ValueError(
                "the tile service needs matching and meshing, each served by this process or given an address "
                "(--matching-address, --meshing-address)"
            )
        self.store = store
        self._builds, self._budget = builds, budget
        self.matching_address = matching_address
        self.meshing_address = meshing_address
        self._matching: BuildMatching = (
            _InProcessMatching(local_matching)
            if matching_address is None
            else _RemoteMatching(matching_address, call_timeout_s)
        )
        self._meshing: BuildMeshing = (
            _InProcessMeshing(local_meshing)
            if meshing_address is None
            else _RemoteMeshing(meshing_address, call_timeout_s)
        )
        self._tile_responses: BoundedCache[bytes] = BoundedCache(tile_response_cache_bytes, size=len)
        self._claims = _BuildClaims()

    @abort_on_error
    def ReconstructSpecimen(self, request, context):
        specimen_id = validate_id(request.specimen_id, field="specimen_id")
        rpc_meshing.unmeasured_of(request.unmeasured)  # checked before it takes a place in the queue
        digest = rpc_tiles.request_digest(request) if request.request_id else ""
        stored = self._stored(specimen_id, request.request_id, digest)
        if stored is None:
            rois, height_requests, shapes = rpc_tiles.checked_rois(
                request.rois, request.request_id
            )  # before it takes a place in the queue
            estimate = self._estimate(height_requests, shapes)
            rows, cols = max(shapes, key=lambda shape: shape[0] * shape[1])
            self._budget.check(
                estimate, f"specimen {specimen_id!r} ({len(rois)} ROIs, the largest of {cols} x {rows} pixels)"
            )
            key = (specimen_id, request.request_id) if request.request_id else None

            def work(job: Job) -> Specimen:
                with self._budget.held(estimate):
                    return self._reconstruct(request, digest, rois, height_requests, job)

            with self._claims.claimed(specimen_id, request.request_id, digest):
                for event in self._builds.follow(context, work, key=key):
                    if isinstance(event, common_pb2.Progress):
                        yield tiles_pb2.ReconstructSpecimenResponse(progress=event)
                    else:
                        stored = event
                        _log.info("specimen built", extra={"request_id": request.request_id})
        if stored is not None:
            yield tiles_pb2.ReconstructSpecimenResponse(specimen=rpc_tiles.specimen_message(stored))

    def _estimate(
        self, height_requests: list[matching_pb2.ComputeHeightMapRequest], shapes: list[tuple[int, int]]
    ) -> int:
        """A reconstruction's estimated peak memory (see budget); InvalidInputError names the ROI."""
        matched_here = []
        for index, height_request in enumerate(height_requests):
            with rpc_tiles.in_roi(index):
                matched_here.append(self._matching.peak_bytes_here(height_request))
        return budget.specimen_bytes(shapes, matched_here=matched_here)

    def _reconstruct(
        self,
        request: tiles_pb2.ReconstructSpecimenRequest,
        digest: str,
        rois: list[RoiRequest],
        height_requests: list[matching_pb2.ComputeHeightMapRequest],
        job: Job,
    ) -> Specimen:
        """Builds the specimen, unless an earlier job of its request id stored it meanwhile; its
        content stays claimed until the build ends, even if every call following it has gone."""
        stored = self._stored(request.specimen_id, request.request_id, digest)
        if stored is not None:
            return stored
        indices = {spec.id: index for index, spec in enumerate(request.rois)}
        with (
            self._claims.claimed(request.specimen_id, request.request_id, digest),
            self.store.building(request.specimen_id),  # one replica at a time builds a specimen
            self._matching.connected() as measure_heights,
            self._meshing.connected() as mesh,
        ):

            def measure(roi: RoiRequest, progress: ProgressCallback) -> MeasuredHeights:
                index = indices[roi.id]
                with rpc_tiles.in_roi(index):
                    return measure_heights(height_requests[index], job, progress)

            return reconstruct_specimen(
                request.specimen_id,
                rois,
                measure=measure,
                mesh_tile=lambda tile: mesh(_mesh_request(tile), job),
                store=self.store,
                request_id=request.request_id,
                request_digest=digest,
                progress=job.progress,
                unmeasured=rpc_meshing.unmeasured_of(request.unmeasured),
            )

    @abort_on_error
    def GetSpecimen(self, request, context):
        return tiles_pb2.GetSpecimenResponse(specimen=rpc_tiles.specimen_message(self.store.load(request.specimen_id)))

    @abort_on_error
    def ListSpecimens(self, request, context):
        return tiles_pb2.ListSpecimensResponse(
            specimens=[rpc_tiles.specimen_message(self.store.load(i)) for i in self.store.ids()]
        )

    @abort_on_error
    def GetTileset(self, request, context):
        return tiles_pb2.GetTilesetResponse(tileset_json=self.store.load(request.specimen_id).tileset_bytes)

    @abort_on_error
    def get_tile_serialized(self, request: tiles_pb2.GetTileRequest, context) -> bytes:
        """GetTile, answered with the serialized GetTileResponse: each tile's response is built and
        serialized once, then served from memory, which saves reading and serializing some 40 kB
        on every call."""
        specimen = self.store.load(request.specimen_id)

        def serialized() -> bytes:
            return rpc_tiles.with_tile(
                tiles_pb2.GetTileResponse(), specimen, specimen.tile_record(request.uri)
            ).SerializeToString()

        return self._tile_responses.get((specimen.id, specimen.version, request.uri), serialized)

    @abort_on_error
    def StreamView(self, request, context):
        specimen = self.store.load(request.specimen_id)
        region = rpc_tiles.region(request.region, "region")
        viewport_px = request.viewport_px or wire.DEFAULT_VIEWPORT_PX
        if not 1 <= viewport_px <= 65536:
            raise InvalidInputError("viewport_px", "must be 1 to 65536")
        for record in quadtree.tiles_for_view(specimen.layout, specimen.tiles, region, viewport_px=viewport_px):
            yield rpc_tiles.with_tile(tiles_pb2.StreamViewResponse(), specimen, record)

    @abort_on_error
    def Zoom(self, request, context):
        specimen = self.store.load(request.specimen_id)
        region = rpc_tiles.region(request.region, "region")
        cell_um = specimen.pixel_size_at_magnification(
            specimen_queries.positive_input(request.magnification, "magnification")
        )
        chosen = quadtree.tiles_in_region(specimen.layout, specimen.tiles, region, cell_um=cell_um)
        return tiles_pb2.ZoomResponse(
            tiles=[rpc_tiles.tile_message(specimen, record, upsampled=upsampled) for record, upsampled in chosen]
        )

    @abort_on_error
    def GetProfile(self, request, context):
        specimen = self.store.load(request.specimen_id)
        with self._admitted(admission.profile_cost(), context), rpc_tiles.chain_fields():
            found = specimen_queries.profile_along(
                specimen,
                [[p.x_um, p.y_um] for p in request.points],
                spacing_um=request.spacing_um,
                magnification=request.magnification,
                chain=rpc_tiles.profile_chain_request(request.chain),
            )
        return rpc_tiles.profile_response(found)

    @abort_on_error
    def GetRoughness(self, request, context):
        specimen = self.store.load(request.specimen_id)
        roi = request.roi or None
        region = rpc_tiles.region(request.region, "region") if request.WhichOneof("area") == "region" else None
        chain = rpc_tiles.chain_request(request.chain)
        cost = admission.roughness_cost(specimen, roi=roi, region_um=region)
        with self._admitted(cost, context), rpc_tiles.chain_fields():
            analysis = specimen_queries.roughness_of(specimen, roi=roi, region_um=region, chain=chain)
        return rpc_tiles.roughness_response(analysis, chain)

    @abort_on_error
    def Export(self, request, context):
        cost = admission.export_request_cost(request, self.store)
        with self._budget.scratch(cost), scratch_folder(self.store.scratch_root, "export") as directory:
            with self._admitted(cost, context):
                exported = rpc_tiles.export(request, directory, self.store)
            first = tiles_pb2.ExportResponse(grid=rpc_tiles.export_grid(exported))
            media_type = EXPORT_FORMATS[exported.file_format].media_type
            yield from rpc_tiles.streamed_file(
                first, exported.path, file_name=exported.path.name, media_type=media_type
            )

    @abort_on_error
    def GetReport(self, request, context):
        file_format = wire.report_format_name(request.format)
        area = rpc_tiles.area_of(request.area, "area")
        specimen = self.store.load(request.area.specimen_id)
        cost = admission.report_cost(specimen, **area)
        with self._budget.scratch(cost), scratch_folder(self.store.scratch_root, "report") as directory:
            with self._admitted(cost, context):
                path = report.write_report(specimen, directory, file_format=file_format, **area)
            yield from rpc_tiles.streamed_file(
                tiles_pb2.GetReportResponse(), path, file_name=path.name, media_type=report.MEDIA_TYPES[file_format]
            )

    def _admitted(self, cost: budget.Cost, context: grpc.ServicerContext):
        """The budget's admission of a query of `cost` for the call of `context`, stopped when it ends."""
        return self._budget.admitted(cost, stopped=lambda: not context.is_active())

    def _stored(self, specimen_id: str, request_id: str, digest: str) -> Specimen | None:
        """The stored specimen that a request with `request_id` and content `digest` built, if any
        (StoredSpecimens.built_by)."""
        return self.store.built_by(specimen_id, request_id, digest)


class SerializedGetTile(grpc.ServerInterceptor):
    """Routes GetTile to `servicer.get_tile_serialized`, whose bytes go out as they are; the
    generated registration would serialize a message on every call."""

    def __init__(self, servicer: TileServicer):
        self._handler = grpc.unary_unary_rpc_method_handler(
            servicer.get_tile_serialized,
            request_deserializer=tiles_pb2.GetTileRequest.FromString,
            response_serializer=None,
        )

    def intercept_service(self, continuation, handler_call_details):
        if handler_call_details.method == GET_TILE_METHOD:
            return self._handler
        return continuation(handler_call_details)


def _mesh_request(tile: TileSamples) -> meshing_pb2.BuildMeshRequest:
    """BuildMesh of one tile of a specimen, at one level with its margin, with its heights' fused
    matching noise and the bound of its ROI (quadtree.TileSamples)."""
    return calls.mesh_request(
        tile.z_um,
        tile.texture,
        pixel_size_um=tile.cell_um,
        origin_um=tile.grid_origin_um,
        level_count=1,
        max_slope=tile.max_slope or 0.0,
        sigma_um=tile.sigma_um if tile.sigma_um is not None else np.full(tile.z_um.shape, tile.noise_um, np.float32),
        max_sigma_um=tile.max_sigma_um,
        resolution_px=tile.resolution_cells,
        margin_cells=MESH_MARGIN_CELLS,
        min_island_px=tile.min_island_cells,
        unmeasured=rpc_meshing.UNMEASURED_CODES[tile.unmeasured],
    )


@contextlib.contextmanager
def _calling(service: str, address: str):
    """Turns the failure of a call to `service` into the error this build fails with (the status
    table read backwards, errors.error_of_code), with what the operator can do about it."""
    try:
        with raised_as_client_errors():
            yield
    except ClientError as error:
        if error.field:
            raise InvalidInputError(error.field, str(error).split(": ", 1)[-1]) from None
        template = _CALL_FAILURES.get(error.code.name, "the {service} service at {address} failed ({code}: {error})")
        message = template.format(service=service, address=address, code=error.code.name, error=error)
        raise error_of_code(error.code.name, message, retry_after_s=error.retry_after_s) from None


_RETRY = "the {service} service at {address} failed ({code}: {error}); nothing was stored, retry"
_TOKEN = (
    "this server could not authenticate to the {service} service at {address} ({code}: {error}); give it a write "
    "token of that service in FRACTO_TOKEN"
)
_CALL_FAILURES = {
    "UNAVAILABLE": _RETRY,
    "DEADLINE_EXCEEDED": _RETRY,
    "UNAUTHENTICATED": _TOKEN,
    "PERMISSION_DENIED": _TOKEN,
    "RESOURCE_EXHAUSTED": "the {service} service at {address} is busy: {error}",
}
