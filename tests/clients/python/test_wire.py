"""Both ends of the wire: values to messages and back, and the core's types through the servers'
conversions, against the values they started from."""

import dataclasses

import numpy as np
import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.matching import messages as rpc_matching
from fractoscope.mesh.levels import Simplification
from fractoscope.mesh.pipeline import MeshingOptions
from fractoscope.meshing import messages as rpc_meshing
from fractoscope.rpc import calls, wire
from fractoscope.stereo import matching as stereo_matching
from fractoscope.stereo.disparity import DisparityResult, StripTask
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.v1 import common_pb2, matching_pb2, meshing_pb2, tiles_pb2


@pytest.mark.parametrize(
    "values",
    [
        np.linspace(-3, 3, 12, dtype=np.float32).reshape(3, 4),
        np.arange(12, dtype=np.uint8).reshape(4, 3),
        (np.arange(12, dtype=np.uint16) * 5000).reshape(2, 6),
    ],
)
def test_rasters_round_trip_exactly(values):
    raster = common_pb2.Raster()
    wire.fill_raster(raster, values)
    back = wire.raster_to_array(raster)
    assert back.dtype == values.dtype and back.shape == values.shape
    np.testing.assert_array_equal(back, values)


def test_float64_travels_as_float32_and_bad_rasters_name_their_field():
    raster = common_pb2.Raster()
    wire.fill_raster(raster, np.array([[0.1, np.nan]]))
    assert wire.raster_to_array(raster).dtype == np.float32 and np.isnan(wire.raster_to_array(raster)[0, 1])
    with pytest.raises(ValueError):
        wire.fill_raster(raster, np.zeros((2, 2, 2), np.float32))
    short = common_pb2.Raster(rows=2, cols=2, data_type=common_pb2.DATA_TYPE_UINT8, data=b"abc")
    with pytest.raises(InvalidInputError) as error:
        wire.raster_to_array(short, field="height_map.z_um")
    assert error.value.field == "height_map.z_um.data"
    with pytest.raises(InvalidInputError) as error:
        wire.raster_to_array(common_pb2.Raster(rows=1, cols=1, data=b"x"), field="left")
    assert error.value.field == "left.data_type"


def test_reports_round_trip_and_unknown_keys_stay_home():
    report = {
        "tilt_deg": [-5.0, 5.0],
        "pixel_size_um": 0.25,
        "valid_fraction": 0.5,
        "warnings": ["look"],
        "strip_count": 3,
        "not_in_the_api": object(),
    }
    back = wire.message_to_report(wire.report_to_message(report))
    assert back["tilt_deg"] == [-5.0, 5.0] and back["warnings"] == ["look"] and back["strip_count"] == 3
    assert back["pixel_size_um"] == 0.25 and back["valid_fraction"] == 0.5 and "not_in_the_api" not in back


@pytest.mark.parametrize("method", list(stereo_matching.METHODS))
def test_the_parameters_as_used_name_the_method_run(method):
    """A report's parameters repeat the run: its method too, not MATCHING_METHOD_UNSPECIFIED."""
    message = wire.report_to_message({"method": method, "parameters": {"window_px": 15}})
    assert (
        message.parameters.method == rpc_matching.method_to_message(method) != matching_pb2.MATCHING_METHOD_UNSPECIFIED
    )
    assert rpc_matching.options_from_message(message.parameters).method == method


