"""What every verb shares: the connection (a server, or the services in-process), progress bars,
usage errors and exit codes."""

from __future__ import annotations

import argparse
import contextlib
import os
from collections.abc import Iterator
from pathlib import Path

import grpc
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from fractoscope.client import FractoscopeClient

EXIT_FAILURE, EXIT_BAD_INPUT, EXIT_UNAVAILABLE, EXIT_NOT_FOUND = 1, 2, 3, 4
EXIT_CODES = {
    grpc.StatusCode.INVALID_ARGUMENT: EXIT_BAD_INPUT,
    grpc.StatusCode.FAILED_PRECONDITION: EXIT_BAD_INPUT,
    grpc.StatusCode.UNAVAILABLE: EXIT_UNAVAILABLE,
    grpc.StatusCode.DEADLINE_EXCEEDED: EXIT_UNAVAILABLE,
    grpc.StatusCode.NOT_FOUND: EXIT_NOT_FOUND,
}
err = Console(stderr=True)
SERVER_HELP = "HOST:PORT of a Fractoscope server (default: FRACTO_SERVER, else in-process)"


class UsageError(Exception):
    """A problem with the command line itself (missing file, bad value)."""


def server_address(explicit: str | None) -> str | None:
    """The server to use: the explicit one, else FRACTO_SERVER, else None (run in-process)."""
    return explicit or os.environ.get("FRACTO_SERVER") or None


@contextlib.contextmanager
def connected(server: str | None, data_dir: str = "./data") -> Iterator[FractoscopeClient]:
    """A client to `server`, FRACTO_SERVER, or services started in-process for this command (with
    specimens kept in `data_dir`)."""
    address = server_address(server)
    if address:
        with FractoscopeClient(address) as client:
            yield client
        return
    from fractoscope.services.runtime import keep_freed_memory
    from fractoscope.services.server import embedded_server

    keep_freed_memory()  # as fracto-server does: the services run in this process
    with embedded_server(data_dir) as local, FractoscopeClient(local) as client:
        yield client


@contextlib.contextmanager
def progress_bar(description: str, enabled: bool):
    """A progress bar on stderr; yields the callback that advances it."""
    if not enabled:
        yield lambda fraction, message: None
        return
    columns = (TextColumn("{task.description}"), BarColumn(), TextColumn("{task.percentage:>3.0f}%"), TimeElapsedColumn())
    with Progress(*columns, console=err, transient=True) as bar:
        task = bar.add_task(description, total=1.0)
        yield lambda fraction, message: bar.update(task, completed=fraction, description=f"{description}: {message}")


def existing_file(text: str) -> Path:
    path = Path(text)
    if not path.is_file():
        raise UsageError(f"cannot read {text}: no such file")
    return path


def region_argument(text: str) -> tuple[float, float, float, float]:
    """X0,Y0,X1,Y1 in µm, for argparse."""
    try:
        x0, y0, x1, y1 = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected X0,Y0,X1,Y1 in µm, got {text!r}") from None
    return x0, y0, x1, y1
