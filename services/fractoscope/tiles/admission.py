"""What the tile service's queries, exports and reports cost, estimated from a specimen's
description and a request's parameters before any heights are read or any byte written, for the
process's one admission budget (runtime.budget.Budget), which gRPC and HTTP share. Inputs that
the query would refuse are refused here already (InvalidInputError naming the field)."""

from __future__ import annotations

from fractoscope.errors import InvalidInputError
from fractoscope.formats import exports as formats
from fractoscope.rpc import wire
from fractoscope.runtime.budget import Cost, analysis_bytes, export_bytes
from fractoscope.specimen import queries
from fractoscope.specimen.model import Specimen
from fractoscope.store.base import StoredSpecimens
from fractoscope.tiles import messages as rpc_tiles
from fractoscope.v1 import tiles_pb2

# A report's file (HTML with its pictures, or a PDF) at most, about.
REPORT_FILE_BYTES = 64 * 1024 * 1024


def roughness_cost(specimen: Specimen, *, roi: str | None, region_um) -> Cost:
    rows, cols = queries.roughness_shape(specimen, roi=roi, region_um=region_um)
    return Cost(f"the roughness of {cols} x {rows} points", analysis_bytes(rows * cols))


def profile_cost() -> Cost:
    """A profile samples at most queries.MAX_PROFILE_SAMPLES points, in strips."""
    return Cost("a profile", export_bytes(queries.MAX_PROFILE_SAMPLES))


def heights_cost(specimen: Specimen, region_um) -> Cost:
    rows, cols = queries.area_shape(specimen, region_um=region_um, allow_point=True)
    return Cost(f"the heights of {cols} x {rows} points", export_bytes(rows * cols))


def report_cost(specimen: Specimen, *, roi: str | None, region_um) -> Cost:
    """A report runs the roughness chain on its area and draws it: about an analysis of it."""
    rows, cols = queries.roughness_shape(specimen, roi=roi, region_um=region_um)
    return Cost(f"a report of {cols} x {rows} points", analysis_bytes(rows * cols), REPORT_FILE_BYTES)


def area_export_cost(
    specimen: Specimen, *, roi: str | None, region_um, pixel_size_um: float | None, file_format: str, solid: bool
) -> Cost:
    rows, cols = queries.area_shape(
        specimen, roi=roi, region_um=region_um, pixel_size_um=pixel_size_um, max_samples=queries.MAX_EXPORT_SAMPLES
    )
    return map_export_cost((rows, cols), file_format=file_format, solid=solid)


def map_export_cost(shape: tuple[int, int], *, file_format: str, solid: bool, source_bytes_per_point: int = 0) -> Cost:
    """An export of a grid of (rows, cols) `shape` in `file_format` (a key of formats.EXPORT_FORMATS, checked
    by the caller), its source held besides (`source_bytes_per_point`: an uploaded map's arrays)."""
    rows, cols = shape
    points = rows * cols
    memory = export_bytes(points) + formats.writer_bytes(file_format, points, solid=solid)
    return Cost(
        f"an export of {cols} x {rows} points as {file_format.upper()}{' (solid)' if solid else ''}",
        memory + source_bytes_per_point * points,
        formats.file_bytes(file_format, points, solid=solid),
    )


def export_request_cost(request: tiles_pb2.ExportRequest, store: StoredSpecimens) -> Cost:
    """An Export call's cost: of its specimen area, or of the height map it carries."""
    options = {"file_format": wire.export_format_name(request.format), "solid": request.solid}
    if request.WhichOneof("source") == "specimen":
        specimen = store.load(request.specimen.specimen_id)
        area = rpc_tiles.area_of(request.specimen, "specimen")
        return area_export_cost(specimen, **area, pixel_size_um=request.pixel_size_um or None, **options)
    if request.WhichOneof("source") != "height_map":
        raise InvalidInputError("source", "give a specimen area or a height map")
    raster = request.height_map.z_um
    return map_export_cost((raster.rows, raster.cols), **options)
