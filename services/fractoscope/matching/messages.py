"""The matching service's messages to and from the stereo package's types: MatchingParameters and
MatchingOptions, strips and their disparities, height map results."""

from __future__ import annotations

import contextlib
import dataclasses
from collections.abc import Iterator

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.rpc import wire
from fractoscope.runtime import budget
from fractoscope.sem import image as sem_image
from fractoscope.stereo import alignment
from fractoscope.stereo.disparity import DisparityResult, StripTask
from fractoscope.stereo.inputs import MatchingOptions, validate_options, validate_same_size, validate_tilt_axis_deg
from fractoscope.stereo.matching import DEFAULT_STRIP_PIXELS
from fractoscope.stereo.pipeline import DEFAULT_TILT_AXIS_DEG, HeightMapResult
from fractoscope.stereo.relief_sign import ReliefSignMode
from fractoscope.v1 import matching_pb2

# MatchingOptions' names that are fields of MatchingParameters, and so of `parameters` in requests.
_PARAMETER_FIELDS = frozenset(field.name for field in dataclasses.fields(MatchingOptions)) & frozenset(
    matching_pb2.MatchingParameters.DESCRIPTOR.fields_by_name
)


@contextlib.contextmanager
def request_fields() -> Iterator[None]:
    """Input errors the stereo package raises about a MatchingOptions value, renamed as the
    request's fields (`window_px` is `parameters.window_px`)."""
    try:
        yield
    except InvalidInputError as error:
        if error.field not in _PARAMETER_FIELDS:
            raise
        raise InvalidInputError(f"parameters.{error.field}", error.message) from None


def method_from_message(code: int) -> str:
    """A MatchingMethod value's name, a key of stereo.matching.METHODS (UNSPECIFIED: the
    default); InvalidInputError for unknown ones."""
    if code == matching_pb2.MATCHING_METHOD_UNSPECIFIED:
        return MatchingOptions().method
    try:
        return wire.method_name(code)
    except ValueError:
        known = ", ".join(name.upper() for name in wire.method_names())
        raise InvalidInputError("parameters.method", f"unknown matching method {code}; known: {known}") from None


def method_to_message(method: str) -> int:
    return wire.method_code(method)


def options_from_message(parameters: matching_pb2.MatchingParameters) -> MatchingOptions:
    """MatchingParameters (zero or absent = default) to MatchingOptions."""
    defaults = MatchingOptions()
    return MatchingOptions(
        window_px=parameters.window_px or defaults.window_px,
        max_disparity_px=parameters.max_disparity_px or None,
        min_confidence=parameters.min_confidence or defaults.min_confidence,
        max_lr_difference_px=parameters.max_lr_difference_px or defaults.max_lr_difference_px,
        tilt_uncertainty_deg=parameters.tilt_uncertainty_deg or defaults.tilt_uncertainty_deg,
        calibrate_tilt=parameters.calibrate_tilt,
        normalize_local_contrast=(
            parameters.normalize_local_contrast
            if parameters.HasField("normalize_local_contrast")
            else defaults.normalize_local_contrast
        ),
        propagate_at_full_resolution=parameters.propagate_at_full_resolution,
        method=method_from_message(parameters.method),
        relief_sign=relief_sign_from_message(parameters.relief_sign),
        detector_from_tilt_axis_deg=(
            parameters.detector_from_tilt_axis_deg
            if parameters.HasField("detector_from_tilt_axis_deg")
            else defaults.detector_from_tilt_axis_deg
        ),
    )


def relief_sign_from_message(code: int) -> ReliefSignMode:
    """A ReliefSignMode value (UNSPECIFIED: auto); InvalidInputError naming the field otherwise."""
    try:
        return ReliefSignMode(wire.relief_sign_name(code))
    except ValueError:
        known = ", ".join(name.upper() for name in wire.relief_sign_names())
        raise InvalidInputError("parameters.relief_sign", f"unknown relief sign mode {code}; known: {known}") from None


def checked_height_map_request(
    request: matching_pb2.ComputeHeightMapRequest,
) -> tuple[tuple[int, int], MatchingOptions]:
    """The first image's (rows, cols) and the options of `request`, checked before any work: at
    least two images, each readable and of the first one's size by its header, the parameters and
    the tilt axis (InvalidInputError names the field)."""
    if len(request.images) < 2:
        raise InvalidInputError("images", f"at least two images are needed, got {len(request.images)}")
    shape = sem_image.image_shape(request.images[0].image.content, field="images[0].image")
    for index, item in enumerate(request.images[1:], start=1):
        validate_same_size(
            shape, sem_image.image_shape(item.image.content, field=f"images[{index}].image"), index=index
        )
    options = options_from_message(request.parameters)
    with request_fields():
        validate_options(options, image_cols=shape[1])
    validate_tilt_axis_deg(tilt_axis_deg(request))
    _, canvas = alignment.rotation_to_vertical_axis(shape, tilt_axis_deg(request))
    if max(canvas) > sem_image.MAX_SIDE_PX:
        raise InvalidInputError(
            "tilt_axis_deg",
            f"turns images of {shape[1]} x {shape[0]} pixels onto a canvas of {canvas[1]} x {canvas[0]}, longer than "
            f"the {sem_image.MAX_SIDE_PX} px OpenCV takes; send smaller images",
        )
    return shape, options


