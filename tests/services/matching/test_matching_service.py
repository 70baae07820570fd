"""The matching service over a real gRPC server on loopback."""

import dataclasses

import grpc
import numpy as np
import pytest
from conftest import fracture_pair, inner_mask, tiff_bytes
from grpc_health.v1 import health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection_pb2, reflection_pb2_grpc

from fractoscope.client import ClientError
from fractoscope.matching.peers import StripPeers
from fractoscope.stereo.disparity import StripTask
from fractoscope.v1 import matching_pb2


def test_health_and_reflection(server_address):
    with grpc.insecure_channel(server_address) as channel:
        health = health_pb2_grpc.HealthStub(channel).Check(
            health_pb2.HealthCheckRequest(service="fractoscope.v1.MatchingService")
        )
        assert health.status == health_pb2.HealthCheckResponse.SERVING
        request = reflection_pb2.ServerReflectionRequest(list_services="")
        responses = reflection_pb2_grpc.ServerReflectionStub(channel).ServerReflectionInfo(iter([request]))
        names = {service.name for service in next(responses).list_services_response.service}
        assert "fractoscope.v1.MatchingService" in names and "grpc.health.v1.Health" in names


@pytest.mark.slow
def test_height_map_of_images_larger_than_four_mib_with_progress(client):
    pair = fracture_pair(size_px=1536, bits=16, seed=3)
    files = [tiff_bytes(image) for image in (pair.first, pair.second)]
    assert min(len(content) for content in files) > 4 * 1024 * 1024
    fractions = []
    result = client.compute_height_map(
        files, tilt_deg=(-5, 5), pixel_size_um=0.1, on_progress=lambda f, m: fractions.append(f)
    )
    assert result.z_um.shape == (1536, 1536) and result.z_um.dtype == np.float32
    assert fractions == sorted(fractions) and len(fractions) >= 5
    inner = inner_mask(result.z_um.shape)
    valid = np.isfinite(result.z_um) & inner
    assert valid[inner].mean() > 0.97
    error = result.z_um[valid] - pair.z_seen_um[valid]
    span = np.ptp(pair.z_seen_um[inner])
    assert np.std(error) / span < 0.02
    assert result.report["tilt_deg"] == [-5.0, 5.0] and result.report["pixel_size_um"] == pytest.approx(0.1)
    assert result.report["tilt_source"] == ["argument", "argument"] and result.report["pixel_size_source"] == "argument"
    assert result.report["parameters"]["window_px"] == 15 and result.report["parameters"]["tilt_uncertainty_deg"] == 0.5
    assert result.report["tilt_axis_source"] == "default"


@pytest.mark.parametrize(
    "case, field",
    [
        ("mismatched sizes", "images[1]"),
        ("equal tilts", "images[1].tilt_deg"),
        ("missing tilt", "images[0].tilt_deg"),
        ("unreadable image", "images[0].image"),
        ("empty image", "images[0].image"),  # its declared 0 x 0 once divided the memory estimate by zero
        ("unreadable second image", "images[1].image"),
        ("one image", "images"),
        ("bad pixel size", "pixel_size_um"),
    ],
)
@pytest.mark.filterwarnings("ignore:.*zero-size array:UserWarning")  # tifffile, on writing the empty image
def test_bad_requests_get_invalid_argument_naming_the_field(client, case, field):
    pair = fracture_pair(size_px=128)
    first, second = tiff_bytes(pair.first), tiff_bytes(pair.second)
    arguments = {"tilt_deg": (-5, 5), "pixel_size_um": 0.1}
    images = [first, second]
    if case == "mismatched sizes":
        images = [first, tiff_bytes(pair.second[:100])]
    elif case == "equal tilts":
        arguments["tilt_deg"] = (5, 5)
    elif case == "missing tilt":
        arguments.pop("tilt_deg")
    elif case == "unreadable image":
        images = [b"garbage", second]
    elif case == "unreadable second image":
        images = [first, b"garbage"]
    elif case == "empty image":
        images = [tiff_bytes(np.zeros((0, 0), np.uint8)), second]
    elif case == "one image":
        images = [first]
    elif case == "bad pixel size":
        arguments["pixel_size_um"] = -1.0
    with pytest.raises(ClientError) as error:
        client.compute_height_map(images, **arguments)
    assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT
    assert error.value.field == field
    assert "Traceback" not in str(error.value)


