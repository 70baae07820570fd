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
import json
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import grpc
import numpy as np
from google.rpc import error_details_pb2
from google.protobuf import json_format
from grpc_status import rpc_status

from fractoscope.rpc import wire
from fractoscope.stereo.disparity import DisparityResult, StripTask
from fractoscope.mesh.pipeline import EncodedTile
from fractoscope.rpc.limits import DEFAULT_MAX_MESSAGE_MB, message_size_options
from fractoscope.v1 import common_pb2, matching_pb2, matching_pb2_grpc, meshing_pb2, meshing_pb2_grpc, tiles_pb2, tiles_pb2_grpc

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


@dataclass(frozen=True)
class Profile:
    """A profile: (n,) distance along the line µm, height µm (NaN unknown), source ROI per sample,
    and its ISO 21920-2 parameters (Ra, Rq, Rz in µm, Rsk, Rku; empty if too few heights)."""

    distance_um: np.ndarray
    z_um: np.ndarray
    source: list[str]
    parameters: dict


Region = tuple[float, float, float, float]
_ZOOM_NAMES = {tiles_pb2.ZOOM_KIND_OPTICAL: "optical", tiles_pb2.ZOOM_KIND_DIGITAL: "digital"}
_ROUGHNESS_NAMES = {
    "sa_um": "Sa", "sq_um": "Sq", "ssk": "Ssk", "sku": "Sku", "sp_um": "Sp", "sv_um": "Sv", "sz_um": "Sz",
    "sdq": "Sdq", "sdr_percent": "Sdr",
}


# The unary calls are idempotent (reads, and matching one strip), so those that fail with
# UNAVAILABLE (a replica restarting) are retried with backoff. Streaming calls are not: a retried
# stream whose server died mid-way can wait forever, and their callers retry whole requests
# (reconstructions per request id). Several resolved addresses (a `dns:///` name of replicas) are
# used round-robin.
_RETRIED_METHODS = ("GetSpecimen", "ListSpecimens", "GetTileset", "GetTile", "Zoom", "GetProfile", "GetRoughness")
_SERVICE_CONFIG = json.dumps({
    "loadBalancingConfig": [{"round_robin": {}}],
    "methodConfig": [{
        "name": [{"service": "fractoscope.v1.TileService", "method": method} for method in _RETRIED_METHODS]
        + [{"service": "fractoscope.v1.MatchingService", "method": "MatchStrip"}],
        "retryPolicy": {
            "maxAttempts": 4, "initialBackoff": "0.2s", "maxBackoff": "2s", "backoffMultiplier": 2,
            "retryableStatusCodes": ["UNAVAILABLE"],
        },
    }],
})


