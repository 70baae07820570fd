"""Builds as jobs: bounded pools and queues, calls that follow and join jobs, cancellation; then
real servers on loopback under concurrent builds, with health checked all along."""

from __future__ import annotations

import threading
import time
from concurrent.futures import ThreadPoolExecutor

import grpc
import numpy as np
import pytest
from conftest import fracture_pair, tiff_bytes
from grpc_health.v1 import health_pb2, health_pb2_grpc

from fractoscope.client import ClientError, FractoscopeClient
from fractoscope.errors import CancelledError, ResourceExhaustedError
from fractoscope.runtime.jobs import JobRunner
from fractoscope.server.config import DEFAULT_BUILD_QUEUE, ServerConfig, default_build_workers
from fractoscope.server.main import create_server
from fractoscope.v1 import common_pb2, matching_pb2_grpc, tiles_pb2, tiles_pb2_grpc


class _Call:
    """What a job runner needs of a gRPC call: its deadline, and callbacks run when it ends."""

    def __init__(self, timeout_s: float = 120.0):
        self._deadline = time.monotonic() + timeout_s
        self._callbacks = []
        self.ended = False

    def time_remaining(self) -> float:
        return max(self._deadline - time.monotonic(), 0.0)

    def add_callback(self, callback) -> bool:
        if self.ended:
            return False
        self._callbacks.append(callback)
        return True

    def end(self) -> None:
        """The client cancels, or the deadline passes."""
        self.ended = True
        for callback in self._callbacks:
            callback()


class _Blocking:
    """Work that reports progress until released; records whether it ran to its end or was stopped."""

    def __init__(self, result="done"):
        self.started, self.release, self.stopped = threading.Event(), threading.Event(), threading.Event()
        self.result, self.runs = result, 0

    def __call__(self, job):
        self.runs += 1
        self.started.set()
        try:
            while not self.release.wait(0.01):
                job.progress(0.5, "working")
        except CancelledError:
            self.stopped.set()
            raise
        return self.result


def _drain(events):
    """(progress messages, final value) of a followed job, or the exception it ended with."""
    progress, final = [], None
    try:
        for event in events:
            if isinstance(event, common_pb2.Progress):
                progress.append(event)
            else:
                final = event
    except Exception as error:
        return progress, error
    return progress, final


def _in_thread(function, *args):
    outcome = {}
    thread = threading.Thread(target=lambda: outcome.setdefault("value", function(*args)), daemon=True)
    thread.start()
    return thread, outcome


def test_a_full_queue_is_refused_with_a_retry_hint_and_a_cancelled_queued_job_frees_its_place():
    runner = JobRunner("builds", workers=1, queue_limit=1)
    running, queued = _Blocking("a"), _Blocking("b")
    first = runner.follow(_Call(), running)
    first_thread, first_outcome = _in_thread(_drain, first)
    assert running.started.wait(30)
    queued_call = _Call()
    second_thread, second_outcome = _in_thread(_drain, runner.follow(queued_call, queued))
    with pytest.raises(ResourceExhaustedError, match="queue of builds is full") as refused:
        runner.follow(_Call(), _Blocking())
    assert refused.value.retry_after_s >= 1
    queued_call.end()  # the client of the queued job goes away
    second_thread.join(30)
    assert second_outcome["value"] == ([], None)
    third = _Blocking("c")
    third_thread, third_outcome = _in_thread(_drain, runner.follow(_Call(), third))  # its place is free again
    running.release.set()
    third.release.set()
    first_thread.join(30)
    third_thread.join(30)
    assert first_outcome["value"][1] == "a" and third_outcome["value"][1] == "c"
    assert queued.runs == 0  # the cancelled job never started


def test_calls_with_one_key_follow_one_job_and_a_cancelled_job_stops_at_its_next_report():
    runner = JobRunner("builds", workers=1, queue_limit=4)
    shared = _Blocking("shared")
    calls = [_Call() for _ in range(3)]
    threads = [_in_thread(_drain, runner.follow(call, shared, key=("steel-1", "lims-1"))) for call in calls]
    assert shared.started.wait(30)
    shared.release.set()
    for thread, _ in threads:
        thread.join(30)
    assert [outcome["value"][1] for _, outcome in threads] == ["shared"] * 3 and shared.runs == 1

    abandoned, call = _Blocking(), _Call()
    thread, outcome = _in_thread(_drain, runner.follow(call, abandoned, key=("steel-2", "lims-2")))
    assert abandoned.started.wait(30)
    call.end()
    assert abandoned.stopped.wait(30)  # its next progress report raised CancelledError
    thread.join(30)
    after = _Blocking("after")
    after.release.set()
    assert (
        _drain(runner.follow(_Call(), after, key=("steel-2", "lims-2")))[1] == "after"
    )  # a new job, not the cancelled one


