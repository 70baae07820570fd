"""Errors to gRPC statuses on the server and back to ClientError at the caller, in one place."""

import grpc
import pytest

from fractoscope.errors import CancelledError, FractoscopeError, InvalidInputError, NotFoundError, UnavailableError
from fractoscope.rpc.status import ClientError, abort_on_error, abort_with_error, raised_as_client_errors


class _Aborted(Exception):
    """What grpc raises out of ServicerContext.abort_with_status."""


class _Context:
    def abort_with_status(self, status):
        self.status = status
        raise _Aborted


class _FailedCall(grpc.RpcError):
    """A call that ended with `status`, as a stub raises it."""

    def __init__(self, status):
        self._status = status

    def code(self):
        return self._status.code

    def details(self):
        return self._status.details

    def trailing_metadata(self):
        return self._status.trailing_metadata


def _status_of(error: Exception):
    context = _Context()
    with pytest.raises(_Aborted):
        abort_with_error(context, error)
    return context.status


@pytest.mark.parametrize(
    "error, code",
    [
        (InvalidInputError("images[1].tilt_deg", "missing"), grpc.StatusCode.INVALID_ARGUMENT),
        (NotFoundError("no specimen 'x'"), grpc.StatusCode.NOT_FOUND),
        (UnavailableError("matching is down"), grpc.StatusCode.UNAVAILABLE),
        (CancelledError("gone"), grpc.StatusCode.CANCELLED),
        (FractoscopeError("peers disagree"), grpc.StatusCode.FAILED_PRECONDITION),
        (KeyError("secret detail"), grpc.StatusCode.INTERNAL),
    ],
)
def test_each_error_becomes_its_status_and_comes_back_as_client_error(error, code):
    status = _status_of(error)
    assert status.code == code
    with pytest.raises(ClientError) as caught, raised_as_client_errors():
        raise _FailedCall(status)
    assert caught.value.code == code
    assert caught.value.field == (error.field if isinstance(error, InvalidInputError) else None)
    if code == grpc.StatusCode.INTERNAL:
        assert "secret detail" not in str(caught.value) and "KeyError" in str(caught.value)
    elif code != grpc.StatusCode.CANCELLED:
        assert str(caught.value) == str(error)


def test_the_decorator_covers_unary_and_streaming_methods():
    class Servicer:
        @abort_on_error
        def Unary(self, request, context):
            raise InvalidInputError("viewport_px", "must be 1 to 65536")

        @abort_on_error
        def Streaming(self, request, context):
            yield "first"
            raise NotFoundError("no tile")

    unary, streaming = _Context(), _Context()
    with pytest.raises(_Aborted):
        Servicer().Unary(None, unary)
    assert unary.status.code == grpc.StatusCode.INVALID_ARGUMENT
    events = Servicer().Streaming(None, streaming)
    assert next(events) == "first"
    with pytest.raises(_Aborted):
        next(events)
    assert streaming.status.code == grpc.StatusCode.NOT_FOUND


def test_a_request_id_longer_than_http_allows_is_refused_before_the_method_runs():
    """A 10 MB request id was accepted and logged as one line; gRPC now keeps HTTP's 128 characters."""
    from fractoscope.v1 import matching_pb2

    ran = []

    class Servicer:
        @abort_on_error
        def Unary(self, request, context):
            ran.append(request.request_id)

        @abort_on_error
        def Streaming(self, request, context):
            ran.append(request.request_id)
            yield "done"

    too_long = matching_pb2.ComputeHeightMapRequest(request_id="x" * 129)
    for call in (
        lambda context: Servicer().Unary(too_long, context),
        lambda context: list(Servicer().Streaming(too_long, context)),
    ):
        context = _Context()
        with pytest.raises(_Aborted):
            call(context)
        assert context.status.code == grpc.StatusCode.INVALID_ARGUMENT and "request_id" in context.status.details
    Servicer().Unary(matching_pb2.ComputeHeightMapRequest(request_id="x" * 128), _Context())
    assert ran == ["x" * 128]
