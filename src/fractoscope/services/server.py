"""The gRPC server: Fractoscope services plus health checking and reflection.

Configuration comes from flags, each with an environment variable as its default:
FRACTO_ADDRESS (listen address), FRACTO_MAX_MESSAGE_MB (largest message either way),
FRACTO_WORKERS (concurrent calls), FRACTO_LOG_LEVEL, FRACTO_DATA_DIR (where specimens are kept),
FRACTO_MATCHING_ADDRESS and FRACTO_MESHING_ADDRESS (the services the tile service calls; default:
this server), FRACTO_STRIP_PEERS (matching replicas that match the strips of large pairs, e.g. the
headless Service of the matching Deployment; empty = match here), FRACTO_STRIP_PIXELS and
FRACTO_STRIP_IN_FLIGHT,
FRACTO_HTTP_ADDRESS (host:port of the plain-HTTP tile endpoint; empty = off), FRACTO_TOKENS
(bearer tokens, see auth; none = open), FRACTO_TLS_CERT and FRACTO_TLS_KEY (serve TLS).
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import json
import logging
import os
import signal
import sys
import threading
import time
from concurrent import futures
from pathlib import Path

import grpc
from grpc_health.v1 import health, health_pb2, health_pb2_grpc
from grpc_reflection.v1alpha import reflection

from fractoscope.services.auth import AuthInterceptor, TokenTable
from fractoscope.rpc.limits import DEFAULT_MAX_MESSAGE_MB, message_size_options
from fractoscope.services.matching.servicer import MatchingServicer
from fractoscope.services.meshing.servicer import MeshingServicer
from fractoscope.services.tiles.http import start_http_server
from fractoscope.services.tiles.servicer import SerializedGetTile, TileServicer
from fractoscope.specimen.store import SpecimenStore
from fractoscope.v1 import matching_pb2, matching_pb2_grpc, meshing_pb2, meshing_pb2_grpc, tiles_pb2, tiles_pb2_grpc

_SERVICES = {
    "matching": (matching_pb2.DESCRIPTOR.services_by_name["MatchingService"], matching_pb2_grpc.add_MatchingServiceServicer_to_server),
    "meshing": (meshing_pb2.DESCRIPTOR.services_by_name["MeshingService"], meshing_pb2_grpc.add_MeshingServiceServicer_to_server),
    "tiles": (tiles_pb2.DESCRIPTOR.services_by_name["TileService"], tiles_pb2_grpc.add_TileServiceServicer_to_server),
}
DEFAULT_DATA_DIR = "data"


def create_server(
    address: str = "[::]:0",
    *,
    services: tuple[str, ...] = tuple(_SERVICES),
    max_message_mb: int = DEFAULT_MAX_MESSAGE_MB,
    workers: int = 8,
    data_dir: str | Path = DEFAULT_DATA_DIR,
    matching_address: str | None = None,
    meshing_address: str | None = None,
    tokens: TokenTable | None = None,
    tls_cert_path: str | None = None,
    tls_key_path: str | None = None,
    strip_peers: str | None = None,
    strip_pixels: int = 2_000_000,
    strip_in_flight: int = 4,
) -> tuple[grpc.Server, int]:
    """A server with the named services, health and reflection, bound to `address`; returns it
    (not started) with the bound port. The tile service keeps specimens under `data_dir` and calls
    matching and meshing at their addresses (default: this server on loopback). With `tokens`,
    calls need a bearer token (see auth); with a certificate and key, the port speaks TLS. The
    matching service farms strips of about `strip_pixels` out to `strip_peers` when given,
    `strip_in_flight` at a time."""
    for name in services:
        if name not in _SERVICES:
            raise ValueError(f"unknown service {name!r}; known: {', '.join(_SERVICES)}")
    interceptors = [AuthInterceptor(tokens)] if tokens is not None and tokens.enabled else []
    if "tiles" in services:
        store = SpecimenStore(Path(data_dir))
        store.discard_unfinished()  # this server is the store's one writer
        tile_servicer = TileServicer(store, matching_address=matching_address, meshing_address=meshing_address)
        interceptors.append(SerializedGetTile(tile_servicer))  # after the token check
    server = grpc.server(
        futures.ThreadPoolExecutor(max_workers=workers), options=message_size_options(max_message_mb), interceptors=interceptors
    )
    health_servicer = health.HealthServicer()
    health_pb2_grpc.add_HealthServicer_to_server(health_servicer, server)
    names = [reflection.SERVICE_NAME, health.SERVICE_NAME]
    for name in services:
        descriptor, add = _SERVICES[name]
        if name == "tiles":
            add(tile_servicer, server)
        elif name == "matching":
            add(MatchingServicer(strip_peers=strip_peers, strip_pixels=strip_pixels, strip_in_flight=strip_in_flight,
                                 coordinator_slots=max(1, workers // 2)), server)
        else:
            add(MeshingServicer(), server)
        names.append(descriptor.full_name)
        health_servicer.set(descriptor.full_name, health_pb2.HealthCheckResponse.SERVING)
    health_servicer.set("", health_pb2.HealthCheckResponse.SERVING)
    reflection.enable_server_reflection(names, server)
    if tls_cert_path and tls_key_path:
        credentials = grpc.ssl_server_credentials([(Path(tls_key_path).read_bytes(), Path(tls_cert_path).read_bytes())])
        port = server.add_secure_port(address, credentials)
    else:
        port = server.add_insecure_port(address)
    if port == 0:
        raise RuntimeError(f"cannot bind {address}")
    if "tiles" in services:
        tile_servicer.matching_address = matching_address or f"127.0.0.1:{port}"
        tile_servicer.meshing_address = meshing_address or f"127.0.0.1:{port}"
    return server, port


class JsonFormatter(logging.Formatter):
    """One JSON object per line with a `severity` field, for log collectors."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "severity": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key in ("request_id", "report"):
            if hasattr(record, key):
                entry[key] = getattr(record, key)
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def configure_logging(level: str) -> None:
    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(JsonFormatter())
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)


