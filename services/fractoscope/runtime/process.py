"""Settings of a serving process: JSON logs, the garbage collector, and malloc's handling of freed
memory (fracto-server, `make run` and in-process `fracto` commands)."""

from __future__ import annotations

import ctypes
import gc
import json
import logging
import sys
import time


class JsonFormatter(logging.Formatter):
    """One JSON object per line with a `severity` field, for log collectors."""

    def format(self, record: logging.LogRecord) -> str:
        entry = {
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.gmtime(record.created)) + f".{int(record.msecs):03d}Z",
            "severity": record.levelname,
            "logger": record.name,
            "message": record.getMessage(),
        }
        for key in ("request_id", "report"):
            if hasattr(record, key):
                entry[key] = getattr(record, key)
        if record.exc_info:
            entry["exception"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def configure_logging(level: str) -> None:
    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(JsonFormatter())
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)


def settle_garbage_collector() -> None:
    """Readies a serving process's garbage collector: what start-up built is collected and frozen
    out of later collections, and the youngest generation is collected every 50,000 allocations
    instead of 700. Every gRPC call allocates many short-lived objects; with Python's defaults the
    collector costs tile fetches about a third of their rate (GetTile at concurrency 50, 15 s runs
    on one CPU: 2,900-3,000/s at p99 28-35 ms with the defaults, 4,200-4,650/s at p99 20-22 ms with
    these settings). Garbage cycles wait at most one such period, a few MB."""
    gc.collect()
    gc.freeze()
    gc.set_threshold(50_000, 20, 10)


def keep_freed_memory() -> None:
    """Lets glibc's malloc keep freed memory for reuse instead of handing it back to the kernel:
    blocks up to 32 MB come from the heap rather than fresh mappings, and the heap is not trimmed.
    Dense matching allocates and frees hundreds of image-sized temporaries per strip; with the
    defaults many are fresh mappings whose pages the kernel faults in and zeroes again (a 512²
    pair: 8,800 page faults per match, 23 with this), which took a quarter of the matching time
    (1024² pair: 0.14 s, 0.12 s with this; system time 0.09 s, 0.02 s). Resident memory then
    stays near its peak. Two arenas at most (glibc's default is eight per CPU): each arena keeps its
    own freed memory, and the default matcher's two directions run on threads of their own, new
    for every strip, so with the default a 1024² pair in 300,000-pixel strips peaked 442 MiB above
    the server's start, 247 MiB with two arenas. Does nothing where the C library is not glibc."""
    try:
        libc = ctypes.CDLL("libc.so.6")
    except OSError:
        return
    m_trim_threshold, m_mmap_threshold, m_arena_max = -1, -3, -8  # mallopt's parameter numbers, from malloc.h
    libc.mallopt(m_mmap_threshold, 32 * 2**20)  # glibc's largest allowed value on 64-bit
    libc.mallopt(m_trim_threshold, 2**30)
    libc.mallopt(m_arena_max, 2)
