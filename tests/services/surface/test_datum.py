"""Height datums: zero on a plane through everything, on the substrate, or on a region."""

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.sem.image import read_sem_image
from fractoscope.stereo import geometry
from fractoscope.stereo.pipeline import compute_height_map
from fractoscope.surface.datum import MAX_RESIDUAL_SIGMAS, level_heights
from fractoscope.surface.filtering import filter_heights

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
    sigma_um = np.full(z.shape, 0.05, np.float32)
    levelled, datum = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="substrate", sigma_um=sigma_um)
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
    # The figures that tell it is a measured level: a measured share of the map, residuals at the
    # 0.05 µm noise, the substrate's tilt.
    assert datum.area_fraction == pytest.approx((off_grain.sum()) / z.size, abs=0.03) and datum.measured_fraction == 1
    assert datum.residual_rms_um == pytest.approx(0.05, abs=0.005) and datum.sigma_um == pytest.approx(0.05)
    assert datum.tilt_deg == pytest.approx(np.degrees(np.arctan(np.hypot(0.05, 0.02))), abs=0.05)
    assert datum.requested == "substrate" and datum.warning == ""


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


def _refused_substrate(z, sigma_um, **options):
    """The substrate datum of a scene that has none: the plane datum, with the warning and figures
    that say so, and the same scene refused when strict."""
    levelled, datum = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="substrate", sigma_um=sigma_um, **options)
    plane_levelled, plane = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="plane", sigma_um=sigma_um, **options)
    assert datum.level == "plane" and datum.requested == "substrate" and "no measured substrate" in datum.warning
    assert np.array_equal(levelled, plane_levelled, equal_nan=True) and datum.offset_um == plane.offset_um
    with pytest.raises(ValueError, match="no measured substrate"):
        level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="substrate", sigma_um=sigma_um, strict=True, **options)
    return datum


def test_a_rough_surface_has_no_substrate():
    """No flat level at all: the lowest fifth grows into the whole rough surface, whose heights
    scatter by some 20 sigmas about its plane."""
    z = synthetic.self_affine_surface((256, 256), hurst=0.8, rms_um=1.0, seed=7, max_wavelength_px=128)
    z = (z + np.random.default_rng(1).normal(0, 0.05, z.shape)).astype(np.float32)
    datum = _refused_substrate(z, np.full(z.shape, 0.05, np.float32))
    assert datum.residual_rms_um > 10 * datum.sigma_um and "times their sigma" in datum.warning


def test_a_grain_on_a_barely_measured_background_has_no_substrate():
    """The failure seen on real data: 3 % of a featureless background measured, the grain all
    measured; the substrate search took every measured point (the grain included) as the level."""
    z, dome = _grain_on_a_tilted_substrate()
    z[(dome == 0) & (np.random.default_rng(5).random(z.shape) > 0.03)] = np.nan
    datum = _refused_substrate(z, np.full(z.shape, 0.05, np.float32))
    assert datum.residual_rms_um > MAX_RESIDUAL_SIGMAS * datum.sigma_um


def test_a_filled_background_is_no_substrate():
    """The background measured at 4 % of its points and filled in between (surface.filtering): a
    smooth, flat, extensive level, but made of interpolations."""
    z, dome = _grain_on_a_tilted_substrate()
    z[(dome == 0) & (np.random.default_rng(5).random(z.shape) > 0.04)] = np.nan
    filtered = filter_heights(z)
    datum = _refused_substrate(filtered.z_um, None, filled=filtered.filled)
    assert "% of the map is measured on it" in datum.warning and np.isnan(datum.sigma_um)


def test_a_region_that_is_no_level_is_said_to_be_one_not():
    """A region datum stays where the user put it, with a warning when it is no level."""
    z, _ = _grain_on_a_tilted_substrate()
    _, datum = level_heights(
        z, pixel_size_um=PIXEL_SIZE_UM, level=(10.0, 10.0, 20.0, 20.0), sigma_um=np.full(z.shape, 0.05, np.float32)
    )
    assert datum.level == "region" and datum.warning.startswith("the region is no measured level")


@pytest.mark.slow
@pytest.mark.real_data
def test_the_real_pollen_substrate_is_the_plane_fitted_by_hand(pollen_series):
    """The ±3° pollen pair (pot_02, pot_04): the substrate datum is within 1° of the plane fitted by
    hand to the points over 700 px from the grain's centre (row 1070, column 730; see
    stereo/test_real_series.py), and its figures say it is a measured level (measured: 0.10°
    apart, 48 % of the map, residual 0.67 µm RMS against a sigma of 0.39 µm, tilt 0.21°)."""
    images = [read_sem_image((pollen_series / f"pot_0{i}.tif").read_bytes()) for i in (2, 4)]
    result = compute_height_map(*images)
    report = result.report
    noise_um = geometry.matching_sigma_um(
        result.z_um,
        result.sigma_um,
        relative_height_error=geometry.series_relative_height_error(
            report["tilt_deg"], tilt_uncertainty_deg=report["tilt_uncertainty_deg"]
        ),
    )
    pixel_size_um = report["pixel_size_um"]
    _, datum = level_heights(result.z_um, pixel_size_um=pixel_size_um, level="substrate", sigma_um=noise_um)
    rows, cols = np.indices(result.z_um.shape)
    by_hand = np.isfinite(result.z_um) & (np.hypot(rows - 1070, cols - 730) > 700)
    design = np.column_stack([cols[by_hand] * pixel_size_um, rows[by_hand] * pixel_size_um, np.ones(by_hand.sum())])
    (slope_x, slope_y, _), *_ = np.linalg.lstsq(design, result.z_um[by_hand].astype(np.float64), rcond=None)
    normals = np.array([[-datum.slope_x, -datum.slope_y, 1.0], [-slope_x, -slope_y, 1.0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    assert datum.level == "substrate" and datum.warning == ""
    assert np.degrees(np.arccos(min(normals[0] @ normals[1], 1.0))) < 1.0
    assert datum.area_fraction > 0.3 and datum.measured_fraction == 1.0 and datum.tilt_deg < 2.0
    assert datum.residual_rms_um < MAX_RESIDUAL_SIGMAS * datum.sigma_um
