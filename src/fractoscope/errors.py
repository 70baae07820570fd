"""The one exception hierarchy of Fractoscope; services map it to gRPC status codes in one place."""


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


class UnauthenticatedError(FractoscopeError):
    """Credentials are missing or refused: the caller's, or this server's toward a service it calls."""
