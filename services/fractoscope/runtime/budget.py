"""The admission budget (`Budget`): memory, CPU and scratch disk, shared by every front end of a
serving process. Each request's peak memory is estimated from its pixel counts before any work,
and refused (RESOURCE_EXHAUSTED naming the size) when it exceeds FRACTO_MAX_REQUEST_MB or what
the requests under way leave.

The factors are measured peaks with headroom: a fracto-server process's VmHWM during its first
call above its VmRSS before (glibc keeping freed memory, as it serves), which
tests/services/test_budget.py checks. A height map by the default method (TGV_ZNCC: the request
read, decoding, alignment, dense matching with its two directions on threads of their own, the
response serialized; malloc held to two arenas) took 160 MiB for a 512² pair, 406 MiB for 1,024²
in one strip and 251 MiB in 300,000-pixel strips, 1,478 MiB for 2,048² in one strip, 1,039 MiB
in 2,000,000-pixel strips (1,136 MiB on CI's machine) and 549 MiB in 500,000-pixel strips, and
1,676 MiB for 4,096² (estimates: 310, 640, 407, 1,960, 1,454, 773 and 2,492 MiB). WINDOW_ZNCC
took 222 MiB for 1,024² in 300,000-pixel strips, and in-process 1,215 MB for 4,096² and
2,098 MB for a 4,096² three-view series. Meshing took about 30 MB plus 51-60 B per height-map
pixel (1,024² to 2,048², every level).
"""

from __future__ import annotations

import contextlib
import os
import shutil
import threading
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from typing import NamedTuple

from fractoscope import progress
from fractoscope.errors import CancelledError, ResourceExhaustedError, TooLargeError
from fractoscope.stereo import alignment, matching
from fractoscope.stereo.pipeline import DEFAULT_TILT_AXIS_DEG

MB = 1024 * 1024
# Per call, whatever its size: a first call's numba compilation, lazily built OpenCV and SIFT
# buffers, thread stacks, the messages (measured about 96 MB).
BASE_BYTES = 200 * MB
# Full-image arrays per pixel and matched view (measured 50-75 B).
HEIGHT_MAP_BYTES_PER_PIXEL = 80
# Per pixel of the largest strip, its two directions matched at once (measured 260-310 B).
STRIP_BYTES_PER_PIXEL = 360
# Per height-map pixel, every level of detail (measured 51-60 B).
MESH_BYTES_PER_PIXEL = 100
# What a built ROI keeps until its specimen is stored, per pixel: heights and texture as
# measured, filtered, placed and fused, about 20-30 B by the arrays' sizes. A 2,048² one-ROI
# specimen peaked at 603 MiB, while its height map was matched; tiling it held 120 MiB less.
SPECIMEN_BYTES_PER_PIXEL = 48
# Share of the server's memory that concurrent requests may take; the rest is the process itself,
# the serving caches and strips matched for peers.
REQUEST_SHARE = 0.6
# An analysis (roughness, profile, report, an export's sampling and writing) per point it works
# on: the chain's float64 copies, filters, spectra and uncertainty maps (measured 290-480 B on
# 512² maps by tracemalloc, plane and cylinder forms).
ANALYSIS_BYTES_PER_SAMPLE = 600
# An export per point beyond the map: the sampled z, sigma, texture and sources, and the
# writers' strips (measured 13-25 B, benchmarks/exports.py).
EXPORT_BYTES_PER_SAMPLE = 40
# Decoding an uploaded image per declared pixel: float64 samples at worst, the grey conversion
# and the data bar's rows.
DECODE_BYTES_PER_PIXEL = 16
# Requests waiting for a CPU slot beyond those running, before more are refused.
DEFAULT_QUEUE = 16
# The largest file one request may write (an export, a report): FRACTO_MAX_FILE_MB, MiB.
DEFAULT_MAX_FILE_MB = 4096
# Share of the scratch folder's free space that files being written may hold.
DISK_SHARE = 0.5
# The retry hint of a request refused for want of room now, s.
RETRY_AFTER_S = 5.0
# How often a request waiting for a CPU slot looks whether its caller has gone, s.
_WATCH_S = 0.1