def test_every_follower_gets_the_error_of_a_failed_job():
    runner = JobRunner("builds", workers=1, queue_limit=2)
    release = threading.Event()

    def failing(job):
        release.wait(30)
        raise ValueError("mesher gone")

    threads = [_in_thread(_drain, runner.follow(_Call(), failing, key="k")) for _ in range(2)]
    release.set()
    for thread, _ in threads:
        thread.join(30)
    assert all(isinstance(outcome["value"][1], ValueError) for _, outcome in threads)


def _specimen_roi(size_px: int, seed: int) -> tiles_pb2.RoiSpec:
    pair = fracture_pair(size_px=size_px, seed=seed)
    spec = tiles_pb2.RoiSpec(id="overview", pixel_size_um=0.1)
    for image, tilt_deg in ((pair.first, -5.0), (pair.second, 5.0)):
        item = spec.images.add(tilt_deg=tilt_deg)
        item.image.content = tiff_bytes(image)
    return spec


# A health check unanswered for this long is a hang (the deadlock's checks never came back); how
# fast checks are answered depends on the machine's load and is measured by benchmarks.serving.
HEALTH_HANG_S = 20.0


class _HealthProbe:
    """Checks health every 50 ms on its own channel while the block runs; records each check's
    latency, s, or its failure."""

    def __init__(self, address: str, timeout_s: float):
        self._channel = grpc.insecure_channel(address)
        self._stub = health_pb2_grpc.HealthStub(self._channel)
        self._timeout_s, self.latencies_s, self.failures = timeout_s, [], []
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(0.05):
            started = time.perf_counter()
            try:
                status = self._stub.Check(health_pb2.HealthCheckRequest(), timeout=self._timeout_s).status
                assert status == health_pb2.HealthCheckResponse.SERVING
                self.latencies_s.append(time.perf_counter() - started)
            except grpc.RpcError as error:
                self.failures.append(error.code())

    def __enter__(self):
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self._channel.close()


@pytest.mark.server
@pytest.mark.timeout(600)
def test_sixteen_concurrent_builds_complete_or_are_refused_while_health_answers_every_check(tmp_path):
    """The server once deadlocked itself here: builds held every RPC thread while they called
    matching and meshing on the same server. With the default workers each build either
    completes or is refused for a full queue; health answers every check throughout. How fast
    it answers is a load figure (printed here; `benchmarks.serving` measures its p99): the
    checks' deadline only tells an answer from none, as the deadlock gave."""
    server, port = create_server(ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data"))
    server.start()
    address = f"127.0.0.1:{port}"
    spec = _specimen_roi(256, seed=3)
    outcomes = {}
    try:
        with (
            _HealthProbe(address, timeout_s=HEALTH_HANG_S) as health,
            FractoscopeClient(address, timeout_s=500) as client,
        ):

            def build(index: int):
                try:
                    return client.reconstruct_specimen(f"steel-{index}", [spec])
                except ClientError as error:
                    return error

            with ThreadPoolExecutor(16) as pool:
                outcomes = dict(zip(range(16), pool.map(build, range(16))))
            stored = {s["id"] for s in client.list_specimens()}
    finally:
        server.stop(grace=None)
    refused = {i for i, o in outcomes.items() if isinstance(o, ClientError)}
    assert all(
        outcomes[i].code == grpc.StatusCode.RESOURCE_EXHAUSTED and outcomes[i].retry_after_s >= 1 for i in refused
    ), outcomes
    completed = {i for i in outcomes if i not in refused}
    assert all(outcomes[i]["id"] == f"steel-{i}" for i in completed)
    assert stored == {f"steel-{i}" for i in completed}
    assert len(completed) >= DEFAULT_BUILD_QUEUE  # refusals only once the queue is full
    assert health.failures == [] and health.latencies_s
    print(
        f"{len(completed)} built, {len(refused)} refused ({default_build_workers()} build workers); health: "
        f"{len(health.latencies_s)} checks, max {max(health.latencies_s) * 1000:.0f} ms"
    )


@pytest.mark.server
@pytest.mark.timeout(300)
def test_a_cancelled_build_frees_its_worker_and_stores_nothing(tmp_path):
    """One build worker: a build whose client cancels it after its first progress report stops
    (nothing stored) and the next build gets the worker."""
    server, port = create_server(
        ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data", build_workers=1, build_queue=1)
    )
    server.start()
    stub_channel = grpc.insecure_channel(f"127.0.0.1:{port}")
    try:
        stub = tiles_pb2_grpc.TileServiceStub(stub_channel)
        call = stub.ReconstructSpecimen(
            tiles_pb2.ReconstructSpecimenRequest(specimen_id="abandoned", rois=[_specimen_roi(384, 4)]), timeout=300
        )
        assert next(call).HasField("progress")
        call.cancel()
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=280) as client:
            assert client.reconstruct_specimen("next", [_specimen_roi(128, 5)])["id"] == "next"
            assert [s["id"] for s in client.list_specimens()] == ["next"]  # the cancelled build stopped before storing
    finally:
        stub_channel.close()
        server.stop(grace=None)


