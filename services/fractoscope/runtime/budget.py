"""The memory budget of one request: its peak estimated from its pixel counts before any work,
and refused (RESOURCE_EXHAUSTED naming the size) when it exceeds FRACTO_MAX_REQUEST_MB.

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

import os
from collections.abc import Sequence
from pathlib import Path

from fractoscope.errors import ResourceExhaustedError
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


class MemoryBudget:
    """Refuses requests whose estimate exceeds `limit_bytes`."""

    def __init__(self, limit_bytes: int):
        self.limit_bytes = limit_bytes

    @classmethod
    def for_server(cls, max_request_mb: int | None, *, concurrent_requests: int) -> MemoryBudget:
        """`max_request_mb`, or by default REQUEST_SHARE of the server's memory shared by
        `concurrent_requests`."""
        if max_request_mb is None:
            return cls(int(REQUEST_SHARE * server_memory_bytes() / max(concurrent_requests, 1)))
        return cls(max_request_mb * MB)

    def check(self, estimate_bytes: int, what: str) -> None:
        """ResourceExhaustedError naming `what` (e.g. "a 16384 x 16384 pair") and both sizes when
        `estimate_bytes` exceeds the limit."""
        if estimate_bytes > self.limit_bytes:
            raise ResourceExhaustedError(
                f"{what} needs about {_size(estimate_bytes)} of memory, more than this server allows one request "
                f"({_size(self.limit_bytes)}, FRACTO_MAX_REQUEST_MB); send smaller images or raise the limit"
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


def _size(value_bytes: int) -> str:
    return f"{value_bytes / 1024**3:.1f} GiB" if value_bytes >= 1024**3 else f"{value_bytes / MB:.0f} MiB"
