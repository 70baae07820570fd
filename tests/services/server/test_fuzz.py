"""Fuzzing: random requests and damaged image files get a clear status, never a crash or a hang."""

from __future__ import annotations

import io

import grpc
import numpy as np
import pytest
import tifffile
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from fractoscope.client import ClientError
from fractoscope.errors import InvalidInputError
from fractoscope.sem.image import read_sem_image
from fractoscope.v1 import common_pb2, matching_pb2, tiles_pb2

FUZZ = settings(
    max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture, HealthCheck.too_slow]
)
EXPECTED = {grpc.StatusCode.INVALID_ARGUMENT, grpc.StatusCode.NOT_FOUND, grpc.StatusCode.FAILED_PRECONDITION}


def _valid_tiff() -> bytes:
    buffer = io.BytesIO()
    tifffile.imwrite(buffer, (np.arange(64 * 64) % 251).astype(np.uint8).reshape(64, 64), compression="zlib")
    return buffer.getvalue()


@FUZZ
@given(data=st.data())
def test_damaged_image_files_are_rejected_cleanly(data):
    original = _valid_tiff()
    kind = data.draw(st.sampled_from(["truncate", "flip", "random"]))
    if kind == "truncate":
        content = original[: data.draw(st.integers(0, len(original) - 1))]
    elif kind == "flip":
        damaged = bytearray(original)
        for index in data.draw(st.lists(st.integers(0, len(original) - 1), min_size=1, max_size=20)):
            damaged[index] ^= data.draw(st.integers(1, 255))
        content = bytes(damaged)
    else:
        content = data.draw(st.sampled_from([b"II*\x00", b"\x89PNG\r\n\x1a\n", b""])) + data.draw(
            st.binary(max_size=2000)
        )
    try:
        image = read_sem_image(content)
    except InvalidInputError as error:
        assert error.field == "image" and str(error)
    else:
        assert image.pixels.ndim == 2  # a flip that left a readable image


def test_a_huge_declared_image_is_refused_before_decoding(monkeypatch):
    from fractoscope.sem import image as sem_image

    monkeypatch.setattr(sem_image, "MAX_IMAGE_PIXELS", 1000)
    with pytest.raises(InvalidInputError, match="larger than the limit"):
        read_sem_image(_valid_tiff())


def _answers_clearly(call) -> None:
    """A call succeeds or fails with an expected status that says why."""
    try:
        call()
    except grpc.RpcError as error:
        assert error.code() in EXPECTED, (error.code(), error.details())
        assert error.details()


finite_or_not = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.sampled_from([0.0, -1.0, 1e300, float("nan")])
)


@FUZZ
@given(
    tilts=st.lists(finite_or_not, min_size=0, max_size=4),
    pixel_size=finite_or_not,
    axis=finite_or_not,
    window=st.integers(-5, 300),
    confidence=finite_or_not,
    images=st.integers(0, 4),
    local_contrast=st.booleans(),
)
def test_random_matching_requests_get_a_status_naming_the_problem(
    client, tilts, pixel_size, axis, window, confidence, images, local_contrast
):
    image = _valid_tiff()
    request_images = [matching_pb2.TiltImage(image=common_pb2.ImageFile(content=image)) for _ in range(images)]
    for item, tilt in zip(request_images, tilts):
        item.tilt_deg = tilt
    request = matching_pb2.ComputeHeightMapRequest(
        images=request_images,
        pixel_size_um=pixel_size,
        tilt_axis_deg=axis,
        parameters=matching_pb2.MatchingParameters(
            window_px=window, min_confidence=confidence, normalize_local_contrast=local_contrast
        ),
    )
    _answers_clearly(lambda: list(client._matching.ComputeHeightMap(request, timeout=60)))