def peak_bytes(
    request: matching_pb2.ComputeHeightMapRequest, *, strip_pixels: int = DEFAULT_STRIP_PIXELS
) -> tuple[int, tuple[int, int]]:
    """The request's estimated peak memory matched in strips of `strip_pixels` (see
    runtime.budget), from its images' declared sizes, and the first image's (rows, cols);
    InvalidInputError (checked_height_map_request) for what cannot be matched at all."""
    shape, options = checked_height_map_request(request)
    estimate = budget.height_map_bytes(
        shape,
        len(request.images),
        tilt_axis_deg=tilt_axis_deg(request),
        window_px=options.window_px,
        max_disparity_px=options.max_disparity_px,
        strip_pixels=strip_pixels,
    )
    return estimate, shape


def tilt_axis_deg(request: matching_pb2.ComputeHeightMapRequest) -> float:
    """The request's tilt axis, degrees (the default where it gives none)."""
    return request.tilt_axis_deg if request.HasField("tilt_axis_deg") else DEFAULT_TILT_AXIS_DEG


def strip_request(task: StripTask, *, request_id: str = "") -> matching_pb2.MatchStripRequest:
    """MatchStrip of one strip; whole-number grey values travel as integers."""
    first, stop = task.keep_rows or (0, 0)
    request = matching_pb2.MatchStripRequest(
        keep_from_row=first,
        keep_to_row=stop,
        parameters=matching_pb2.MatchingParameters(
            window_px=task.window_px,
            max_disparity_px=task.max_disparity_px,
            min_confidence=task.min_confidence,
            max_lr_difference_px=task.max_lr_difference_px,
            propagate_at_full_resolution=task.propagate_at_full_resolution,
            method=method_to_message(task.method),
        ),
        request_id=request_id,
    )
    wire.fill_raster(request.left, _exact_integers(task.left))
    wire.fill_raster(request.right, _exact_integers(task.right))
    return request


def request_to_strip_task(request: matching_pb2.MatchStripRequest) -> StripTask:
    """The strip a MatchStripRequest holds, validated (InvalidInputError names the field)."""
    left = wire.raster_to_array(request.left, field="left").astype(np.float32)
    right = wire.raster_to_array(request.right, field="right").astype(np.float32)
    if left.shape != right.shape:
        raise InvalidInputError("right", f"size {right.shape[::-1]} differs from the left strip's {left.shape[::-1]}")
    if left.size > sem_image.MAX_IMAGE_PIXELS:
        raise InvalidInputError(
            "left",
            f"{left.size} pixels is more than the limit of {sem_image.MAX_IMAGE_PIXELS} (FRACTO_MAX_IMAGE_PIXELS)",
        )
    if max(left.shape) > sem_image.MAX_SIDE_PX:  # a strip's sides are far apart, but neither may pass this
        raise InvalidInputError(
            "left", f"a strip of {left.shape[1]} x {left.shape[0]} pixels is longer than {sem_image.MAX_SIDE_PX} px"
        )
    for name, values in (("left", left), ("right", right)):
        if not np.isfinite(values).all():
            raise InvalidInputError(name, "grey values must be finite")
    options = options_from_message(request.parameters)
    if options.max_disparity_px is None:
        raise InvalidInputError("parameters.max_disparity_px", "is required for a strip")
    if min(left.shape) < options.window_px:
        raise InvalidInputError(
            "left",
            f"a strip of {left.shape[1]} x {left.shape[0]} pixels is smaller than the {options.window_px} px window",
        )
    with request_fields():
        validate_options(options, image_cols=left.shape[1])
    keep_rows = None
    if request.keep_from_row or request.keep_to_row:
        if not 0 <= request.keep_from_row < request.keep_to_row <= left.shape[0]:
            raise InvalidInputError(
                "keep_to_row",
                f"rows [{request.keep_from_row}, {request.keep_to_row}) are not within the strip's {left.shape[0]}",
            )
        keep_rows = (request.keep_from_row, request.keep_to_row)
    return StripTask(
        left,
        right,
        options.window_px,
        options.max_disparity_px,
        options.min_confidence,
        options.max_lr_difference_px,
        keep_rows=keep_rows,
        propagate_at_full_resolution=options.propagate_at_full_resolution,
        method=options.method,
    )


def strip_response(result: DisparityResult, *, worker: str) -> matching_pb2.MatchStripResponse:
    response = matching_pb2.MatchStripResponse(worker=worker)
    wire.fill_raster(response.disparity_px, result.disparity_px)
    wire.fill_raster(response.confidence, result.confidence)
    wire.fill_raster(response.sigma_px, result.sigma_px)
    return response


def response_to_disparity(response: matching_pb2.MatchStripResponse) -> DisparityResult:
    return DisparityResult(
        *(wire.raster_to_array(raster) for raster in (response.disparity_px, response.confidence, response.sigma_px))
    )


def height_map_response(result: HeightMapResult, texture: np.ndarray) -> matching_pb2.ComputeHeightMapResponse:
    """The final ComputeHeightMap response: the maps, the reference image as texture, the report."""
    response = matching_pb2.ComputeHeightMapResponse(report=wire.report_to_message(result.report))
    height_map = response.height_map
    height_map.pixel_size_um = result.report["pixel_size_um"]
    for field, values in (
        ("z_um", result.z_um),
        ("sigma_um", result.sigma_um),
        ("confidence", result.confidence),
        ("texture", texture),
        ("views_used", result.views_used),
    ):
        wire.fill_raster(getattr(height_map, field), values)
    return response


def _exact_integers(values: np.ndarray) -> np.ndarray:
    """Float grey values that are whole numbers within 0..65535 as uint8 or uint16 (half or a
    quarter of the bytes on the wire, the same values), others unchanged."""
    if values.dtype.kind != "f" or values.size == 0:
        return values
    low, high = float(values.min()), float(values.max())
    if low < 0 or high > 65535 or not np.array_equal(values, np.rint(values)):
        return values
    return values.astype(np.uint8 if high <= 255 else np.uint16)
