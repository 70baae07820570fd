"""TileService: multi-scale specimens built on the matching and meshing services, and queries."""

from __future__ import annotations

import logging
import tempfile
from pathlib import Path

import grpc

from fractoscope import report
from fractoscope.errors import InvalidInputError, NotFoundError, UnavailableError
from fractoscope.formats.exports import MEDIA_TYPES
from fractoscope.rpc import calls, wire
from fractoscope.rpc import tiles as rpc_tiles
from fractoscope.rpc.channel import open_channel
from fractoscope.rpc.status import ClientError, abort_on_error, raised_as_client_errors
from fractoscope.services.caches import BoundedCache
from fractoscope.services.streaming import stream_progress
from fractoscope.specimen import quadtree
from fractoscope.specimen import queries as specimen_queries
from fractoscope.specimen.build import MeasuredHeights, RoiRequest, reconstruct_specimen
from fractoscope.specimen.store import Specimen, SpecimenStore, validate_id
from fractoscope.surface import areal_parameters
from fractoscope.v1 import common_pb2, matching_pb2_grpc, meshing_pb2_grpc, tiles_pb2, tiles_pb2_grpc

_log = logging.getLogger("fractoscope.tiles")
GET_TILE_METHOD = "/fractoscope.v1.TileService/GetTile"


class TileServicer(tiles_pb2_grpc.TileServiceServicer):
    """Thin wrappers over reconstruction, the specimen store and the analysis modules. Matching and
    meshing run on the services at `matching_address` and `meshing_address` (gRPC targets; a
    `dns:///` name of several replicas is balanced round-robin); None means this server, filled in
    once it knows its port. Every call to them has a deadline of `call_timeout_s`.

    GetTile is answered by `get_tile_serialized`, which the server routes there (SerializedGetTile);
    up to `tile_response_cache_bytes` of serialized tile responses are kept."""

    def __init__(
        self, store: SpecimenStore, *, matching_address: str | None = None, meshing_address: str | None = None,
        call_timeout_s: float = 1800.0, tile_response_cache_bytes: int = 256 * 1024 * 1024,
    ):
        self.store = store
        self.matching_address = matching_address
        self.meshing_address = meshing_address
        self.call_timeout_s = call_timeout_s
        self._tile_responses: BoundedCache[bytes] = BoundedCache(tile_response_cache_bytes, size=len)

    @abort_on_error
    def ReconstructSpecimen(self, request, context):
        specimen_id = validate_id(request.specimen_id, field="specimen_id")
        if request.request_id:
            existing = self._existing(specimen_id)
            if existing is not None and existing.request_id == request.request_id:
                yield tiles_pb2.ReconstructSpecimenResponse(specimen=rpc_tiles.specimen_message(existing))
                return
        rois = [rpc_tiles.roi_request(spec, index) for index, spec in enumerate(request.rois)]
        for event in stream_progress(context, lambda progress: self._reconstruct(request, rois, progress)):
            if isinstance(event, common_pb2.Progress):
                yield tiles_pb2.ReconstructSpecimenResponse(progress=event)
            else:
                _log.info("specimen built", extra={"request_id": request.request_id})
                yield tiles_pb2.ReconstructSpecimenResponse(specimen=rpc_tiles.specimen_message(event))

    def _reconstruct(self, request: tiles_pb2.ReconstructSpecimenRequest, rois: list[RoiRequest], progress) -> Specimen:
        """Builds the specimen with matching and meshing called on their services."""
        specs = {spec.id: (index, spec) for index, spec in enumerate(request.rois)}
        timeout_s = self.call_timeout_s
        with open_channel(self.matching_address) as matching_channel, open_channel(self.meshing_address) as meshing_channel:
            matching = matching_pb2_grpc.MatchingServiceStub(matching_channel)
            meshing = meshing_pb2_grpc.MeshingServiceStub(meshing_channel)

            def measure(roi: RoiRequest) -> MeasuredHeights:
                index, spec = specs[roi.id]
                return _measure(matching, spec, index, request_id=request.request_id, timeout_s=timeout_s)

            def mesh_tile(z_um, texture, cell_um, origin_um) -> bytes:
                mesh_request = calls.mesh_request(z_um, texture, pixel_size_um=cell_um, origin_um=origin_um, level_count=1)
                with raised_as_client_errors():
                    tiles, _ = calls.read_mesh(meshing.BuildMesh(mesh_request, timeout=timeout_s), None)
                return tiles[0].glb

            try:
                return reconstruct_specimen(
                    request.specimen_id, rois, measure=measure, mesh_tile=mesh_tile, store=self.store,
                    request_id=request.request_id, progress=progress,
                )
            except ClientError as error:
                if error.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                    raise UnavailableError(f"a service the reconstruction needs failed ({error}); nothing was stored, retry") from None
                raise

    @abort_on_error
    def GetSpecimen(self, request, context):
        return tiles_pb2.GetSpecimenResponse(specimen=rpc_tiles.specimen_message(self.store.load(request.specimen_id)))

    @abort_on_error
    def ListSpecimens(self, request, context):
        return tiles_pb2.ListSpecimensResponse(specimens=[rpc_tiles.specimen_message(self.store.load(i)) for i in self.store.ids()])

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
            return rpc_tiles.with_tile(tiles_pb2.GetTileResponse(), specimen, specimen.tile_record(request.uri)).SerializeToString()

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
        cell_um = specimen.pixel_size_at_magnification(specimen_queries.positive(request.magnification, "magnification"))
        chosen = quadtree.tiles_in_region(specimen.layout, specimen.tiles, region, cell_um=cell_um)
        return tiles_pb2.ZoomResponse(tiles=[rpc_tiles.tile_message(specimen, record, upsampled=upsampled) for record, upsampled in chosen])

    @abort_on_error
    def GetProfile(self, request, context):
        specimen = self.store.load(request.specimen_id)
        found = specimen_queries.profile_along(
            specimen, [[p.x_um, p.y_um] for p in request.points], spacing_um=request.spacing_um, magnification=request.magnification,
        )
        response = tiles_pb2.GetProfileResponse(
            distance_um=found.distance_um, z_um=found.z_um, source_index=found.source_index, sources=found.sources
        )
        if found.parameters:
            response.parameters.CopyFrom(wire.profile_parameters_message(found.parameters))
        return response

    @abort_on_error
    def GetRoughness(self, request, context):
        specimen = self.store.load(request.specimen_id)
        area = request.WhichOneof("area")
        values = specimen_queries.roughness_of(
            specimen, roi=request.roi if area == "roi" else None,
            region_um=rpc_tiles.region(request.region, "region") if area == "region" else None,
        )
        return wire.roughness_response(values, areal_parameters.UNITS)

    @abort_on_error
    def Export(self, request, context):
        with tempfile.TemporaryDirectory(prefix="fractoscope-export-") as directory:
            exported = rpc_tiles.export(request, Path(directory), self.store)
            first = tiles_pb2.ExportResponse(grid=rpc_tiles.export_grid(exported))
            media_type = MEDIA_TYPES[exported.file_format]
            yield from rpc_tiles.streamed_file(first, exported.path, file_name=exported.path.name, media_type=media_type)

    @abort_on_error
    def GetReport(self, request, context):
        file_format = wire.report_format_name(request.format)
        area = rpc_tiles.area_of(request.area, "area")
        with tempfile.TemporaryDirectory(prefix="fractoscope-report-") as directory:
            path = report.write_report(self.store.load(request.area.specimen_id), Path(directory), file_format=file_format, **area)
            yield from rpc_tiles.streamed_file(tiles_pb2.GetReportResponse(), path, file_name=path.name, media_type=report.MEDIA_TYPES[file_format])

    def _existing(self, specimen_id: str) -> Specimen | None:
        try:
            return self.store.load(specimen_id)
        except NotFoundError:
            return None