def build_parser() -> argparse.ArgumentParser:
    """fracto-server's flags, each defaulting to its environment variable."""
    parser = argparse.ArgumentParser(prog="fracto-server", description="Serve Fractoscope's gRPC services.")
    parser.add_argument("--address", default=os.environ.get("FRACTO_ADDRESS", "[::]:50051"))
    parser.add_argument("--services", default=os.environ.get("FRACTO_SERVICES", ",".join(_SERVICES)),
                        help="comma-separated services to serve")
    parser.add_argument("--max-message-mb", type=int, default=int(os.environ.get("FRACTO_MAX_MESSAGE_MB", DEFAULT_MAX_MESSAGE_MB)))
    parser.add_argument("--workers", type=int, default=int(os.environ.get("FRACTO_WORKERS", "8")))
    parser.add_argument("--log-level", default=os.environ.get("FRACTO_LOG_LEVEL", "INFO"))
    parser.add_argument("--data", default=os.environ.get("FRACTO_DATA_DIR", DEFAULT_DATA_DIR), help="specimen directory")
    parser.add_argument("--matching-address", default=os.environ.get("FRACTO_MATCHING_ADDRESS") or None,
                        help="matching service for the tile service, e.g. dns:///matching:50051 (default: this server)")
    parser.add_argument("--meshing-address", default=os.environ.get("FRACTO_MESHING_ADDRESS") or None,
                        help="meshing service for the tile service (default: this server)")
    parser.add_argument("--strip-peers", default=os.environ.get("FRACTO_STRIP_PEERS") or None,
                        help="matching replicas that match strips of large pairs in parallel, e.g. "
                             "dns:///matching:50051 or ipv4:10.0.0.1:50051,10.0.0.2:50051 (default: match here)")
    parser.add_argument("--strip-pixels", type=int, default=int(os.environ.get("FRACTO_STRIP_PIXELS", "2000000")),
                        help="pixels per strip of dense matching")
    parser.add_argument("--strip-in-flight", type=int, default=int(os.environ.get("FRACTO_STRIP_IN_FLIGHT", "4")),
                        help="strips sent to the peers at a time (about the number of matching replicas)")
    parser.add_argument("--http-address", default=os.environ.get("FRACTO_HTTP_ADDRESS", "0.0.0.0:8080"),
                        help="host:port of the HTTP tile endpoint; empty = off")
    parser.add_argument("--tls-cert", default=os.environ.get("FRACTO_TLS_CERT") or None, help="PEM certificate: serve TLS")
    parser.add_argument("--tls-key", default=os.environ.get("FRACTO_TLS_KEY") or None, help="PEM private key of --tls-cert")
    parser.add_argument("--grace-s", type=float, default=30.0, help="seconds in-flight calls get on SIGTERM")
    return parser


