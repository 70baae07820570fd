"""Inputs a hostile user sends (issue 49, items 5 and 10): images with a side OpenCV cannot take,
maps of one cell's height, enumeration values the API lacks. Each is refused with
INVALID_ARGUMENT (HTTP 400) naming the input, or answered, never INTERNAL."""

from __future__ import annotations

import json

import cv2
import grpc
import numpy as np
import pytest
import requests
from probe_servers import WRITE, WRITE_METADATA

from fractoscope.rpc import calls
from fractoscope.rpc.status import ClientError, raised_as_client_errors
from fractoscope.v1 import (
    common_pb2,
    matching_pb2,
    matching_pb2_grpc,
    meshing_pb2_grpc,
    tiles_pb2,
    tiles_pb2_grpc,
)

MAX_SIDE_PX = 32766  # sem.image.MAX_SIDE_PX: OpenCV takes sides below SHRT_MAX


def _png(rows: int, cols: int, seed: int = 0) -> bytes:
    return cv2.imencode(".png", np.random.default_rng(seed).integers(0, 255, (rows, cols), np.uint8))[1].tobytes()


def _refusal(call) -> ClientError:
    """The ClientError a call (a function of no arguments that makes it) ends with."""
    with pytest.raises(ClientError) as refused, raised_as_client_errors():
        result = call()
        if not isinstance(result, matching_pb2.MatchStripResponse):
            list(result)
    return refused.value


@pytest.fixture(scope="module")
def channel(live):
    with grpc.insecure_channel(live.grpc_address, options=[("grpc.max_receive_message_length", 1 << 30)]) as opened:
        yield opened


def _pair(rows: int, cols: int) -> list[tuple[bytes, str]]:
    return [(_png(rows, cols, 0), "left.png"), (_png(rows, cols, 1), "right.png")]


@pytest.mark.parametrize("rows, cols", [(64, 40000), (32767, 32)])
def test_an_image_side_of_32767_px_or_more_is_refused_naming_the_image(channel, rows, cols):
    """Once INTERNAL (OpenCV's SHRT_MAX assertion) in ComputeHeightMap and ReconstructSpecimen."""
    request = calls.height_map_request(_pair(rows, cols), tilt_deg=[-5, 5], pixel_size_um=0.1)
    stub = matching_pb2_grpc.MatchingServiceStub(channel)
    refused = _refusal(lambda: stub.ComputeHeightMap(request, metadata=WRITE_METADATA, timeout=60))
    assert (refused.code, refused.field) == (grpc.StatusCode.INVALID_ARGUMENT, "images[0].image")
    assert str(MAX_SIDE_PX) in str(refused)
    roi = tiles_pb2.RoiSpec(id="overview", images=request.images, pixel_size_um=0.1)
    build = tiles_pb2.ReconstructSpecimenRequest(specimen_id="wide", rois=[roi])
    tiles = tiles_pb2_grpc.TileServiceStub(channel)
    refused = _refusal(lambda: tiles.ReconstructSpecimen(build, metadata=WRITE_METADATA, timeout=60))
    assert (refused.code, refused.field) == (grpc.StatusCode.INVALID_ARGUMENT, "rois[0].images[0].image")


def test_a_tilt_axis_that_turns_images_past_opencvs_sides_is_refused_naming_it(channel):
    """32000 x 8000 images are within the sides, but a tilt axis at 14° turns them onto a canvas
    32,985 px high, on which the matcher would fail as above."""
    flat = cv2.imencode(".png", np.zeros((8000, 32000), np.uint8))[1].tobytes()
    request = calls.height_map_request(
        [(flat, "left.png"), (flat, "right.png")], tilt_deg=[-5, 5], pixel_size_um=0.1, tilt_axis_deg=14.0
    )
    stub = matching_pb2_grpc.MatchingServiceStub(channel)
    refused = _refusal(lambda: stub.ComputeHeightMap(request, metadata=WRITE_METADATA, timeout=60))
    assert (refused.code, refused.field) == (grpc.StatusCode.INVALID_ARGUMENT, "tilt_axis_deg")