@FUZZ
@given(
    shapes=st.lists(st.tuples(st.integers(0, 70), st.integers(0, 70)), min_size=2, max_size=2),
    data_types=st.lists(st.sampled_from([0, 1, 2, 3, 99]), min_size=2, max_size=2),
    truncate=st.booleans(),
    window=st.integers(-5, 300),
    max_disparity=st.integers(-5, 300),
    confidence=finite_or_not,
    lr=finite_or_not,
    fill=finite_or_not,
)
def test_random_strips_get_a_status_naming_the_problem(
    client, shapes, data_types, truncate, window, max_disparity, confidence, lr, fill
):
    rasters = []
    for (rows, cols), data_type in zip(shapes, data_types):
        item_size = {1: 4, 2: 1, 3: 2}.get(data_type, 1)
        data = np.full(rows * cols * item_size, 7, np.uint8)
        if data_type == 1 and data.size:
            data = np.random.default_rng(rows * 71 + cols).normal(size=rows * cols).astype("<f4")
            with np.errstate(over="ignore"):
                data[0] = fill  # NaN, infinite or out of float32 range now and then
            data = data.view(np.uint8)
        rasters.append(
            common_pb2.Raster(
                rows=rows, cols=cols, data_type=data_type, data=data.tobytes()[: -1 if truncate else None]
            )
        )
    request = matching_pb2.MatchStripRequest(
        left=rasters[0],
        right=rasters[1],
        parameters=matching_pb2.MatchingParameters(
            window_px=window, max_disparity_px=max_disparity, min_confidence=confidence, max_lr_difference_px=lr
        ),
    )
    _answers_clearly(lambda: client._matching.MatchStrip(request, timeout=60))


@FUZZ
@given(
    specimen=st.text(max_size=80),
    uri=st.text(max_size=80),
    coordinates=st.lists(finite_or_not, min_size=4, max_size=4),
    magnification=finite_or_not,
)
def test_random_tile_queries_get_a_status_naming_the_problem(
    client, tmp_path, specimen, uri, coordinates, magnification
):
    out = tmp_path / "out"
    out.mkdir(exist_ok=True)
    calls = [
        lambda: client.export_area(
            specimen, out / "out.x3p", region_um=tuple(coordinates), pixel_size_um=abs(magnification)
        ),
        lambda: client.report(specimen, out / "report.html", region_um=tuple(coordinates)),
        lambda: client.get_tile(specimen, uri),
        lambda: client.zoom(specimen, tuple(coordinates), magnification=magnification),
        lambda: client.profile(specimen, [tuple(coordinates[:2]), tuple(coordinates[2:])], magnification=magnification),
        lambda: client.roughness(specimen, region_um=tuple(coordinates)),
    ]
    for call in calls:
        with pytest.raises(ClientError) as caught:  # no specimens exist on this server
            call()
        assert caught.value.code in EXPECTED and str(caught.value)
    assert list(out.iterdir()) == []  # a failed export or report leaves no file, not even a part of one


@FUZZ
@given(
    shape=st.tuples(st.integers(0, 40), st.integers(0, 40)),
    data_type=st.sampled_from([0, 1, 2, 3, 99]),
    truncate=st.booleans(),
    fill=finite_or_not,
    map_pixel_size=finite_or_not,
    pixel_size=finite_or_not,
    file_format=st.integers(-1, 8),
    units=st.integers(-1, 4),
    solid=st.booleans(),
)
def test_random_height_map_exports_get_a_status_naming_the_problem(
    client, shape, data_type, truncate, fill, map_pixel_size, pixel_size, file_format, units, solid
):
    rows, cols = shape
    with np.errstate(over="ignore"):  # out of float32 range now and then
        heights = np.full(rows * cols, fill, "<f4")
    data = (
        heights.view(np.uint8) if data_type == 1 else np.full(rows * cols * (2 if data_type == 3 else 1), 7, np.uint8)
    )
    request = tiles_pb2.ExportRequest(format=file_format, pixel_size_um=pixel_size, units=units, solid=solid)
    request.height_map.pixel_size_um = map_pixel_size
    request.height_map.z_um.CopyFrom(
        common_pb2.Raster(rows=rows, cols=cols, data_type=data_type, data=data.tobytes()[: -1 if truncate else None])
    )
    _answers_clearly(lambda: list(client._tiles.Export(request, timeout=60)))


def test_path_tricks_in_roi_ids_are_refused(client):
    pair = [matching_pb2.TiltImage(image=common_pb2.ImageFile(content=_valid_tiff()))] * 2
    request = tiles_pb2.ReconstructSpecimenRequest(specimen_id="x", rois=[tiles_pb2.RoiSpec(id="a/b", images=pair)])
    with pytest.raises(grpc.RpcError) as caught:
        for _ in client._tiles.ReconstructSpecimen(request, timeout=30):
            pass
    assert caught.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "rois[0].id" in caught.value.details()


def test_a_tiff_that_decodes_to_no_pixels_is_refused():
    """Found by the fuzzer: one flipped byte gives a TIFF page of zero size."""
    damaged = bytearray(_valid_tiff())
    damaged[43] ^= 1
    with pytest.raises(InvalidInputError, match="image"):
        read_sem_image(bytes(damaged))
