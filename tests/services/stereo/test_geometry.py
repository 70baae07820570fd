import numpy as np
import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.stereo import geometry, tilt_series


@pytest.mark.parametrize("pixel_size_um, expected_um", [(0.005, 0.0287), (1.0, 5.74)])
def test_one_pixel_of_disparity_matches_the_papers_figures(pixel_size_um, expected_um):
    """The sigma of a flat surface whose disparity is known to one pixel: the height per pixel."""
    flat, one_pixel = np.zeros((1, 1), np.float32), [np.ones((1, 1), np.float32)]
    per_px = geometry.height_sigma_um(
        flat, one_pixel, tilt_deg=(-5.0, 5.0), pixel_size_um=pixel_size_um, tilt_uncertainty_deg=0.5
    )[0, 0]
    assert per_px == pytest.approx(expected_um, abs=5e-4 if pixel_size_um < 0.1 else 5e-3)


def test_tilt_error_of_half_a_degree_at_five_degrees_is_ten_percent():
    relative = geometry.relative_height_error_from_tilt(tilt_deg=(-5.0, 5.0), tilt_uncertainty_deg=0.5)
    assert relative == pytest.approx(np.radians(0.5) / np.tan(np.radians(5.0)))
    assert relative == pytest.approx(0.0998, abs=5e-4)


def test_general_formula_reduces_to_symmetric_case():
    x1 = np.array([-300.0, 0.0, 250.0])
    disparity = np.array([3.0, -2.0, 10.0])
    z = _pair_heights_px(x1, disparity, (-5.0, 5.0)) * 0.2
    np.testing.assert_allclose(z, disparity * 0.2 / (2 * np.sin(np.radians(5.0))))


def test_general_formula_inverts_parallel_projection_for_asymmetric_tilts():
    rng = np.random.default_rng(0)
    x_px, z_um = rng.uniform(-500, 500, 50), rng.uniform(-20, 20, 50)
    t1, t2 = np.radians([0.0, 10.0])
    pixel_size_um = 0.25
    x1 = x_px * np.cos(t1) + z_um / pixel_size_um * np.sin(t1)
    x2 = x_px * np.cos(t2) + z_um / pixel_size_um * np.sin(t2)
    recovered = _pair_heights_px(x1, x2 - x1, (0.0, 10.0)) * pixel_size_um
    np.testing.assert_allclose(recovered, z_um, atol=1e-9)


def test_sigma_combines_disparity_and_tilt_terms():
    """Two pixels of interest, heights 0 and 10 µm on a map whose median height is 5 µm, the
    first's disparity known to one pixel, the second's exactly."""
    z = np.array([[0.0, 10.0, 10.0, 10.0, 10.0]], np.float32)
    disparity_sigma = np.array([[1.0, 0.0, 0.0, 0.0, 0.0]], np.float32)
    sigma = geometry.height_sigma_um(
        z, [disparity_sigma], tilt_deg=(-5.0, 5.0), pixel_size_um=1.0, tilt_uncertainty_deg=0.5
    ).ravel()
    relative = geometry.relative_height_error_from_tilt(tilt_deg=(-5.0, 5.0), tilt_uncertainty_deg=0.5)
    assert sigma[0] == pytest.approx(np.hypot(5.737, relative * 5.0), rel=1e-3)
    assert sigma[1] == pytest.approx(relative * 5.0, rel=1e-6)


def _pair_heights_px(x1_px, disparity_px, tilt_deg):
    """Heights (px) of a pair as the pipeline solves them (tilt_series, reference first)."""
    z_px, _ = tilt_series.heights_px(x1_px, np.stack([np.zeros_like(disparity_px), disparity_px]), tilt_deg)
    return z_px


@pytest.mark.parametrize("tilts", [(5.0, 5.0), (np.nan, 5.0), (-95.0, 5.0)])
def test_unusable_tilts_are_rejected(tilts):
    with pytest.raises(InvalidInputError) as error:
        geometry.validate_tilts(tilts)
    assert error.value.field == "tilt_deg"
