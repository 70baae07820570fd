"""Building a specimen in-process (matching and meshing passed in): the overview's datum."""

import math

import numpy as np
import pytest

from fractoscope.reconstruction.build import MeasuredHeights, RoiRequest, reconstruct_specimen
from fractoscope.store.folder import SpecimenStore
from fractoscope.tiles.messages import specimen_message

PIXEL_SIZE_UM = 0.1


def _grain(*, background_measured: float, size: int = 160, seed: int = 4) -> MeasuredHeights:
    """A 15 µm dome on a substrate tilted by 0.03 in x, 0.05 µm of noise (its sigma), with
    `background_measured` of the substrate's points measured; tilts ±5° known exactly."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size] * PIXEL_SIZE_UM
    dome = 15.0 * np.sqrt(np.clip(1 - ((cols - 8) ** 2 + (rows - 8) ** 2) / 5.0**2, 0, None))
    z = (0.03 * cols + dome + rng.normal(0, 0.05, rows.shape)).astype(np.float32)
    z[(dome == 0) & (rng.random(z.shape) > background_measured)] = np.nan
    report = {"tilt_deg": [-5.0, 5.0], "tilt_uncertainty_deg": 0.0, "warnings": []}
    texture = rng.integers(0, 255, z.shape, dtype=np.uint8)
    return MeasuredHeights(z, texture, PIXEL_SIZE_UM, report, sigma_um=np.full(z.shape, 0.05, np.float32))


@pytest.mark.parametrize("background_measured", [1.0, 0.03])
def test_the_overview_datum_is_a_measured_substrate_or_says_it_is_not(tmp_path, background_measured):
    """A measured substrate is the datum, with its figures in the stored ROI and the specimen
    summary; a barely measured one (3 % of its points, filled in between) gives the plane datum
    with a warning, and the summary says "plane", never "substrate"."""
    heights = _grain(background_measured=background_measured)
    specimen = reconstruct_specimen(
        "grain",
        [RoiRequest("overview", level="substrate")],
        measure=lambda roi, progress: heights,
        mesh_tile=lambda samples: b"glb",
        store=SpecimenStore(tmp_path),
    )
    stored = specimen.rois[0].datum
    summary = specimen_message(specimen).rois[0]
    assert summary.datum.requested == "substrate"
    if background_measured == 1.0:
        assert summary.level == stored["level"] == "substrate" and not stored["warning"]
        assert stored["slope_x"] == pytest.approx(0.03, abs=1e-3) and stored["measured_fraction"] > 0.95
        assert stored["residual_rms_um"] == pytest.approx(0.05, abs=0.01)
        assert summary.datum.sigma_um == pytest.approx(0.05)
        assert summary.datum.residual_rms_um == stored["residual_rms_um"]
    else:  # lone measured points, which the filter takes for outliers: nothing to rest a plane on
        assert summary.level == stored["level"] == "none" and "no measured substrate" in summary.datum.warning
        assert "left as measured" in stored["warning"] and math.isnan(summary.datum.residual_rms_um)
        coverage = specimen.rois[0].coverage
        assert summary.coverage.measured_fraction == coverage["measured_fraction"] < 0.4
