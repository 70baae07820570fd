"""`make bench`: how often `relief_sign=auto` puts the relief the right way up, per detector
azimuth, morphology and cue (issue 46).

Renderers stand in for other microscopes: a side detector in the chamber at 8 azimuths as
displayed (0°: the image's right, 90°: its top) and an in-lens one (no side). Cases are 256² at
0.1 µm/px, 2 % noise; case s renders the surface of seed s at one of the tilt pairs ±5°, ∓5°,
0/5°, 5/0° (s mod 4). Each case runs the full height-map request with the default method:

- "typed as rendered, no detector": must never be inverted (`inverted` counts the decisive
  verdicts that turned correct tilts round);
- "typed reversed, no detector": what geometry alone corrects (occlusion);
- "typed reversed, detector given" (where it has a side): what the lighting corrects.

A result is right when its heights correlate positively with the truth. `wrong` counts decisive
verdicts whose heights are upside down (confidently wrong); `kept` undecided ones that kept the
tilts as given. Writes bench-results/relief_sign.json and prints the tables.
"""

from __future__ import annotations

import argparse
import json
from collections import Counter
from pathlib import Path

import numpy as np

from fractoscope import synthetic
from fractoscope.errors import InvalidInputError
from fractoscope.sem.image import SemImage
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_series_height_map
from fractoscope.synthetic.physics import SemPhysics

TILT_PAIRS_DEG = ((-5.0, 5.0), (5.0, -5.0), (0.0, 5.0), (5.0, 0.0))
SIZE_PX, MARGIN_PX, PIXEL_SIZE_UM = 256, 64, 0.1
AZIMUTHS_DEG = tuple(range(0, 360, 45))


def renderers() -> dict[str, SemPhysics]:
    """The detector placements measured: a side detector at each of AZIMUTHS_DEG, and in-lens."""
    sides = {
        f"side {azimuth:3d}°": SemPhysics(
            detector_azimuth_deg=float(azimuth), detector_in_chamber=True, detector_strength=0.5
        )
        for azimuth in AZIMUTHS_DEG
    }
    return sides | {"in-lens": SemPhysics(detector_strength=0.0)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench-results"))
    parser.add_argument("--seeds", type=int, default=8, help="seeded cases per renderer and surface (default 8)")
    parser.add_argument(
        "--surfaces",
        nargs="+",
        default=list(synthetic.REFERENCE_SURFACES),
        help="surfaces (synthetic.surface: the reference ones, or particles, sharp_steps, rounded_steps, pits; "
        "benchmarks.occlusion measures those at 512²)",
    )
    args = parser.parse_args()
    results = {}
    for name, physics in renderers().items():
        for kind in args.surfaces:
            counts = {condition: Counter() for condition in CONDITIONS}
            for seed in range(args.seeds):
                for condition, (outcome, cue) in cases(kind, seed, physics).items():
                    counts[condition][outcome] += 1
                    counts[condition][f"by {cue}"] += outcome in ("right", "corrected")
            results[f"{name} / {kind}"] = {condition: dict(count) for condition, count in counts.items()}
            print(f"{name:10s} {kind:12s} " + "  |  ".join(_line(c, counts[c]) for c in CONDITIONS), flush=True)
    totals = {condition: Counter() for condition in CONDITIONS}
    for entry in results.values():
        for condition, count in entry.items():
            totals[condition].update(count)
    print("all cases            " + "  |  ".join(_line(c, totals[c]) for c in CONDITIONS))
    args.out.mkdir(parents=True, exist_ok=True)
    document = {"cases": results, "totals": {c: dict(t) for c, t in totals.items()}}
    (args.out / "relief_sign.json").write_text(json.dumps(document, indent=1))


CONDITIONS = ("as rendered, no detector", "reversed, no detector", "reversed, detector given")


def _line(condition: str, count: Counter) -> str:
    keys = ("right", "inverted", "kept") if condition.startswith("as rendered") else ("corrected", "wrong", "kept")
    cues = ", ".join(f"{key[3:]} {value}" for key, value in sorted(count.items()) if key.startswith("by ") and value)
    return f"{condition}: " + " ".join(f"{key} {count.get(key, 0)}" for key in keys) + (f" ({cues})" if cues else "")


def cases(kind: str, seed: int, physics: SemPhysics) -> dict[str, tuple[str, str]]:
    """(outcome, cue) of seeded case `seed` of surface `kind` under each of CONDITIONS (the
    detector-given one only for a renderer with a side detector)."""
    tilts = TILT_PAIRS_DEG[seed % 4]
    surface = synthetic.surface(kind, SIZE_PX + MARGIN_PX, seed=1000 + seed)
    pair = synthetic.render_stereo_pair(
        surface,
        pixel_size_um=PIXEL_SIZE_UM,
        tilt_deg=tilts,
        output_shape=(SIZE_PX, SIZE_PX),
        seed=seed,
        physics=physics,
    )
    reversed_tilts = (-tilts[0], -tilts[1])
    place = physics.detector_from_tilt_axis_deg if physics.detector_strength > 0 else None
    runs = {CONDITIONS[0]: (tilts, None), CONDITIONS[1]: (reversed_tilts, None)}
    if place is not None:
        runs[CONDITIONS[2]] = (reversed_tilts, place)
    return {
        condition: _outcome(pair, stated, place, as_rendered=stated == tilts)
        for condition, (stated, place) in runs.items()
    }


def _outcome(pair, stated, place, *, as_rendered: bool) -> tuple[str, str]:
    views = [SemImage(image, tilt, PIXEL_SIZE_UM, 0) for image, tilt in zip((pair.first, pair.second), stated)]
    options = MatchingOptions(detector_from_tilt_axis_deg=float("nan") if place is None else place)
    try:
        result = compute_series_height_map(views, options=options)
    except InvalidInputError:
        return "refused", "none"
    known = np.isfinite(result.z_um)
    right = np.corrcoef(result.z_um[known], pair.z_seen_um[known])[0, 1] > 0
    decided, cue = result.report["relief_sign_decided"], result.report["relief_sign_cue"]
    if as_rendered:
        return ("inverted" if not right else "right" if decided else "kept"), cue
    if right:
        return "corrected", cue
    return ("wrong" if decided else "kept"), cue


if __name__ == "__main__":
    main()
