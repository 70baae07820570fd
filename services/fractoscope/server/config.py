"""fracto-server's configuration: one ServerConfig, read once from its flags (`from_flags`), each
flag defaulting to its environment variable.

FRACTO_ADDRESS (listen address), FRACTO_SERVICES, FRACTO_MAX_MESSAGE_MB (largest message either
way), FRACTO_WORKERS (threads answering queries), FRACTO_BUILD_WORKERS and FRACTO_BUILD_QUEUE
(builds, height maps and meshes run at once and waiting; strips matched for peers likewise, on
threads of their own), FRACTO_MAX_REQUEST_MB (memory one such request may take; default: 60 % of
the server's memory over the build workers), FRACTO_LOG_LEVEL, FRACTO_DATA_DIR (where specimens are
kept), FRACTO_STORE (s3://bucket/prefix: specimens in object storage instead),
FRACTO_MATCHING_ADDRESS and FRACTO_MESHING_ADDRESS (the services the tile service calls; default:
this process's own, called in-process), FRACTO_STRIP_PEERS (matching replicas that match
the strips of large pairs, e.g. the headless Service of the matching Deployment; empty = match
here), FRACTO_STRIP_PIXELS and FRACTO_STRIP_IN_FLIGHT, FRACTO_HTTP_ADDRESS (host:port of the
plain-HTTP tile endpoint; empty = off). Tokens (FRACTO_TOKENS, see auth) and TLS (FRACTO_TLS_CERT,
FRACTO_TLS_KEY) likewise, and FRACTO_INSTRUMENTS (the instrument profiles file, see
sem.instruments). FRACTO_WEB_ROOT (the installed web viewer, read by http.server; default
sys.prefix/share/fractoscope/web), FRACTO_HTTP_IDLE_TIMEOUT_S and FRACTO_HTTP_MAX_CONNECTIONS
(how long an HTTP connection may go without a whole request, default 15 s, and how many are kept
open, default 1000 and at most half the file descriptors; http.server) and FRACTO_UPLOAD_MAX_AGE_S
(how long HTTP uploads are kept, read by http.uploads; default 24 h) have no flag.
"""

from __future__ import annotations

import argparse
import os
from dataclasses import dataclass
from pathlib import Path

from fractoscope.rpc.limits import DEFAULT_MAX_MESSAGE_MB
from fractoscope.sem.instruments import ENVIRONMENT_VARIABLE, profiles_path
from fractoscope.stereo.matching import DEFAULT_STRIP_PIXELS

SERVICE_NAMES = ("matching", "meshing", "tiles")
DEFAULT_DATA_DIR = "data"
DEFAULT_BUILD_QUEUE = 8


@dataclass(frozen=True)
class ServerConfig:
    """What a server runs with: its listen `address`, its `services`, the largest message either
    way, the threads answering queries (`workers`), the builds, height maps and meshes run at once
    (`build_workers`; None: half the CPUs) and waiting (`build_queue`) and the memory one may take
    (`max_request_mb`; None: its share), where the tile service keeps specimens (`data_dir`, or
    `store_url` s3://bucket/prefix) and the services it calls (None: this process's own), the TLS
    certificate and key, the matching's strip peers, strip size and strips in flight, the
    instrument profiles file, the HTTP endpoint's host:port ('' none), the log level and the
    seconds in-flight calls get on SIGTERM. The defaults are those of a server made in a process
    (tests, in-process `fracto`); fracto-server's come from its flags and environment."""

    address: str = "[::]:0"
    services: tuple[str, ...] = SERVICE_NAMES
    max_message_mb: int = DEFAULT_MAX_MESSAGE_MB
    workers: int = 8
    build_workers: int | None = None
    build_queue: int = DEFAULT_BUILD_QUEUE
    max_request_mb: int | None = None
    data_dir: str | Path = DEFAULT_DATA_DIR
    store_url: str | None = None
    matching_address: str | None = None
    meshing_address: str | None = None
    tls_cert_path: str | None = None
    tls_key_path: str | None = None
    strip_peers: str | None = None
    strip_pixels: int = DEFAULT_STRIP_PIXELS
    strip_in_flight: int = 4
    instruments_path: str | None = None
    http_address: str = ""
    log_level: str = "INFO"
    grace_s: float = 30.0

    @classmethod
    def from_flags(cls, argv: list[str] | None = None) -> ServerConfig:
        """fracto-server's configuration from its command line and environment (build_parser)."""
        args = build_parser().parse_args(argv)
        return cls(
            address=args.address,
            services=tuple(name.strip() for name in args.services.split(",") if name.strip()),
            max_message_mb=args.max_message_mb,
            workers=args.workers,
            build_workers=args.build_workers,
            build_queue=args.build_queue,
            max_request_mb=args.max_request_mb,
            data_dir=args.data,
            store_url=args.store,
            matching_address=args.matching_address,
            meshing_address=args.meshing_address,
            tls_cert_path=args.tls_cert,
            tls_key_path=args.tls_key,
            strip_peers=args.strip_peers,
            strip_pixels=args.strip_pixels,
            strip_in_flight=args.strip_in_flight,
            instruments_path=args.instruments,
            http_address=args.http_address,
            log_level=args.log_level,
            grace_s=args.grace_s,
        )


