"""Running long work in a worker thread while a server-streaming call reports its progress."""

from __future__ import annotations

import queue
import threading
from collections.abc import Callable, Iterator
from typing import Any

import grpc

from fractoscope.errors import CancelledError
from fractoscope.v1 import common_pb2

_DONE = object()


def stream_progress(
    context: grpc.ServicerContext, work: Callable[[Callable[[float, str], None]], Any]
) -> Iterator[common_pb2.Progress | Any]:
    """Runs `work(progress)` in a thread; yields a Progress message for each report and finally
    the work's result. Raises what the work raised. When the client goes away, the next progress
    report inside the work raises CancelledError, so the thread stops early."""
    events: queue.Queue = queue.Queue()
    cancelled = threading.Event()
    context.add_callback(cancelled.set)
    outcome: dict[str, Any] = {}

    def progress(fraction: float, message: str) -> None:
        if cancelled.is_set():
            raise CancelledError("the client cancelled the call")
        stage = message.split(" ", 1)[0]
        events.put(common_pb2.Progress(stage=stage, fraction=float(fraction), message=message))

    def run() -> None:
        try:
            outcome["result"] = work(progress)
        except BaseException as error:  # handed to the calling thread, which re-raises it
            outcome["error"] = error
        finally:
            events.put(_DONE)

    threading.Thread(target=run, name="fractoscope-work", daemon=True).start()
    while (event := events.get()) is not _DONE:
        yield event
    if "error" in outcome:
        raise outcome["error"]
    yield outcome["result"]
