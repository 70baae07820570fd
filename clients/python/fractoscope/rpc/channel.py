"""Channels to Fractoscope servers, as the client and the services that call each other open them."""

from __future__ import annotations

import json
import os
from pathlib import Path

import grpc

from fractoscope.rpc.limits import DEFAULT_MAX_MESSAGE_MB, message_size_options

# The unary calls are idempotent (reads, and matching one strip), so those that fail with
# UNAVAILABLE (a replica restarting) are retried with backoff. Streaming calls are not: a retried
# stream whose server died mid-way can wait forever, and their callers retry whole requests
# (reconstructions per request id). Several resolved addresses (a `dns:///` name of replicas) are
# used round-robin.
_RETRIED_METHODS = ("GetSpecimen", "ListSpecimens", "GetTileset", "GetTile", "Zoom", "GetProfile", "GetRoughness")
_SERVICE_CONFIG = json.dumps(
    {
        "loadBalancingConfig": [{"round_robin": {}}],
        "methodConfig": [
            {
                "name": [{"service": "fractoscope.v1.TileService", "method": method} for method in _RETRIED_METHODS]
                + [{"service": "fractoscope.v1.MatchingService", "method": "MatchStrip"}],
                # gRPC's most attempts, 0-0.4 s, 0-0.8 s, 0-1 s and 0-1 s apart (1.6 s in all on average,
                # 3.2 s at most, so that a misconfigured server is still UNAVAILABLE, not a 5 s deadline):
                # they outlast the reconnection's backoff below but for 0.2 % of draws (the old 0.2 s start
                # and four attempts, 0.7 s on average, often ended before a restarted server was tried again).
                "retryPolicy": {
                    "maxAttempts": 5,
                    "initialBackoff": "0.4s",
                    "maxBackoff": "1s",
                    "backoffMultiplier": 2,
                    "retryableStatusCodes": ["UNAVAILABLE"],
                },
            }
        ],
    }
)
# A channel whose server went away tries to reconnect with exponential backoff, by default up to
# two minutes apart, and fails calls at once meanwhile: a replica restarted after a crash would be
# found again only that late. Every 0.3 s at most instead (±20 % jitter), well within the retries.
_RECONNECT_OPTIONS = [("grpc.initial_reconnect_backoff_ms", 200), ("grpc.max_reconnect_backoff_ms", 300)]


def open_channel(
    address: str,
    *,
    max_message_mb: int = DEFAULT_MAX_MESSAGE_MB,
    token: str | None = None,
    tls_ca_path: str | None = None,
) -> grpc.Channel:
    """A channel to `address` (a gRPC target; several replicas are balanced round-robin) that
    retries idempotent calls. `token` (default FRACTO_TOKEN) is sent as a bearer token;
    `tls_ca_path` (default FRACTO_TLS_CA) switches to TLS, trusting that PEM certificate authority."""
    options = message_size_options(max_message_mb) + [
        ("grpc.service_config", _SERVICE_CONFIG),
        ("grpc.enable_retries", 1),
    ]
    options += _RECONNECT_OPTIONS
    tls_ca_path = tls_ca_path or os.environ.get("FRACTO_TLS_CA") or None
    if tls_ca_path:
        credentials = grpc.ssl_channel_credentials(root_certificates=Path(tls_ca_path).read_bytes())
        channel = grpc.secure_channel(address, credentials, options=options)
    else:
        channel = grpc.insecure_channel(address, options=options)
    token = token or os.environ.get("FRACTO_TOKEN") or None
    return grpc.intercept_channel(channel, _BearerToken(token)) if token else channel


class ChannelOwner:
    """Something that calls over its own channel (`self._channel`): closed by close() or at the
    end of a with block."""

    _channel: grpc.Channel

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def close(self) -> None:
        self._channel.close()


class _BearerToken(grpc.UnaryUnaryClientInterceptor, grpc.UnaryStreamClientInterceptor):
    """Adds `authorization: Bearer TOKEN` to every call."""

    def __init__(self, token: str):
        self._metadata = ("authorization", f"Bearer {token}")

    def _with_token(self, details):
        # grpc passes its call details as a namedtuple.
        return details._replace(metadata=list(details.metadata or []) + [self._metadata])

    def intercept_unary_unary(self, continuation, details, request):
        return continuation(self._with_token(details), request)

    def intercept_unary_stream(self, continuation, details, request):
        return continuation(self._with_token(details), request)