def test_regions_zoom_kinds_roughness_and_profile_parameters_round_trip():
    assert wire.message_to_region(wire.region_message((1.0, 2.0, 3.5, 4.5))) == (1.0, 2.0, 3.5, 4.5)
    assert [wire.zoom_name(wire.ZOOM_KINDS[name]) for name in ("optical", "digital")] == ["optical", "digital"]
    assert wire.zoom_name(tiles_pb2.ZOOM_KIND_UNSPECIFIED) == "unknown"
    values = {
        "Sa": 1.0,
        "Sq": 1.25,
        "Ssk": -0.5,
        "Sku": 3.0,
        "Sp": 4.0,
        "Sv": 3.5,
        "Sz": 7.5,
        "Sdq": 0.75,
        "Sdr": 12.5,
        "hurst_exponent": 0.8,
        "hurst_fit_min_um": 1.0,
        "hurst_fit_max_um": 9.0,
        "fractal_dimension": 2.2,
    }
    response = wire.values_to_roughness_response(values)
    assert response.sa_um == 1.0 and response.sdr_percent == 12.5 and response.hurst_exponent == 0.8
    response.parameters.add(
        name="Str", value=float("nan"), unit="1", u_total=float("nan"), u_tilt=0.0, u_noise=float("nan")
    )
    back = wire.response_to_roughness(response)
    assert {key: back[key] for key in values} == values
    assert back["Str"] is None and back["uncertainty"]["Str"] == {"u_total": None, "u_tilt": 0.0, "u_noise": None}
    parameters = {
        "Ra": 0.5,
        "Rq": 0.75,
        "Rz": 3.0,
        "Rsk": 0.25,
        "Rku": 2.5,
        "Rp": 1.5,
        "Rv": 1.5,
        "Rt": 3.5,
        "Rdq": 0.1,
        "RSm": 12.0,
        "Rk": 1.0,
        "Rpk": 0.25,
        "Rvk": 0.5,
        "Rmr1": 10.0,
        "Rmr2": 90.0,
    }
    message = wire.profile_parameters_message(parameters)
    assert message.ra_um == 0.5 and message.rku == 2.5 and message.rmr2_percent == 90.0
    assert wire.message_to_profile_parameters(message) == parameters


def test_the_surface_chain_round_trips_with_its_defaults_left_out():
    message = wire.chain_message(form="poly3", l_filter_um=80.0, levelling_region_um=(0.0, 0.0, 5.0, 5.0))
    assert message.form == tiles_pb2.FORM_POLY3 and not message.HasField("s_filter_um")
    back = wire.chain_to_dict(message)
    assert back["form"] == "poly3" and back["l_filter_um"] == 80.0 and back["s_filter_um"] is None
    assert back["levelling_region_um"] == [0.0, 0.0, 5.0, 5.0]
    assert wire.chain_to_dict(tiles_pb2.SurfaceChain())["form"] == "plane"  # unspecified means a plane
    assert set(wire.FORMS) == {"none", "plane", "poly2", "poly3", "poly4", "poly5", "poly6", "sphere", "cylinder"}
    with pytest.raises(InvalidInputError, match="chain.form"):
        wire.chain_message(form="poly7")


def test_matching_parameters_left_empty_mean_the_defaults():
    assert rpc_matching.options_from_message(matching_pb2.MatchingParameters()) == MatchingOptions()
    given = matching_pb2.MatchingParameters(
        window_px=21,
        max_disparity_px=40,
        min_confidence=0.5,
        max_lr_difference_px=2.0,
        tilt_uncertainty_deg=0.1,
        calibrate_tilt=True,
        normalize_local_contrast=False,
        propagate_at_full_resolution=True,
        method=matching_pb2.MATCHING_METHOD_WINDOW_ZNCC,
    )
    assert rpc_matching.options_from_message(given) == MatchingOptions(
        window_px=21,
        max_disparity_px=40,
        min_confidence=0.5,
        max_lr_difference_px=2.0,
        tilt_uncertainty_deg=0.1,
        calibrate_tilt=True,
        normalize_local_contrast=False,
        propagate_at_full_resolution=True,
        method="window_zncc",
    )
    assert MatchingOptions().method == "tgv_zncc"


def test_matching_methods_by_name_and_by_code():
    """Each name is its MATCHING_METHOD_<NAME> and back (tests/test_registries.py holds the names
    equal to the matcher's registry)."""
    for name in wire.method_names():
        code = wire.method_code(name)
        assert matching_pb2.MatchingMethod.Name(code) == f"MATCHING_METHOD_{name.upper()}"
        assert wire.method_name(code) == name
    assert wire.method_code("fast") == matching_pb2.MATCHING_METHOD_FAST
    fast = matching_pb2.MatchingParameters(method=matching_pb2.MATCHING_METHOD_FAST)
    assert rpc_matching.options_from_message(fast).method == "fast"


def test_an_unknown_matching_method_names_the_field():
    with pytest.raises(InvalidInputError) as raised:
        rpc_matching.options_from_message(matching_pb2.MatchingParameters(method=7))
    assert raised.value.field == "parameters.method" and "FAST" in raised.value.message


