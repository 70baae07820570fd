"""Height datums: zero on a plane through everything, on the substrate, or on a region."""

import numpy as np
import pytest

from fractoscope.surface.datum import level_heights

PIXEL_SIZE_UM = 0.1


def _grain_on_a_tilted_substrate(size=300, seed=3):
    """A 20 µm dome (a grain) on a substrate tilted by 0.05 in x and -0.02 in y, 5 µm below the
    measured zero, with 0.05 µm of noise and a third of the points unknown."""
    rng = np.random.default_rng(seed)
    rows, cols = np.mgrid[0:size, 0:size] * PIXEL_SIZE_UM
    substrate = -5.0 + 0.05 * cols - 0.02 * rows
    dome = 20.0 * np.sqrt(np.clip(1 - ((cols - 15) ** 2 + (rows - 15) ** 2) / 8.0**2, 0, None))
    z = (substrate + dome + rng.normal(0, 0.05, rows.shape)).astype(np.float32)
    z[rng.random(z.shape) < 0.33] = np.nan
    return z, dome


def test_the_substrate_datum_puts_zero_on_the_substrate():
    z, dome = _grain_on_a_tilted_substrate()
    levelled, datum = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="substrate")
    known = np.isfinite(z)
    off_grain = known & (dome == 0)
    assert abs(np.median(levelled[off_grain])) < 0.01 and np.std(levelled[off_grain]) < 0.06
    assert np.nanmax(levelled) == pytest.approx(20.0, abs=0.25)  # the grain's height above the substrate
    assert (
        datum.level == "substrate"
        and datum.slope_x == pytest.approx(0.05, abs=1e-3)
        and datum.slope_y == pytest.approx(-0.02, abs=1e-3)
    )
    assert datum.fraction == pytest.approx(off_grain.sum() / known.sum(), abs=0.03)


def test_a_region_datum_and_a_plane_datum():
    z, dome = _grain_on_a_tilted_substrate()
    levelled, datum = level_heights(
        z, pixel_size_um=PIXEL_SIZE_UM, level=(0.0, 0.0, 5.0, 29.9)
    )  # a strip left of the grain
    assert datum.level == "region" and datum.region_um == (0.0, 0.0, 5.0, 29.9)
    assert abs(np.nanmedian(levelled[:, :50])) < 0.01 and np.nanmax(levelled) == pytest.approx(20.0, abs=0.25)
    _, plane = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="plane")
    assert plane.level == "plane" and plane.fraction == 1.0
    with pytest.raises(ValueError, match="at least 3"):
        level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level=(100.0, 100.0, 101.0, 101.0))
    with pytest.raises(ValueError, match="level must be"):
        level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="floor")