class FractoscopeClient:
    """Typed methods over one channel to a Fractoscope server."""

    def __init__(
        self,
        address: str,
        *,
        max_message_mb: int = DEFAULT_MAX_MESSAGE_MB,
        timeout_s: float | None = 3600.0,
        token: str | None = None,
        tls_ca_path: str | None = None,
    ):
        """`token` (default FRACTO_TOKEN) is sent as a bearer token; `tls_ca_path` (default
        FRACTO_TLS_CA) switches to TLS, trusting that PEM certificate authority."""
        options = message_size_options(max_message_mb) + [("grpc.service_config", _SERVICE_CONFIG), ("grpc.enable_retries", 1)]
        tls_ca_path = tls_ca_path or os.environ.get("FRACTO_TLS_CA") or None
        if tls_ca_path:
            credentials = grpc.ssl_channel_credentials(root_certificates=Path(tls_ca_path).read_bytes())
            channel = grpc.secure_channel(address, credentials, options=options)
        else:
            channel = grpc.insecure_channel(address, options=options)
        token = token or os.environ.get("FRACTO_TOKEN") or None
        self._channel = grpc.intercept_channel(channel, _BearerToken(token)) if token else channel
        self._raw_channel = channel
        self._matching = matching_pb2_grpc.MatchingServiceStub(self._channel)
        self._meshing = meshing_pb2_grpc.MeshingServiceStub(self._channel)
        self._tiles = tiles_pb2_grpc.TileServiceStub(self._channel)
        self._timeout_s = timeout_s

    def __enter__(self) -> FractoscopeClient:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._raw_channel.close()

    def compute_height_map(
        self,
        images: Sequence[str | Path | bytes],
        *,
        tilt_deg: Sequence[float] | None = None,
        pixel_size_um: float | None = None,
        tilt_axis_deg: float | None = None,
        parameters: matching_pb2.MatchingParameters | None = None,
        calibrate_tilt: bool = False,
        normalize_local_contrast: bool | None = None,
        propagate_at_full_resolution: bool = False,
        on_progress: ProgressCallback | None = None,
        request_id: str = "",
    ) -> HeightMap:
        """Heights from a pair or tilt series of images (paths or file bytes), reference first;
        tilts and pixel size default to the files' metadata. With `calibrate_tilt` (three or more
        images) the tilts are estimated from the images; the report then holds them in `tilt_deg`
        with `tilt_deg_nominal`, `tilt_sigma_deg` and `tilt_residual_px`. `normalize_local_contrast`
        (None: the server's default, on) and `propagate_at_full_resolution`: see
        MatchingParameters (against shading that changes with the tilt, and for surfaces with
        steps)."""
        request = matching_pb2.ComputeHeightMapRequest(request_id=request_id, parameters=parameters)
        if calibrate_tilt:
            request.parameters.calibrate_tilt = True
        if normalize_local_contrast is not None:
            request.parameters.normalize_local_contrast = normalize_local_contrast
        if propagate_at_full_resolution:
            request.parameters.propagate_at_full_resolution = True
        for index, image in enumerate(images):
            content = image if isinstance(image, bytes) else Path(image).read_bytes()
            name = "" if isinstance(image, bytes) else Path(image).name
            item = request.images.add()  # filled in place: nesting a built message would copy the image
            item.image.content, item.image.filename = content, name
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


    def match_strip(self, task: StripTask, *, request_id: str = "") -> tuple[DisparityResult, str]:
        """Dense disparity of one strip of a rectified pair, matched by the server; returns it
        with the id of the replica that matched it."""
        first, stop = task.keep_rows or (0, 0)
        request = matching_pb2.MatchStripRequest(
            keep_from_row=first, keep_to_row=stop,
            parameters=matching_pb2.MatchingParameters(
                window_px=task.window_px, max_disparity_px=task.max_disparity_px,
                min_confidence=task.min_confidence, max_lr_difference_px=task.max_lr_difference_px,
                propagate_at_full_resolution=task.propagate_at_full_resolution,
            ),
            request_id=request_id,
        )
        wire.fill_raster(request.left, _exact_integers(task.left))
        wire.fill_raster(request.right, _exact_integers(task.right))
        with _translated_errors():
            response = self._matching.MatchStrip(request, timeout=self._timeout_s)
        arrays = (wire.raster_to_array(raster) for raster in (response.disparity_px, response.confidence, response.sigma_px))
        return DisparityResult(*arrays), response.worker

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
        plain_glb: bool = False,
    ) -> tuple[list[EncodedTile], dict]:
        """GLB levels of detail of a height map ((rows, cols) µm, NaN unknown) textured with a grey
        image of the same shape, pixel (0, 0) placed at `origin_um` (x, y); returns the tiles (finest
        level first) and the filter report. `plain_glb`: float32 GLBs without extensions, for tools
        that lack a meshopt decoder (about five times larger)."""
        request = meshing_pb2.BuildMeshRequest(
            filter=filter_parameters, method=method, level_count=level_count, request_id=request_id, plain_glb=plain_glb,
            origin_um=common_pb2.PointUm(x_um=origin_um[0], y_um=origin_um[1]),
        )
        request.height_map.pixel_size_um = pixel_size_um
        wire.fill_raster(request.height_map.z_um, np.asarray(z_um, np.float32))
        if texture is not None:
            wire.fill_raster(request.height_map.texture, texture)
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


    def reconstruct_specimen(
        self,
        specimen_id: str,
        rois: Sequence[tiles_pb2.RoiSpec],
        *,
        request_id: str = "",
        on_progress: ProgressCallback | None = None,
    ) -> dict:
        """Builds a specimen from its ROIs (see `manifest.load_manifest`); returns its summary."""
        request = tiles_pb2.ReconstructSpecimenRequest(specimen_id=specimen_id, rois=rois, request_id=request_id)
        final = None
        with _translated_errors():
            for response in self._tiles.ReconstructSpecimen(request, timeout=self._timeout_s):
                if response.HasField("progress"):
                    if on_progress:
                        on_progress(response.progress.fraction, response.progress.message)
                else:
                    final = response.specimen
        if final is None:
            raise ClientError(grpc.StatusCode.INTERNAL, "the server closed the stream without a specimen")
        return _as_dict(final)

    def get_specimen(self, specimen_id: str) -> dict:
        """A stored specimen's summary: ROIs with placement and fit figures, tileset URI."""
        with _translated_errors():
            return _as_dict(self._tiles.GetSpecimen(tiles_pb2.GetSpecimenRequest(specimen_id=specimen_id), timeout=self._timeout_s).specimen)

    def list_specimens(self) -> list[dict]:
        with _translated_errors():
            return [_as_dict(s) for s in self._tiles.ListSpecimens(tiles_pb2.ListSpecimensRequest(), timeout=self._timeout_s).specimens]

    def get_tileset(self, specimen_id: str) -> dict:
        """The specimen's 3D Tiles 1.1 tileset.json, parsed."""
        with _translated_errors():
            response = self._tiles.GetTileset(tiles_pb2.GetTilesetRequest(specimen_id=specimen_id), timeout=self._timeout_s)
        return json.loads(response.tileset_json)

    def get_tile(self, specimen_id: str, uri: str) -> bytes:
        """One tile's GLB, by its URI in tileset.json."""
        with _translated_errors():
            return self._tiles.GetTile(tiles_pb2.GetTileRequest(specimen_id=specimen_id, uri=uri), timeout=self._timeout_s).tile.glb

    def stream_view(self, specimen_id: str, region_um: Region, *, viewport_px: int = 1024) -> Iterator[tiles_pb2.Tile]:
        """The tiles that show a region (x0, y0, x1, y1) µm on a screen `viewport_px` wide, coarse first."""
        request = tiles_pb2.StreamViewRequest(specimen_id=specimen_id, region=_region(region_um), viewport_px=viewport_px)
        with _translated_errors():
            for response in self._tiles.StreamView(request, timeout=self._timeout_s):
                yield response.tile

    def zoom(self, specimen_id: str, region_um: Region, *, magnification: float) -> list[dict]:
        """The tiles that show a region at a magnification: uri, roi, magnification, zoom
        ("optical" where that ROI's data is at least as fine, "digital" where it is upsampled)."""
        request = tiles_pb2.ZoomRequest(specimen_id=specimen_id, region=_region(region_um), magnification=magnification)
        with _translated_errors():
            tiles = self._tiles.Zoom(request, timeout=self._timeout_s).tiles
        return [
            {"uri": t.uri, "roi": t.roi, "magnification": t.magnification, "zoom": _ZOOM_NAMES.get(t.zoom, "unknown"),
             "geometric_error_m": t.geometric_error_m}
            for t in tiles
        ]

    def profile(
        self, specimen_id: str, points_um: Sequence[tuple[float, float]], *, spacing_um: float = 0.0, magnification: float = 0.0
    ) -> Profile:
        """Heights along a polyline of (x, y) µm points in the specimen frame; finest data unless a
        magnification is given."""
        request = tiles_pb2.GetProfileRequest(
            specimen_id=specimen_id, points=[common_pb2.PointUm(x_um=x, y_um=y) for x, y in points_um],
            spacing_um=spacing_um, magnification=magnification,
        )
        with _translated_errors():
            response = self._tiles.GetProfile(request, timeout=self._timeout_s)
        parameters = {}
        if response.HasField("parameters"):
            p = response.parameters
            parameters = {"Ra": p.ra_um, "Rq": p.rq_um, "Rz": p.rz_um, "Rsk": p.rsk, "Rku": p.rku}
        names = list(response.sources) + [""]  # index -1: no data
        return Profile(
            np.array(response.distance_um), np.array(response.z_um), [names[i] for i in response.source_index], parameters
        )

    def roughness(self, specimen_id: str, *, roi: str | None = None, region_um: Region | None = None) -> dict:
        """ISO 25178-2 parameters by their ISO names (Sa ... Sz in µm, Sdr in %) and fracture
        metrics (hurst_exponent, its fit range in µm, fractal_dimension, the height-height curve)
        of an ROI or a region of the fused surface (default: the overview ROI)."""
        request = tiles_pb2.GetRoughnessRequest(specimen_id=specimen_id)
        if region_um is not None:
            request.region.CopyFrom(_region(region_um))
        elif roi is not None:
            request.roi = roi
        else:
            request.roi = self.get_specimen(specimen_id)["rois"][0]["id"]
        with _translated_errors():
            response = self._tiles.GetRoughness(request, timeout=self._timeout_s)
        values = json_format.MessageToDict(response, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)
        return {_ROUGHNESS_NAMES.get(key, key): value for key, value in values.items()}


