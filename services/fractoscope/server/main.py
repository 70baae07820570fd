"""The gRPC server: Fractoscope's services plus health checking and reflection, from one process
(`make run`, in-process `fracto` commands) to one service per process (`--services`, as deployed).
Configuration: see config."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import threading
from collections.abc import Iterator, Sequence
from concurrent import futures
from pathlib import Path

# gRPC core reads this once, when grpc is imported: it would log transport events (GOAWAY when a
# client or peer goes away) at INFO on stderr, between the JSON log lines. GRPC_VERBOSITY set in
# the environment still wins, for debugging.
os.environ.setdefault("GRPC_VERBOSITY", "ERROR")
import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from fractoscope.http.server import start_http_server
from fractoscope.matching.servicer import MatchingServicer
from fractoscope.meshing.servicer import MeshingServicer
from fractoscope.rpc.limits import message_size_options
from fractoscope.runtime.auth import AuthInterceptor, TokenTable, peer_token_problem
from fractoscope.runtime.budget import Budget
from fractoscope.runtime.decoding import MalformedRequests
from fractoscope.runtime.jobs import JobRunner
from fractoscope.runtime.process import (
    configure_logging,
    filter_grpc_logs,
    keep_freed_memory,
    settle_garbage_collector,
)
from fractoscope.runtime.threads import ThreadPoolRouting
from fractoscope.sem.instruments import InstrumentProfile, load_profiles, profiles_path
from fractoscope.server.config import DEFAULT_DATA_DIR, SERVICE_NAMES, ServerConfig, default_build_workers
from fractoscope.store.base import StoredSpecimens
from fractoscope.store.folder import SpecimenStore
from fractoscope.store.s3 import open_specimen_store
from fractoscope.tiles.servicer import SerializedGetTile, TileServicer
from fractoscope.v1 import matching_pb2, matching_pb2_grpc, meshing_pb2, meshing_pb2_grpc, tiles_pb2, tiles_pb2_grpc

_log = logging.getLogger("fractoscope.server")
_REGISTRATIONS = {
    "matching": (
        matching_pb2.DESCRIPTOR.services_by_name["MatchingService"],
        matching_pb2_grpc.add_MatchingServiceServicer_to_server,
    ),
    "meshing": (
        meshing_pb2.DESCRIPTOR.services_by_name["MeshingService"],
        meshing_pb2_grpc.add_MeshingServiceServicer_to_server,
    ),
    "tiles": (tiles_pb2.DESCRIPTOR.services_by_name["TileService"], tiles_pb2_grpc.add_TileServiceServicer_to_server),
}
# The calls that follow jobs (see jobs), answered on threads of their own (see threads).
_JOB_METHODS = (
    "/fractoscope.v1.MatchingService/ComputeHeightMap",
    "/fractoscope.v1.MatchingService/MatchStrip",
    "/fractoscope.v1.MeshingService/BuildMesh",
    "/fractoscope.v1.TileService/ReconstructSpecimen",
)
# The analyses the budget admits (see budget), answered on threads of their own (see threads).
_ANALYSIS_METHODS = (
    "/fractoscope.v1.TileService/GetRoughness",
    "/fractoscope.v1.TileService/GetProfile",
    "/fractoscope.v1.TileService/Export",
    "/fractoscope.v1.TileService/GetReport",
)
# Threads beyond those for every call the job runners or the budget admit, to refuse the others at once.
_SPARE_JOB_CALL_THREADS = 8


def create_server(
    config: ServerConfig = ServerConfig(),
    *,
    store: StoredSpecimens | None = None,
    tokens: TokenTable | None = None,
    instruments: Sequence[InstrumentProfile] = (),
    budget: Budget | None = None,
) -> tuple[grpc.Server, int]:
    """A server of `config`'s services, health and reflection, bound to its address; returns it
    (not started) with the bound port. Queries are answered on `config.workers` threads; builds,
    height maps and meshes run `build_workers` at a time, `build_queue` waiting, strips for peers
    likewise, each within `max_request_mb` of estimated memory, every request under `budget`
    (default: one of this server's; pass the one an HTTP endpoint of this process shares, see
    runtime.budget). The tile service keeps specimens in `store` (default: under
    `config.data_dir`) and calls matching and meshing at their addresses (default: in-process).
    `tokens`: bearer tokens (auth). Matching applies the `instruments` profiles images' metadata
    names."""
    services = config.services
    _check_known(services)
    filter_grpc_logs()  # a token in a call's metadata must not reach the log through gRPC's own lines
    build_workers = config.build_workers or default_build_workers()
    builds = JobRunner("builds", workers=build_workers, queue_limit=config.build_queue)
    strips = JobRunner("strips", workers=build_workers, queue_limit=config.build_queue)
    store = store or (SpecimenStore(Path(config.data_dir)) if "tiles" in services else None)
    budget = budget or process_budget(
        config.max_request_mb, build_workers=build_workers, store=store, data_dir=config.data_dir
    )
    servicers = {}
    if "matching" in services:
        servicers["matching"] = MatchingServicer(
            builds=builds,
            strips=strips,
            budget=budget,
            strip_peers=config.strip_peers,
            strip_pixels=config.strip_pixels,
            strip_in_flight=config.strip_in_flight,
            instruments=instruments,
        )
    if "meshing" in services:
        servicers["meshing"] = MeshingServicer(builds=builds, budget=budget)
    if "tiles" in services:
        servicers["tiles"] = _tile_servicer(
            store, builds, budget, servicers, config.matching_address, config.meshing_address
        )
    tokens = tokens if tokens is not None and tokens.enabled else None
    _warn_of_peer_credentials(tokens, servicers)
    interceptors = _interceptors(tokens, servicers.get("tiles"), job_runners=(builds, strips), budget=budget)
    server = _grpc_server(servicers, interceptors, workers=config.workers, max_message_mb=config.max_message_mb)
    port = _bind(server, config.address, config.tls_cert_path, config.tls_key_path)
    _log_limits(build_workers, config.build_queue, budget)
    return server, port


def process_budget(
    max_request_mb: int | None, *, build_workers: int, store: StoredSpecimens | None, data_dir: str | Path
) -> Budget:
    """The admission budget of a server process, one for its gRPC and HTTP front ends (see
    runtime.budget): `max_request_mb` a request (default: its share over the build workers),
    files written under the store's scratch folder (else `data_dir`/tmp)."""
    scratch_root = store.scratch_root if store is not None else Path(data_dir) / "tmp"
    return Budget.for_server(max_request_mb, concurrent_requests=build_workers, scratch_root=scratch_root)


