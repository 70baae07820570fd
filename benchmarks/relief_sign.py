"""`make bench`: how often `relief_sign=auto` puts the relief the right way up.

For each reference surface (synthetic.reference_surface: self-affine, dimples, cleavage), seeded
cases of 256² at 0.1 µm/px, 2 % noise: case s renders the surface of seed s at one of the tilt
pairs ±5°, ∓5°, 0/5° and 5/0° (s mod 4) and states the tilts as rendered or with their signs
reversed (s div 4 mod 2; the same as swapped images or an axis 180° off). The full height map
request runs with the default method; a case is right when its verdict is decisive and its
heights correlate positively with the truth, wrong when decisive and negatively, and undecided
otherwise (the tilts as given kept, with a warning); refused where the request is refused (a pair
of which nothing matched).

Writes bench-results/relief_sign.json and prints the table.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from fractoscope import synthetic
from fractoscope.errors import InvalidInputError
from fractoscope.sem.image import SemImage
from fractoscope.stereo.pipeline import compute_series_height_map

TILT_PAIRS_DEG = ((-5.0, 5.0), (5.0, -5.0), (0.0, 5.0), (5.0, 0.0))
SIZE_PX, MARGIN_PX, PIXEL_SIZE_UM = 256, 64, 0.1


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench-results"))
    parser.add_argument("--cases", type=int, default=100, help="seeded cases per surface (default 100)")
    args = parser.parse_args()
    results = {}
    for kind in synthetic.REFERENCE_SURFACES:
        counts = {"right": 0, "wrong": 0, "undecided": 0, "refused": 0}
        for seed in range(args.cases):
            counts[outcome(kind, seed)] += 1
        results[kind] = counts
        print(f"{kind:12s} " + "  ".join(f"{name} {count:4d}" for name, count in counts.items()))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "relief_sign.json").write_text(json.dumps(results, indent=1))


def outcome(kind: str, seed: int) -> str:
    """The outcome of seeded case `seed` of surface `kind` (see the module's docstring)."""
    tilts = TILT_PAIRS_DEG[seed % 4]
    stated = tilts if (seed // 4) % 2 == 0 else (-tilts[0], -tilts[1])
    surface = synthetic.reference_surface(kind, SIZE_PX + MARGIN_PX, seed=1000 + seed)
    pair = synthetic.render_stereo_pair(
        surface, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=tilts, output_shape=(SIZE_PX, SIZE_PX), seed=seed
    )
    views = [SemImage(image, tilt, PIXEL_SIZE_UM, 0) for image, tilt in zip((pair.first, pair.second), stated)]
    try:
        result = compute_series_height_map(views)
    except InvalidInputError:
        return "refused"
    if not result.report["relief_sign_decided"]:
        return "undecided"
    known = np.isfinite(result.z_um)
    correlation = np.corrcoef(result.z_um[known], pair.z_seen_um[known])[0, 1]
    return "right" if correlation > 0 else "wrong"


if __name__ == "__main__":
    main()
