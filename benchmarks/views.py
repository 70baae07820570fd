"""`make bench`: what extra views of a tilt series add (issue 37, item 3).

One surface rendered at -5, -2.5, 0, 2.5 and 5° (synthetic.render_tilt_series, 0.1 µm/px, 2 %
noise per image); its ±5° pair alone, the -5/0/+5° series and all five views, each measured
by the default method with the nominal tilts. RMS error after the mean offset, % of the true
height range, 16 px border left out (synthetic.height_errors), each series' ratio to its pair,
and the share of pixels whose height rests on every view (HeightMapResult.views_used).

Writes bench-results/views.json and prints the table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo.pipeline import compute_series_height_map

TILTS_DEG = (-5.0, -2.5, 0.0, 2.5, 5.0)
# The views of each row, indices into TILTS_DEG: the pair alone first, the ratios are to it.
SUBSETS = {"pair": (0, 4), "three": (0, 2, 4), "five": (0, 1, 2, 3, 4)}
MARGIN_PX = 64
BORDER_PX = 16


def series_row(kind: str, size_px: int, seed: int) -> dict:
    """The figures of one rendered series: per subset its RMS error (% of range), valid share,
    share of pixels that every view of it measured, and time (s, on whatever machine runs it)."""
    surface = synthetic.reference_surface(kind, size_px + MARGIN_PX, seed=seed)
    images, truth = synthetic.render_tilt_series(
        surface,
        pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM,
        tilt_deg=TILTS_DEG,
        output_shape=(size_px, size_px),
        seed=seed,
    )
    row = {"surface": kind, "size_px": size_px, "seed": seed}
    for name, subset in SUBSETS.items():
        started = time.perf_counter()
        result = compute_series_height_map(
            [SemImage(images[i], None, synthetic.REFERENCE_PIXEL_SIZE_UM, 0) for i in subset],
            tilt_deg=[TILTS_DEG[i] for i in subset],
        )
        errors = synthetic.height_errors(result.z_um, truth, border_px=BORDER_PX)
        row[name] = {
            "rms_percent_of_range": 100 * errors.rms_of_range,
            "valid_percent": 100 * errors.valid_fraction,
            "all_views_percent": 100 * float(np.mean(result.views_used == len(subset))),
            "elapsed_s": time.perf_counter() - started,
        }
    return row


def _print(rows: list[dict], out: Path) -> None:
    print(f"{'surface':<12}{'size':>6}{'seed':>6}{'±5° pair':>10}{'3 views':>17}{'5 views':>17}{'all 5 used':>12}")
    for row in rows:
        pair = row["pair"]["rms_percent_of_range"]
        cells = "".join(
            f"{row[name]['rms_percent_of_range']:>8.3f} % {row[name]['rms_percent_of_range'] / pair:>5.3f}x"
            for name in ("three", "five")
        )
        print(
            f"{row['surface']:<12}{row['size_px']:>6}{row['seed']:>6}{pair:>8.3f} %{cells}"
            f"{row['five']['all_views_percent']:>10.1f} %"
        )
    for name in ("three", "five"):
        ratios = [row[name]["rms_percent_of_range"] / row["pair"]["rms_percent_of_range"] for row in rows]
        print(f"{name} views / pair: mean {np.mean(ratios):.3f}x, worst {np.max(ratios):.3f}x over {len(rows)} series")
    print("RMS error after the mean offset, % of the true height range; x: ratio to the ±5° pair of the same images.")
    print(f"Written to {out / 'views.json'}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default="bench-results")
    parser.add_argument(
        "--surfaces", nargs="+", default=["dimples", "self_affine"], choices=synthetic.REFERENCE_SURFACES
    )
    parser.add_argument("--sizes", nargs="+", type=int, default=[640])
    parser.add_argument("--seeds", nargs="+", type=int, default=[1, 2, 3])
    args = parser.parse_args()
    rows = [series_row(kind, size, seed) for kind in args.surfaces for size in args.sizes for seed in args.seeds]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "views.json").write_text(json.dumps({"tilt_deg": TILTS_DEG, "rows": rows}, indent=1))
    _print(rows, out)


if __name__ == "__main__":
    main()
