"""`make bench`: our matching methods against OpenCV StereoSGBM and per-pixel matchTemplate (the
paper's method), side by side on one synthetic 1024² pair with a ±32 px disparity range: the
default (TGV_ZNCC), window correlation (WINDOW_ZNCC, also with propagation at full resolution,
an option), FAST (DIS optical flow refined by window correlation), StereoSGBM as this benchmark
always ran it (block 5, five paths) and as 3D-SEM configures it (benchmarks.peers); and a 4096²
pair for the default's time and peak memory. Each method runs in its own process so peak RSS is
its own; each row also gives the CPU time its fastest run took over its wall time (how many cores
it kept busy; the number of CPUs the benchmark may use is printed).
Matching II's targets: the default within 1.5 times StereoSGBM's time at half its RMS error or
less, window correlation within 1.0 times; a 4096² pair under 3 GB. Matching III's: FAST within
1.5 times StereoSGBM's time at 0.8 times its RMS error or less. Issue 37's: the default height map
of the 4096² pair within 20 s and 3 GB on two cores, of the 1024² pair within 5 times StereoSGBM's
time.

Writes bench-results/matching.json and prints a table, with each method's time and RMS error as
multiples of StereoSGBM's.
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
from pathlib import Path

import cv2
import numpy as np

from benchmarks import peers
from fractoscope import synthetic
from fractoscope.runtime.process import keep_freed_memory
from fractoscope.sem.image import SemImage
from fractoscope.stereo.matching import match_disparity
from fractoscope.stereo.pipeline import compute_height_map
from fractoscope.stereo.semi_global import sgbm_disparity

PIXEL_SIZE_UM = 0.1
TILTS_DEG = (-5.0, 5.0)
DISPARITY_RANGE_PX = 32
WINDOW_PX = 15
BORDER_PX = 48
TIMING_REPEATS = 3
ROUNDS = 3
TIMED_METHODS = ("fractoscope", "tgv_zncc", "window_zncc", "window_zncc_propagating", "fast", "sgbm", "sgbm_3d_sem")


def make_pair(size_px: int, path: Path) -> None:
    """A self-affine pair whose disparities span about ±DISPARITY_RANGE_PX, saved as .npz."""
    surface = synthetic.self_affine_surface((size_px + 64,) * 2, hurst=0.8, rms_um=1.0, seed=42)
    per_px_um = PIXEL_SIZE_UM / (2 * np.sin(np.radians(5.0)))
    surface *= 2 * DISPARITY_RANGE_PX * per_px_um / np.ptp(surface)
    pair = synthetic.render_stereo_pair(
        surface, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=TILTS_DEG, output_shape=(size_px, size_px), seed=1
    )
    np.savez(path, first=pair.first, second=pair.second, truth_um=pair.z_seen_um.astype(np.float32))


def _heights_from_our_matcher(first, second):
    result = compute_height_map(
        SemImage(first, None, None, 0), SemImage(second, None, None, 0), tilt_deg=TILTS_DEG, pixel_size_um=PIXEL_SIZE_UM
    )
    return result.z_um


def _heights_from_matcher_only(first, second, *, method="tgv_zncc", propagate_at_full_resolution=False):
    """A matching method alone on the (already rectified) pair, as StereoSGBM gets it."""
    disparity = match_disparity(
        first,
        second,
        max_disparity_px=DISPARITY_RANGE_PX + 8,
        method=method,
        propagate_at_full_resolution=propagate_at_full_resolution,
    ).disparity_px
    return disparity * PIXEL_SIZE_UM / (2 * np.sin(np.radians(5.0)))


def _heights_from_sgbm(first, second):
    """OpenCV's semi-global block matching (block 5, five paths, uniqueness 5)."""
    limit = DISPARITY_RANGE_PX + 8
    disparity = sgbm_disparity(first, second, min_px=-limit, max_px=limit, block_px=5, uniqueness_percent=5)
    return disparity * PIXEL_SIZE_UM / (2 * np.sin(np.radians(5.0)))


def _heights_from_3d_sem(first, second):
    return peers.sgbm_3d_sem(first, second, DISPARITY_RANGE_PX + 8) * PIXEL_SIZE_UM / (2 * np.sin(np.radians(5.0)))


