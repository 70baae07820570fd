"""TileService: multi-scale specimens built on the matching and meshing services, and queries."""

from __future__ import annotations

import logging
import math

import grpc

from fractoscope.rpc import wire
from fractoscope.specimen import quadtree
from fractoscope.specimen import queries as specimen_queries
from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.errors import InvalidInputError, NotFoundError, UnavailableError
from fractoscope.units import METRES_PER_UM
from fractoscope.specimen.build import MeasuredHeights, RoiRequest, reconstruct_specimen
from fractoscope.services.caches import BoundedCache
from fractoscope.rpc.status import abort_with_error
from fractoscope.services.streaming import stream_progress
from fractoscope.specimen.store import Specimen, SpecimenStore, validate_id
from fractoscope.stereo.geometry import validate_pixel_size_um
from fractoscope.specimen.quadtree import TileRecord
from fractoscope.v1 import common_pb2, tiles_pb2, tiles_pb2_grpc

_log = logging.getLogger("fractoscope.tiles")
_ZOOM_KINDS = {quadtree.OPTICAL: tiles_pb2.ZOOM_KIND_OPTICAL, quadtree.DIGITAL: tiles_pb2.ZOOM_KIND_DIGITAL}
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

    def ReconstructSpecimen(self, request, context):
        try:
            specimen_id = validate_id(request.specimen_id, field="specimen_id")
            if request.request_id:
                existing = self._existing(specimen_id)
                if existing is not None and existing.request_id == request.request_id:
                    yield tiles_pb2.ReconstructSpecimenResponse(specimen=specimen_message(existing))
                    return
            rois = [_roi_request(spec, index) for index, spec in enumerate(request.rois)]
            specs = {spec.id: (index, spec) for index, spec in enumerate(request.rois)}

            def work(progress):
                with (
                    FractoscopeClient(self.matching_address, timeout_s=self.call_timeout_s) as matching,
                    FractoscopeClient(self.meshing_address, timeout_s=self.call_timeout_s) as meshing,
                ):
                    def measure(roi: RoiRequest) -> MeasuredHeights:
                        index, spec = specs[roi.id]
                        return _measure(matching, spec, index, request.request_id)

                    def mesh_tile(z_um, texture, cell_um, origin_um) -> bytes:
                        tiles, _ = meshing.build_mesh(z_um, texture, pixel_size_um=cell_um, origin_um=origin_um, level_count=1)
                        return tiles[0].glb

                    try:
                        return reconstruct_specimen(
                            specimen_id, rois, measure=measure, mesh_tile=mesh_tile, store=self.store,
                            request_id=request.request_id, progress=progress,
                        )
                    except ClientError as error:
                        if error.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                            raise UnavailableError(f"a service the reconstruction needs failed ({error}); nothing was stored, retry") from None
                        raise

            for event in stream_progress(context, work):
                if isinstance(event, common_pb2.Progress):
                    yield tiles_pb2.ReconstructSpecimenResponse(progress=event)
                else:
                    _log.info("specimen built", extra={"request_id": request.request_id})
                    yield tiles_pb2.ReconstructSpecimenResponse(specimen=specimen_message(event))
        except Exception as error:  # every failure becomes a gRPC status in one place
            abort_with_error(context, error)

    def GetSpecimen(self, request, context):
        try:
            return tiles_pb2.GetSpecimenResponse(specimen=specimen_message(self.store.load(request.specimen_id)))
        except Exception as error:
            abort_with_error(context, error)

    def ListSpecimens(self, request, context):
        try:
            return tiles_pb2.ListSpecimensResponse(specimens=[specimen_message(self.store.load(i)) for i in self.store.ids()])
        except Exception as error:
            abort_with_error(context, error)

    def GetTileset(self, request, context):
        try:
            return tiles_pb2.GetTilesetResponse(tileset_json=self.store.load(request.specimen_id).tileset_bytes)
        except Exception as error:
            abort_with_error(context, error)

    def get_tile_serialized(self, request: tiles_pb2.GetTileRequest, context) -> bytes:
        """GetTile, answered with the serialized GetTileResponse: each tile's response is built and
        serialized once, then served from memory, which saves reading and serializing some 40 kB
        on every call."""
        try:
            specimen = self.store.load(request.specimen_id)

            def serialized() -> bytes:
                return _with_tile(tiles_pb2.GetTileResponse(), specimen, specimen.tile_record(request.uri)).SerializeToString()

            return self._tile_responses.get((specimen.id, specimen.version, request.uri), serialized)
        except Exception as error:
            abort_with_error(context, error)

    def StreamView(self, request, context):
        try:
            specimen = self.store.load(request.specimen_id)
            region = _region(request.region, "region")
            viewport_px = request.viewport_px or 1024
            if not 1 <= viewport_px <= 65536:
                raise InvalidInputError("viewport_px", "must be 1 to 65536")
            for record in quadtree.tiles_for_view(specimen.layout, specimen.tiles, region, viewport_px=viewport_px):
                yield _with_tile(tiles_pb2.StreamViewResponse(), specimen, record)
        except Exception as error:
            abort_with_error(context, error)

    def Zoom(self, request, context):
        try:
            specimen = self.store.load(request.specimen_id)
            region = _region(request.region, "region")
            cell_um = specimen.pixel_size_at_magnification(specimen_queries.positive(request.magnification, "magnification"))
            chosen = quadtree.tiles_in_region(specimen.layout, specimen.tiles, region, cell_um=cell_um)
            return tiles_pb2.ZoomResponse(
                tiles=[tile_message(specimen, record, upsampled=upsampled) for record, upsampled in chosen]
            )
        except Exception as error:
            abort_with_error(context, error)

    def GetProfile(self, request, context):
        try:
            specimen = self.store.load(request.specimen_id)
            found = specimen_queries.profile_along(
                specimen, [[p.x_um, p.y_um] for p in request.points],
                spacing_um=request.spacing_um, magnification=request.magnification,
            )
            response = tiles_pb2.GetProfileResponse(
                distance_um=found.distance_um, z_um=found.z_um, source_index=found.source_index, sources=found.sources
            )
            if found.parameters:
                values = found.parameters
                response.parameters.CopyFrom(
                    tiles_pb2.ProfileParameters(ra_um=values["Ra"], rq_um=values["Rq"], rz_um=values["Rz"], rsk=values["Rsk"], rku=values["Rku"])
                )
            return response
        except Exception as error:
            abort_with_error(context, error)

    def GetRoughness(self, request, context):
        try:
            specimen = self.store.load(request.specimen_id)
            area = request.WhichOneof("area")
            values = specimen_queries.roughness_of(
                specimen, roi=request.roi if area == "roi" else None,
                region_um=_region(request.region, "region") if area == "region" else None,
            )
            names = {"Sa": "sa_um", "Sq": "sq_um", "Ssk": "ssk", "Sku": "sku", "Sp": "sp_um", "Sv": "sv_um", "Sz": "sz_um", "Sdq": "sdq", "Sdr": "sdr_percent"}
            return tiles_pb2.GetRoughnessResponse(**{names.get(key, key): value for key, value in values.items()})
        except Exception as error:
            abort_with_error(context, error)

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


