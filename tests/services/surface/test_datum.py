"""Height datums: zero on a plane through everything, on the substrate, or on a region."""

import cv2
import numpy as np
import pytest
from conftest import tiff_bytes

from fractoscope import synthetic
from fractoscope.sem.image import read_sem_image
from fractoscope.stereo import geometry
from fractoscope.stereo.pipeline import compute_height_map
from fractoscope.surface.datum import MAX_RESIDUAL_SIGMAS, level_heights
from fractoscope.surface.filtering import filter_heights
from fractoscope.surface.measurement import measurement
from fractoscope.synthetic.particles import particle_scene

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


def _refused_substrate(z, sigma_um, *, instead: str, **options):
    """The substrate datum of a scene that has none: `instead` ("background" or "none"), with the
    warning that says so and which, never the plane through all heights; refused when strict."""
    levelled, datum = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="substrate", sigma_um=sigma_um, **options)
    assert datum.level == instead and datum.requested == "substrate" and "no measured substrate" in datum.warning
    if instead == "none":
        assert np.array_equal(levelled, z, equal_nan=True) and datum.tilt_deg == 0 and datum.offset_um == 0
        assert "left as measured" in datum.warning
    else:
        assert "background plane" in datum.warning
    with pytest.raises(ValueError, match="no measured substrate"):
        level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="substrate", sigma_um=sigma_um, strict=True, **options)
    return levelled, datum


def test_a_rough_surface_has_no_substrate_and_is_left_as_measured():
    """No flat level at all: the lowest fifth grows into the whole rough surface, whose heights
    scatter by some 20 sigmas about its plane, and no plane lies under it all."""
    z = synthetic.self_affine_surface((256, 256), hurst=0.8, rms_um=1.0, seed=7, max_wavelength_px=128)
    z = (z + np.random.default_rng(1).normal(0, 0.05, z.shape)).astype(np.float32)
    _, datum = _refused_substrate(z, np.full(z.shape, 0.05, np.float32), instead="none")
    assert "times their sigma" in datum.warning and datum.to_dict()["residual_rms_um"] is None


def test_a_grain_on_a_barely_measured_background_is_left_as_measured():
    """The failure seen on real data: 3 % of a featureless background measured, the grain all
    measured; the substrate search took every measured point (the grain included) as the level,
    and the plane through all heights went through the grain. So few heights carry no plane:
    the heights stay as measured, whose tilt is the stage's (here the substrate's 3.1°)."""
    z, dome = _grain_on_a_tilted_substrate()
    z[(dome == 0) & (np.random.default_rng(5).random(z.shape) > 0.03)] = np.nan
    _, datum = _refused_substrate(z, np.full(z.shape, 0.05, np.float32), instead="none")
    _, plane = level_heights(z, pixel_size_um=PIXEL_SIZE_UM, level="plane")
    assert _angle_deg(plane, 0.05, -0.02) > 1.0  # what the old fallback did


def test_a_large_grain_is_levelled_on_the_background_around_it():
    """A grain filling most of the field, the substrate measured only in the corners (5 % of the
    map, too little for a substrate): the background plane rests on the corners' blocks and is
    the substrate's within 0.1°, under the grain, which stands 20 µm high on it."""
    z, dome = _grain_on_a_tilted_substrate()
    rows, cols = np.mgrid[0:300, 0:300] * PIXEL_SIZE_UM
    big = 20.0 * np.sqrt(np.clip(1 - ((cols - 15) ** 2 + (rows - 15) ** 2) / 16.5**2, 0, None))
    z = np.where(big > 0, z - dome + big, z)
    around = np.isnan(z) & (big == 0)
    z[around] = (-5.0 + 0.05 * cols - 0.02 * rows)[around]  # the background measured wherever it shows
    levelled, datum = _refused_substrate(z, np.full(z.shape, 0.05, np.float32), instead="background")
    assert _angle_deg(datum, 0.05, -0.02) < 0.1 and np.nanmax(levelled) == pytest.approx(20.0, abs=0.3)