def height_map_bytes(
    shape: tuple[int, int],
    views: int,
    *,
    tilt_axis_deg: float = DEFAULT_TILT_AXIS_DEG,
    window_px: int = matching.DEFAULT_WINDOW_PX,
    max_disparity_px: int | None = None,
    strip_pixels: int = matching.DEFAULT_STRIP_PIXELS,
) -> int:
    """Estimated peak bytes of a height map of `views` images of `shape` (rows, cols): the full
    images on the canvas that turns the tilt axis vertical, and the largest strip the matcher cuts times
    the strips it matches at once (matching.strip_workers)."""
    _, canvas = alignment.rotation_to_vertical_axis(shape, tilt_axis_deg)
    disparity = max_disparity_px or matching.default_max_disparity_px(canvas[1])
    strips = matching.strip_bounds(canvas, window_px=window_px, max_disparity_px=disparity, strip_pixels=strip_pixels)
    strip_pixels_max = max(bottom - top for top, _, _, bottom in strips) * canvas[1]
    full_pixels = canvas[0] * canvas[1]
    return (
        BASE_BYTES
        + HEIGHT_MAP_BYTES_PER_PIXEL * full_pixels * max(views - 1, 1)
        + STRIP_BYTES_PER_PIXEL * strip_pixels_max * min(matching.strip_workers(), len(strips))
    )


def strip_bytes(shape: tuple[int, int]) -> int:
    """Estimated peak bytes of matching one strip of `shape` (rows, cols) for a peer."""
    return BASE_BYTES + STRIP_BYTES_PER_PIXEL * shape[0] * shape[1]


def mesh_bytes(shape: tuple[int, int]) -> int:
    """Estimated peak bytes of meshing a height map of `shape` (rows, cols)."""
    return BASE_BYTES + MESH_BYTES_PER_PIXEL * shape[0] * shape[1]


def specimen_bytes(roi_shapes: Sequence[tuple[int, int]], *, matched_here: Sequence[int] = ()) -> int:
    """Estimated peak bytes of building a specimen whose ROIs' images have `roi_shapes` (rows,
    cols): what every ROI keeps until it is stored, plus the largest of `matched_here` (the
    estimates of ROIs matched in this process, one at a time)."""
    kept = sum(SPECIMEN_BYTES_PER_PIXEL * rows * cols for rows, cols in roi_shapes)
    return max([BASE_BYTES, *matched_here]) + kept


class Cost(NamedTuple):
    """What a request would take, estimated before any work: `what` names it in refusals."""

    what: str
    memory_bytes: int
    disk_bytes: int = 0


class Ticket:
    """An admitted request's hold on the budget, given up once it has run (or `release`d unrun)."""

    def __init__(self, budget: Budget, cost: Cost):
        self._budget, self._cost, self._released = budget, cost, False

    @contextlib.contextmanager
    def running(self, stopped: Callable[[], bool] | None = None) -> Iterator[None]:
        """Runs the block on a CPU slot, waiting for one; while it waits, and in the block's
        `progress.checkpoint()`s, `stopped()` true (its caller gone) raises CancelledError."""
        slots = self._budget._slots
        try:
            while not slots.acquire(timeout=_WATCH_S):
                if stopped is not None and stopped():
                    raise CancelledError("the caller went away while its request waited")
            try:
                with progress.stoppable(stopped):
                    yield
            finally:
                slots.release()
        finally:
            self.release()

    def release(self) -> None:
        if not self._released:
            self._released = True
            self._budget._release(self._cost)


