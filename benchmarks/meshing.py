"""`make bench` (meshing): a 4096² height map to its full chain of levels, timed, with the
size of the coarsest level and each level's measured geometric error.

Writes bench-results/meshing.json and prints a table.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from fractoscope import synthetic
from fractoscope.mesh.levels import Simplification
from fractoscope.mesh.pipeline import MeshingOptions, mesh_height_map

PIXEL_SIZE_UM = 0.1
TIMING_REPEATS = 2


def height_map(size_px: int) -> tuple[np.ndarray, np.ndarray]:
    """A self-affine fracture surface with 1 % of unknown points in small holes, and its texture."""
    z_um = synthetic.self_affine_surface((size_px, size_px), hurst=0.8, rms_um=3.0, seed=7).astype(np.float32)
    rng = np.random.default_rng(7)
    for row, col in rng.integers(0, size_px - 12, size=(size_px * size_px // 10_000, 2)):
        z_um[row : row + 10, col : col + 10] = np.nan
    texture = np.clip((np.nan_to_num(z_um) - np.nanmin(z_um)) / np.nanmax(z_um - np.nanmin(z_um)) * 255, 0, 255).astype(
        np.uint8
    )
    return z_um, texture


def run(size_px: int, method: Simplification) -> dict:
    z_um, texture = height_map(size_px)
    seconds = []
    for _ in range(TIMING_REPEATS):  # the fastest run: shared machines add noise, never speed
        started = time.perf_counter()
        tiles, report = mesh_height_map(
            z_um, texture, pixel_size_um=PIXEL_SIZE_UM, options=MeshingOptions(method=method)
        )
        seconds.append(time.perf_counter() - started)
    levels = sorted({tile.level for tile in tiles})
    per_level = [
        {
            "level": level,
            "tiles": sum(1 for t in tiles if t.level == level),
            "triangles": sum(t.triangle_count for t in tiles if t.level == level),
            "bytes": sum(len(t.glb) for t in tiles if t.level == level),
            "geometric_error_um": max(t.geometric_error_m for t in tiles if t.level == level) * 1e6,
        }
        for level in levels
    ]
    errors = [row["geometric_error_um"] for row in per_level]
    return {
        "size_px": size_px,
        "method": method.value,
        "seconds": min(seconds),
        "levels": per_level,
        "coarsest_level_bytes": per_level[-1]["bytes"],
        "errors_monotone": all(a < b for a, b in zip(errors, errors[1:])),
        "filter": vars(report),
    }


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="bench-results")
    parser.add_argument("--size-px", type=int, default=4096)
    args = parser.parse_args()
    results = [run(args.size_px, Simplification.VERTEX_CLUSTERING), run(args.size_px // 2, Simplification.QUADRIC)]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "meshing.json").write_text(json.dumps(results, indent=2))
    for result in results:
        print(
            f"{result['size_px']}² {result['method']}: {result['seconds']:.2f} s, coarsest level "
            f"{result['coarsest_level_bytes'] / 1024:.0f} KB, errors monotone: {result['errors_monotone']}"
        )
        for row in result["levels"]:
            print(
                f"  level {row['level']}: {row['tiles']:4d} tiles {row['triangles']:10d} triangles "
                f"{row['bytes'] / 1e6:9.2f} MB  max error {row['geometric_error_um']:.4f} µm"
            )
    print(f"written to {out / 'meshing.json'}")


if __name__ == "__main__":
    main()
