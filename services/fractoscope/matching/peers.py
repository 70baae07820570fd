"""Strip peers: matching replicas that match the strips of a large pair in parallel (MatchStrip)."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor

import grpc

from fractoscope.errors import FractoscopeError, UnavailableError
from fractoscope.matching import messages as rpc_matching
from fractoscope.rpc.channel import ChannelOwner, open_channel
from fractoscope.rpc.status import ClientError, raised_as_client_errors
from fractoscope.stereo.disparity import DisparityResult, StripTask
from fractoscope.stereo.matching import match_strip
from fractoscope.v1 import matching_pb2_grpc


class StripPeers(ChannelOwner):
    """The matching replicas behind one gRPC target (several addresses or a `dns:///` name are
    balanced round-robin)."""

    def __init__(self, address: str):
        self._channel = open_channel(address)
        self._stub = matching_pb2_grpc.MatchingServiceStub(self._channel)

    def match_strip(self, task: StripTask, *, timeout_s: float, request_id: str = "") -> tuple[DisparityResult, str]:
        """Dense disparity of one strip of a rectified pair, matched by a peer within `timeout_s`;
        returns it with the id of the replica that matched it. Failures raise ClientError."""
        request = rpc_matching.strip_request(task, request_id=request_id)
        with raised_as_client_errors():
            response = self._stub.MatchStrip(request, timeout=timeout_s)
        return rpc_matching.response_to_disparity(response), response.worker


class PeerStripMatcher:
    """Matches strips on `peers`, up to `in_flight` at a time, each call within `timeout_s()`
    seconds (what the caller of the height map still waits), and remembers which replicas did
    (`workers`). A strip that the peers are too busy to take is matched here. One per height map."""

    def __init__(self, peers: StripPeers, *, in_flight: int, timeout_s: Callable[[], float], request_id: str = ""):
        self.peers = peers
        self.in_flight = in_flight
        self.timeout_s = timeout_s
        self.request_id = request_id
        self.workers: set[str] = set()

    def __call__(self, tasks: Iterable[StripTask]) -> Iterator[DisparityResult]:
        with ThreadPoolExecutor(max_workers=self.in_flight) as pool:
            yield from pool.map(self._match, tasks)

    def _match(self, task: StripTask) -> DisparityResult:
        try:
            result, worker = self.peers.match_strip(task, timeout_s=self.timeout_s(), request_id=self.request_id)
        except ClientError as error:
            if error.code == grpc.StatusCode.RESOURCE_EXHAUSTED:
                return match_strip(task)
            if error.code in (grpc.StatusCode.UNAVAILABLE, grpc.StatusCode.DEADLINE_EXCEEDED):
                raise UnavailableError(f"a strip peer failed ({error}); retry") from None
            # A peer that refuses what this replica sends runs another version or other limits.
            raise FractoscopeError(
                f"a strip peer refused a strip ({error.code.name}: {error}); check that the matching replicas agree"
            ) from None
        self.workers.add(worker)
        return result