class Budget:
    """The one admission budget of a serving process, shared by its gRPC and HTTP front ends.

    Memory: one request may be estimated at `request_limit_bytes` at most (FRACTO_MAX_REQUEST_MB;
    `check`), and those admitted hold their estimates within `memory_bytes` while they run
    (`admitted`; builds, bounded by their own pools, are counted as they run, `held`). CPU:
    `cpu_slots` admitted requests run at once, `queue_limit` more wait for a slot (watching
    whether their caller has gone). Scratch disk: a file to be written may be estimated at
    `max_file_bytes` at most (FRACTO_MAX_FILE_MB), and those being written hold their estimates
    within DISK_SHARE of the scratch folder's free space. A request that can never fit is
    TooLargeError (HTTP 413), one that cannot fit now ResourceExhaustedError with a retry hint
    (HTTP 429): both at once, before any decoding or writing; nothing waits for memory or disk."""

    def __init__(
        self,
        *,
        memory_bytes: int,
        request_limit_bytes: int,
        cpu_slots: int,
        queue_limit: int = DEFAULT_QUEUE,
        scratch_root: Path | None = None,
        max_file_bytes: int = DEFAULT_MAX_FILE_MB * MB,
    ):
        self.memory_bytes, self.limit_bytes = memory_bytes, request_limit_bytes
        self.cpu_slots, self.queue_limit = cpu_slots, queue_limit
        self.scratch_root, self.max_file_bytes = scratch_root, max_file_bytes
        self._lock = threading.Lock()
        self._slots = threading.Semaphore(cpu_slots)
        self._held_bytes = self._disk_bytes = self._admitted = 0

    @classmethod
    def for_server(
        cls, max_request_mb: int | None, *, concurrent_requests: int, scratch_root: Path | None = None
    ) -> Budget:
        """REQUEST_SHARE of the server's memory, each request `max_request_mb` at most or by default
        that share over `concurrent_requests` (the build workers); a slot per CPU; files within
        FRACTO_MAX_FILE_MB (default DEFAULT_MAX_FILE_MB) under `scratch_root`."""
        share = int(REQUEST_SHARE * server_memory_bytes())
        limit = max_request_mb * MB if max_request_mb is not None else share // max(concurrent_requests, 1)
        return cls(
            memory_bytes=max(share, limit),
            request_limit_bytes=limit,
            cpu_slots=len(os.sched_getaffinity(0)),
            scratch_root=scratch_root,
            max_file_bytes=int(os.environ.get("FRACTO_MAX_FILE_MB", DEFAULT_MAX_FILE_MB)) * MB,
        )

    def check(self, estimate_bytes: int, what: str) -> None:
        """TooLargeError naming `what` (e.g. "a 16384 x 16384 pair") and both sizes when
        `estimate_bytes` exceeds the limit of one request."""
        if estimate_bytes > self.limit_bytes:
            raise TooLargeError(
                f"{what} needs about {_size(estimate_bytes)} of memory, more than this server allows one request "
                f"({_size(self.limit_bytes)}, FRACTO_MAX_REQUEST_MB); send smaller images or raise the limit"
            )

    def check_file(self, estimate_bytes: int, what: str) -> None:
        """TooLargeError naming `what` when a file of `estimate_bytes` exceeds max_file_bytes."""
        if estimate_bytes > self.max_file_bytes:
            raise TooLargeError(
                f"{what} would be about {_size(estimate_bytes)}, more than this server writes for one request "
                f"({_size(self.max_file_bytes)}, FRACTO_MAX_FILE_MB); ask for a smaller area or a coarser pixel size"
            )

    @contextlib.contextmanager
    def held(self, estimate_bytes: int) -> Iterator[None]:
        """Counts a build's estimate as held for the block, whatever the others hold (its own pool
        and the limit of one request bound builds)."""
        with self._lock:
            self._held_bytes += estimate_bytes
        try:
            yield
        finally:
            with self._lock:
                self._held_bytes -= estimate_bytes

    @contextlib.contextmanager
    def admitted(self, cost: Cost, *, stopped: Callable[[], bool] | None = None) -> Iterator[None]:
        """Runs the block as one admitted request of `cost` (`admit`, then its ticket's `running`)."""
        with self.admit(cost).running(stopped):
            yield

    def admit(self, cost: Cost) -> Ticket:
        """Admits a request of `cost`'s memory, or refuses it at once (see the class; its disk is
        `scratch`'s): the ticket holds its memory and its place until it has run (Ticket.running)."""
        self.check(cost.memory_bytes, cost.what)
        with self._lock:
            self._refuse_unless(cost.what, self._room_for(cost.memory_bytes))
            self._held_bytes += cost.memory_bytes
            self._admitted += 1
        return Ticket(self, cost)

    def _release(self, cost: Cost) -> None:
        with self._lock:
            self._held_bytes -= cost.memory_bytes
            self._admitted -= 1

    @contextlib.contextmanager
    def scratch(self, cost: Cost) -> Iterator[None]:
        """Holds `cost`'s file on the scratch disk for the block (it is written and sent there), or
        refuses it at once (see the class)."""
        self.check_file(cost.disk_bytes, cost.what)
        with self._lock:
            free_bytes = DISK_SHARE * _free_bytes(self.scratch_root)
            if self._disk_bytes + cost.disk_bytes > free_bytes:
                self._refuse_unless(
                    cost.what, f"files being written hold {_size(self._disk_bytes)} of its scratch disk's free share"
                )
            self._disk_bytes += cost.disk_bytes
        try:
            yield
        finally:
            with self._lock:
                self._disk_bytes -= cost.disk_bytes

    def _room_for(self, memory_bytes: int) -> str | None:
        """Under the lock: why a request of `memory_bytes` cannot be admitted now, None if it can."""
        if self._admitted >= self.cpu_slots + self.queue_limit:
            return f"{self._admitted} requests are running or waiting on its {self.cpu_slots} CPUs"
        if self._held_bytes + memory_bytes > self.memory_bytes:
            return f"the requests under way hold {_size(self._held_bytes)} of its {_size(self.memory_bytes)}"
        return None

    @staticmethod
    def _refuse_unless(what: str, reason: str | None) -> None:
        if reason is not None:
            raise ResourceExhaustedError(
                f"this server cannot take {what} now: {reason}; retry in about {RETRY_AFTER_S:.0f} s",
                retry_after_s=RETRY_AFTER_S,
            )


