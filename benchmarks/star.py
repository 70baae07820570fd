"""`make bench`: spatial resolution against noise, as DIC codes are judged (the DIC Challenge 2.0
star pattern: P. L. Reu et al., "DIC Challenge 2.0: developing images and guidelines for evaluating
accuracy and resolution of 2D analyses", Exp. Mech. 62 (2022) 639-654,
doi:10.1007/s11340-021-00806-6).

A flat texture and the texture displaced along rows by u = 0.5 px · cos(2π (col − centre) / p),
the period p growing from 10 px in the first row to 300 px in the last (4000 × 501 px, the
challenge's star turned so that its displacement runs along our matching direction), each image
integrated from a 4× finer grid and given 2 % noise (synthetic.textures): a speckle pattern (4 px
speckles) and an SEM-like texture (the default renderer's shading of a rough surface seen flat
on). Each method matches the pair as a rectified one (benchmarks.matching does the same):
the default (TGV_ZNCC), WINDOW_ZNCC, FAST and OpenCV's StereoSGBM (block 5, five paths).

Per band of rows (periods within 2 %), the measured disparity is regressed on the true one:
its slope is the amplitude measured. Spatial resolution: the shortest period from which every
longer one is measured within 10 % of its amplitude. Noise: the RMS error over the periods of
200 px and more. Issue 47's goal: resolution × noise ≤ 0.5 px² for the default (a subset-DIC
code with 11 px / 17 px subsets measured 0.73 px² on the issue's own star).

Writes bench-results/star.json and prints the table per texture.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from fractoscope.stereo.matching import match_disparity
from fractoscope.stereo.semi_global import sgbm_disparity
from fractoscope.synthetic import textures

SHAPE = (4000, 501)
AMPLITUDE_PX = 0.5
PERIODS_PX = (10.0, 300.0)
FACTOR = 4
SPECKLE_PX = 4.0
PIXEL_SIZE_UM = 0.1
NOISE_FRACTION = 0.02
SEARCH_PX = 8
BORDER_PX = 24
# A band of rows spans periods within 2 % (at least 3 rows): long periods get more rows, so that
# their amplitudes are measured as precisely as the short ones'.
BAND_PERIOD_SPAN = 0.02
BAND_MIN_ROWS = 3
WITHIN = 0.10
LONG_PERIOD_PX = 200.0
METHODS = ("tgv_zncc", "window_zncc", "fast", "sgbm")


def period_px(row_px: np.ndarray) -> np.ndarray:
    """The star's period at each row, px: linear from PERIODS_PX[0] to PERIODS_PX[1]."""
    low, high = PERIODS_PX
    return low + (high - low) * row_px / (SHAPE[0] - 1)


def displacement_px(row_px: np.ndarray, col_px: np.ndarray) -> np.ndarray:
    """u(row, col), px along rows."""
    centre = (SHAPE[1] - 1) / 2.0
    return AMPLITUDE_PX * np.cos(2.0 * np.pi * (col_px - centre) / period_px(row_px))


