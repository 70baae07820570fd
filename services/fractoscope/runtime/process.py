"""Settings of a serving process: JSON logs without credentials, the garbage collector, and
malloc's handling of freed memory (fracto-server, `make run` and in-process `fracto` commands)."""

from __future__ import annotations

import ctypes
import gc
import json
import logging
import re
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
    handler.addFilter(CREDENTIAL_FILTER)  # whatever logger a record comes from
    logging.basicConfig(level=level.upper(), handlers=[handler], force=True)


# Credentials in a log line: a header's value to the end of its line, a bearer token, a query's token.
_CREDENTIALS = re.compile(r"(?i)(authorization[ \t]*[:=][ \t]*)[^\r\n]*|(bearer[ \t]+)\S+|([?&;]token=)[^&\s]*")
# gRPC's report of a metadata value that is not UTF-8 (grpc._cython.cygrpc._decode): it quotes the
# value whole, an Authorization header's too, with or without "Bearer".
_UNDECODABLE_METADATA = "Invalid encoding on "
# The loggers of gRPC Python that log what a client sent (filters act on the logger a record is
# made on, not on its parents).
GRPC_LOGGERS = ("grpc._cython.cygrpc", "grpc._server", "grpc._common", "grpc._channel")


def redacted(text: str) -> str:
    """`text` with every credential _CREDENTIALS finds replaced by "[redacted]"."""
    return _CREDENTIALS.sub(lambda found: (found[1] or found[2] or found[3]) + "[redacted]", text)


class CredentialFilter(logging.Filter):
    """Records without credentials: their message and traceback redacted (the traceback formatted
    now, in place of the exception a handler would format), and gRPC's report of an undecodable
    metadata value, which may be a token, without the value or its traceback (a warning)."""

    def filter(self, record: logging.LogRecord) -> bool:
        message = record.getMessage()
        if message.startswith(_UNDECODABLE_METADATA):
            message = "a call's metadata held a value that is not UTF-8 (not logged: it may be a credential)"
            record.levelno, record.levelname, record.exc_info, record.exc_text = logging.WARNING, "WARNING", None, None
        record.msg, record.args = redacted(message), None
        if record.exc_info:
            record.exc_text = redacted(logging.Formatter().formatException(record.exc_info))
            record.exc_info = None
        return True


CREDENTIAL_FILTER = CredentialFilter()


def filter_grpc_logs() -> None:
    """Puts CREDENTIAL_FILTER on gRPC's own loggers (once: a filter is not added twice), for
    servers whose process logs through handlers of its own."""
    for name in GRPC_LOGGERS:
        logging.getLogger(name).addFilter(CREDENTIAL_FILTER)


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
