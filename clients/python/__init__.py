"""Python client library of Fractoscope's gRPC API.

Example::

    from fractoscope.client import FractoscopeClient, embedded_server

    with embedded_server() as address, FractoscopeClient(address) as client:
        result = client.compute_height_map(["left.tif", "right.tif"], tilt_deg=(-5, 5), pixel_size_um=0.1)
        print(result.report["valid_fraction"], result.z_um.shape)
"""

from __future__ import annotations

import contextlib
import os

# gRPC core logs connection teardown (GOAWAY) at INFO on stderr, which would break the CLI's
# one-line errors; users can still ask for more with GRPC_VERBOSITY.
os.environ.setdefault("GRPC_VERBOSITY", "ERROR")
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
from google.rpc import error_details_pb2
from grpc_status import rpc_status

from fractoscope import wire
from fractoscope.meshing import EncodedTile
from fractoscope.services.server import DEFAULT_MAX_MESSAGE_MB, create_server, message_size_options
from fractoscope.v1 import common_pb2, matching_pb2, matching_pb2_grpc, meshing_pb2, meshing_pb2_grpc

ProgressCallback = Callable[[float, str], None]


class ClientError(Exception):
    """A call failed; `code` is the gRPC status code, `field` the offending request field if any."""

    def __init__(self, code: grpc.StatusCode, message: str, field: str | None = None):
        super().__init__(message)
        self.code = code
        self.field = field


@dataclass(frozen=True)
class HeightMap:
    """A height map on the first image's grid: arrays (rows, cols) float32, heights in µm."""

    z_um: np.ndarray
    sigma_um: np.ndarray
    confidence: np.ndarray
    texture: np.ndarray
    pixel_size_um: float
    report: dict


class FractoscopeClient:
    """Typed methods over one channel to a Fractoscope server."""

    def __init__(self, address: str, *, max_message_mb: int = DEFAULT_MAX_MESSAGE_MB, timeout_s: float | None = 3600.0):
        self._channel = grpc.insecure_channel(address, options=message_size_options(max_message_mb))
        self._matching = matching_pb2_grpc.MatchingServiceStub(self._channel)
        self._meshing = meshing_pb2_grpc.MeshingServiceStub(self._channel)
        self._timeout_s = timeout_s

    def __enter__(self) -> FractoscopeClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._channel.close()

    def compute_height_map(
        self,
        images: Sequence[str | Path | bytes],
        *,
        tilt_deg: Sequence[float] | None = None,
        pixel_size_um: float | None = None,
        tilt_axis_deg: float | None = None,
        parameters: matching_pb2.MatchingParameters | None = None,
        on_progress: ProgressCallback | None = None,
        request_id: str = "",
    ) -> HeightMap:
        """Heights from images (paths or file bytes), reference first; tilts and pixel size default
        to the files' metadata."""
        request = matching_pb2.ComputeHeightMapRequest(request_id=request_id, parameters=parameters)
        for index, image in enumerate(images):
            content = image if isinstance(image, bytes) else Path(image).read_bytes()
            name = "" if isinstance(image, bytes) else Path(image).name
            item = request.images.add(image=common_pb2.ImageFile(content=content, filename=name))
            if tilt_deg is not None:
                item.tilt_deg = float(tilt_deg[index])
        if pixel_size_um is not None:
            request.pixel_size_um = pixel_size_um
        if tilt_axis_deg is not None:
            request.tilt_axis_deg = tilt_axis_deg
        final = None
        with _translated_errors():
            for response in self._matching.ComputeHeightMap(request, timeout=self._timeout_s):
                if response.HasField("progress"):
                    if on_progress:
                        on_progress(response.progress.fraction, response.progress.message)
                else:
                    final = response
        if final is None:
            raise ClientError(grpc.StatusCode.INTERNAL, "the server closed the stream without a result")
        height_map = final.height_map
        return HeightMap(
            z_um=wire.raster_to_array(height_map.z_um),
            sigma_um=wire.raster_to_array(height_map.sigma_um),
            confidence=wire.raster_to_array(height_map.confidence),
            texture=wire.raster_to_array(height_map.texture),
            pixel_size_um=height_map.pixel_size_um,
            report=wire.message_to_report(final.report),
        )


    def build_mesh(
        self,
        z_um: np.ndarray,
        texture: np.ndarray | None,
        *,
        pixel_size_um: float,
        origin_um: tuple[float, float] = (0.0, 0.0),
        method: int = meshing_pb2.SIMPLIFICATION_METHOD_VERTEX_CLUSTERING,
        level_count: int = 0,
        filter_parameters: meshing_pb2.FilterParameters | None = None,
        on_progress: ProgressCallback | None = None,
        request_id: str = "",
    ) -> tuple[list[EncodedTile], dict]:
        """GLB levels of detail of a height map ((rows, cols) µm, NaN unknown) textured with a grey
        image of the same shape, pixel (0, 0) placed at `origin_um` (x, y); returns the tiles (finest
        level first) and the filter report."""
        height_map = common_pb2.HeightMap(z_um=wire.array_to_raster(np.asarray(z_um, np.float32)), pixel_size_um=pixel_size_um)
        if texture is not None:
            height_map.texture.CopyFrom(wire.array_to_raster(texture))
        request = meshing_pb2.BuildMeshRequest(
            height_map=height_map, filter=filter_parameters, method=method, level_count=level_count, request_id=request_id,
            origin_um=common_pb2.PointUm(x_um=origin_um[0], y_um=origin_um[1]),
        )
        tiles, report = [], {}
        with _translated_errors():
            for response in self._meshing.BuildMesh(request, timeout=self._timeout_s):
                event = response.WhichOneof("event")
                if event == "progress" and on_progress:
                    on_progress(response.progress.fraction, response.progress.message)
                elif event == "tile":
                    tile = response.tile
                    tiles.append(EncodedTile(tile.level, tile.tile_row, tile.tile_col, tile.glb, tile.geometric_error_m, tile.vertex_count, tile.triangle_count))
                elif event == "filter_report":
                    counts = response.filter_report
                    report = {name: getattr(counts, name) for name in ("outliers_removed", "holes_filled", "points_smoothed")}
        return tiles, report


@contextlib.contextmanager
def _translated_errors() -> Iterator[None]:
    try:
        yield
    except grpc.RpcError as error:
        status = rpc_status.from_call(error)
        field = None
        if status is not None:
            for detail in status.details:
                if detail.Is(error_details_pb2.BadRequest.DESCRIPTOR):
                    bad_request = error_details_pb2.BadRequest()
                    detail.Unpack(bad_request)
                    field = bad_request.field_violations[0].field if bad_request.field_violations else None
        raise ClientError(error.code(), error.details() or str(error.code()), field) from None


def server_address(explicit: str | None) -> str | None:
    """The server to use: the explicit one, else FRACTO_SERVER, else None (run embedded)."""
    return explicit or os.environ.get("FRACTO_SERVER") or None


@contextlib.contextmanager
def embedded_server() -> Iterator[str]:
    """Runs all services in this process on a free loopback port for the block's duration."""
    server, port = create_server("127.0.0.1:0")
    server.start()
    try:
        yield f"127.0.0.1:{port}"
    finally:
        server.stop(grace=None)
