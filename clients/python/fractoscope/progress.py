"""Progress reports of long computations: `progress(fraction, message)`, fraction 0 to 1."""

from __future__ import annotations

from collections.abc import Callable

ProgressCallback = Callable[[float, str], None]


def silent(fraction: float, message: str) -> None:
    """The progress callback of a caller that does not listen."""