@pytest.fixture()
def peers(server_address):
    """The loopback server as a strip peer, as a coordinating matching replica sees it."""
    with StripPeers(server_address) as connected:
        yield connected


@pytest.mark.parametrize(
    "change, field",
    [
        (lambda task: dataclasses.replace(task, right=task.right[:-1]), "right"),
        (lambda task: dataclasses.replace(task, left=np.full_like(task.left, np.nan)), "left"),
        (lambda task: dataclasses.replace(task, max_disparity_px=0), "parameters.max_disparity_px"),
        (lambda task: dataclasses.replace(task, window_px=4), "parameters.window_px"),
        (lambda task: dataclasses.replace(task, keep_rows=(10, 500)), "keep_to_row"),
        (lambda task: dataclasses.replace(task, left=task.left[:1, :1], right=task.right[:1, :1]), "left"),
    ],
)
def test_a_bad_strip_gets_invalid_argument_naming_the_field(peers, change, field):
    pair = fracture_pair(size_px=128)
    task = StripTask(pair.first.astype(np.float32), pair.second.astype(np.float32), 15, 16, 0.5, 1.0)
    result, worker = peers.match_strip(task, timeout_s=120)
    assert np.isfinite(result.disparity_px).mean() > 0.5 and worker
    kept, _ = peers.match_strip(
        dataclasses.replace(task, keep_rows=(8, 40)), timeout_s=120
    )  # only those rows come back
    np.testing.assert_array_equal(kept.disparity_px, result.disparity_px[8:40])
    with pytest.raises(ClientError) as error:
        peers.match_strip(change(task), timeout_s=120)
    assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT and error.value.field == field


def test_a_strip_searched_across_its_whole_width_is_matched(peers):
    """max_disparity_px may be the strip's width; semi-global matching, which cannot search that
    far, once failed the call with INTERNAL."""
    pair = fracture_pair(size_px=128)
    task = StripTask(pair.first.astype(np.float32), pair.second.astype(np.float32), 15, 128, 0.5, 1.0)
    result, _ = peers.match_strip(task, timeout_s=120)
    assert np.isfinite(result.disparity_px).mean() > 0.5


def test_a_raster_that_holds_fewer_bytes_than_it_declares_is_invalid_not_too_large(server_address):
    """65536 x 65536 declared with 64 KiB of data: the memory estimate, which trusts the declared
    size, once answered RESOURCE_EXHAUSTED (880 GiB) for what is a malformed request."""
    from fractoscope.v1 import common_pb2, matching_pb2_grpc

    raster = common_pb2.Raster(rows=65536, cols=65536, data_type=common_pb2.DATA_TYPE_UINT8, data=bytes(65536))
    request = matching_pb2.MatchStripRequest(
        left=raster, right=raster, parameters=matching_pb2.MatchingParameters(max_disparity_px=8)
    )
    with grpc.insecure_channel(server_address) as channel, pytest.raises(grpc.RpcError) as error:
        matching_pb2_grpc.MatchingServiceStub(channel).MatchStrip(request, timeout=30)
    assert error.value.code() == grpc.StatusCode.INVALID_ARGUMENT and "left.data" in error.value.details()


def test_a_height_map_by_the_fast_method_names_it(client):
    pair = fracture_pair(size_px=256)
    result = client.compute_height_map(
        [tiff_bytes(pair.first), tiff_bytes(pair.second)], tilt_deg=(-5, 5), pixel_size_um=0.1, method="fast"
    )
    assert result.report["method"] == "fast"
    assert result.report["parameters"]["method"] == matching_pb2.MATCHING_METHOD_FAST
    inner = inner_mask(result.z_um.shape)
    valid = np.isfinite(result.z_um) & inner
    np.testing.assert_array_equal(np.isfinite(result.sigma_um), np.isfinite(result.z_um))
    assert valid[inner].mean() > 0.9  # measured 0.97
    error = result.z_um[valid] - pair.z_seen_um[valid]
    assert np.std(error) / np.ptp(pair.z_seen_um[inner]) < 0.05  # measured 0.035


def test_a_strip_peer_matches_by_the_fast_method(peers):
    pair = fracture_pair(size_px=128)
    task = StripTask(pair.first.astype(np.float32), pair.second.astype(np.float32), 15, 16, 0.3, 1.0, method="fast")
    result, _ = peers.match_strip(task, timeout_s=120)
    assert np.isfinite(result.disparity_px).mean() > 0.8
