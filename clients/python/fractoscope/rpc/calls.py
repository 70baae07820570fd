"""The streaming calls' requests and the reading of their responses, shared by the client and by
the tile service, which calls matching and meshing. Numpy and protobuf only."""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np

from fractoscope.progress import ProgressCallback
from fractoscope.rpc import wire
from fractoscope.rpc.status import ClientError
from fractoscope.v1 import common_pb2, matching_pb2, meshing_pb2


@dataclass(frozen=True)
class HeightMap:
    """A height map on the first image's grid: arrays (rows, cols) float32, heights in µm;
    `views_used` (uint8) how many views each height rests on, None from servers without it."""

    z_um: np.ndarray
    sigma_um: np.ndarray
    confidence: np.ndarray
    texture: np.ndarray
    pixel_size_um: float
    report: dict
    views_used: np.ndarray | None = None


def height_map_request(
    images: Sequence[tuple[bytes, str]],
    *,
    tilt_deg: Sequence[float] | None = None,
    pixel_size_um: float | None = None,
    tilt_axis_deg: float | None = None,
    parameters: matching_pb2.MatchingParameters | None = None,
    request_id: str = "",
) -> matching_pb2.ComputeHeightMapRequest:
    """ComputeHeightMap of images given as (file bytes, file name), reference first; None leaves
    a value to the files' metadata (tilts, pixel size) or the server (tilt axis)."""
    request = matching_pb2.ComputeHeightMapRequest(request_id=request_id, parameters=parameters)
    for index, (content, name) in enumerate(images):
        item = request.images.add()  # filled in place: nesting a built message would copy the image
        item.image.content, item.image.filename = content, name
        if tilt_deg is not None:
            item.tilt_deg = float(tilt_deg[index])
    if pixel_size_um is not None:
        request.pixel_size_um = pixel_size_um
    if tilt_axis_deg is not None:
        request.tilt_axis_deg = tilt_axis_deg
    return request


def read_final(responses: Iterable, on_progress: ProgressCallback | None, *, missing: str):
    """The response a stream of progress reports ends with; `missing` names it in the error when
    the stream ends without one."""
    final = None
    for response in responses:
        if response.HasField("progress"):
            if on_progress:
                on_progress(response.progress.fraction, response.progress.message)
        else:
            final = response
    if final is None:
        raise ClientError(grpc.StatusCode.INTERNAL, f"the server closed the stream without {missing}")
    return final


def read_height_map(
    responses: Iterable[matching_pb2.ComputeHeightMapResponse], on_progress: ProgressCallback | None
) -> HeightMap:
    """The height map a ComputeHeightMap stream ends with, progress handed to `on_progress`."""
    final = read_final(responses, on_progress, missing="a result")
    height_map = final.height_map
    return HeightMap(
        z_um=wire.raster_to_array(height_map.z_um),
        sigma_um=wire.raster_to_array(height_map.sigma_um),
        confidence=wire.raster_to_array(height_map.confidence),
        texture=wire.raster_to_array(height_map.texture),
        pixel_size_um=height_map.pixel_size_um,
        report=wire.message_to_report(final.report),
        views_used=wire.raster_to_array(height_map.views_used) if height_map.HasField("views_used") else None,
    )


def mesh_request(
    z_um: np.ndarray,
    texture: np.ndarray | None,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    sigma_um: np.ndarray | None = None,
    **settings,
) -> meshing_pb2.BuildMeshRequest:
    """BuildMesh of a height map ((rows, cols) µm, NaN unknown) and a grey texture of its shape
    (None: flat grey), pixel (0, 0) at `origin_um` (x, y), with each height's local uncertainty
    `sigma_um` (optional, µm); `settings` are the request's other fields (method, level_count,
    filter, request_id, plain_glb, max_slope, unmeasured, min_island_px, margin_cells,
    max_sigma_um)."""
    request = meshing_pb2.BuildMeshRequest(
        origin_um=common_pb2.PointUm(x_um=origin_um[0], y_um=origin_um[1]), **settings
    )
    request.height_map.pixel_size_um = pixel_size_um
    wire.fill_raster(request.height_map.z_um, np.asarray(z_um, np.float32))
    if texture is not None:
        wire.fill_raster(request.height_map.texture, texture)
    if sigma_um is not None:
        wire.fill_raster(request.height_map.sigma_um, np.asarray(sigma_um, np.float32))
    return request


FILTER_COUNTS = ("outliers_removed", "holes_filled", "points_smoothed", "islands_dropped", "uncertain_dropped")


def read_mesh(
    responses: Iterable[meshing_pb2.BuildMeshResponse], on_progress: ProgressCallback | None
) -> tuple[list[meshing_pb2.MeshTile], dict]:
    """The tiles (finest level first) and the filter report (counts by name) of a BuildMesh stream."""
    tiles, report = [], {}
    for response in responses:
        event = response.WhichOneof("event")
        if event == "progress" and on_progress:
            on_progress(response.progress.fraction, response.progress.message)
        elif event == "tile":
            tiles.append(response.tile)
        elif event == "filter_report":
            report = {name: getattr(response.filter_report, name) for name in FILTER_COUNTS}
    return tiles, report


CHUNK_BYTES = 1 << 20  # a file stream's chunks, at most


def read_file(responses: Iterable, path: str | os.PathLike):
    """Writes a file stream (a FileHeader, then its chunks in order; ExportResponse or
    GetReportResponse) to `path` and returns its first response. The file appears complete or
    not at all: it is written beside `path` and renamed into place once every byte has come."""
    path = Path(path)
    partial = path.with_name(f".{path.name}.part")
    first, received = None, 0
    try:
        with open(partial, "wb") as out:
            for response in responses:
                if response.WhichOneof("event") == "file":
                    first = response
                elif first is not None:
                    out.write(response.chunk)
                    received += len(response.chunk)
        if first is None:
            raise ClientError(grpc.StatusCode.INTERNAL, "the server closed the stream without a file")
        if received != first.file.size_bytes:
            raise ClientError(
                grpc.StatusCode.INTERNAL, f"the stream carried {received} of the file's {first.file.size_bytes} bytes"
            )
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return first
