"""The meshing service's messages to and from the mesh package's types: requests to MeshingOptions
and arrays, encoded tiles and filter reports to responses."""

from __future__ import annotations

import math

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.mesh.levels import Simplification
from fractoscope.mesh.outline import Unmeasured
from fractoscope.mesh.pipeline import EncodedTile, MeshingOptions, MeshReport
from fractoscope.mesh.walls import max_meshed_sigma_um
from fractoscope.rpc import wire
from fractoscope.stereo.geometry import validate_pixel_size_um
from fractoscope.v1 import common_pb2, meshing_pb2

_METHODS = {
    meshing_pb2.SIMPLIFICATION_METHOD_UNSPECIFIED: Simplification.VERTEX_CLUSTERING,
    meshing_pb2.SIMPLIFICATION_METHOD_VERTEX_CLUSTERING: Simplification.VERTEX_CLUSTERING,
    meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC: Simplification.QUADRIC,
}
UNMEASURED = {
    common_pb2.UNMEASURED_AREAS_UNSPECIFIED: Unmeasured.ABSENT,
    common_pb2.UNMEASURED_AREAS_ABSENT: Unmeasured.ABSENT,
    common_pb2.UNMEASURED_AREAS_FLAT: Unmeasured.FLAT,
}
UNMEASURED_CODES = {kind: code for code, kind in UNMEASURED.items() if code}
MAX_MARGIN_CELLS = 16


def options_from_request(request: meshing_pb2.BuildMeshRequest) -> MeshingOptions:
    """BuildMeshRequest settings (zero = default) to MeshingOptions, validated."""
    defaults = MeshingOptions()
    parameters = request.filter
    options = MeshingOptions(
        outlier_threshold_sigma=parameters.outlier_threshold_sigma or defaults.outlier_threshold_sigma,
        max_fill_distance_px=parameters.max_fill_distance_px or defaults.max_fill_distance_px,
        smoothing_um=parameters.smoothing_um,
        method=_METHODS.get(request.method, None) or _invalid("method", f"unknown method {request.method}"),
        level_count=request.level_count or None,
        plain_glb=request.plain_glb,
        max_slope=request.max_slope or None,
        unmeasured=unmeasured_of(request.unmeasured),
        min_island_px=request.min_island_px if request.HasField("min_island_px") else defaults.min_island_px,
        margin_cells=request.margin_cells,
        max_sigma_um=_max_sigma_um(request),
        resolution_px=max(request.resolution_px, 1.0),
    )
    if not options.outlier_threshold_sigma > 0:
        _invalid("filter.outlier_threshold_sigma", "must be > 0")
    if not 0 <= options.max_fill_distance_px <= 1000:
        _invalid("filter.max_fill_distance_px", "must be 0 to 1000")
    if not (np.isfinite(options.smoothing_um) and options.smoothing_um >= 0):
        _invalid("filter.smoothing_um", "must be >= 0")
    if not 0 <= request.level_count <= 16:
        _invalid("level_count", "must be 0 (automatic) to 16")
    if not (np.isfinite(request.max_slope) and request.max_slope >= 0):
        _invalid("max_slope", f"must be 0 (no walls) or positive, got {request.max_slope}")
    if not (np.isfinite(options.min_island_px) and options.min_island_px >= 0):
        _invalid("min_island_px", f"must be 0 (keep every island) or positive, got {options.min_island_px} px")
    if not (math.isfinite(request.resolution_px) and 0 <= request.resolution_px <= 1000):
        _invalid("resolution_px", f"must be 0 to 1000 pixels, got {request.resolution_px}")
    if not 0 <= request.margin_cells <= MAX_MARGIN_CELLS:
        _invalid("margin_cells", f"must be 0 to {MAX_MARGIN_CELLS}, got {request.margin_cells}")
    if request.margin_cells and request.level_count != 1:
        _invalid(
            "margin_cells", f"needs level_count 1 (a margin is one level's), got level_count {request.level_count}"
        )
    return options


def unmeasured_of(code: int) -> Unmeasured:
    """An UnmeasuredAreas value of a request (BuildMesh, ReconstructSpecimen) as mesh.outline's;
    InvalidInputError naming `unmeasured` for a number the enumeration lacks."""
    if code not in UNMEASURED:
        known = ", ".join(f"{common_pb2.UnmeasuredAreas.Name(known)} ({known})" for known in UNMEASURED)
        raise InvalidInputError("unmeasured", f"unknown value {code}; known: {known}")
    return UNMEASURED[code]