class _BearerToken(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor):
    """Adds `authorization: Bearer TOKEN` to every call."""

    def __init__(self, token: str):
        self._metadata = ("authorization", f"Bearer {token}")

    def _with_token(self, details):
        # grpc passes its call details as a namedtuple.
        return details._replace(metadata=list(details.metadata or []) + [self._metadata])

    def intercept_unary_unary(self, continuation, details, request):
        return continuation(self._with_token(details), request)

    def intercept_unary_stream(self, continuation, details, request):
        return continuation(self._with_token(details), request)


def _exact_integers(values: np.ndarray) -> np.ndarray:
    """Float grey values that are whole numbers within 0..65535 as uint8 or uint16 (half or a
    quarter of the bytes on the wire, the same values), others unchanged."""
    if values.dtype.kind != "f" or values.size == 0:
        return values
    low, high = float(values.min()), float(values.max())
    if low < 0 or high > 65535 or not np.array_equal(values, np.rint(values)):
        return values
    return values.astype(np.uint8 if high <= 255 else np.uint16)


def _region(region_um: Region) -> tiles_pb2.RegionUm:
    x0, y0, x1, y1 = region_um
    return tiles_pb2.RegionUm(min=common_pb2.PointUm(x_um=x0, y_um=y0), max=common_pb2.PointUm(x_um=x1, y_um=y1))


def _as_dict(message) -> dict:
    return json_format.MessageToDict(message, preserving_proto_field_name=True, always_print_fields_with_no_presence=True)


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
def embedded_server(data_dir: str | Path = "data", *, host: str = "127.0.0.1", port: int = 0) -> Iterator[str]:
    """Runs all services in this process on `host:port` (port 0: a free one) for the block's
    duration, with specimens kept under `data_dir`; yields the address."""
    from fractoscope.services.server import create_server

    server, bound = create_server(f"{host}:{port}", data_dir=data_dir)
    server.start()
    try:
        yield f"{host}:{bound}"
    finally:
        server.stop(grace=None)
