"""Python client library of Fractoscope's gRPC API. It loads gRPC, protobuf and numpy, never the
image processing and meshing libraries the services use.

Example::

    from fractoscope.client import FractoscopeClient

    with FractoscopeClient("127.0.0.1:50051") as client:
        result = client.compute_height_map(["left.tif", "right.tif"], tilt_deg=(-5, 5), pixel_size_um=0.1)
        print(result.report["valid_fraction"], result.z_um.shape)

(`fractoscope.server.main.embedded_server()` runs the services in-process for such a block.)
"""

from __future__ import annotations

import os

# gRPC core logs connection teardown (GOAWAY) at INFO on stderr, which would break the CLI's
# one-line errors; users can still ask for more with GRPC_VERBOSITY.
os.environ.setdefault("GRPC_VERBOSITY", "ERROR")
import json
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from google.protobuf import json_format

from fractoscope.errors import InvalidInputError
from fractoscope.rpc import calls, wire
from fractoscope.rpc.calls import HeightMap, ProgressCallback
from fractoscope.rpc.channel import ChannelOwner, open_channel
from fractoscope.rpc.limits import DEFAULT_MAX_MESSAGE_MB
from fractoscope.rpc.status import ClientError, raised_as_client_errors
from fractoscope.rpc.wire import Region
from fractoscope.v1 import (
    common_pb2,
    matching_pb2,
    matching_pb2_grpc,
    meshing_pb2,
    meshing_pb2_grpc,
    tiles_pb2,
    tiles_pb2_grpc,
)

__all__ = ["ClientError", "FractoscopeClient", "HeightMap", "Profile"]


@dataclass(frozen=True)
class Profile:
    """A profile: (n,) distance along the line µm, height µm (NaN unknown), source ROI per sample,
    the ISO 21920-2 parameters of its roughness profile (Ra ... Rmr2 by ISO name, µm where
    dimensional; empty if too few heights), the roughness profile (n,) µm (NaN where unknown), and
    the chain that made it: {"form", "s_filter_um", "l_filter_um", ...,
    "cutoffs_from_iso_table", "spacing_within_iso"} (0: filter not applied)."""

    distance_um: np.ndarray
    z_um: np.ndarray
    source: list[str]
    parameters: dict
    roughness_um: np.ndarray | None = None
    chain: dict = field(default_factory=dict)