def _log_limits(build_workers: int, build_queue: int, budget: Budget) -> None:
    _log.info(
        f"builds: {build_workers} at a time, {build_queue} waiting, {budget.limit_bytes // 2**20} MiB of memory per "
        f"request; {budget.memory_bytes // 2**20} MiB and {budget.cpu_slots} CPUs for all requests"
    )


def _check_known(services: tuple[str, ...]) -> None:
    """ValueError naming the first of `services` that this server has none of."""
    for name in services:
        if name not in _REGISTRATIONS:
            raise ValueError(f"unknown service {name!r}; known: {', '.join(SERVICE_NAMES)}")


def _tile_servicer(
    store: StoredSpecimens,
    builds: JobRunner,
    budget: Budget,
    servicers: dict,
    matching_address: str | None,
    meshing_address: str | None,
) -> TileServicer:
    """The tile service over `store`, restored first, calling matching and meshing at their
    addresses or else in `servicers`."""
    restored, _ = store.recover()  # this server is the store's one writer
    for specimen_id in restored:
        _log.warning(
            f"specimen {specimen_id!r}: a build was killed while it replaced the stored one, which is restored"
        )
    return TileServicer(
        store,
        builds=builds,
        budget=budget,
        local_matching=servicers.get("matching") if matching_address is None else None,
        matching_address=matching_address,
        local_meshing=servicers.get("meshing") if meshing_address is None else None,
        meshing_address=meshing_address,
    )


def _interceptors(
    tokens: TokenTable | None, tiles: TileServicer | None, *, job_runners: tuple[JobRunner, ...], budget: Budget
) -> list[grpc.ServerInterceptor]:
    """The token check (with `tokens`), then the routing of job calls and analyses to threads of
    their own, one for every call the `job_runners` or the `budget` admit and some spare, then the rest."""
    job_call_threads = sum(runner.max_followers for runner in job_runners) + _SPARE_JOB_CALL_THREADS
    interceptors = [AuthInterceptor(tokens)] if tokens else []
    routing = ThreadPoolRouting(
        _JOB_METHODS,
        job_call_threads=job_call_threads,
        analysis_methods=_ANALYSIS_METHODS,
        analysis_threads=budget.cpu_slots + budget.queue_limit + _SPARE_JOB_CALL_THREADS,
    )
    interceptors.append(routing)
    interceptors.append(MalformedRequests())  # within the routing, which keeps its deserializer
    if tiles is not None:
        interceptors.append(SerializedGetTile(tiles))  # after the token check
    return interceptors


def _grpc_server(
    servicers: dict, interceptors: list[grpc.ServerInterceptor], *, workers: int, max_message_mb: int
) -> grpc.Server:
    """A server of the servicers (see _register) answering on `workers` threads, not yet bound."""
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=workers),
        options=message_size_options(max_message_mb),
        interceptors=interceptors,
    )
    _register(server, servicers)
    return server


