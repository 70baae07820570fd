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

from fractoscope.errors import InvalidInputError
from fractoscope.rpc import matching as rpc_matching
from fractoscope.rpc.status import abort_on_error
from fractoscope.sem.image import read_sem_image
from fractoscope.services.matching.peers import PeerStripMatcher, StripPeers
from fractoscope.services.streaming import stream_progress
from fractoscope.stereo.matching import DEFAULT_STRIP_PIXELS
from fractoscope.stereo.pipeline import compute_series_height_map
from fractoscope.stereo.window_zncc import match_strip
from fractoscope.v1 import common_pb2, matching_pb2, matching_pb2_grpc

_log = logging.getLogger("fractoscope.matching")
WORKER_ID = f"{socket.gethostname()}:{os.getpid()}"


class MatchingServicer(matching_pb2_grpc.MatchingServiceServicer):
    """Decodes the request, runs `compute_series_height_map`, streams progress and the result.
    With `strip_peers`, dense matching is split into strips of about `strip_pixels` pixels,
    `strip_in_flight` of which are matched by the peers at a time.

    At most `coordinator_slots` height maps at once wait on peers (keep it below the server's
    worker threads); more match their strips here. Peers may include this replica, so threads
    are always left to answer MatchStrip, which waits on nothing: no deadlock among replicas."""

    def __init__(self, *, strip_peers: str | None = None, strip_pixels: int = DEFAULT_STRIP_PIXELS, strip_in_flight: int = 4,
                 coordinator_slots: int = 4, call_timeout_s: float = 600.0):
        self.strip_pixels = strip_pixels
        self.strip_in_flight = strip_in_flight
        self._peers = StripPeers(strip_peers, timeout_s=call_timeout_s) if strip_peers else None
        self._coordinator_slots = threading.BoundedSemaphore(coordinator_slots)

    @abort_on_error
    def ComputeHeightMap(self, request, context):
        if len(request.images) < 2:
            raise InvalidInputError("images", f"at least two images are needed, got {len(request.images)}")
        images = [read_sem_image(item.image.content, field=f"images[{i}].image") for i, item in enumerate(request.images)]
        tilts = tuple(item.tilt_deg if item.HasField("tilt_deg") else None for item in request.images)
        options = dataclasses.replace(rpc_matching.options_from_message(request.parameters), strip_pixels=self.strip_pixels)

        def work(progress):
            coordinating = self._peers is not None and self._coordinator_slots.acquire(blocking=False)
            peers = PeerStripMatcher(self._peers, in_flight=self.strip_in_flight, request_id=request.request_id) if coordinating else None
            try:
                result = compute_series_height_map(
                    images,
                    tilt_deg=tilts,
                    pixel_size_um=request.pixel_size_um if request.HasField("pixel_size_um") else None,
                    tilt_axis_deg=request.tilt_axis_deg if request.HasField("tilt_axis_deg") else None,
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
                yield rpc_matching.height_map_response(event, images[0].pixels)
                _log.info("height map done", extra={"request_id": request.request_id, "report": event.report})

    @abort_on_error
    def MatchStrip(self, request, context):
        return rpc_matching.strip_response(match_strip(rpc_matching.request_to_strip_task(request)), worker=WORKER_ID)
