"""Requests whose bytes do not parse as their message: INVALID_ARGUMENT naming `request`, where
gRPC Python would answer INTERNAL ("Exception deserializing request!") as if the server failed."""

from __future__ import annotations

import grpc

from fractoscope.errors import InvalidInputError
from fractoscope.rpc.status import abort_with_error


class _Undecodable:
    """What a request's deserializer returns for bytes that are not its message."""

    def __init__(self, reason: str):
        self.reason = reason


class MalformedRequests(grpc.ServerInterceptor):
    """Lets every unary request's deserializer fail softly, and the method then refuse the call as
    the client's error. (All Fractoscope methods take one request message.)"""

    def __init__(self):
        self._wrapped: dict[str, grpc.RpcMethodHandler] = {}

    def intercept_service(self, continuation, handler_call_details):
        method = handler_call_details.method
        wrapped = self._wrapped.get(method)
        if wrapped is None:
            handler = continuation(handler_call_details)
            if handler is None or handler.request_streaming or handler.request_deserializer is None:
                return handler
            wrapped = self._wrapped[method] = _tolerant(handler, method)
        return wrapped


def _tolerant(handler: grpc.RpcMethodHandler, method: str) -> grpc.RpcMethodHandler:
    """`handler` with a deserializer that cannot raise and a behavior that refuses what it could not decode."""
    name = "unary_stream" if handler.response_streaming else "unary_unary"
    deserialize, behavior = handler.request_deserializer, getattr(handler, name)

    def tolerant_deserializer(data: bytes):
        try:
            return deserialize(data)
        except Exception as error:  # protobuf's DecodeError, or whatever a custom parser raises
            return _Undecodable(str(error) or type(error).__name__)

    def refuse_undecodable(request, context) -> None:
        if isinstance(request, _Undecodable):
            abort_with_error(
                context, InvalidInputError("request", f"is not a valid {method} request ({request.reason})")
            )

    def unary(request, context):
        refuse_undecodable(request, context)
        return behavior(request, context)

    def streaming(request, context):
        refuse_undecodable(request, context)
        yield from behavior(request, context)

    return handler._replace(
        request_deserializer=tolerant_deserializer, **{name: streaming if handler.response_streaming else unary}
    )