def _warn_of_peer_credentials(tokens: TokenTable | None, servicers: dict) -> None:
    """Warns when this server requires tokens but its own calls to other servers will not carry
    a good one (see auth.peer_token_problem)."""
    tiles, matching = servicers.get("tiles"), servicers.get("matching")
    peers = [
        target
        for target in (
            tiles and tiles.matching_address,
            tiles and tiles.meshing_address,
            matching and matching.strip_peers,
        )
        if target
    ]
    problem = peer_token_problem(tokens, os.environ.get("FRACTO_TOKEN")) if tokens and peers else None
    if problem:
        _log.warning(f"{problem} ({', '.join(peers)}); builds that need them will fail with UNAUTHENTICATED")


def _register(server: grpc.Server, servicers: dict) -> None:
    """Adds the servicers (by service name, in SERVICE_NAMES order) with health and reflection."""
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    names = [reflection.SERVICE_NAME, health.SERVICE_NAME]
    for name, servicer in servicers.items():
        descriptor, add = _REGISTRATIONS[name]
        add(servicer, server)
        names.append(descriptor.full_name)
        health_servicer.set(descriptor.full_name, health_pb2.HealthCheckResponse.SERVING)
    health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
    reflection.enable_server_reflection(names, server)


def _bind(server: grpc.Server, address: str, tls_cert_path: str | None, tls_key_path: str | None) -> int:
    if tls_cert_path and tls_key_path:
        credentials = grpc.ssl_server_credentials([(Path(tls_key_path).read_bytes(), Path(tls_cert_path).read_bytes())])
        port = server.add_secure_port(address, credentials)
    else:
        port = server.add_insecure_port(address)
    if port == 0:
        raise RuntimeError(f"cannot bind {address}")
    return port


@contextlib.contextmanager
def embedded_server(
    data_dir: str | Path = DEFAULT_DATA_DIR,
    *,
    host: str = "127.0.0.1",
    port: int = 0,
    store: StoredSpecimens | None = None,
    services: tuple[str, ...] = SERVICE_NAMES,
) -> Iterator[str]:
    """Runs `services` (default: all) in this process on `host:port` (port 0: a free one) for the
    block's duration, the tile service keeping specimens in `store` (default: under `data_dir`,
    which only the tile service touches), with the user's instrument profiles (`profiles_path`);
    yields the address."""
    server, bound = create_server(
        ServerConfig(address=f"{host}:{port}", services=services, data_dir=data_dir),
        store=store,
        instruments=load_profiles(profiles_path()),
    )
    server.start()
    try:
        yield f"{host}:{bound}"
    finally:
        server.stop(grace=None)


def main(argv: list[str] | None = None) -> None:
    config = ServerConfig.from_flags(argv)
    configure_logging(config.log_level)
    keep_freed_memory()
    tokens = TokenTable.from_environment()
    services = config.services
    store = open_specimen_store(config.store_url, Path(config.data_dir)) if "tiles" in services else None
    build_workers = config.build_workers or default_build_workers()
    budget = process_budget(config.max_request_mb, build_workers=build_workers, store=store, data_dir=config.data_dir)
    instruments = load_profiles(Path(config.instruments_path)) if config.instruments_path else ()
    server, port = create_server(config, store=store, tokens=tokens, instruments=instruments, budget=budget)
    settle_garbage_collector()
    server.start()
    _log.info(f"serving {', '.join(services)} on port {port}")
    http = _http(config, store, tokens, port, budget) if store is not None and config.http_address else None
    stopped = threading.Event()

    def stop(signum, frame):
        _log.info("stopping")
        server.stop(config.grace_s).wait()
        if http is not None:
            http.shutdown()
        stopped.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    stopped.wait()
    # A build whose call is gone may still run on a job pool's thread; the interpreter's exit
    # would tear that thread down inside native code (abort: "terminate called without an active
    # exception", exit status -6). The process ends here instead, as a kill would end it, which
    # both stores are made for (a folder's SpecimenStore.recover; a bucket's lease and sweep).
    logging.shutdown()
    os._exit(0)


def _http(config: ServerConfig, store: StoredSpecimens, tokens: TokenTable, grpc_port: int, budget: Budget):
    """The HTTP endpoint at the config's http_address, sending builds to this process's gRPC port,
    sharing its budget."""
    host, _, http_port = config.http_address.rpartition(":")
    http = start_http_server(
        store,
        host or "0.0.0.0",
        int(http_port),
        tokens=tokens,
        grpc_address=f"127.0.0.1:{grpc_port}",
        max_upload_bytes=config.max_message_mb * 1024 * 1024,
        budget=budget,
    )
    _log.info(f"serving tilesets over HTTP on port {http.server_port}")
    return http


if __name__ == "__main__":
    main()
