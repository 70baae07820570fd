"""The one exception hierarchy of Fractoscope, and the one table (`OUTCOMES`) of what each failure
becomes for a gRPC caller, an HTTP caller and the command line."""

from __future__ import annotations

from dataclasses import dataclass


class FractoscopeError(Exception):
    """Root of every error Fractoscope raises on purpose."""


class InvalidInputError(FractoscopeError, ValueError):
    """A request or file is unusable; `field` names the offending input (e.g. ``images[1].tilt_deg``)."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message


class NotFoundError(FractoscopeError, LookupError):
    """A named resource (specimen, ROI, tile) does not exist; `field` names the request input that
    named it (e.g. ``specimen_id``), when known."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


class AlreadyExistsError(FractoscopeError):
    """What a request would create exists already, made from other content (a request id reused
    for a different build); `field` names the request input at fault (e.g. ``request_id``)."""

    def __init__(self, message: str, field: str | None = None):
        super().__init__(message)
        self.field = field


class CancelledError(FractoscopeError):
    """The caller went away; long computations stop at their next progress report."""


class UnavailableError(FractoscopeError):
    """A service this one depends on cannot be reached; the request can be retried later."""


class ResourceExhaustedError(FractoscopeError):
    """The server cannot take this on now (full work queue, memory budget, disk); `retry_after_s`
    hints when a retry may succeed (None: not without changing the request or the server)."""

    def __init__(self, message: str, *, retry_after_s: float | None = None):
        super().__init__(message)
        self.retry_after_s = retry_after_s


class TooLargeError(ResourceExhaustedError):
    """A request larger than this server ever takes (its estimated memory, a file it would write):
    a retry unchanged cannot succeed, so it carries no retry hint (HTTP 413)."""

    def __init__(self, message: str):
        super().__init__(message, retry_after_s=None)


class UnauthenticatedError(FractoscopeError):
    """Credentials are missing or refused: the caller's, or this server's toward a service it calls."""


@dataclass(frozen=True)
class Outcome:
    """How one kind of failure reaches each kind of caller: a gRPC status code (its name, as in
    grpc.StatusCode and google.rpc.Code), an HTTP status and an exit code of the `fracto` command."""

    grpc_code: str
    http_status: int
    exit_code: int


# The one table from failures to what callers see; gRPC (rpc.status), the HTTP API (http.api)
# and the command line (cli.main) all read it. Codes a server never sends on purpose (INTERNAL,
# UNKNOWN) and those only the transport gives (DEADLINE_EXCEEDED) have rows too, for the callers
# that pass a status on. Rows go by their gRPC code, but for TOO_LARGE: RESOURCE_EXHAUSTED that
# no retry mends, which HTTP tells apart (413, not 429).
OUTCOMES = {"TOO_LARGE": Outcome("RESOURCE_EXHAUSTED", 413, 3)} | {
    outcome.grpc_code: outcome
    for outcome in (
        Outcome("INVALID_ARGUMENT", 400, 2),
        Outcome("FAILED_PRECONDITION", 400, 2),
        Outcome("NOT_FOUND", 404, 4),
        Outcome("ALREADY_EXISTS", 409, 2),
        Outcome("UNAUTHENTICATED", 401, 5),
        Outcome("PERMISSION_DENIED", 403, 5),
        Outcome("RESOURCE_EXHAUSTED", 429, 3),
        Outcome("UNAVAILABLE", 503, 3),
        Outcome("DEADLINE_EXCEEDED", 504, 3),
        Outcome("CANCELLED", 499, 130),
        Outcome("INTERNAL", 500, 1),
        Outcome("UNKNOWN", 500, 1),
    )
}
# Each error class's status code; a subclass takes its nearest listed base's.
_ERROR_CODES: tuple[tuple[type[Exception], str], ...] = (
    (InvalidInputError, "INVALID_ARGUMENT"),
    (NotFoundError, "NOT_FOUND"),
    (AlreadyExistsError, "ALREADY_EXISTS"),
    (UnauthenticatedError, "UNAUTHENTICATED"),
    (TooLargeError, "TOO_LARGE"),
    (ResourceExhaustedError, "RESOURCE_EXHAUSTED"),
    (UnavailableError, "UNAVAILABLE"),
    (CancelledError, "CANCELLED"),
    (FractoscopeError, "FAILED_PRECONDITION"),
)


def outcome_of(error: BaseException) -> Outcome:
    """The table's row for an exception: its class's code, INTERNAL for anything not raised on purpose."""
    code = next((name for kind, name in _ERROR_CODES if isinstance(error, kind)), "INTERNAL")
    return OUTCOMES[code]


def outcome_of_code(grpc_code_name: str) -> Outcome:
    """The table's row for a status code received (by name); UNKNOWN's for a code it lacks."""
    return OUTCOMES.get(grpc_code_name, OUTCOMES["UNKNOWN"])


# Received codes that have no error class of their own, and the class that stands for them.
_RECEIVED_AS = {"DEADLINE_EXCEEDED": "UNAVAILABLE", "PERMISSION_DENIED": "UNAUTHENTICATED"}


def error_of_code(
    grpc_code_name: str, message: str, *, field: str | None = None, retry_after_s: float | None = None
) -> FractoscopeError:
    """The table read backwards: the error a status received from another service stands for
    (InvalidInputError whenever a field is named; FractoscopeError for codes without a class)."""
    if field:
        return InvalidInputError(field, message)
    code = _RECEIVED_AS.get(grpc_code_name, grpc_code_name)
    kind = next((kind for kind, name in _ERROR_CODES if name == code), FractoscopeError)
    if kind is NotFoundError:
        return NotFoundError(message)
    if kind is ResourceExhaustedError:
        return ResourceExhaustedError(message, retry_after_s=retry_after_s)
    return kind(message)
