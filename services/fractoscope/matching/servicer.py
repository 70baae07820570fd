"""MatchingService: stereo pairs of SEM images to calibrated height maps.

A replica given strip peers (a gRPC target such as `dns:///matching:50051`, balanced round-robin)
farms the strips of its dense matching out to them through MatchStrip and stitches the results;
any replica answers MatchStrip."""

from __future__ import annotations

import dataclasses
import logging
import os
import socket
from collections.abc import Sequence

import numpy as np

from fractoscope.matching import messages as rpc_matching
from fractoscope.matching.peers import PeerStripMatcher, StripPeers
from fractoscope.progress import ProgressCallback
from fractoscope.rpc import wire
from fractoscope.rpc.status import abort_on_error
from fractoscope.runtime import budget
from fractoscope.runtime.jobs import Job, JobRunner
from fractoscope.sem.image import read_sem_image
from fractoscope.sem.instruments import InstrumentProfile
from fractoscope.stereo.matching import DEFAULT_STRIP_PIXELS, match_strip
from fractoscope.stereo.pipeline import HeightMapResult, compute_series_height_map
from fractoscope.v1 import common_pb2, matching_pb2, matching_pb2_grpc

_log = logging.getLogger("fractoscope.matching")
WORKER_ID = f"{socket.gethostname()}:{os.getpid()}"


class MatchingServicer(matching_pb2_grpc.MatchingServiceServicer):
    """Checks the request against the memory budget, then decodes it and runs
    `compute_series_height_map` as one of the `builds` jobs, streaming progress and the result;
    strips matched for peers are `strips` jobs. With `strip_peers`, dense matching is split into
    strips of about `strip_pixels` pixels, `strip_in_flight` of which are matched by the peers at
    a time. Strips never wait on anything, so replicas that are each other's peers never wait on
    each other in a circle."""

    def __init__(
        self,
        *,
        builds: JobRunner,
        strips: JobRunner,
        budget: budget.Budget,
        strip_peers: str | None = None,
        strip_pixels: int = DEFAULT_STRIP_PIXELS,
        strip_in_flight: int = 4,
        call_timeout_s: float = 600.0,
        instruments: Sequence[InstrumentProfile] = (),
    ):
        self.strip_pixels = strip_pixels
        self.strip_in_flight = strip_in_flight
        self.strip_peers = strip_peers
        self._builds, self._strips, self._budget = builds, strips, budget
        self._peers = StripPeers(strip_peers) if strip_peers else None
        self._call_timeout_s = call_timeout_s
        self.instruments = tuple(instruments)

    @abort_on_error
    def ComputeHeightMap(self, request, context):
        estimate, (rows, cols) = self._estimate(request)
        self._budget.check(estimate, f"a height map of {len(request.images)} images of {cols} x {rows} pixels")

        def work(job: Job):
            with self._budget.held(estimate):
                return self.height_map(request, job, job.progress)

        for event in self._builds.follow(context, work):
            if isinstance(event, common_pb2.Progress):
                yield matching_pb2.ComputeHeightMapResponse(progress=event)
            else:
                result, texture = event
                yield rpc_matching.height_map_response(result, texture)
                _log.info("height map done", extra={"request_id": request.request_id, "report": result.report})

    def peak_bytes(self, request: matching_pb2.ComputeHeightMapRequest) -> int:
        """The request's estimated peak memory (see budget), from the first image's declared size;
        InvalidInputError for what cannot be matched at all."""
        return self._estimate(request)[0]

    def _estimate(self, request: matching_pb2.ComputeHeightMapRequest) -> tuple[int, tuple[int, int]]:
        """`peak_bytes` and the first image's (rows, cols)."""
        return rpc_matching.peak_bytes(request, strip_pixels=self.strip_pixels)

    def height_map(
        self, request: matching_pb2.ComputeHeightMapRequest, job: Job, progress: ProgressCallback
    ) -> tuple[HeightMapResult, np.ndarray]:
        """ComputeHeightMap's work, in the thread of `job` (this call's, or a specimen build's that
        calls it in-process): the height map and its texture (the reference image as stored)."""
        images = [
            read_sem_image(item.image.content, field=f"images[{i}].image") for i, item in enumerate(request.images)
        ]
        tilts = tuple(item.tilt_deg if item.HasField("tilt_deg") else None for item in request.images)
        options = dataclasses.replace(
            rpc_matching.options_from_message(request.parameters), strip_pixels=self.strip_pixels
        )
        peers = None
        if self._peers is not None:
            peers = PeerStripMatcher(
                self._peers,
                in_flight=self.strip_in_flight,
                request_id=request.request_id,
                timeout_s=lambda: job.time_remaining_s(at_most_s=self._call_timeout_s),
            )
        with rpc_matching.request_fields():
            result = compute_series_height_map(
                images,
                tilt_deg=tilts,
                pixel_size_um=request.pixel_size_um if request.HasField("pixel_size_um") else None,
                tilt_axis_deg=request.tilt_axis_deg if request.HasField("tilt_axis_deg") else None,
                options=options,
                strip_matcher=peers,
                instruments=self.instruments,
                progress=progress,
            )
        if peers is not None:
            result.report["strip_workers"] = sorted(peers.workers)
        return result, images[0].pixels

    @abort_on_error
    def MatchStrip(self, request, context):
        for name in ("left", "right"):  # the estimate below trusts the declared sizes: the data must hold them
            wire.raster_to_array(getattr(request, name), field=name)
        estimate = budget.strip_bytes((request.left.rows, request.left.cols))
        self._budget.check(estimate, f"a strip of {request.left.cols} x {request.left.rows} pixels")
        task = rpc_matching.request_to_strip_task(request)

        def work(job: Job):
            with self._budget.held(estimate):
                return rpc_matching.strip_response(match_strip(task), worker=WORKER_ID)

        return self._strips.result(context, work)