def test_a_strip_longer_than_opencv_takes_is_refused_naming_left(channel):
    """Once INTERNAL from MatchStrip."""
    strip = np.zeros((16, 40000), np.uint8)
    request = matching_pb2.MatchStripRequest(
        parameters=matching_pb2.MatchingParameters(window_px=11, max_disparity_px=8)
    )
    calls.wire.fill_raster(request.left, strip)
    calls.wire.fill_raster(request.right, strip)
    stub = matching_pb2_grpc.MatchingServiceStub(channel)
    refused = _refusal(lambda: stub.MatchStrip(request, metadata=WRITE_METADATA, timeout=60))
    assert (refused.code, refused.field) == (grpc.StatusCode.INVALID_ARGUMENT, "left")


def test_an_upload_of_an_image_too_long_a_side_is_refused_naming_the_manifest_entry(live):
    """Once 201, and the job failed later (INTERNAL)."""
    manifest = {
        "specimen": "wide",
        "rois": [{"id": "overview", "left": "l.png", "right": "r.png", "tilt_deg": [-5, 5], "pixel_size_um": 0.1}],
    }
    parts = [("manifest", (None, json.dumps(manifest), "application/json"))] + [
        ("images", (name, content, "image/png")) for (content, _), name in zip(_pair(64, 40000), ("l.png", "r.png"))
    ]
    answer = requests.post(f"{live.http}/api/uploads", files=parts, headers=WRITE, timeout=60)
    assert answer.status_code == 400, answer.text
    assert answer.json()["field"] == "manifest.rois[0].left"


def test_a_mesh_of_a_two_row_map_is_built(channel):
    """BuildMesh on 2 x 100000 maps once answered INTERNAL: its coarser levels have one row of
    cells, no quad, which drop_islands handed to OpenCV as an empty image."""
    z_um = np.random.default_rng(1).normal(size=(2, 100000)).astype(np.float32)
    request = calls.mesh_request(z_um, None, pixel_size_um=1.0)
    stub = meshing_pb2_grpc.MeshingServiceStub(channel)
    with raised_as_client_errors():
        tiles, _ = calls.read_mesh(stub.BuildMesh(request, metadata=WRITE_METADATA, timeout=300), None)
    finest = [tile for tile in tiles if tile.level == 0]
    assert finest and sum(tile.triangle_count for tile in finest) == 2 * 99999


@pytest.mark.parametrize("call", ["BuildMesh", "ReconstructSpecimen"])
def test_an_unknown_unmeasured_value_is_refused_naming_it(channel, call):
    """unmeasured=99 was taken as ABSENT by ReconstructSpecimen."""
    if call == "BuildMesh":
        request = calls.mesh_request(np.zeros((64, 64), np.float32), None, pixel_size_um=1.0, unmeasured=99)
        make = lambda: meshing_pb2_grpc.MeshingServiceStub(channel).BuildMesh(  # noqa: E731
            request, metadata=WRITE_METADATA, timeout=60
        )
    else:
        pair = calls.height_map_request(_pair(64, 64), tilt_deg=[-5, 5], pixel_size_um=0.1)
        roi = tiles_pb2.RoiSpec(id="overview", images=pair.images, pixel_size_um=0.1)
        request = tiles_pb2.ReconstructSpecimenRequest(specimen_id="enum", rois=[roi], unmeasured=99)
        make = lambda: tiles_pb2_grpc.TileServiceStub(channel).ReconstructSpecimen(  # noqa: E731
            request, metadata=WRITE_METADATA, timeout=60
        )
    refused = _refusal(make)
    assert (refused.code, refused.field) == (grpc.StatusCode.INVALID_ARGUMENT, "unmeasured")
    assert common_pb2.UnmeasuredAreas.Name(common_pb2.UNMEASURED_AREAS_FLAT) in str(refused)