class SerializedGetTile(grpc.ServerInterceptor):
    """Routes GetTile to `servicer.get_tile_serialized`, whose bytes go out as they are; the
    generated registration would serialize a message on every call."""

    def __init__(self, servicer: TileServicer):
        self._handler = grpc.unary_unary_rpc_method_handler(
            servicer.get_tile_serialized, request_deserializer=tiles_pb2.GetTileRequest.FromString, response_serializer=None
        )

    def intercept_service(self, continuation, handler_call_details):
        if handler_call_details.method == GET_TILE_METHOD:
            return self._handler
        return continuation(handler_call_details)


def _measure(stub, spec: tiles_pb2.RoiSpec, index: int, *, request_id: str, timeout_s: float) -> MeasuredHeights:
    """One ROI's height map from the matching service; its errors name the ROI's fields."""
    tilts = [item.tilt_deg for item in spec.images] if all(item.HasField("tilt_deg") for item in spec.images) else None
    request = calls.height_map_request(
        [(item.image.content, "") for item in spec.images],
        tilt_deg=tilts,
        pixel_size_um=spec.pixel_size_um if spec.HasField("pixel_size_um") else None,
        tilt_axis_deg=spec.tilt_axis_deg if spec.HasField("tilt_axis_deg") else None,
        parameters=spec.parameters,
        request_id=request_id,
    )
    try:
        with raised_as_client_errors():
            result = calls.read_height_map(stub.ComputeHeightMap(request, timeout=timeout_s), None)
    except ClientError as error:
        if error.field:
            raise InvalidInputError(f"rois[{index}].{error.field}", str(error).split(": ", 1)[-1]) from None
        raise
    return MeasuredHeights(result.z_um, result.texture, result.pixel_size_um, result.report, result.sigma_um)
