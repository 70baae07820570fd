"""The one place where Fractoscope exceptions become gRPC statuses."""

from __future__ import annotations

import logging

import grpc
from google.protobuf import any_pb2
from google.rpc import code_pb2, error_details_pb2, status_pb2
from grpc_status import rpc_status

from fractoscope.errors import CancelledError, FractoscopeError, InvalidInputError, NotFoundError, UnavailableError

_log = logging.getLogger("fractoscope.services")


def abort_with_error(context: grpc.ServicerContext, error: Exception) -> None:
    """Ends the call with a status naming the problem; unexpected errors are logged, not leaked."""
    if isinstance(error, InvalidInputError):
        violation = error_details_pb2.BadRequest.FieldViolation(field=error.field, description=error.message)
        detail = any_pb2.Any()
        detail.Pack(error_details_pb2.BadRequest(field_violations=[violation]))
        status = status_pb2.Status(code=code_pb2.INVALID_ARGUMENT, message=str(error), details=[detail])
    elif isinstance(error, NotFoundError):
        status = status_pb2.Status(code=code_pb2.NOT_FOUND, message=str(error))
    elif isinstance(error, UnavailableError):
        status = status_pb2.Status(code=code_pb2.UNAVAILABLE, message=str(error))
    elif isinstance(error, CancelledError):
        status = status_pb2.Status(code=code_pb2.CANCELLED, message="cancelled by the client")
    elif isinstance(error, FractoscopeError):
        status = status_pb2.Status(code=code_pb2.FAILED_PRECONDITION, message=str(error))
    else:
        _log.exception("internal error")
        status = status_pb2.Status(code=code_pb2.INTERNAL, message=f"internal error ({type(error).__name__})")
    context.abort_with_status(rpc_status.to_status(status))