def _angle_deg(datum, slope_x: float, slope_y: float) -> float:
    """The angle between a datum's plane and a plane of the given slopes, degrees."""
    normals = np.array([[-datum.slope_x, -datum.slope_y, 1.0], [-slope_x, -slope_y, 1.0]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return float(np.degrees(np.arccos(min(normals[0] @ normals[1], 1.0))))


def test_a_filled_background_is_no_substrate():
    """The background measured in 3 x 3 px patches on about 4 % of its points (the filter takes
    lone points for outliers) and filled in between (surface.filtering): a smooth, flat, extensive
    level, but made of interpolations, which are no part of it and carry no plane."""
    z, dome = _grain_on_a_tilted_substrate()
    seeds = (np.random.default_rng(5).random(z.shape) < 0.005).astype(np.uint8)
    patches = cv2.dilate(seeds, np.ones((3, 3), np.uint8)).astype(bool)
    z[(dome == 0) & ~patches] = np.nan
    filtered = filter_heights(z)
    _, datum = _refused_substrate(filtered.z_um, None, filled=filtered.filled, instead="none")
    assert "% of the map is measured on it" in datum.warning and datum.fraction < 0.5


@pytest.mark.parametrize("centre_um", [(15.0, 15.0), (4.0, 12.0)])
def test_a_grain_filling_a_barely_measured_field_is_left_as_measured(centre_um):
    """A grain that fills the field, the background around it measured nowhere: the lowest
    points of each block lie on its flanks or its foot, no level, so the heights stay as
    measured (a plane under the flanks of a grain off the centre tilts by some 20°)."""
    rows, cols = np.mgrid[0:300, 0:300] * PIXEL_SIZE_UM
    dome = 20.0 * np.sqrt(np.clip(1 - ((cols - centre_um[0]) ** 2 + (rows - centre_um[1]) ** 2) / 14.0**2, 0, None))
    z = np.where(dome > 0, dome - 5.0, np.nan).astype(np.float32)
    _refused_substrate(z, np.full(z.shape, 0.05, np.float32), instead="none")


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


PARTICLE_SCENES = {
    "one grain, featureless background": dict(radii_um=(28.0,), centres_px=((250, 210),), seed=3),
    "two grains, faint background, tilted substrate": dict(
        radii_um=(18.0, 12.0),
        centres_px=((150, 170), (320, 300)),
        seed=5,
        substrate_contrast=0.02,
        substrate_slope=(0.01, -0.005),
    ),
}


@pytest.mark.slow
@pytest.mark.parametrize("scene", PARTICLE_SCENES)
def test_a_particle_on_a_barely_measured_background_is_never_tilted(scene):
    """Particles the product has never seen, rendered at ±3° on a background it barely measures
    (a ring of heights around each grain, biased by its edge): `--level substrate` never levels on
    a plane through the grains (the plane through all heights, the old fallback, tilts them by
    3.7° and 14.6°): the result's substrate is within 3° of the truth's (measured: 0° with no
    levelling on the first, 2.2° on the second's faint ring taken for a substrate)."""
    spec = PARTICLE_SCENES[scene]
    pixel_size_um = 0.2
    truth = particle_scene(448, pixel_size_um=pixel_size_um, **spec)
    pair = synthetic.render_stereo_pair(
        truth.z_um, pixel_size_um=pixel_size_um, tilt_deg=(-3, 3), output_shape=(384, 384), material=truth.material
    )
    images = [read_sem_image(tiff_bytes(image)) for image in (pair.first, pair.second)]
    result = compute_height_map(*images, tilt_deg=(-3.0, 3.0), pixel_size_um=pixel_size_um)
    kept = measurement(
        result.z_um,
        result.sigma_um,
        pixel_size_um=pixel_size_um,
        tilt_deg=result.report["tilt_deg"],
        tilt_uncertainty_deg=result.report["tilt_uncertainty_deg"],
        level="substrate",
    )
    datum = kept.datum
    # What stands in for the substrate varies with what the matcher saw (the faint background's
    # ring passes for a substrate, the featureless one gives none): never the plane through all.
    assert datum.requested == "substrate" and datum.level != "plane"
    # The levelled substrate: the truth's plane less the datum's.
    slope_x, slope_y = np.subtract(truth.substrate_slope, (datum.slope_x, datum.slope_y))
    assert np.degrees(np.arctan(np.hypot(slope_x, slope_y))) < 3.0
