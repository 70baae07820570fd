"""The tile service's messages to and from the specimen package's types: stored specimens and
their tiles, ROI specs, checked regions."""

from __future__ import annotations

import math

from fractoscope.errors import InvalidInputError
from fractoscope.rpc import wire
from fractoscope.sem.image import nominal_magnification
from fractoscope.specimen.build import RoiRequest
from fractoscope.specimen.quadtree import TileRecord
from fractoscope.specimen.queries import checked_region
from fractoscope.specimen.store import Specimen
from fractoscope.stereo.geometry import validate_pixel_size_um
from fractoscope.surface.datum import LEVELS
from fractoscope.units import METRES_PER_UM
from fractoscope.v1 import tiles_pb2


def specimen_message(specimen: Specimen) -> tiles_pb2.Specimen:
    message = tiles_pb2.Specimen(id=specimen.id, tileset_uri=f"/specimens/{specimen.id}/tileset.json")
    for roi in specimen.rois:
        message.rois.append(
            tiles_pb2.RoiSummary(
                id=roi.id, parent=roi.parent, magnification=roi.magnification, pixel_size_um=roi.pixel_size_um,
                region=wire.region_message(roi.region_um), alignment_residual_um=roi.alignment_residual_um,
                matching=wire.report_to_message(roi.matching), registration_score=roi.registration_score,
                level=(roi.datum or {}).get("level", ""),
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
    """An ROI spec's placement, validated (errors name `rois[index]`'s fields); without a
    magnification, the one its reference image's metadata states."""
    if len(spec.images) != 2:
        raise InvalidInputError(f"rois[{index}].images", f"an ROI needs a stereo pair, got {len(spec.images)} images")
    if spec.HasField("pixel_size_um"):
        validate_pixel_size_um(spec.pixel_size_um, field=f"rois[{index}].pixel_size_um")
    if not (math.isfinite(spec.magnification) and spec.magnification >= 0):
        raise InvalidInputError(f"rois[{index}].magnification", "must be finite and >= 0")
    if spec.level and (spec.level not in LEVELS or spec.parent):
        raise InvalidInputError(f"rois[{index}].level", f"must be empty or one of {', '.join(LEVELS)}, and is for the overview only")
    centre = None
    if spec.HasField("center_um"):
        centre = (spec.center_um.x_um, spec.center_um.y_um)
        if not all(math.isfinite(v) for v in centre):
            raise InvalidInputError(f"rois[{index}].center_um", "must be finite")
    magnification = spec.magnification or nominal_magnification(spec.images[0].image.content) or 0.0
    return RoiRequest(spec.id, spec.parent, magnification, centre, spec.level)


def region(message: tiles_pb2.RegionUm, field: str) -> tuple[float, float, float, float]:
    """A RegionUm as (x_min, y_min, x_max, y_max) µm, checked."""
    return checked_region(wire.message_to_region(message), field)