def _max_sigma_um(request: meshing_pb2.BuildMeshRequest) -> float | None:
    """The request's max_sigma_um (0: none), or by default the height two pixels of disparity make
    (mesh.walls.max_meshed_sigma_um) where the request gives a max_slope; None: every height."""
    if request.HasField("max_sigma_um"):
        if not (math.isfinite(request.max_sigma_um) and request.max_sigma_um >= 0):
            _invalid("max_sigma_um", f"must be 0 (mesh every height) or positive, got {request.max_sigma_um} µm")
        return request.max_sigma_um or None
    if not (request.max_slope > 0 and math.isfinite(request.max_slope) and request.height_map.pixel_size_um > 0):
        return None
    return max_meshed_sigma_um(max_slope=request.max_slope, pixel_size_um=request.height_map.pixel_size_um)


def _invalid(field: str, message: str):
    raise InvalidInputError(field, message)


def height_map_arrays(height_map: common_pb2.HeightMap, *, field: str = "height_map"):
    """(z_um, texture, pixel_size_um, sigma_um or None) from a HeightMap message, validated."""
    z_um = wire.raster_to_array(height_map.z_um, field=f"{field}.z_um")
    if z_um.dtype != np.float32:
        _invalid(f"{field}.z_um.data_type", "must be FLOAT32")
    if height_map.HasField("texture"):
        texture = wire.raster_to_array(height_map.texture, field=f"{field}.texture")
        if texture.shape != z_um.shape:
            _invalid(
                f"{field}.texture",
                f"{texture.shape[1]} x {texture.shape[0]} differs from z_um's {z_um.shape[1]} x {z_um.shape[0]}",
            )
        if texture.dtype == np.uint16:
            texture = (texture.astype(np.float32) / 257.0).astype(np.uint8)
    else:
        texture = np.full(z_um.shape, 128, np.uint8)
    pixel_size_um = validate_pixel_size_um(height_map.pixel_size_um, field=f"{field}.pixel_size_um")
    if min(z_um.shape) < 2:
        _invalid(f"{field}.z_um", "needs at least 2 x 2 heights")
    if not np.isfinite(z_um).any():
        _invalid(f"{field}.z_um", "has no finite heights: nothing to mesh")
    sigma_um = None
    if height_map.HasField("sigma_um"):
        sigma_um = wire.raster_to_array(height_map.sigma_um, field=f"{field}.sigma_um")
        if sigma_um.shape != z_um.shape:
            _invalid(
                f"{field}.sigma_um",
                f"{sigma_um.shape[1]} x {sigma_um.shape[0]} differs from z_um's {z_um.shape[1]} x {z_um.shape[0]}",
            )
        if np.any(sigma_um < 0):
            _invalid(f"{field}.sigma_um", f"must be >= 0 µm (NaN where unknown), got {np.nanmin(sigma_um)}")
    return z_um, texture, pixel_size_um, sigma_um


# GLB positions are float32 and offset by the origin: beyond a metre they lose the map's detail
# (float32 resolves 0.06 µm there), and far beyond it they overflow.
MAX_ORIGIN_UM = 1e6


def origin_from_request(request: meshing_pb2.BuildMeshRequest) -> tuple[float, float]:
    origin_um = (request.origin_um.x_um, request.origin_um.y_um)
    if not all(math.isfinite(value) and abs(value) <= MAX_ORIGIN_UM for value in origin_um):
        _invalid("origin_um", f"must be finite and within ±{MAX_ORIGIN_UM:g} µm (a metre), got {origin_um}")
    return origin_um


def tile_response(tile: EncodedTile) -> meshing_pb2.BuildMeshResponse:
    response = meshing_pb2.BuildMeshResponse(
        tile=meshing_pb2.MeshTile(
            level=tile.level,
            tile_row=tile.tile_row,
            tile_col=tile.tile_col,
            geometric_error_m=tile.geometric_error_m,
            vertex_count=tile.vertex_count,
            triangle_count=tile.triangle_count,
            wall_triangle_count=tile.wall_triangle_count,
            level_error_m=tile.level_error_m,
        )
    )
    response.tile.glb = tile.glb  # set in place: nesting a message copies it
    return response


def filter_report_response(report: MeshReport) -> meshing_pb2.BuildMeshResponse:
    return meshing_pb2.BuildMeshResponse(
        filter_report=meshing_pb2.FilterReport(
            outliers_removed=report.filtered.outliers_removed,
            holes_filled=report.filtered.holes_filled,
            points_smoothed=report.filtered.points_smoothed,
            islands_dropped=report.islands_dropped,
            uncertain_dropped=report.uncertain_dropped,
        )
    )
