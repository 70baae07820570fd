"""Failures that once got the wrong status or blamed the wrong field: a full disk, a PNG over the
size limits, a child ROI centred far outside its parent, and one that matches nothing in it."""

from __future__ import annotations

import errno
import pathlib
import struct
import zlib

import grpc
import numpy as np
import pytest
from conftest import fracture_pair, tiff_bytes

from fractoscope.client import ClientError
from fractoscope.sem import image as sem_image
from fractoscope.v1 import common_pb2, tiles_pb2


def _roi(
    roi_id: str, first: np.ndarray, second: np.ndarray, *, pixel_size_um: float, parent: str = "", center_um=None
) -> tiles_pb2.RoiSpec:
    spec = tiles_pb2.RoiSpec(id=roi_id, parent=parent, pixel_size_um=pixel_size_um)
    if center_um is not None:
        spec.center_um.CopyFrom(common_pb2.PointUm(x_um=center_um[0], y_um=center_um[1]))
    for image, tilt_deg in ((first, -5.0), (second, 5.0)):
        spec.images.add(tilt_deg=tilt_deg).image.content = tiff_bytes(image)
    return spec


@pytest.fixture(scope="module")
def overview() -> tiles_pb2.RoiSpec:
    pair = fracture_pair(size_px=256, seed=11)
    return _roi("overview", pair.first, pair.second, pixel_size_um=0.1)


def test_a_full_disk_is_resource_exhausted_with_its_message_and_keeps_the_stored_build(client, overview, monkeypatch):
    first = client.reconstruct_specimen("steel-1", [overview], request_id="first")
    original = pathlib.Path.write_bytes

    def full(path, data):
        if ".staging-" in str(path):
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        return original(path, data)

    monkeypatch.setattr(pathlib.Path, "write_bytes", full)
    with pytest.raises(ClientError) as refused:
        client.reconstruct_specimen("steel-1", [overview], request_id="second")
    assert refused.value.code == grpc.StatusCode.RESOURCE_EXHAUSTED
    assert "disk is full (No space left on device)" in str(refused.value) and ".staging" not in str(refused.value)
    monkeypatch.undo()
    assert client.get_specimen("steel-1") == first


def _png_declaring(cols: int, rows: int) -> bytes:
    """A PNG whose header declares cols x rows grey pixels (the data that follows is not that much)."""

    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    header = struct.pack(">IIBBBBB", cols, rows, 8, 0, 0, 0, 0)
    return (
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", header)
        + chunk(b"IDAT", zlib.compress(b"\0" * (cols + 1)))
        + chunk(b"IEND", b"")
    )


def test_a_png_over_the_pixel_limit_is_invalid_argument_about_its_size(client):
    pair = fracture_pair(size_px=64, seed=1)
    for cols, rows in ((20000, 20000), (16384, 16385)):  # over Pillow's own limit too, which called it corrupt
        with pytest.raises(ClientError) as refused:
            client.compute_height_map(
                [_png_declaring(cols, rows), tiff_bytes(pair.second)], tilt_deg=(-5, 5), pixel_size_um=0.1
            )
        assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT and refused.value.field == "images[0].image"
        assert f"{cols}x{rows} pixels is larger than the limit of {sem_image.MAX_IMAGE_PIXELS}" in str(refused.value)
        assert "corrupt" not in str(refused.value)


def test_pngs_within_the_limit_are_not_refused_by_pillows_smaller_one():
    from PIL import Image

    assert Image.MAX_IMAGE_PIXELS >= sem_image.MAX_IMAGE_PIXELS


def test_a_child_centred_far_outside_its_parent_is_blamed_on_its_center_um(client, overview):
    child = fracture_pair(size_px=128, seed=12)
    far = _roi("zoom", child.first, child.second, pixel_size_um=0.05, parent="overview", center_um=(5000.0, 5000.0))
    with pytest.raises(ClientError) as refused:
        client.reconstruct_specimen("steel-2", [overview, far])
    assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT and refused.value.field == "rois[1].center_um"
    assert "'zoom'" in str(refused.value) and "'overview'" in str(refused.value)


def test_a_child_that_matches_nothing_in_its_parent_is_not_placed_automatically(client, overview):
    """Pure noise (the same in both views, so that it matches as a flat surface) cannot be found
    in the overview: refused naming the registration score, instead of placed at random."""
    noise = np.random.default_rng(5).integers(0, 256, (128, 128), dtype=np.uint8)
    lost = _roi("zoom", noise, noise, pixel_size_um=0.05, parent="overview")
    with pytest.raises(ClientError) as refused:
        client.reconstruct_specimen("steel-3", [overview, lost])
    assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT and refused.value.field == "rois[1].center_um"
    assert "registration score 0." in str(refused.value) and "give its center_um" in str(refused.value)


@pytest.mark.parametrize(
    "method",
    [
        "/fractoscope.v1.TileService/GetSpecimen",  # unary
        "/fractoscope.v1.TileService/GetTile",  # unary, its own registration
        "/fractoscope.v1.MatchingService/ComputeHeightMap",  # server-streaming
    ],
)
def test_bytes_that_are_not_the_request_message_are_invalid_argument_about_the_request(server_address, method):
    """gRPC Python answers a request it cannot parse with INTERNAL, as if the server had failed;
    the client sent it, so it is INVALID_ARGUMENT naming `request`."""
    from fractoscope.rpc.status import raised_as_client_errors

    with grpc.insecure_channel(server_address) as channel:
        streaming = method.endswith("ComputeHeightMap")
        call = (channel.unary_stream if streaming else channel.unary_unary)(method)
        with pytest.raises(ClientError) as refused, raised_as_client_errors():
            answer = call(b"\xff\xff\xff\xff", timeout=30)  # a field tag with no end
            if streaming:  # a stream's status comes with its first read
                list(answer)
    assert refused.value.code == grpc.StatusCode.INVALID_ARGUMENT and refused.value.field == "request"
    assert method in str(refused.value)