def settle_garbage_collector() -> None:
    """Readies a serving process's garbage collector: what start-up built is collected and frozen
    out of later collections, and the youngest generation is collected every 50,000 allocations
    instead of 700. Every gRPC call allocates many short-lived objects; with Python's defaults the
    collector costs tile fetches about a third of their rate (GetTile at concurrency 50, 15 s runs
    on one CPU: 2,900-3,000/s at p99 28-35 ms with the defaults, 4,200-4,650/s at p99 20-22 ms with
    these settings). Garbage cycles wait at most one such period, a few MB."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(50_000, 20, 10)


def keep_freed_memory() -> None:
    """Lets glibc's malloc keep freed memory for reuse instead of handing it back to the kernel:
    blocks up to 32 MB come from the heap rather than fresh mappings, and the heap is not trimmed.
    Dense matching allocates and frees hundreds of image-sized temporaries per strip; with the
    defaults many are fresh mappings whose pages the kernel faults in and zeroes again (a 512²
    pair: 8,800 page faults per match, 23 with this), which took a quarter of the matching time
    (1024² pair: 0.14 s, 0.12 s with this; system time 0.09 s, 0.02 s). Resident memory then
    stays near its peak. Does nothing where the C library is not glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold = -1, -3  # mallopt's parameter numbers, from malloc.h
    libc.mallopt(m_mmap_threshold, 32 * 2**20)  # glibc's largest allowed value on 64-bit
    libc.mallopt(m_trim_threshold, 2**30)


def main(argv: list[str] | None = None) -> None:
    parser = build_parser()
    args = parser.parse_args(argv)
    configure_logging(args.log_level)
    keep_freed_memory()
    tokens = TokenTable.from_environment()
    services = tuple(name.strip() for name in args.services.split(",") if name.strip())
    server, port = create_server(
        args.address, services=services, max_message_mb=args.max_message_mb, workers=args.workers,
        data_dir=args.data, matching_address=args.matching_address, meshing_address=args.meshing_address,
        tokens=tokens, tls_cert_path=args.tls_cert, tls_key_path=args.tls_key,
        strip_peers=args.strip_peers, strip_pixels=args.strip_pixels, strip_in_flight=args.strip_in_flight,
    )
    settle_garbage_collector()
    server.start()
    log = logging.getLogger("fractoscope.server")
    log.info(f"serving {', '.join(services)} on port {port}")
    http = None
    if "tiles" in services and args.http_address:
        host, _, http_port = args.http_address.rpartition(":")
        http = start_http_server(SpecimenStore(Path(args.data)), host or "0.0.0.0", int(http_port), tokens=tokens)
        log.info(f"serving tilesets over HTTP on port {http.server_port}")
    stopped = threading.Event()

    def stop(signum, frame):
        logging.getLogger("fractoscope.server").info("stopping")
        server.stop(args.grace_s).wait()
        if http is not None:
            http.shutdown()
        stopped.set()

    signal.signal(signal.SIGTERM, stop)
    signal.signal(signal.SIGINT, stop)
    stopped.wait()


if __name__ == "__main__":
    main()