def test_a_strip_and_its_disparities_cross_the_wire_unchanged():
    rng = np.random.default_rng(0)
    grey = rng.integers(0, 256, (40, 64)).astype(np.float32)  # whole numbers: sent as uint8
    task = StripTask(
        grey,
        np.roll(grey, 2, axis=1),
        15,
        16,
        0.3,
        1.0,
        keep_rows=(5, 30),
        propagate_at_full_resolution=True,
        method="window_zncc",
    )
    request = rpc_matching.strip_request(task, request_id="r")
    assert request.left.data_type == common_pb2.DATA_TYPE_UINT8 and request.request_id == "r"
    back = rpc_matching.request_to_strip_task(request)
    assert dataclasses.replace(back, left=None, right=None) == dataclasses.replace(task, left=None, right=None)
    np.testing.assert_array_equal(back.left, task.left)
    np.testing.assert_array_equal(back.right, task.right)
    fractional = dataclasses.replace(task, left=grey + 0.5)
    assert rpc_matching.strip_request(fractional).left.data_type == common_pb2.DATA_TYPE_FLOAT32
    disparity = np.where(rng.random((25, 64)) < 0.2, np.nan, rng.normal(0, 3, (25, 64))).astype(np.float32)
    result = DisparityResult(disparity, rng.random((25, 64)).astype(np.float32), np.abs(disparity) / 10)
    response = rpc_matching.strip_response(result, worker="host:1")
    assert response.worker == "host:1"
    received = rpc_matching.response_to_disparity(response)
    for sent, got in zip(dataclasses.astuple(result), dataclasses.astuple(received)):
        np.testing.assert_array_equal(got, sent)


def test_mesh_requests_decode_to_their_options_arrays_and_origin():
    z_um = np.arange(12, dtype=np.float32).reshape(3, 4)
    texture = (np.arange(12, dtype=np.uint16) * 257).reshape(3, 4)
    request = calls.mesh_request(
        z_um,
        texture,
        pixel_size_um=0.5,
        origin_um=(1.0, 2.0),
        method=meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC,
        level_count=3,
        filter=meshing_pb2.FilterParameters(smoothing_um=0.2),
        plain_glb=True,
        max_slope=9.5,
        sigma_um=z_um / 10,
    )
    assert rpc_meshing.options_from_request(request) == MeshingOptions(
        smoothing_um=np.float32(0.2),
        method=Simplification.QUADRIC,
        level_count=3,
        plain_glb=True,
        max_slope=9.5,
        max_sigma_um=2 * 9.5 * 0.5,  # the default bound: two pixels of disparity (mesh.walls)
    )
    decoded_z, decoded_texture, pixel_size_um, sigma_um = rpc_meshing.height_map_arrays(request.height_map)
    np.testing.assert_array_equal(decoded_z, z_um)
    np.testing.assert_array_equal(sigma_um, z_um / 10)
    np.testing.assert_array_equal(decoded_texture, np.arange(12, dtype=np.uint8).reshape(3, 4))  # 16-bit grey to 8-bit
    assert pixel_size_um == 0.5 and rpc_meshing.origin_from_request(request) == (1.0, 2.0)
    for far_um in (float("nan"), 1e40):  # 1e40 once overflowed the GLB's float32 bounds: INTERNAL
        far = meshing_pb2.BuildMeshRequest(origin_um={"x_um": far_um})
        with pytest.raises(InvalidInputError) as error:
            rpc_meshing.origin_from_request(far)
        assert error.value.field == "origin_um"
    request.max_slope = -1
    with pytest.raises(InvalidInputError) as error:
        rpc_meshing.options_from_request(request)
    assert error.value.field == "max_slope"
    request.method = 7
    with pytest.raises(InvalidInputError) as error:
        rpc_meshing.options_from_request(request)
    assert error.value.field == "method"


def test_a_streamed_height_map_is_read_with_its_progress():
    response = matching_pb2.ComputeHeightMapResponse(report=wire.report_to_message({"valid_fraction": 0.75}))
    response.height_map.pixel_size_um = 0.1
    for field in ("z_um", "sigma_um", "confidence"):
        wire.fill_raster(getattr(response.height_map, field), np.full((2, 3), 0.5, np.float32))
    wire.fill_raster(response.height_map.texture, np.zeros((2, 3), np.uint8))
    progress = matching_pb2.ComputeHeightMapResponse(progress=common_pb2.Progress(fraction=0.5, message="matching"))
    seen = []
    height_map = calls.read_height_map([progress, response], lambda fraction, message: seen.append((fraction, message)))
    assert seen == [(0.5, "matching")] and height_map.pixel_size_um == pytest.approx(0.1)
    assert height_map.report["valid_fraction"] == 0.75 and height_map.z_um.shape == (2, 3)
    with pytest.raises(calls.ClientError, match="without a result"):
        calls.read_height_map([progress], None)