class FractoscopeClient(ChannelOwner):
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
        self._channel = open_channel(address, max_message_mb=max_message_mb, token=token, tls_ca_path=tls_ca_path)
        self._matching = matching_pb2_grpc.MatchingServiceStub(self._channel)
        self._meshing = meshing_pb2_grpc.MeshingServiceStub(self._channel)
        self._tiles = tiles_pb2_grpc.TileServiceStub(self._channel)
        self._timeout_s = timeout_s

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
        method: str | None = None,
        relief_sign: str | None = None,
        detector_from_tilt_axis_deg: float | None = None,
        on_progress: ProgressCallback | None = None,
        request_id: str = "",
    ) -> HeightMap:
        """Heights from a pair or tilt series of images (paths or file bytes), reference first;
        tilts and pixel size default to the files' metadata. With `calibrate_tilt` (three or more
        images) the tilts are estimated from the images; the report then holds them in `tilt_deg`
        with `tilt_deg_nominal`, `tilt_sigma_deg` and `tilt_residual_px`. `normalize_local_contrast`
        (None: the server's default, on) and `propagate_at_full_resolution`: see
        MatchingParameters (against shading that changes with the tilt, and for surfaces with
        steps). `method`: one of wire.method_names() (None: the server's default; see the API's
        MatchingMethod). `relief_sign`: one of wire.relief_sign_names() (None: the server's
        default, auto; see ReliefSignMode), with where the detector lies,
        `detector_from_tilt_axis_deg` (° from the tilt axis; None: not known, see MatchingParameters).
        The report's relief_sign fields give the verdict."""
        files = [
            (image, "") if isinstance(image, bytes) else (Path(image).read_bytes(), Path(image).name)
            for image in images
        ]
        request = calls.height_map_request(
            files,
            tilt_deg=tilt_deg,
            pixel_size_um=pixel_size_um,
            tilt_axis_deg=tilt_axis_deg,
            parameters=parameters,
            request_id=request_id,
        )
        if calibrate_tilt:
            request.parameters.calibrate_tilt = True
        if normalize_local_contrast is not None:
            request.parameters.normalize_local_contrast = normalize_local_contrast
        if propagate_at_full_resolution:
            request.parameters.propagate_at_full_resolution = True
        if method is not None:
            request.parameters.method = _matching_method(method)
        if relief_sign is not None:
            request.parameters.relief_sign = _relief_sign_mode(relief_sign)
        if detector_from_tilt_axis_deg is not None:
            request.parameters.detector_from_tilt_axis_deg = detector_from_tilt_axis_deg
        with raised_as_client_errors():
            return calls.read_height_map(self._matching.ComputeHeightMap(request, timeout=self._timeout_s), on_progress)

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
        max_slope: float = 0.0,
        sigma_um: np.ndarray | None = None,
        unmeasured: int = 0,
        min_island_px: float | None = None,
        resolution_px: float = 0.0,
    ) -> tuple[list[meshing_pb2.MeshTile], dict]:
        """GLB levels of detail of a height map ((rows, cols) µm, NaN unknown) textured with a grey
        image of the same shape, pixel (0, 0) placed at `origin_um` (x, y); returns the tiles (finest
        level first; MeshTile messages: level, tile_row, tile_col, glb, geometric_error_m,
        vertex_count, triangle_count, wall_triangle_count; tiles with nothing measured are left
        out) and the filter report. `plain_glb`: float32 GLBs without extensions, for tools that
        lack a meshopt decoder (about five times larger). `max_slope` (the steepest slope the
        heights' measurement supports) with `sigma_um` (each height's local uncertainty, µm)
        marks the triangles across steeper jumps as walls (see BuildMeshRequest). `unmeasured`
        (UnmeasuredAreas), `min_island_px` (None: the server's default) and `resolution_px` (the
        heights' horizontal resolution, which the normals are shaded at) as BuildMeshRequest says."""
        request = calls.mesh_request(
            z_um,
            texture,
            pixel_size_um=pixel_size_um,
            origin_um=origin_um,
            sigma_um=sigma_um,
            method=method,
            level_count=level_count,
            filter=filter_parameters,
            request_id=request_id,
            plain_glb=plain_glb,
            max_slope=max_slope,
            unmeasured=unmeasured,
            resolution_px=resolution_px,
            **({} if min_island_px is None else {"min_island_px": min_island_px}),
        )
        with raised_as_client_errors():
            return calls.read_mesh(self._meshing.BuildMesh(request, timeout=self._timeout_s), on_progress)

    def reconstruct_specimen(
        self,
        specimen_id: str,
        rois: Sequence[tiles_pb2.RoiSpec],
        *,
        request_id: str = "",
        on_progress: ProgressCallback | None = None,
        unmeasured: int = 0,
    ) -> dict:
        """Builds a specimen from its ROIs (see `client.manifest.load_manifest`); returns its summary.
        `unmeasured` (UnmeasuredAreas): how its tiles show what nothing measured."""
        request = tiles_pb2.ReconstructSpecimenRequest(
            specimen_id=specimen_id, rois=rois, request_id=request_id, unmeasured=unmeasured
        )
        with raised_as_client_errors():
            final = calls.read_final(
                self._tiles.ReconstructSpecimen(request, timeout=self._timeout_s), on_progress, missing="a specimen"
            )
        return _as_dict(final.specimen)

    def get_specimen(self, specimen_id: str) -> dict:
        """A stored specimen's summary: ROIs with placement and fit figures, tileset URI."""
        with raised_as_client_errors():
            return _as_dict(
                self._tiles.GetSpecimen(
                    tiles_pb2.GetSpecimenRequest(specimen_id=specimen_id), timeout=self._timeout_s
                ).specimen
            )

    def list_specimens(self) -> list[dict]:
        with raised_as_client_errors():
            return [
                _as_dict(s)
                for s in self._tiles.ListSpecimens(tiles_pb2.ListSpecimensRequest(), timeout=self._timeout_s).specimens
            ]

    def get_tileset(self, specimen_id: str) -> dict:
        """The specimen's 3D Tiles 1.1 tileset.json, parsed."""
        with raised_as_client_errors():
            response = self._tiles.GetTileset(
                tiles_pb2.GetTilesetRequest(specimen_id=specimen_id), timeout=self._timeout_s
            )
        return json.loads(response.tileset_json)

    def get_tile(self, specimen_id: str, uri: str) -> bytes:
        """One tile's GLB, by its URI in tileset.json."""
        with raised_as_client_errors():
            return self._tiles.GetTile(
                tiles_pb2.GetTileRequest(specimen_id=specimen_id, uri=uri), timeout=self._timeout_s
            ).tile.glb

    def stream_view(
        self, specimen_id: str, region_um: Region, *, viewport_px: int = wire.DEFAULT_VIEWPORT_PX
    ) -> Iterator[tiles_pb2.Tile]:
        """The tiles that show a region (x0, y0, x1, y1) µm on a screen `viewport_px` wide, coarse first."""
        request = tiles_pb2.StreamViewRequest(
            specimen_id=specimen_id, region=wire.region_message(region_um), viewport_px=viewport_px
        )
        with raised_as_client_errors():
            for response in self._tiles.StreamView(request, timeout=self._timeout_s):
                yield response.tile

    def zoom(self, specimen_id: str, region_um: Region, *, magnification: float) -> list[dict]:
        """The tiles that show a region at a magnification: uri, roi, magnification, zoom
        ("optical" where that ROI's data is at least as fine, "digital" where it is upsampled)."""
        request = tiles_pb2.ZoomRequest(
            specimen_id=specimen_id, region=wire.region_message(region_um), magnification=magnification
        )
        with raised_as_client_errors():
            tiles = self._tiles.Zoom(request, timeout=self._timeout_s).tiles
        return [
            {
                "uri": t.uri,
                "roi": t.roi,
                "magnification": t.magnification,
                "zoom": wire.zoom_name(t.zoom),
                "geometric_error_m": t.geometric_error_m,
            }
            for t in tiles
        ]

    def profile(
        self,
        specimen_id: str,
        points_um: Sequence[tuple[float, float]],
        *,
        spacing_um: float = 0.0,
        magnification: float = 0.0,
        form: str | None = None,
        s_filter_um: float | None = None,
        l_filter_um: float | None = None,
    ) -> Profile:
        """Heights along a polyline of (x, y) µm points in the specimen frame; finest data unless a
        magnification is given. The roughness profile: `form` removed ("plane", the default, is
        the least-squares line; "none", "poly2" ... "poly6", "sphere", "cylinder"), then the S- and
        L-filters (cut-offs µm; None: the ISO 21920-3 defaults for the length, 0: none)."""
        request = tiles_pb2.GetProfileRequest(
            specimen_id=specimen_id,
            points=[common_pb2.PointUm(x_um=x, y_um=y) for x, y in points_um],
            spacing_um=spacing_um,
            magnification=magnification,
            chain=wire.chain_message(form=form, s_filter_um=s_filter_um, l_filter_um=l_filter_um),
        )
        with raised_as_client_errors():
            response = self._tiles.GetProfile(request, timeout=self._timeout_s)
        parameters = wire.message_to_profile_parameters(response.parameters) if response.HasField("parameters") else {}
        names = list(response.sources) + [""]  # index -1: no data
        chain = {}
        if response.HasField("chain"):
            chain = {
                **wire.chain_to_dict(response.chain),
                "cutoffs_from_iso_table": response.cutoffs_from_iso_table,
                "spacing_within_iso": response.spacing_within_iso,
            }
        return Profile(
            np.array(response.distance_um),
            np.array(response.z_um),
            [names[i] for i in response.source_index],
            parameters,
            np.array(response.roughness_um) if len(response.roughness_um) else None,
            chain,
        )

    def roughness(self, specimen_id: str, *, roi: str | None = None, region_um: Region | None = None, **chain) -> dict:
        """The ISO 25178 chain on an ROI or a region of the fused surface (default: the overview
        ROI), set by `chain`, the keywords of `wire.chain_message` (None: the default): `form`
        removed (default "plane", by least squares, or robustly with `robust_form`; levelled on
        `levelling_region_um` if given), the S- and L-filters `s_filter_um`, `l_filter_um`
        (cut-offs µm; None or 0: none); then every ISO 25178-2 parameter by ISO name with its
        uncertainty, the Hurst exponent by both methods along and across `direction_deg`
        (fitted from `min_windows` matching windows of `window_px` up), the PSD, and the chain as
        run (see `wire.response_to_roughness` for the keys)."""
        request = tiles_pb2.GetRoughnessRequest(specimen_id=specimen_id, chain=wire.chain_message(**chain))
        if region_um is not None:
            request.region.CopyFrom(wire.region_message(region_um))
        elif roi is not None:
            request.roi = roi  # neither: the server takes the overview
        with raised_as_client_errors():
            response = self._tiles.GetRoughness(request, timeout=self._timeout_s)
        return wire.response_to_roughness(response)

    def export_area(
        self,
        specimen_id: str,
        path: str | Path,
        *,
        roi: str | None = None,
        region_um: Region | None = None,
        pixel_size_um: float | None = None,
        solid: bool = False,
        units: str = "um",
    ) -> dict:
        """Writes an ROI (default: the overview) or a region (x0, y0, x1, y1) µm of a specimen to
        `path`, in the format its extension names (.x3p, .tif, .csv, .stl, .ply, .obj), at
        `pixel_size_um` (default: the ROI's, or the finest in the region); `solid` and `units`
        ("um" or "mm") for meshes. The file appears complete or not at all. Returns the grid
        written (rows, cols, pixel_size_um, origin_um)."""
        request = tiles_pb2.ExportRequest(specimen=wire.specimen_area(specimen_id, roi=roi, region_um=region_um))
        return self._export(request, path, pixel_size_um=pixel_size_um, solid=solid, units=units)

    def export_height_map(
        self,
        z_um: np.ndarray,
        path: str | Path,
        *,
        pixel_size_um: float,
        sigma_um: np.ndarray | None = None,
        report: dict | None = None,
        export_pixel_size_um: float | None = None,
        solid: bool = False,
        units: str = "um",
    ) -> dict:
        """Writes a height map ((rows, cols) µm, NaN unknown, grid step `pixel_size_um`) to `path`
        as `export_area` does, area-averaged onto `export_pixel_size_um` when given; `report` (a
        height map's matching report) puts its calibration into the file."""
        request = tiles_pb2.ExportRequest(report=wire.report_to_message(report) if report else None)
        request.height_map.pixel_size_um = pixel_size_um
        wire.fill_raster(request.height_map.z_um, np.asarray(z_um, np.float32))
        if sigma_um is not None:
            wire.fill_raster(request.height_map.sigma_um, np.asarray(sigma_um, np.float32))
        return self._export(request, path, pixel_size_um=export_pixel_size_um, solid=solid, units=units)

    def _export(self, request: tiles_pb2.ExportRequest, path, *, pixel_size_um, solid, units) -> dict:
        request.format = wire.EXPORT_FORMATS[wire.export_format_of(str(path))]
        request.pixel_size_um = pixel_size_um or 0.0
        request.solid = solid
        if units not in wire.LENGTH_UNITS:
            raise InvalidInputError("units", f"{units!r} is none of {sorted(wire.LENGTH_UNITS)}")
        request.units = wire.LENGTH_UNITS[units]
        with raised_as_client_errors():
            first = calls.read_file(self._tiles.Export(request, timeout=self._timeout_s), path)
        return _as_dict(first.grid)

    def report(
        self, specimen_id: str, path: str | Path, *, roi: str | None = None, region_um: Region | None = None
    ) -> Path:
        """Writes the measurement report of an ROI (default: the overview) or a region to `path`,
        HTML or PDF as its extension says (.html, .pdf)."""
        suffix = Path(path).suffix.lower().lstrip(".")
        if suffix not in wire.REPORT_FORMATS:
            raise InvalidInputError("output", f"extension .{suffix} is neither .html nor .pdf")
        request = tiles_pb2.GetReportRequest(
            area=wire.specimen_area(specimen_id, roi=roi, region_um=region_um), format=wire.REPORT_FORMATS[suffix]
        )
        with raised_as_client_errors():
            calls.read_file(self._tiles.GetReport(request, timeout=self._timeout_s), path)
        return Path(path)


def _as_dict(message) -> dict:
    return json_format.MessageToDict(
        message, preserving_proto_field_name=True, always_print_fields_with_no_presence=True
    )


def _matching_method(name: str) -> int:
    """A matching method's name (one of wire.method_names()) as a MatchingMethod value;
    ValueError naming `method` otherwise."""
    try:
        return wire.method_code(name)
    except ValueError:
        known = ", ".join(repr(known) for known in wire.method_names())
        raise ValueError(f"method must be one of {known}, got {name!r}") from None


def _relief_sign_mode(name: str) -> int:
    """A relief sign mode's name (one of wire.relief_sign_names()) as a ReliefSignMode value;
    ValueError naming `relief_sign` otherwise."""
    try:
        return wire.relief_sign_code(name)
    except ValueError:
        known = ", ".join(repr(known) for known in wire.relief_sign_names())
        raise ValueError(f"relief_sign must be one of {known}, got {name!r}") from None