def default_build_workers() -> int:
    """Half this process's CPUs (at least one): a build keeps about two busy."""
    return max(1, len(os.sched_getaffinity(0)) // 2)


def build_parser() -> argparse.ArgumentParser:
    """fracto-server's flags, each defaulting to its environment variable."""
    parser = argparse.ArgumentParser(prog="fracto-server", description="Serve Fractoscope's gRPC services.")
    parser.add_argument(
        "--address",
        default=os.environ.get("FRACTO_ADDRESS", "[::]:50051"),
        help="host:port the gRPC services listen on (FRACTO_ADDRESS; default %(default)s)",
    )
    parser.add_argument(
        "--services",
        default=os.environ.get("FRACTO_SERVICES", ",".join(SERVICE_NAMES)),
        help="comma-separated services to serve (FRACTO_SERVICES; default %(default)s)",
    )
    parser.add_argument(
        "--max-message-mb",
        type=int,
        default=int(os.environ.get("FRACTO_MAX_MESSAGE_MB", DEFAULT_MAX_MESSAGE_MB)),
        help="largest gRPC message either way, MB (FRACTO_MAX_MESSAGE_MB; default %(default)s)",
    )
    parser.add_argument(
        "--workers",
        type=int,
        default=int(os.environ.get("FRACTO_WORKERS", "8")),
        help="threads answering queries (FRACTO_WORKERS; default %(default)s)",
    )
    parser.add_argument(
        "--build-workers",
        type=int,
        default=int(os.environ.get("FRACTO_BUILD_WORKERS", default_build_workers())),
        help="builds, height maps and meshes run at once, and strips for peers (FRACTO_BUILD_WORKERS; default "
        "%(default)s: half the CPUs)",
    )
    parser.add_argument(
        "--build-queue",
        type=int,
        default=int(os.environ.get("FRACTO_BUILD_QUEUE", DEFAULT_BUILD_QUEUE)),
        help="of those, how many may wait; more get RESOURCE_EXHAUSTED (FRACTO_BUILD_QUEUE; default %(default)s)",
    )
    max_request_mb = os.environ.get("FRACTO_MAX_REQUEST_MB")
    parser.add_argument(
        "--max-request-mb",
        type=int,
        default=int(max_request_mb) if max_request_mb else None,
        help="estimated peak memory one request may take, MB (FRACTO_MAX_REQUEST_MB; default: 60%% of the server's "
        "memory over the build workers)",
    )
    parser.add_argument(
        "--log-level",
        default=os.environ.get("FRACTO_LOG_LEVEL", "INFO"),
        help="DEBUG, INFO, WARNING or ERROR (FRACTO_LOG_LEVEL; default %(default)s)",
    )
    parser.add_argument(
        "--data",
        default=os.environ.get("FRACTO_DATA_DIR", DEFAULT_DATA_DIR),
        help="specimen directory (FRACTO_DATA_DIR; default %(default)s)",
    )
    parser.add_argument(
        "--store",
        default=os.environ.get("FRACTO_STORE") or None,
        help="s3://BUCKET/PREFIX: specimens, jobs and leases in object storage, shared by tile replicas (endpoint "
        "and keys from AWS_ENDPOINT_URL, AWS_ACCESS_KEY_ID, AWS_SECRET_ACCESS_KEY, AWS_REGION; --data keeps "
        "scratch files); default: the folder --data",
    )
    parser.add_argument(
        "--matching-address",
        default=os.environ.get("FRACTO_MATCHING_ADDRESS") or None,
        help="matching service for the tile service, e.g. dns:///matching:50051 (default: this process's, in-process)",
    )
    parser.add_argument(
        "--meshing-address",
        default=os.environ.get("FRACTO_MESHING_ADDRESS") or None,
        help="meshing service for the tile service (default: this process's, in-process)",
    )
    parser.add_argument(
        "--strip-peers",
        default=os.environ.get("FRACTO_STRIP_PEERS") or None,
        help="matching replicas that match strips of large pairs in parallel, e.g. "
        "dns:///matching:50051 or ipv4:10.0.0.1:50051,10.0.0.2:50051 (default: match here)",
    )
    parser.add_argument(
        "--strip-pixels",
        type=int,
        default=int(os.environ.get("FRACTO_STRIP_PIXELS", DEFAULT_STRIP_PIXELS)),
        help="pixels per strip of dense matching (FRACTO_STRIP_PIXELS; default %(default)s)",
    )
    parser.add_argument(
        "--strip-in-flight",
        type=int,
        default=int(os.environ.get("FRACTO_STRIP_IN_FLIGHT", "4")),
        help="strips sent to the peers at a time, about the number of matching replicas (FRACTO_STRIP_IN_FLIGHT; "
        "default %(default)s)",
    )
    parser.add_argument(
        "--http-address",
        default=os.environ.get("FRACTO_HTTP_ADDRESS", "0.0.0.0:8080"),
        help="host:port of the HTTP endpoint (tilesets, JSON API, viewer); empty: none (FRACTO_HTTP_ADDRESS; "
        "default %(default)s)",
    )
    parser.add_argument(
        "--tls-cert",
        default=os.environ.get("FRACTO_TLS_CERT") or None,
        help="PEM certificate: serve TLS (FRACTO_TLS_CERT; default: none, plain gRPC)",
    )
    parser.add_argument(
        "--tls-key",
        default=os.environ.get("FRACTO_TLS_KEY") or None,
        help="PEM private key of --tls-cert (FRACTO_TLS_KEY; default: none)",
    )
    parser.add_argument(
        "--grace-s", type=float, default=30.0, help="seconds in-flight calls get on SIGTERM (default %(default)s)"
    )
    parser.add_argument(
        "--instruments",
        default=str(profiles_path()),
        help="instrument profiles applied to the images their metadata names (fracto instrument learn writes them; "
        f"default: {ENVIRONMENT_VARIABLE}, else the user's configuration folder: %(default)s)",
    )
    return parser
