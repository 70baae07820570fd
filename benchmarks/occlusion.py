"""How often the occlusion cue (`stereo.occlusion`) tells the relief's sign, and how often wrongly.

Each case renders a surface (synthetic.wall_surface's particles, steps and pits, or a reference
surface) at 0.1 µm/px, 2 % noise, at one of the tilt pairs ±5°, ∓5°, 0/5° and 5/0°, with one of the
renderer's physics (the default, the PHYSICS_VARIANTS, and "in_lens": the default with
detector_strength 0), matches it as the height map request does (global alignment, the second view
resampled onto the first's grid, the default method over a quarter of the width, before photometric
fusion) and asks the cue
with the tilts stated as rendered and with their signs reversed. A verdict is right when it is
decisive and says "inverted" exactly when the tilts were reversed, wrong when decisive otherwise,
undecided when not decisive.

    python -m benchmarks.occlusion --seeds 2 [--kinds particles,pits] [--physics default,texture_only]

Writes bench-results/occlusion.json and prints one line per surface and physics.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
from pathlib import Path

import numpy as np

from fractoscope import synthetic
from fractoscope.stereo import alignment, matching, occlusion

TILT_PAIRS_DEG = ((-5.0, 5.0), (5.0, -5.0), (0.0, 5.0), (5.0, 0.0))
WALL_SIZE_PX, REFERENCE_SIZE_PX = 512, 384
PHYSICS = {
    "default": synthetic.DEFAULT_PHYSICS,
    "in_lens": dataclasses.replace(synthetic.DEFAULT_PHYSICS, detector_strength=0.0),
    **synthetic.PHYSICS_VARIANTS,
}
KINDS = (*synthetic.WALL_MORPHOLOGIES, *synthetic.REFERENCE_SURFACES)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("bench-results"))
    parser.add_argument("--seeds", type=int, default=2, help="surface seeds per tilt pair (default 2)")
    parser.add_argument("--kinds", default=",".join(KINDS), help="surfaces, comma-separated")
    parser.add_argument("--physics", default=",".join(PHYSICS), help="renderers, comma-separated")
    args = parser.parse_args()
    results = {}
    for kind in args.kinds.split(","):
        for physics in args.physics.split(","):
            counts = {"right": 0, "wrong": 0, "undecided": 0}
            right_per_pair = {f"{first:g}/{second:g}": 0 for first, second in TILT_PAIRS_DEG}
            for seed in range(1, args.seeds + 1):
                for pair, tilt_deg in zip(list(right_per_pair), TILT_PAIRS_DEG):
                    for outcome in outcomes(kind, PHYSICS[physics], tilt_deg, seed):
                        counts[outcome] += 1
                        right_per_pair[pair] += outcome == "right"
            results[f"{kind}/{physics}"] = {**counts, "right_per_tilt_pair": right_per_pair}
            per_pair = " ".join(f"{pair}: {n}" for pair, n in right_per_pair.items())
            print(
                f"{kind:14s} {physics:28s} " + "  ".join(f"{name} {n:3d}" for name, n in counts.items()),
                f"(right per tilt pair {per_pair})",
                flush=True,
            )
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "occlusion.json").write_text(json.dumps(results, indent=1))


def outcomes(kind: str, physics: synthetic.SemPhysics, tilt_deg: tuple[float, float], seed: int) -> list[str]:
    """The outcomes with the tilts stated as rendered and reversed (see the module docstring)."""
    votes = occlusion.wall_votes(*matched_pair(kind, physics, tilt_deg, seed))
    step = np.sign(tilt_deg[1] - tilt_deg[0])
    found = []
    for reversed_ in (False, True):
        told = occlusion.verdict(votes, tilt_step_sign=-step if reversed_ else step)
        found.append("undecided" if not told.decided else "right" if told.inverted == reversed_ else "wrong")
    return found


def matched_pair(kind: str, physics: synthetic.SemPhysics, tilt_deg, seed: int):
    """A rendered pair matched as the height map request matches it: (reference, the second view
    on the reference's grid, the default method's disparities), (rows, cols) float32."""
    size_px = WALL_SIZE_PX if kind in synthetic.WALL_MORPHOLOGIES else REFERENCE_SIZE_PX
    pair = synthetic.render_surface_pair(kind, size_px, tilt_deg=tilt_deg, seed=seed, physics=physics)
    reference, second = pair.first.astype(np.float32), pair.second.astype(np.float32)
    placement = alignment.estimate_alignment(reference, second)
    on_first = alignment.apply_affine(
        second, alignment.second_to_first_matrix(placement, reference.shape), reference.shape, inverse=True
    )
    # The request's search range comes from the features' parallax spread, which on particles
    # whose features lie mostly on the substrate misses their tops: search a quarter of the width.
    matched = matching.match_disparity(
        reference, on_first, max_disparity_px=matching.default_max_disparity_px(reference.shape[1])
    )
    return reference, on_first, matched.disparity_px


if __name__ == "__main__":
    main()
