"""`make bench` (page faults): what keep_freed_memory saves. A 512² pair is matched in a fresh
interpreter, with the C library's defaults and with the setting (which fracto-server, `make run`
and in-process `fracto` commands call; why: its docstring), and the minor page faults of a second
match are counted. The count depends on the machine and its load (measured 23 with the setting
and 8,800 without on an idle one), so it is a figure to watch, not a test.

Writes bench-results/page_faults.json and prints the figures.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

_PROBE = (
    "import json, resource, numpy as np, cv2; from fractoscope.stereo.matching import match_disparity;from "
    "fractoscope.runtime.process import keep_freed_memory;{setting}image = "
    "cv2.GaussianBlur((np.random.default_rng(0).random((512, 512)) * 255).astype(np.uint8), (0, 0), 1.5);pair = "
    "(image, np.roll(image, 3, axis=1)); match_disparity(*pair, max_disparity_px=16);before = "
    "resource.getrusage(resource.RUSAGE_SELF).ru_minflt; match_disparity(*pair, "
    "max_disparity_px=16);print(json.dumps(resource.getrusage(resource.RUSAGE_SELF).ru_minflt - before))"
)


def page_faults(keep: bool) -> int:
    """Minor page faults of one 512² match after a first one, in a fresh interpreter."""
    probe = _PROBE.format(setting="keep_freed_memory();" if keep else "")
    return json.loads(subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True).stdout)


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--out", default="bench-results")
    args = parser.parse_args()
    result = {
        "pair_px": 512,
        "page_faults_with_keep_freed_memory": page_faults(keep=True),
        "page_faults_with_defaults": page_faults(keep=False),
    }
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "page_faults.json").write_text(json.dumps(result, indent=2))
    print(
        f"512² match: {result['page_faults_with_keep_freed_memory']} page faults with keep_freed_memory, "
        f"{result['page_faults_with_defaults']} with the C library's defaults"
    )
    print(f"written to {out / 'page_faults.json'}")


if __name__ == "__main__":
    main()
