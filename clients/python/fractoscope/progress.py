"""Progress reports of long computations: `progress(fraction, message)`, fraction 0 to 1; and
their stopping when the caller has gone: the work runs `stoppable(stopped)`, and long loops call
`checkpoint()` between steps, which raises CancelledError once `stopped()` is true. Work handed
to other threads takes the scope along (`carried`)."""

from __future__ import annotations

import contextlib
import contextvars
import functools
from collections.abc import Callable, Iterator

from fractoscope.errors import CancelledError

ProgressCallback = Callable[[float, str], None]
_STOPPED: contextvars.ContextVar[Callable[[], bool] | None] = contextvars.ContextVar(
    "fractoscope_stopped", default=None
)


def silent(fraction: float, message: str) -> None:
    """The progress callback of a caller that does not listen."""


def checkpoint() -> None:
    """Raises CancelledError when the caller of the work under way has gone (see `stoppable`);
    costs a context lookup otherwise."""
    stopped = _STOPPED.get()
    if stopped is not None and stopped():
        raise CancelledError("the caller went away")


@contextlib.contextmanager
def stoppable(stopped: Callable[[], bool] | None) -> Iterator[None]:
    """The block's `checkpoint()`s (those of threads it hands work to by `carried` too) raise
    CancelledError once `stopped()` is true; None: never."""
    token = _STOPPED.set(stopped)
    try:
        yield
    finally:
        _STOPPED.reset(token)


def carried(function: Callable) -> Callable:
    """`function` to be run once on another thread within this one's `stoppable` scope (in a copy
    of the current context, made now: a context is never entered by two threads at once)."""
    return functools.partial(contextvars.copy_context().run, function)
