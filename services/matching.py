"""MatchingService: stereo pairs of SEM images to calibrated height maps."""

from __future__ import annotations

import logging

from fractoscope import wire
from fractoscope.errors import InvalidInputError
from fractoscope.height_map import MatchingOptions, compute_series_height_map
from fractoscope.sem_image import read_sem_image
from fractoscope.services.errors import abort_with_error
from fractoscope.services.progress import stream_progress
from fractoscope.v1 import common_pb2, matching_pb2, matching_pb2_grpc

_log = logging.getLogger("fractoscope.matching")


def options_from_message(parameters: matching_pb2.MatchingParameters) -> MatchingOptions:
    """MatchingParameters (zero = default) to MatchingOptions."""
    defaults = MatchingOptions()
    return MatchingOptions(
        window_px=parameters.window_px or defaults.window_px,
        max_disparity_px=parameters.max_disparity_px or None,
        min_confidence=parameters.min_confidence or defaults.min_confidence,
        max_lr_difference_px=parameters.max_lr_difference_px or defaults.max_lr_difference_px,
        tilt_uncertainty_deg=parameters.tilt_uncertainty_deg or defaults.tilt_uncertainty_deg,
        calibrate_tilt=parameters.calibrate_tilt,
    )


class MatchingServicer(matching_pb2_grpc.MatchingServiceServicer):
    """Decodes the request, runs `compute_height_map`, streams progress and the result."""

    def ComputeHeightMap(self, request, context):
        try:
            if len(request.images) < 2:
                raise InvalidInputError("images", f"at least two images are needed, got {len(request.images)}")
            images = [read_sem_image(item.image.content, field=f"images[{i}].image") for i, item in enumerate(request.images)]
            tilts = tuple(item.tilt_deg if item.HasField("tilt_deg") else None for item in request.images)
            options = options_from_message(request.parameters)

            def work(progress):
                return compute_series_height_map(
                    images,
                    tilt_deg=tilts,
                    pixel_size_um=request.pixel_size_um if request.HasField("pixel_size_um") else None,
                    tilt_axis_deg=request.tilt_axis_deg if request.HasField("tilt_axis_deg") else 90.0,
                    options=options,
                    progress=progress,
                )

            for event in stream_progress(context, work):
                if isinstance(event, common_pb2.Progress):
                    yield matching_pb2.ComputeHeightMapResponse(progress=event)
                else:
                    yield _result_message(event, images[0].pixels)
                    _log.info("height map done", extra={"request_id": request.request_id, "report": event.report})
        except Exception as error:  # every failure becomes a gRPC status in one place
            abort_with_error(context, error)


def _result_message(result, texture) -> matching_pb2.ComputeHeightMapResponse:
    height_map = common_pb2.HeightMap(
        z_um=wire.array_to_raster(result.z_um),
        sigma_um=wire.array_to_raster(result.sigma_um),
        confidence=wire.array_to_raster(result.confidence),
        pixel_size_um=result.report["pixel_size_um"],
        texture=wire.array_to_raster(texture),
    )
    return matching_pb2.ComputeHeightMapResponse(height_map=height_map, report=wire.report_to_message(result.report))