def star_pair(texture: str, *, seed: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(first, second, true disparity) of the star with `texture` ("speckle" or "sem")."""
    fine_shape = (SHAPE[0] * FACTOR, SHAPE[1] * FACTOR)
    if texture == "speckle":
        fine = textures.speckle_texture(fine_shape, speckle_px=SPECKLE_PX * FACTOR, seed=seed)
    else:
        fine = textures.sem_texture(fine_shape, pixel_size_um=PIXEL_SIZE_UM / FACTOR, seed=seed)
    return textures.displaced_pair(fine, displacement_px, factor=FACTOR, noise_fraction=NOISE_FRACTION, seed=seed)


def matched_px(method: str, first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """The disparity `method` finds, (rows, cols) float32 px, NaN where it gives none."""
    if method == "sgbm":
        return sgbm_disparity(first, second, min_px=-SEARCH_PX, max_px=SEARCH_PX, block_px=5, uniqueness_percent=5)
    return match_disparity(first, second, max_disparity_px=SEARCH_PX, method=method).disparity_px


def scores(measured_px: np.ndarray, truth_px: np.ndarray) -> dict:
    """Amplitude measured per band of rows, spatial resolution, noise and valid share (see the
    module docstring)."""
    rows, cols = truth_px.shape
    inner = (slice(BORDER_PX, rows - BORDER_PX), slice(BORDER_PX, cols - BORDER_PX))
    measured, truth = measured_px[inner].astype(np.float64), truth_px[inner]
    offset = np.nanmedian(measured - truth)
    periods, amplitudes = [], []
    per_row_px = (PERIODS_PX[1] - PERIODS_PX[0]) / (rows - 1)
    top = 0
    while top < measured.shape[0]:
        band_rows = max(BAND_MIN_ROWS, int(BAND_PERIOD_SPAN * period_px(np.array(BORDER_PX + top)) / per_row_px))
        band = slice(top, top + band_rows)
        top += band_rows
        known = np.isfinite(measured[band])
        periods.append(float(np.mean(period_px(BORDER_PX + np.arange(rows)[band][: known.shape[0]]))))
        if known.mean() < 0.5:
            amplitudes.append(float("nan"))
            continue
        m, t = measured[band][known] - offset, truth[band][known]
        t_centred = t - t.mean()
        amplitudes.append(float(np.dot(m - m.mean(), t_centred) / np.dot(t_centred, t_centred)))
    periods, amplitudes = np.array(periods), np.array(amplitudes)
    failing = ~(np.abs(amplitudes - 1.0) <= WITHIN)
    if failing[-1]:
        resolution = float("nan")  # even the longest period is not measured within 10 %
    else:
        resolution = float(periods[np.nonzero(failing)[0].max() + 1]) if failing.any() else float(periods[0])
    long_rows = period_px(np.arange(rows)[inner[0]]) >= LONG_PERIOD_PX
    error = (measured - offset - truth)[long_rows]
    noise = float(np.sqrt(np.nanmean(error**2)))
    return {
        "resolution_px": resolution,
        "noise_px": noise,
        "product_px2": resolution * noise,
        "valid_fraction": float(np.isfinite(measured).mean()),
        "periods_px": periods.tolist(),
        "amplitudes": amplitudes.tolist(),
    }


def run(texture: str, methods: tuple[str, ...]) -> dict:
    first, second, truth = star_pair(texture)
    rows = {}
    for method in methods:
        started = time.perf_counter()
        measured = matched_px(method, first, second)
        rows[method] = {"seconds": time.perf_counter() - started, **scores(measured, truth)}
    return rows


def _print(texture: str, rows: dict) -> None:
    print(
        f"\n{texture}: star pattern {SHAPE[0]} × {SHAPE[1]} px, {AMPLITUDE_PX} px amplitude, {NOISE_FRACTION:.0%} noise"
    )
    print(f"{'method':<14}{'resolution px':>15}{'noise px':>10}{'res × noise px²':>17}{'valid %':>9}{'seconds':>9}")
    for method, row in rows.items():
        print(
            f"{method:<14}{row['resolution_px']:>15.1f}{row['noise_px']:>10.4f}{row['product_px2']:>17.3f}"
            f"{100 * row['valid_fraction']:>9.1f}{row['seconds']:>9.2f}"
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--textures", nargs="+", default=["speckle", "sem"], choices=["speckle", "sem"])
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    args = parser.parse_args()
    results = {}
    for texture in args.textures:
        results[texture] = run(texture, tuple(args.methods))
        _print(texture, results[texture])
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "star.json").write_text(json.dumps(results, indent=1))
    print(
        f"resolution: the shortest period from which every longer one is measured within {WITHIN:.0%}; noise: RMS "
        f"error at periods ≥ {LONG_PERIOD_PX:g} px. Written to {out / 'star.json'}"
    )


if __name__ == "__main__":
    main()
