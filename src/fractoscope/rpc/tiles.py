"""The tile service's messages to and from the specimen package's types: stored specimens and
their tiles, ROI specs, checked regions."""

from __future__ import annotations

import math
from collections.abc import Iterator
from pathlib import Path

from fractoscope.errors import InvalidInputError
from fractoscope.rpc import wire
from fractoscope.rpc.calls import CHUNK_BYTES
from fractoscope.formats.calibration import Calibration
from fractoscope.specimen import exports
from fractoscope.specimen.build import RoiRequest
from fractoscope.specimen.exports import ExportedFile
from fractoscope.specimen.quadtree import TileRecord
from fractoscope.specimen.queries import checked_region
from fractoscope.specimen.store import Specimen, SpecimenStore
from fractoscope.stereo.geometry import validate_pixel_size_um
from fractoscope.units import METRES_PER_UM
from fractoscope.v1 import common_pb2, tiles_pb2


def specimen_message(specimen: Specimen) -> tiles_pb2.Specimen:
    message = tiles_pb2.Specimen(id=specimen.id, tileset_uri=f"/specimens/{specimen.id}/tileset.json")
    for roi in specimen.rois:
        message.rois.append(
            tiles_pb2.RoiSummary(
                id=roi.id, parent=roi.parent, magnification=roi.magnification, pixel_size_um=roi.pixel_size_um,
                region=wire.region_message(roi.region_um), alignment_residual_um=roi.alignment_residual_um,
                matching=wire.report_to_message(roi.matching), registration_score=roi.registration_score,
            )
        )
    return message


def with_tile(response, specimen: Specimen, record: TileRecord):
    """`response` (a message with a `tile` field) holding the tile and its GLB. The GLB is set on
    the response's own tile: nesting a filled message copies it, which for a tile of tens of kB
    costs more than the rest of the call."""
    response.tile.CopyFrom(tile_message(specimen, record))
    response.tile.glb = specimen.tile_bytes(record.key.uri)
    return response


def tile_message(specimen: Specimen, record: TileRecord, *, upsampled: bool = False) -> tiles_pb2.Tile:
    """A tile's identity without its GLB (see `with_tile`); `upsampled` marks a tile shown
    beyond its resolution (digital)."""
    zoom = tiles_pb2.ZOOM_KIND_DIGITAL if upsampled else wire.ZOOM_KINDS[record.zoom]
    return tiles_pb2.Tile(
        uri=record.key.uri,
        roi=record.roi,
        magnification=record.magnification,
        zoom=zoom,
        geometric_error_m=record.geometric_error_um * METRES_PER_UM,
    )


def roi_request(spec: tiles_pb2.RoiSpec, index: int) -> RoiRequest:
    """An ROI spec's placement, validated (errors name `rois[index]`'s fields)."""
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
    images = tuple((item.image.filename, item.image.content) for item in spec.images)
    return RoiRequest(spec.id, spec.parent, spec.magnification, centre, images)


def region(message: tiles_pb2.RegionUm, field: str) -> tuple[float, float, float, float]:
    """A RegionUm as (x_min, y_min, x_max, y_max) µm, checked."""
    return checked_region(wire.message_to_region(message), field)


def streamed_file(first, path: Path, *, file_name: str, media_type: str) -> Iterator:
    """A file's stream: `first` (a fresh ExportResponse or GetReportResponse, which may carry more)
    with its FileHeader, then the file's bytes in chunks of calls.CHUNK_BYTES, read as they go."""
    first.file.CopyFrom(tiles_pb2.FileHeader(file_name=file_name, media_type=media_type, size_bytes=path.stat().st_size))
    yield first
    with open(path, "rb") as source:
        while chunk := source.read(CHUNK_BYTES):
            yield type(first)(chunk=chunk)


def area_of(message: tiles_pb2.SpecimenArea, field: str) -> dict:
    """A SpecimenArea as the keyword arguments roi / region_um (neither: the overview), checked;
    errors name `field`'s members."""
    kind = message.WhichOneof("area")
    if kind == "region":
        return {"roi": None, "region_um": region(message.region, f"{field}.region")}
    return {"roi": message.roi if kind == "roi" else None, "region_um": None}


def export(request: tiles_pb2.ExportRequest, directory: Path, store: SpecimenStore) -> ExportedFile:
    """The file an ExportRequest asks for, written in `directory`."""
    options = {
        "file_format": wire.export_format_name(request.format),
        "solid": request.solid,
        "units": wire.length_unit_name(request.units),
    }
    pixel_size_um = request.pixel_size_um or None
    if request.WhichOneof("source") == "specimen":
        area = request.specimen
        return exports.export_area(store.load(area.specimen_id), directory, **area_of(area, "specimen"), pixel_size_um=pixel_size_um, **options)
    if request.WhichOneof("source") != "height_map":
        raise InvalidInputError("source", "give a specimen area or a height map")
    height_map = request.height_map
    z_um = wire.raster_to_array(height_map.z_um, field="height_map.z_um")
    sigma_um = wire.raster_to_array(height_map.sigma_um, field="height_map.sigma_um") if height_map.HasField("sigma_um") else None
    calibration = Calibration.from_report(wire.message_to_report(request.report)) if request.HasField("report") else None
    return exports.export_height_map(
        directory, z_um, pixel_size_um=validate_pixel_size_um(height_map.pixel_size_um, field="height_map.pixel_size_um"),
        sigma_um=sigma_um, calibration=calibration, export_pixel_size_um=pixel_size_um, **options,
    )


def export_grid(exported: ExportedFile) -> tiles_pb2.ExportGrid:
    rows, cols = exported.shape
    return tiles_pb2.ExportGrid(
        rows=rows, cols=cols, pixel_size_um=exported.pixel_size_um,
        origin_um=common_pb2.PointUm(x_um=exported.origin_um[0], y_um=exported.origin_um[1]),
    )
