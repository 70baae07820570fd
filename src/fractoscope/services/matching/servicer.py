"""MatchingService: stereo pairs of SEM images to calibrated height maps.

A replica given strip peers (a gRPC target such as `dns:///matching:50051`, balanced round-robin)
farms the strips of its dense matching out to them through MatchStrip and stitches the results;
any replica answers MatchStrip."""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
import threading
from collections.abc import Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import grpc
import numpy as np

from fractoscope.rpc import wire
from fractoscope.sem import image as sem_image
from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.stereo.disparity import DisparityResult, StripTask
from fractoscope.stereo.window_zncc import match_strip
from fractoscope.errors import FractoscopeError, InvalidInputError, UnavailableError
from fractoscope.stereo.pipeline import MatchingOptions, compute_series_height_map, validate_options
from fractoscope.rpc.status import abort_with_error
from fractoscope.services.streaming import stream_progress
from fractoscope.v1 import common_pb2, matching_pb2, matching_pb2_grpc

_log = logging.getLogger("fractoscope.matching")
WORKER_ID = f"{socket.gethostname()}:{os.getpid()}"


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
            parameters.normalize_local_contrast if parameters.HasField("normalize_local_contrast") else defaults.normalize_local_contrast
        ),
        propagate_at_full_resolution=parameters.propagate_at_full_resolution,
    )


class PeerStripMatcher:
    """Matches strips on the replicas behind `client`'s target, up to `in_flight` at a time, and
    remembers which replicas did (`workers`). One per height map."""

    def __init__(self, client: FractoscopeClient, *, in_flight: int, request_id: str = ""):
        self.client = client
        self.in_flight = in_flight
        self.request_id = request_id
        self.workers: set[str] = set()

    def __call__(self, tasks: Iterable[StripTask]) -> Iterator[DisparityResult]:
        with ThreadPoolExecutor(max_workers=self.in_flight) as pool:
            yield from pool.map(self._match, tasks)

    def _match(self, task: StripTask) -> DisparityResult:
        try:
            result, worker = self.client.match_strip(task, request_id=self.request_id)
        except ClientError as error:
            if error.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                raise UnavailableError(f"a strip peer failed ({error}); retry") from None
            # A peer that refuses what this replica sends runs another version or other limits.
            raise FractoscopeError(f"a strip peer refused a strip ({error.code.name}: {error}); check that the matching replicas agree") from None
        self.workers.add(worker)
        return result


class MatchingServicer(matching_pb2_grpc.MatchingServiceServicer):
    """Decodes the request, runs `compute_series_height_map`, streams progress and the result.
    With `strip_peers`, dense matching is split into strips of about `strip_pixels` pixels,
    `strip_in_flight` of which are matched by the peers at a time.

    At most `coordinator_slots` height maps at once wait on peers (keep it below the server's
    worker threads); more match their strips here. Peers may include this replica, so threads
    are always left to answer MatchStrip, which waits on nothing: no deadlock among replicas."""

    def __init__(self, *, strip_peers: str | None = None, strip_pixels: int = 2_000_000, strip_in_flight: int = 4,
                 coordinator_slots: int = 4, call_timeout_s: float = 600.0):
        self.strip_pixels = strip_pixels
        self.strip_in_flight = strip_in_flight
        self._peers = FractoscopeClient(strip_peers, timeout_s=call_timeout_s) if strip_peers else None
        self._coordinator_slots = threading.BoundedSemaphore(coordinator_slots)

    def ComputeHeightMap(self, request, context):
        try:
            if len(request.images) < 2:
                raise InvalidInputError("images", f"at least two images are needed, got {len(request.images)}")
            images = [sem_image.read_sem_image(item.image.content, field=f"images[{i}].image") for i, item in enumerate(request.images)]
            tilts = tuple(item.tilt_deg if item.HasField("tilt_deg") else None for item in request.images)
            options = dataclasses.replace(options_from_message(request.parameters), strip_pixels=self.strip_pixels)

            def work(progress):
                coordinating = self._peers is not None and self._coordinator_slots.acquire(blocking=False)
                peers = PeerStripMatcher(self._peers, in_flight=self.strip_in_flight, request_id=request.request_id) if coordinating else None
                try:
                    result = compute_series_height_map(
                        images,
                        tilt_deg=tilts,
                        pixel_size_um=request.pixel_size_um if request.HasField("pixel_size_um") else None,
                        tilt_axis_deg=request.tilt_axis_deg if request.HasField("tilt_axis_deg") else 90.0,
                        options=options,
                        strip_matcher=peers,
                        progress=progress,
                    )
                finally:
                    if coordinating:
                        self._coordinator_slots.release()
                if peers is not None:
                    result.report["strip_workers"] = sorted(peers.workers)
                return result

            for event in stream_progress(context, work):
                if isinstance(event, common_pb2.Progress):
                    yield matching_pb2.ComputeHeightMapResponse(progress=event)
                else:
                    yield _result_message(event, images[0].pixels)
                    _log.info("height map done", extra={"request_id": request.request_id, "report": event.report})
        except Exception as error:  # every failure becomes a gRPC status in one place
            abort_with_error(context, error)

    def MatchStrip(self, request, context):
        try:
            result = match_strip(_strip_task(request))
            response = matching_pb2.MatchStripResponse(worker=WORKER_ID)
            wire.fill_raster(response.disparity_px, result.disparity_px)
            wire.fill_raster(response.confidence, result.confidence)
            wire.fill_raster(response.sigma_px, result.sigma_px)
            return response
        except Exception as error:
            abort_with_error(context, error)


def _strip_task(request: matching_pb2.MatchStripRequest) -> StripTask:
    left = wire.raster_to_array(request.left, field="left").astype(np.float32)
    right = wire.raster_to_array(request.right, field="right").astype(np.float32)
    if left.shape != right.shape:
        raise InvalidInputError("right", f"size {right.shape[::-1]} differs from the left strip's {left.shape[::-1]}")
    if left.size > sem_image.MAX_IMAGE_PIXELS:
        raise InvalidInputError("left", f"{left.size} pixels is more than the limit of {sem_image.MAX_IMAGE_PIXELS} (FRACTO_MAX_IMAGE_PIXELS)")
    for name, values in (("left", left), ("right", right)):
        if not np.isfinite(values).all():
            raise InvalidInputError(name, "grey values must be finite")
    options = options_from_message(request.parameters)
    if options.max_disparity_px is None:
        raise InvalidInputError("parameters.max_disparity_px", "is required for a strip")
    validate_options(options, image_cols=left.shape[1])
    keep_rows = None
    if request.keep_from_row or request.keep_to_row:
        if not 0 <= request.keep_from_row < request.keep_to_row <= left.shape[0]:
            raise InvalidInputError("keep_to_row", f"rows [{request.keep_from_row}, {request.keep_to_row}) are not within the strip's {left.shape[0]}")
        keep_rows = (request.keep_from_row, request.keep_to_row)
    return StripTask(left, right, options.window_px, options.max_disparity_px, options.min_confidence, options.max_lr_difference_px,
                     keep_rows=keep_rows, propagate_at_full_resolution=options.propagate_at_full_resolution)


def _result_message(result, texture) -> matching_pb2.ComputeHeightMapResponse:
    response = matching_pb2.ComputeHeightMapResponse(report=wire.report_to_message(result.report))
    height_map = response.height_map
    height_map.pixel_size_um = result.report["pixel_size_um"]
    for field, values in (("z_um", result.z_um), ("sigma_um", result.sigma_um), ("confidence", result.confidence), ("texture", texture)):
        wire.fill_raster(getattr(height_map, field), values)
    return response
