"""`make bench`: the matching methods on pairs from renderers they were not tuned on.

For the default renderer and each of synthetic.PHYSICS_VARIANTS (other secondary-electron yield
laws, exponents, detector placements, edge contrast and textures), a 1024² pair of ductile
dimples (synthetic.reference_surface "dimples", seed 1) at ±5°, 2 % noise: the full height-map
request (stereo.pipeline.compute_height_map, told the detector's side as a user would) with the
default method (TGV_ZNCC), WINDOW_ZNCC and FAST, and OpenCV StereoSGBM as benchmarks.matching
runs it (block 5, five paths, uniqueness 5), its disparities turned into heights by the
pipeline's formula. Each method's time and RMS height error (synthetic.height_errors, % of the
range) and both as multiples of StereoSGBM's on the same pair; the photometric fusion's weight.
Issue 37's target: the default at 0.4 times StereoSGBM's RMS error or less on every renderer
but the tuning one ("texture_only", whose shading carries no slope at all, is the control).

The methods alternate within one process over `--rounds` rounds, each keeping its fastest time.
Writes bench-results/renderers.json and prints a table per renderer.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo import tilt_series
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_height_map
from fractoscope.stereo.semi_global import sgbm_disparity

TILTS_DEG = (-5.0, 5.0)
PIXEL_SIZE_UM = synthetic.REFERENCE_PIXEL_SIZE_UM
SGBM_LIMIT_PX = 16  # the dimples' disparities span about ±5 px
METHODS = ("tgv_zncc", "window_zncc", "fast", "sgbm")


def _pair(physics: synthetic.SemPhysics, size_px: int) -> synthetic.StereoPair:
    surface = synthetic.reference_surface("dimples", size_px + 64, seed=1)
    return synthetic.render_stereo_pair(
        surface,
        pixel_size_um=PIXEL_SIZE_UM,
        tilt_deg=TILTS_DEG,
        output_shape=(size_px, size_px),
        seed=1,
        physics=physics,
    )


def _ours(pair, physics, method) -> tuple[np.ndarray, dict]:
    options = MatchingOptions(method=method, detector_from_tilt_axis_deg=physics.detector_from_tilt_axis_deg)
    first, second = (SemImage(image, None, None, 0) for image in (pair.first, pair.second))
    result = compute_height_map(first, second, tilt_deg=TILTS_DEG, pixel_size_um=PIXEL_SIZE_UM, options=options)
    return result.z_um, result.report


def _sgbm(pair) -> tuple[np.ndarray, dict]:
    disparity = sgbm_disparity(
        pair.first, pair.second, min_px=-SGBM_LIMIT_PX, max_px=SGBM_LIMIT_PX, block_px=5, uniqueness_percent=5
    )
    columns_px = np.arange(pair.first.shape[1], dtype=np.float64) - (pair.first.shape[1] - 1) / 2.0
    x_px = np.broadcast_to(columns_px[None, :], pair.first.shape)
    z_px, _ = tilt_series.heights_px(x_px, np.stack([np.zeros_like(disparity), disparity]), TILTS_DEG)
    return z_px * PIXEL_SIZE_UM, {}


def run_renderer(physics: synthetic.SemPhysics, *, size_px: int, rounds: int) -> dict:
    """Each method's fastest time over `rounds` alternating rounds, its RMS error (% of the
    range) and valid share, and the default's photometric weight."""
    pair = _pair(physics, size_px)
    rows = {}
    for _ in range(rounds):
        for method in METHODS:
            started = time.perf_counter()
            z_um, report = _sgbm(pair) if method == "sgbm" else _ours(pair, physics, method)
            seconds = time.perf_counter() - started
            if method in rows:
                rows[method]["seconds"] = min(rows[method]["seconds"], seconds)
                continue
            errors = synthetic.height_errors(z_um, pair.z_seen_um)
            rows[method] = {
                "seconds": seconds,
                "rms_percent_of_range": 100 * errors.rms_of_range,
                "valid_fraction": errors.valid_fraction,
                "photometric_agreement": report.get("photometric_agreement", [float("nan")])[0],
                "photometric_weight": report.get("photometric_weight", [0.0])[0],
                "photometric_used": report.get("photometric_slopes_used", [False])[0],
            }
    sgbm = rows["sgbm"]
    for row in rows.values():
        row["time_vs_sgbm"] = row["seconds"] / sgbm["seconds"]
        row["rms_vs_sgbm"] = row["rms_percent_of_range"] / sgbm["rms_percent_of_range"]
    return rows


def _print(name: str, rows: dict) -> None:
    print(f"\n{name}")
    print(
        f"{'method':<14}{'seconds':>9}{'RMS % range':>13}{'valid %':>9}{'× SGBM s':>10}{'× SGBM RMS':>12}{'fused':>7}"
    )
    for method, row in rows.items():
        print(
            f"{method:<14}{row['seconds']:>9.2f}{row['rms_percent_of_range']:>13.2f}{100 * row['valid_fraction']:>9.1f}"
            f"{row['time_vs_sgbm']:>10.2f}{row['rms_vs_sgbm']:>12.2f}{'yes' if row['photometric_used'] else '':>7}"
        )


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--size-px", type=int, default=1024)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--variants", nargs="*", help="renderer names (default: the tuning one and every variant)")
    args = parser.parse_args()
    renderers = {"default": synthetic.DEFAULT_PHYSICS, **synthetic.PHYSICS_VARIANTS}
    names = args.variants or list(renderers)
    unknown = sorted(set(names) - set(renderers))
    if unknown:
        parser.error(f"--variants: unknown {unknown}; known: {sorted(renderers)}")
    results = {}
    for name in names:
        results[name] = run_renderer(renderers[name], size_px=args.size_px, rounds=args.rounds)
        _print(name, results[name])
    others = [results[name]["tgv_zncc"]["rms_vs_sgbm"] for name in names if name not in ("default", "texture_only")]
    results["summary"] = {"worst_default_rms_vs_sgbm_on_other_renderers": max(others, default=float("nan"))}
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "renderers.json").write_text(json.dumps(results, indent=2))
    print(json.dumps(results["summary"], indent=2))
    print(f"written to {out / 'renderers.json'}")


if __name__ == "__main__":
    main()
