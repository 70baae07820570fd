"""The example specimen of the demo and the tests, written as a user would give it: PNG pairs and
a specimen manifest (see client.manifest)."""

from __future__ import annotations

import json
from pathlib import Path

import cv2

from fractoscope.synthetic.rendering import MultiscaleSpecimen, render_multiscale_specimen

MULTISCALE_MAGNIFICATIONS = (100.0, 400.0)


def write_multiscale_specimen(directory: Path, *, specimen_id: str = "synthetic") -> MultiscaleSpecimen:
    """Renders the multi-scale demo specimen (an overview at 1 µm/px and a 4x ROI, placed
    automatically) as PNG pairs with `manifest.json` in `directory`; returns the truth."""
    spec = render_multiscale_specimen()
    directory.mkdir(parents=True, exist_ok=True)
    rois = []
    for roi_id, pair, pixel_um, magnification in [
        ("overview", spec.overview, spec.overview_pixel_size_um, MULTISCALE_MAGNIFICATIONS[0]),
        ("zoom", spec.roi, spec.roi_pixel_size_um, MULTISCALE_MAGNIFICATIONS[1]),
    ]:
        cv2.imwrite(str(directory / f"{roi_id}_left.png"), pair.first)
        cv2.imwrite(str(directory / f"{roi_id}_right.png"), pair.second)
        rois.append(
            {
                "id": roi_id,
                "left": f"{roi_id}_left.png",
                "right": f"{roi_id}_right.png",
                "tilt_deg": list(spec.tilt_deg),
                "pixel_size_um": pixel_um,
                "magnification": magnification,
            }
        )
    rois[1].update(parent="overview", center_um="auto")
    (directory / "manifest.json").write_text(json.dumps({"specimen": specimen_id, "rois": rois}, indent=1))
    return spec