def specimen_message(specimen: Specimen) -> tiles_pb2.Specimen:
    message = tiles_pb2.Specimen(id=specimen.id, tileset_uri=f"/specimens/{specimen.id}/quadtree.json")
    for roi in specimen.rois:
        x0, y0, x1, y1 = roi.region_um
        message.rois.append(
            tiles_pb2.RoiSummary(
                id=roi.id, parent=roi.parent, magnification=roi.magnification, pixel_size_um=roi.pixel_size_um,
                region=_region_message(x0, y0, x1, y1), alignment_residual_um=roi.alignment_residual_um,
                matching=wire.report_to_message(roi.matching), registration_score=roi.registration_score,
            )
        )
    return message


def _with_tile(response, specimen: Specimen, record: TileRecord):
    """`response` (a message with a `tile` field) holding the tile and its GLB. The GLB is set on
    the response's own tile: nesting a filled message copies it, which for a tile of tens of kB
    costs more than the rest of the call."""
    response.tile.CopyFrom(tile_message(specimen, record))
    response.tile.glb = specimen.tile_bytes(record.key.uri)
    return response


def tile_message(specimen: Specimen, record: TileRecord, *, upsampled: bool = False) -> tiles_pb2.Tile:
    """A tile's identity without its GLB (see `_with_tile`); `upsampled` marks a tile shown
    beyond its resolution (digital)."""
    zoom = tiles_pb2.ZOOM_KIND_DIGITAL if upsampled else _ZOOM_KINDS[record.zoom]
    return tiles_pb2.Tile(
        uri=record.key.uri,
        roi=record.roi,
        magnification=record.magnification,
        zoom=zoom,
        geometric_error_m=record.geometric_error_um * METRES_PER_UM,
    )


def _measure(client: FractoscopeClient, spec: tiles_pb2.RoiSpec, index: int, request_id: str) -> MeasuredHeights:
    """One ROI's height map from the matching service; its errors name the ROI's fields."""
    tilts = [item.tilt_deg for item in spec.images] if all(item.HasField("tilt_deg") for item in spec.images) else None
    try:
        result = client.compute_height_map(
            [item.image.content for item in spec.images],
            tilt_deg=tilts,
            pixel_size_um=spec.pixel_size_um if spec.HasField("pixel_size_um") else None,
            tilt_axis_deg=spec.tilt_axis_deg if spec.HasField("tilt_axis_deg") else None,
            parameters=spec.parameters,
            request_id=request_id,
        )
    except ClientError as error:
        if error.field:
            raise InvalidInputError(f"rois[{index}].{error.field}", str(error).split(": ", 1)[-1]) from None
        raise
    return MeasuredHeights(result.z_um, result.texture, result.pixel_size_um, result.report)


def _roi_request(spec: tiles_pb2.RoiSpec, index: int) -> RoiRequest:
    if len(spec.images) != 2:
        raise InvalidInputError(f"rois[{index}].images", f"an ROI needs a stereo pair, got {len(spec.images)} images")
    if spec.HasField("pixel_size_um"):
        validate_pixel_size_um(spec.pixel_size_um, field=f"rois[{index}].pixel_size_um")
    if not (math.isfinite(spec.magnification) and spec.magnification >= 0):
        raise InvalidInputError(f"rois[{index}].magnification", "must be finite and >= 0")
    centre = None
    if spec.HasField("center_um"):
        centre = (spec.center_um.x_um, spec.center_um.y_um)
        if not all(math.isfinite(v) for v in centre):
            raise InvalidInputError(f"rois[{index}].center_um", "must be finite")
    return RoiRequest(spec.id, spec.parent, spec.magnification, centre)


def _region(message: tiles_pb2.RegionUm, field: str) -> tuple[float, float, float, float]:
    return specimen_queries.checked_region((message.min.x_um, message.min.y_um, message.max.x_um, message.max.y_um), field)


def _region_message(x0, y0, x1, y1) -> tiles_pb2.RegionUm:
    return tiles_pb2.RegionUm(min=common_pb2.PointUm(x_um=x0, y_um=y0), max=common_pb2.PointUm(x_um=x1, y_um=y1))