def _per_pixel_template_seconds(first, second, *, vertical_reach_px, samples=400):
    """Time of the paper's per-pixel search, extrapolated to every pixel: matchTemplate of a
    pattern window inside a search window around the same position in the second image (parabola
    sub-pixel). The paper matches unrectified images, so its search window spans the disparity
    range across rows as well as along them; `vertical_reach_px` = 0 gives a one-row strip."""
    rng = np.random.default_rng(0)
    half, reach = WINDOW_PX // 2, DISPARITY_RANGE_PX + 8
    rows = rng.integers(half + vertical_reach_px + 1, first.shape[0] - half - vertical_reach_px - 1, samples)
    cols = rng.integers(half + reach + 1, first.shape[1] - half - reach - 1, samples)
    first_f, second_f = first.astype(np.float32), second.astype(np.float32)
    started = time.perf_counter()
    for row, col in zip(rows, cols):
        pattern = first_f[row - half : row + half + 1, col - half : col + half + 1]
        search = second_f[
            row - half - vertical_reach_px : row + half + vertical_reach_px + 1,
            col - half - reach : col + half + reach + 1,
        ]
        scores = cv2.matchTemplate(search, pattern, cv2.TM_CCOEFF_NORMED)
        best_row, best_col = np.unravel_index(int(np.argmax(scores)), scores.shape)
        if 0 < best_col < scores.shape[1] - 1:
            left, centre, right = scores[best_row, best_col - 1 : best_col + 2]
            _ = best_col + 0.5 * (left - right) / (left - 2 * centre + right)
    per_pixel_s = (time.perf_counter() - started) / samples
    return per_pixel_s * first.size


def _accuracy(z_um, truth_um):
    inner = np.zeros(truth_um.shape, bool)
    inner[BORDER_PX:-BORDER_PX, BORDER_PX:-BORDER_PX] = True
    valid = np.isfinite(z_um) & inner
    error = z_um[valid] - truth_um[valid]
    error -= np.median(error)
    return {
        "valid_fraction": float(valid[inner].mean()),
        "rms_error_um": float(np.sqrt(np.mean(error**2))),
        "rms_error_percent_of_range": float(100 * np.sqrt(np.mean(error**2)) / np.ptp(truth_um[inner])),
    }