def server_memory_bytes() -> int:
    """The memory this process may use: its cgroup's limit (v2 or v1), else the machine's."""
    limits = [os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")]
    for path in ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes"):
        try:
            text = Path(path).read_text().strip()
        except OSError:
            continue
        if text.isdigit():
            limits.append(int(text))
    return min(limits)


def analysis_bytes(samples: int) -> int:
    """Estimated peak bytes of an analysis of `samples` points (see ANALYSIS_BYTES_PER_SAMPLE)."""
    return BASE_BYTES + ANALYSIS_BYTES_PER_SAMPLE * samples


def export_bytes(samples: int) -> int:
    """Estimated peak bytes of an export of `samples` points, beyond its source's arrays."""
    return BASE_BYTES + EXPORT_BYTES_PER_SAMPLE * samples


def decode_bytes(shapes: Sequence[tuple[int, int]]) -> int:
    """Estimated peak bytes of decoding images of `shapes` (rows, cols) one at a time."""
    return BASE_BYTES + DECODE_BYTES_PER_PIXEL * max((rows * cols for rows, cols in shapes), default=0)


def _free_bytes(root: Path | None) -> int:
    """Free space of the volume of `root` (or of its nearest existing parent); unbounded without one."""
    if root is None:
        return 1 << 62
    path = Path(root)
    while not path.exists() and path != path.parent:
        path = path.parent
    return shutil.disk_usage(path).free


def _size(value_bytes: int) -> str:
    return f"{value_bytes / 1024**3:.1f} GiB" if value_bytes >= 1024**3 else f"{value_bytes / MB:.0f} MiB"
