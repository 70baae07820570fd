"""`make bench`: where the default method's time goes, against what this machine's memory allows.

The full height-map request (stereo.pipeline.compute_height_map) on benchmarks.matching's 1024²
pair, its stages timed by wrapping the functions that do them (wall time, and the process's CPU
time while each ran: the two directions of a strip are refined at once, so their CPU shows in
both), with the bytes each stage moves: the arrays it takes and gives (each read or written at
least once), and for the TGV² iterations the arrays their kernels stream per sweep
(`_TGV_ARRAYS_PER_SWEEP`). The floor is those bytes at the memory bandwidth a STREAM-like add
(c = a + b over float32 arrays far larger than the caches, on as many threads as there are CPUs)
measures here; the fraction of the floor is the floor's time over the stage's.

Then the time from 512² to 8192² (`--sizes`), the exponent of a power law fitted to it (1: linear
in pixels), and the peak memory (VmHWM) at each size, each size in a process of its own.

Writes bench-results/profile.json and prints the tables.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import fields, is_dataclass
from pathlib import Path

import numpy as np

from benchmarks.matching import PIXEL_SIZE_UM, TILTS_DEG, make_pair
from fractoscope.runtime.process import keep_freed_memory
from fractoscope.sem.image import SemImage
from fractoscope.stereo import (
    alignment,
    matching,
    orientation,
    photometric,
    pipeline,
    semi_global,
    tgv_refinement,
    tgv_zncc,
    visibility,
    window_zncc,
)

# The stages: (module, function) wrapped, in the order they run.
STAGES = (
    (alignment, "estimate_alignment"),
    (alignment, "apply_affine"),
    (matching, "local_contrast"),
    (window_zncc, "match_directions"),
    (semi_global, "seed_disparity"),
    (tgv_zncc, "_propagated"),
    (tgv_refinement, "refine_disparity"),
    (visibility, "unsupported_beside_occlusions"),
    (tgv_zncc, "_peaked"),
    (photometric, "fused_disparity"),
    (alignment, "residual_misplacement"),
    (orientation, "oriented"),
)
# Per sweep of tgv_refinement.WAVEFRONT_ITERATIONS iterations, the 13 arrays (d, v, their
# over-relaxed copies, p, q, the target and the precision) are read once and all but the target
# and the precision written once: the rows in between stay in cache.
_TGV_ARRAYS_PER_SWEEP = 13 + 11
_STREAM_BYTES = 256 * 2**20


def stream_bandwidth_gb_s(*, repeats: int = 5) -> float:
    """Memory bandwidth of c = a + b over float32 arrays of 256 MiB each, split over as many
    threads as this process may use (numpy releases the GIL), the best of `repeats`: bytes read
    and written (3 per element) per second, GB/s."""
    count = _STREAM_BYTES // 4
    a, b, c = (np.ones(count, np.float32) for _ in range(3))
    threads = len(os.sched_getaffinity(0))
    bounds = [(count * k // threads, count * (k + 1) // threads) for k in range(threads)]
    best = float("inf")
    with ThreadPoolExecutor(max_workers=threads) as pool:
        for _ in range(repeats):
            started = time.perf_counter()
            list(
                pool.map(
                    lambda span: np.add(a[span[0] : span[1]], b[span[0] : span[1]], out=c[span[0] : span[1]]), bounds
                )
            )
            best = min(best, time.perf_counter() - started)
    return 3 * _STREAM_BYTES / best / 1e9


def _array_bytes(value) -> int:
    """Bytes of the numpy arrays in `value` (arrays, tuples, lists, dataclasses, nested)."""
    if isinstance(value, np.ndarray):
        return value.nbytes
    if isinstance(value, (tuple, list)):
        return sum(_array_bytes(item) for item in value)
    if is_dataclass(value) and not isinstance(value, type):
        return sum(_array_bytes(getattr(value, field.name)) for field in fields(value))
    return 0


class _Profile:
    """Wall time, CPU time, calls and bytes per stage, accumulated by wrapped functions."""

    def __init__(self) -> None:
        self.rows = {f"{module.__name__.rsplit('.', 1)[-1]}.{name}": [0.0, 0.0, 0, 0] for module, name in STAGES}

    def wrap(self, module, name: str) -> None:
        original = getattr(module, name)
        key = f"{module.__name__.rsplit('.', 1)[-1]}.{name}"

        @functools.wraps(original)
        def timed(*args, **kwargs):
            started, started_cpu = time.perf_counter(), time.process_time()
            result = original(*args, **kwargs)
            row = self.rows[key]
            row[0] += time.perf_counter() - started
            row[1] += time.process_time() - started_cpu
            row[2] += 1
            row[3] += _array_bytes(args) + _array_bytes(kwargs) + _array_bytes(result)
            return result

        setattr(module, name, timed)

    def wrap_tgv_iterations(self) -> None:
        """Counts the bytes the TGV² kernels stream (`_TGV_ARRAYS_PER_SWEEP` float32 arrays per
        sweep) on top of refine_disparity's own arrays."""
        original = tgv_refinement._State.iterate
        row = self.rows["tgv_refinement.refine_disparity"]

        def iterate(state, target, precision, **kwargs):
            sweeps = -(-kwargs["iterations"] // tgv_refinement.WAVEFRONT_ITERATIONS)
            row[3] += _TGV_ARRAYS_PER_SWEEP * state.disparity.nbytes * sweeps
            return original(state, target, precision, **kwargs)

        tgv_refinement._State.iterate = iterate


def profile(pair_path: Path) -> dict:
    """The stage table of one full request on the pair at `pair_path` (after a warm-up run)."""
    with np.load(pair_path) as arrays:
        first, second = SemImage(arrays["first"], None, None, 0), SemImage(arrays["second"], None, None, 0)
    pipeline.compute_height_map(first, second, tilt_deg=TILTS_DEG, pixel_size_um=PIXEL_SIZE_UM)  # compiles, warms
    recorder = _Profile()
    for module, name in STAGES:
        recorder.wrap(module, name)
    recorder.wrap_tgv_iterations()
    started, started_cpu = time.perf_counter(), time.process_time()
    pipeline.compute_height_map(first, second, tilt_deg=TILTS_DEG, pixel_size_um=PIXEL_SIZE_UM)
    total = {"seconds": time.perf_counter() - started, "cpu_seconds": time.process_time() - started_cpu}
    bandwidth = stream_bandwidth_gb_s()
    stages = {
        key: {
            "seconds": wall,
            "cpu_seconds": cpu,
            "calls": calls,
            "bytes": moved,
            "floor_seconds": moved / (bandwidth * 1e9),
            "fraction_of_floor": moved / (bandwidth * 1e9) / wall if wall else float("nan"),
        }
        for key, (wall, cpu, calls, moved) in recorder.rows.items()
    }
    return {"total": total, "stream_gb_s": bandwidth, "cpus": len(os.sched_getaffinity(0)), "stages": stages}


def run_size(size_px: int, pair_path: Path) -> dict:
    """One full request on a pair of `size_px`², in this process (after a 256² warm-up that
    compiles the kernels): seconds and peak memory."""
    keep_freed_memory()
    warm = Path(tempfile.mkdtemp()) / "warm.npz"
    make_pair(256, warm)
    for path in (warm, pair_path):
        with np.load(path) as arrays:
            first, second = SemImage(arrays["first"], None, None, 0), SemImage(arrays["second"], None, None, 0)
        started = time.perf_counter()
        pipeline.compute_height_map(first, second, tilt_deg=TILTS_DEG, pixel_size_um=PIXEL_SIZE_UM)
        seconds = time.perf_counter() - started
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            peak_mb = int(line.split()[1]) / 1024
    return {"size_px": size_px, "seconds": seconds, "peak_rss_mb": peak_mb}


def _print(result: dict, scaling: list[dict]) -> None:
    total = result["total"]
    print(
        f"full request, 1024²: {total['seconds']:.2f} s wall, {total['cpu_seconds']:.2f} s CPU on {result['cpus']} "
        f"CPUs; memory bandwidth (STREAM-like add): {result['stream_gb_s']:.1f} GB/s"
    )
    print(f"{'stage':<42}{'calls':>6}{'s':>8}{'CPU s':>8}{'% of req':>9}{'MB moved':>10}{'floor s':>9}{'of floor':>10}")
    for key, row in result["stages"].items():
        print(
            f"{key:<42}{row['calls']:>6}{row['seconds']:>8.3f}{row['cpu_seconds']:>8.3f}"
            f"{100 * row['seconds'] / total['seconds']:>8.1f}%{row['bytes'] / 1e6:>10.0f}{row['floor_seconds']:>9.3f}"
            f"{100 * row['fraction_of_floor']:>9.1f}%"
        )
    print("Stages nest: match_directions, seed_disparity, _propagated and refine_disparity run inside the matching.")
    if scaling:
        sizes = np.array([row["size_px"] ** 2 for row in scaling], float)
        seconds = np.array([row["seconds"] for row in scaling])
        exponent = np.polyfit(np.log(sizes), np.log(seconds), 1)[0] if len(scaling) > 1 else float("nan")
        for row in scaling:
            print(f"{row['size_px']:>5}²: {row['seconds']:8.2f} s, peak {row['peak_rss_mb'] / 1024:6.2f} GB")
        print(f"time ∝ pixels^{exponent:.2f} from {scaling[0]['size_px']}² to {scaling[-1]['size_px']}²")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--sizes", type=int, nargs="*", default=[512, 1024, 2048, 4096, 8192])
    parser.add_argument("--one", type=int)
    parser.add_argument("--pair")
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_size(args.one, Path(args.pair))))
        return
    with tempfile.TemporaryDirectory() as scratch:
        pair_1024 = Path(scratch) / "pair_1024.npz"
        make_pair(1024, pair_1024)
        result = profile(pair_1024)
        scaling = []
        for size_px in args.sizes:
            path = Path(scratch) / f"pair_{size_px}.npz"
            make_pair(size_px, path)
            command = [sys.executable, "-m", "benchmarks.profile", "--one", str(size_px), "--pair", str(path)]
            output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
            scaling.append(json.loads(output.strip().splitlines()[-1]))
            path.unlink()
    result["scaling"] = scaling
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "profile.json").write_text(json.dumps(result, indent=1))
    _print(result, scaling)
    print(f"written to {out / 'profile.json'}")


if __name__ == "__main__":
    main()