def _peak_rss_mb() -> float:
    """This process's peak resident memory (VmHWM), MB. Unlike getrusage's ru_maxrss, it is not
    inherited from the parent process across fork and exec."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmHWM:"):
            return int(line.split()[1]) / 1024
    raise RuntimeError("VmHWM not found in /proc/self/status")


def run_one(method: str, pair_path: Path) -> dict:
    """Runs one method in this process, with the C library's allocator set as in fracto-server;
    returns its figures including peak RSS."""
    keep_freed_memory()
    with np.load(pair_path) as arrays:
        first, second, truth = arrays["first"], arrays["second"], arrays["truth_um"]
    baseline_mb = _peak_rss_mb()
    if method == "template_2d":
        seconds = _per_pixel_template_seconds(first, second, vertical_reach_px=DISPARITY_RANGE_PX + 8)
        return {"method": method, "seconds": seconds, "extrapolated": True}
    if method == "template_row":
        return {
            "method": method,
            "seconds": _per_pixel_template_seconds(first, second, vertical_reach_px=0),
            "extrapolated": True,
        }
    window = functools.partial(_heights_from_matcher_only, method="window_zncc")
    heights = {
        "fractoscope": _heights_from_our_matcher,
        "tgv_zncc": _heights_from_matcher_only,
        "window_zncc": window,
        "window_zncc_propagating": functools.partial(window, propagate_at_full_resolution=True),
        "fast": functools.partial(_heights_from_matcher_only, method="fast"),
        "sgbm": _heights_from_sgbm,
        "sgbm_3d_sem": _heights_from_3d_sem,
    }
    runs = []
    for _ in range(TIMING_REPEATS):  # the fastest of a few runs: shared machines add noise, never speed
        started, started_cpu = time.perf_counter(), time.process_time()
        z_um = heights[method](first, second)
        runs.append((time.perf_counter() - started, time.process_time() - started_cpu))
    seconds, cpu_seconds = min(runs)
    peak_mb = _peak_rss_mb()
    return {
        "method": method,
        "size_px": first.shape[0],
        "seconds": seconds,
        "cpu_seconds": cpu_seconds,
        "cpu_per_wall": cpu_seconds / seconds,
        "peak_rss_mb": peak_mb,
        "peak_rss_above_inputs_mb": peak_mb - baseline_mb,
        **_accuracy(z_um, truth),
    }


def _in_subprocess(method: str, pair_path: Path) -> dict:
    output = subprocess.run(
        [sys.executable, "-m", "benchmarks.matching", "--one", method, "--pair", str(pair_path)],
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    return json.loads(output.strip().splitlines()[-1])


def _print_table(results: dict) -> None:
    """One row per method: time, RMS error, valid share, peak memory, and time and RMS error as
    multiples of StereoSGBM's (on the same pair; the large pair's row has no such ratios)."""
    sgbm = results["sgbm"]
    print(
        f"{'method':<32}{'seconds':>10}{'CPU/wall':>10}{'RMS µm':>10}{'RMS % range':>13}{'valid %':>9}"
        f"{'peak MB':>9}{'× SGBM s':>10}{'× SGBM RMS':>12}"
    )
    for name, row in results.items():
        if name == "summary":
            continue
        same_pair = row.get("size_px", sgbm["size_px"]) == sgbm["size_px"]
        time_ratio = row["seconds"] / sgbm["seconds"] if same_pair else float("nan")
        rms_ratio = row.get("rms_error_um", float("nan")) / sgbm["rms_error_um"] if same_pair else float("nan")
        print(
            f"{name:<32}{row['seconds']:>10.2f}{row.get('cpu_per_wall', float('nan')):>10.2f}"
            f"{row.get('rms_error_um', float('nan')):>10.3f}"
            f"{row.get('rms_error_percent_of_range', float('nan')):>13.2f}"
            f"{100 * row.get('valid_fraction', float('nan')):>9.1f}{row.get('peak_rss_mb', float('nan')):>9.0f}"
            f"{time_ratio:>10.2f}{rms_ratio:>12.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--one")
    parser.add_argument("--pair")
    parser.add_argument("--large-px", type=int, default=4096)
    args = parser.parse_args()
    if args.one:
        print(json.dumps(run_one(args.one, Path(args.pair))))
        return
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as scratch:
        pair_1024 = Path(scratch) / "pair_1024.npz"
        make_pair(1024, pair_1024)
        # Timed methods alternate over a few rounds, so a slow spell of a shared machine does not
        # fall on one of them only; each keeps its fastest round.
        results = {}
        for _ in range(ROUNDS):
            for method in TIMED_METHODS:
                run = _in_subprocess(method, pair_1024)
                if method not in results or run["seconds"] < results[method]["seconds"]:
                    results[method] = run
        for method in ("template_2d", "template_row"):
            results[method] = _in_subprocess(method, pair_1024)
        pair_large = Path(scratch) / "pair_large.npz"
        make_pair(args.large_px, pair_large)
        results["fractoscope_large"] = _in_subprocess("fractoscope", pair_large)
    ours, default, window, fast, sgbm, sgbm_3d_sem = (
        results[name] for name in ("fractoscope", "tgv_zncc", "window_zncc", "fast", "sgbm", "sgbm_3d_sem")
    )
    results["summary"] = {
        "default_time_vs_sgbm": default["seconds"] / sgbm["seconds"],
        "default_rms_error_vs_sgbm": default["rms_error_um"] / sgbm["rms_error_um"],
        "default_time_vs_sgbm_3d_sem": default["seconds"] / sgbm_3d_sem["seconds"],
        "default_rms_error_vs_sgbm_3d_sem": default["rms_error_um"] / sgbm_3d_sem["rms_error_um"],
        "window_time_vs_sgbm": window["seconds"] / sgbm["seconds"],
        "window_rms_error_vs_sgbm": window["rms_error_um"] / sgbm["rms_error_um"],
        "fast_time_vs_sgbm": fast["seconds"] / sgbm["seconds"],
        "fast_rms_error_vs_sgbm": fast["rms_error_um"] / sgbm["rms_error_um"],
        "pipeline_time_vs_sgbm": ours["seconds"] / sgbm["seconds"],
        "default_speed_vs_per_pixel_template_2d": results["template_2d"]["seconds"] / default["seconds"],
        "pipeline_speed_vs_per_pixel_template_row": results["template_row"]["seconds"] / ours["seconds"],
        "large_seconds": results["fractoscope_large"]["seconds"],
        "large_peak_rss_gb": results["fractoscope_large"]["peak_rss_mb"] / 1024,
        "large_cpu_per_wall": results["fractoscope_large"]["cpu_per_wall"],
        "pipeline_cpu_per_wall": ours["cpu_per_wall"],
        "cpus": len(os.sched_getaffinity(0)),
        "propagating_window_time_vs_window": results["window_zncc_propagating"]["seconds"] / window["seconds"],
    }
    (out / "matching.json").write_text(json.dumps(results, indent=2))
    _print_table(results)
    print(json.dumps(results["summary"], indent=2))
    print(f"written to {out / 'matching.json'}")


if __name__ == "__main__":
    main()
