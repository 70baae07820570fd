"""Fractoscope exceptions as gRPC statuses (servers, by the table errors.OUTCOMES) and statuses as
ClientError again (callers: the client, and services calling each other)."""

from __future__ import annotations

import contextlib
import errno
import functools
import inspect
import logging
from collections.abc import Iterator

import grpc
from google.protobuf import any_pb2, duration_pb2
from google.rpc import code_pb2, error_details_pb2, status_pb2
from grpc_status import rpc_status

from fractoscope.errors import CancelledError, InvalidInputError, ResourceExhaustedError, outcome_of
from fractoscope.rpc.limits import MAX_REQUEST_ID_CHARS

_log = logging.getLogger("fractoscope.server")


# A full disk or quota: the data volume, not the request, is at fault.
_DISK_FULL = (errno.ENOSPC, errno.EDQUOT)


class ClientError(Exception):
    """A call failed; `code` is the gRPC status code, `field` the offending request field if any,
    `retry_after_s` the server's hint (google.rpc.RetryInfo) for RESOURCE_EXHAUSTED, s."""

    def __init__(
        self, code: grpc.StatusCode, message: str, field: str | None = None, retry_after_s: float | None = None
    ):
        super().__init__(message)
        self.code = code
        self.field = field
        self.retry_after_s = retry_after_s


def abort_with_error(context: grpc.ServicerContext, error: Exception) -> None:
    """Ends the call with the status errors.OUTCOMES gives the error, naming the problem (a
    BadRequest detail names an invalid field, a RetryInfo detail the delay to wait); unexpected
    errors are logged, not leaked."""
    if isinstance(error, OSError) and error.errno in _DISK_FULL:
        error = ResourceExhaustedError(f"the server's disk is full ({error.strerror})")
    code = code_pb2.Code.Value(outcome_of(error).grpc_code)
    if code == code_pb2.INTERNAL:
        _log.exception("internal error")
        status = status_pb2.Status(code=code, message=f"internal error ({type(error).__name__})")
    elif isinstance(error, CancelledError):
        status = status_pb2.Status(code=code, message="cancelled by the client")
    else:
        status = status_pb2.Status(code=code, message=str(error))
    if isinstance(error, InvalidInputError):
        violation = error_details_pb2.BadRequest.FieldViolation(field=error.field, description=error.message)
        status.details.append(_packed(error_details_pb2.BadRequest(field_violations=[violation])))
    if isinstance(error, ResourceExhaustedError) and error.retry_after_s is not None:
        delay = duration_pb2.Duration()
        delay.FromMilliseconds(round(error.retry_after_s * 1000))
        status.details.append(_packed(error_details_pb2.RetryInfo(retry_delay=delay)))
    status.message = _bounded(status.message)
    for detail in status.details:
        if detail.Is(error_details_pb2.BadRequest.DESCRIPTOR):
            bad_request = error_details_pb2.BadRequest()
            detail.Unpack(bad_request)
            for violation in bad_request.field_violations:
                violation.description = _bounded(violation.description)
            detail.Pack(bad_request)
    context.abort_with_status(rpc_status.to_status(status))


# gRPC carries the status in headers of at most 8 KiB in all: a message that echoes a client's
# 20,000-character id would break the status itself (RESOURCE_EXHAUSTED: metadata too large).
_MAX_MESSAGE_CHARS = 1000


def _check_request_id(request) -> None:
    request_id = getattr(request, "request_id", "")
    if len(request_id) > MAX_REQUEST_ID_CHARS:
        raise InvalidInputError(
            "request_id", f"must be at most {MAX_REQUEST_ID_CHARS} characters, got {len(request_id)}"
        )


def _bounded(message: str) -> str:
    return message if len(message) <= _MAX_MESSAGE_CHARS else message[: _MAX_MESSAGE_CHARS - 1] + "…"


def _packed(detail) -> any_pb2.Any:
    packed = any_pb2.Any()
    packed.Pack(detail)
    return packed


def abort_on_error(method):
    """Decorates a servicer method (unary or server-streaming): every exception it raises ends
    the call through `abort_with_error`, and a request id over MAX_REQUEST_ID_CHARS is refused
    before it runs."""
    if inspect.isgeneratorfunction(method):

        @functools.wraps(method)
        def streaming(self, request, context):
            try:
                _check_request_id(request)
                yield from method(self, request, context)
            except Exception as error:
                abort_with_error(context, error)

        return streaming

    @functools.wraps(method)
    def unary(self, request, context):
        try:
            _check_request_id(request)
            return method(self, request, context)
        except Exception as error:
            abort_with_error(context, error)

    return unary


@contextlib.contextmanager
def raised_as_client_errors() -> Iterator[None]:
    """Turns a failed call's grpc.RpcError into ClientError, with the field a BadRequest detail
    names and the delay a RetryInfo detail gives."""
    try:
        yield
    except grpc.RpcError as error:
        status = rpc_status.from_call(error)
        field = retry_after_s = None
        for detail in status.details if status is not None else ():
            if detail.Is(error_details_pb2.BadRequest.DESCRIPTOR):
                bad_request = error_details_pb2.BadRequest()
                detail.Unpack(bad_request)
                field = bad_request.field_violations[0].field if bad_request.field_violations else None
            elif detail.Is(error_details_pb2.RetryInfo.DESCRIPTOR):
                retry = error_details_pb2.RetryInfo()
                detail.Unpack(retry)
                retry_after_s = retry.retry_delay.ToMilliseconds() / 1000
        raise ClientError(error.code(), error.details() or str(error.code()), field, retry_after_s) from None