@pytest.mark.server
@pytest.mark.timeout(300)
def test_concurrent_repeats_of_a_request_id_join_one_build(tmp_path):
    """Six calls at once with one request id on a server that queues one build at most: were
    they six builds, the queue would refuse most of them."""
    server, port = create_server(
        ServerConfig(address="127.0.0.1:0", data_dir=tmp_path / "data", build_workers=1, build_queue=1)
    )
    server.start()
    spec = _specimen_roi(256, seed=6)
    try:
        with FractoscopeClient(f"127.0.0.1:{port}", timeout_s=280) as client, ThreadPoolExecutor(6) as pool:
            summaries = list(
                pool.map(lambda _: client.reconstruct_specimen("steel-9", [spec], request_id="lims-9"), range(6))
            )
    finally:
        server.stop(grace=None)
    assert all(summary == summaries[0] for summary in summaries) and summaries[0]["id"] == "steel-9"


def test_height_maps_are_jobs_too_and_health_answers_while_they_run(server_address):
    """ComputeHeightMap and BuildMesh follow jobs like builds; a check made while one runs is answered."""
    pair = fracture_pair(size_px=256, seed=8)
    with (
        FractoscopeClient(server_address, timeout_s=120) as client,
        _HealthProbe(server_address, timeout_s=HEALTH_HANG_S) as health,
    ):
        stages = []
        result = client.compute_height_map(
            [tiff_bytes(pair.first), tiff_bytes(pair.second)],
            tilt_deg=(-5, 5),
            pixel_size_um=0.1,
            on_progress=lambda fraction, message: stages.append(message),
        )
        tiles, _ = client.build_mesh(np.nan_to_num(result.z_um), None, pixel_size_um=0.1)
    assert np.isfinite(result.z_um).mean() > 0.9 and tiles and stages
    assert health.failures == []


class _StalledMatching(matching_pb2_grpc.MatchingServiceServicer):
    """A remote matching service that never finishes: records the deadline its ComputeHeightMap
    call came with, and when that call is cancelled."""

    def __init__(self):
        self.called, self.cancelled = threading.Event(), threading.Event()
        self.time_remaining_s = None

    def ComputeHeightMap(self, request, context):
        self.time_remaining_s = context.time_remaining()
        context.add_callback(self.cancelled.set)
        self.called.set()
        self.cancelled.wait(60)
        yield from ()


@pytest.mark.server
@pytest.mark.timeout(120)
def test_a_remote_matching_call_gets_the_callers_deadline_and_is_cancelled_with_the_build(tmp_path):
    """The tile service on its own, its matching remote: the call it makes for a build carries
    what is left of the build's caller's deadline (not its own 1,800 s), and the client's cancel
    reaches the remote call."""
    stalled = _StalledMatching()
    peer = grpc.server(ThreadPoolExecutor(4))
    matching_pb2_grpc.add_MatchingServiceServicer_to_server(stalled, peer)
    peer_port = peer.add_insecure_port("127.0.0.1:0")
    peer.start()
    tiles, port = create_server(
        ServerConfig(
            address="127.0.0.1:0",
            services=("tiles",),
            data_dir=tmp_path / "data",
            matching_address=f"127.0.0.1:{peer_port}",
            meshing_address=f"127.0.0.1:{peer_port}",
        )
    )
    tiles.start()
    channel = grpc.insecure_channel(f"127.0.0.1:{port}")
    try:
        request = tiles_pb2.ReconstructSpecimenRequest(specimen_id="remote", rois=[_specimen_roi(128, 7)])
        call = tiles_pb2_grpc.TileServiceStub(channel).ReconstructSpecimen(request, timeout=60)
        assert stalled.called.wait(30)
        assert 0 < stalled.time_remaining_s < 90  # the caller's 60 s (gRPC rounds it up a little), not 1,800 s
        call.cancel()
        assert stalled.cancelled.wait(15)  # long before the deadline
    finally:
        channel.close()
        tiles.stop(grace=None)
        peer.stop(grace=None)
