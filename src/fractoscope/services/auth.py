"""Bearer-token authentication for the gRPC services and the HTTP endpoint (off when no tokens).

Tokens come from FRACTO_TOKENS: comma-separated `client:token:access` entries, access `write`
(everything) or `read` (queries and tiles only, for viewers). Clients send `authorization:
Bearer TOKEN` (gRPC metadata or HTTP header; HTTP also accepts `?token=` for viewers that load
tilesets by URL). Health checking and reflection stay open for probes.
"""

from __future__ import annotations

import hmac
import os
from dataclasses import dataclass

import grpc

WRITE, READ = "write", "read"
# Calls that compute or store; a read token may call everything else.
_WRITING_METHODS = {
    "/fractoscope.v1.MatchingService/ComputeHeightMap",
    "/fractoscope.v1.MeshingService/BuildMesh",
    "/fractoscope.v1.TileService/ReconstructSpecimen",
}
_OPEN_PREFIXES = ("/grpc.health.v1.Health/", "/grpc.reflection.")


@dataclass(frozen=True)
class Grant:
    client: str
    access: str


class TokenTable:
    """Known tokens and what each may do; empty means authentication is off."""

    def __init__(self, entries: dict[str, Grant]):
        self._entries = entries

    @classmethod
    def from_text(cls, text: str) -> TokenTable:
        """`client:token:access,...`; ValueError names a malformed entry."""
        entries = {}
        for item in filter(None, (part.strip() for part in text.split(","))):
            parts = item.split(":")
            if len(parts) != 3 or not parts[1] or parts[2] not in (WRITE, READ):
                raise ValueError(f"FRACTO_TOKENS entry {parts[0]!r} must be client:token:write|read")
            entries[parts[1]] = Grant(parts[0], parts[2])
        return cls(entries)

    @classmethod
    def from_environment(cls) -> TokenTable:
        return cls.from_text(os.environ.get("FRACTO_TOKENS", ""))

    @property
    def enabled(self) -> bool:
        return bool(self._entries)

    def grant(self, authorization: str | None) -> Grant | None:
        """The grant of an `authorization` value (`Bearer TOKEN`), None when unknown."""
        if not authorization or not authorization.startswith("Bearer "):
            return None
        offered = authorization[len("Bearer "):].strip()
        for token, grant in self._entries.items():
            if hmac.compare_digest(token, offered):
                return grant
        return None


class AuthInterceptor(grpc.ServerInterceptor):
    """Rejects calls without a known token (UNAUTHENTICATED) and writing calls with a read-only
    token (PERMISSION_DENIED)."""

    def __init__(self, tokens: TokenTable):
        self._tokens = tokens

    def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method
        if method.startswith(_OPEN_PREFIXES):
            return continuation(handler_call_details)
        metadata = dict(handler_call_details.invocation_metadata or ())
        grant = self._tokens.grant(metadata.get("authorization"))
        if grant is None:
            return _refusal(continuation(handler_call_details), grpc.StatusCode.UNAUTHENTICATED, "a valid bearer token is required")
        if grant.access != WRITE and method in _WRITING_METHODS:
            return _refusal(continuation(handler_call_details), grpc.StatusCode.PERMISSION_DENIED, f"client {grant.client!r} may only read")
        return continuation(handler_call_details)


def _refusal(handler, code: grpc.StatusCode, message: str):
    """A handler of the same streaming shape that aborts with `code`."""
    def abort(request, context):
        context.abort(code, message)

    def abort_stream(request, context):
        context.abort(code, message)
        yield  # pragma: no cover - makes this a generator for server-streaming methods

    if handler is None:
        return None
    if handler.response_streaming:
        return grpc.unary_stream_rpc_method_handler(abort_stream, request_deserializer=handler.request_deserializer,
                                                    response_serializer=handler.response_serializer)
    return grpc.unary_unary_rpc_method_handler(abort, request_deserializer=handler.request_deserializer,
                                               response_serializer=handler.response_serializer)
