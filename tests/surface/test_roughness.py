"""De-tilting, the fracture metrics and profile parameters against known truth."""

from __future__ import annotations

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.surface import areal_parameters, profiles, roughness


@pytest.fixture(scope="module")
def rough_surface() -> np.ndarray:
    tilt = np.add.outer(0.02 * np.arange(256), -0.01 * np.arange(256))
    return synthetic.self_affine_surface((256, 256), hurst=0.8, rms_um=1.5, seed=7) + tilt


def test_unknown_points_are_left_out(rough_surface):
    holes = rough_surface.copy()
    holes[100:110, 50:60] = np.nan
    values = areal_parameters.areal_parameters(roughness.detilted_heights_um(holes), pixel_size_um=0.2)
    assert all(np.isfinite(v) for v in values.values())
    whole = areal_parameters.areal_parameters(roughness.detilted_heights_um(rough_surface), pixel_size_um=0.2)
    assert values["Sa"] == pytest.approx(whole["Sa"], rel=0.02)


@pytest.mark.parametrize("hurst", [0.6, 0.8, 0.9])
def test_hurst_exponent_of_self_affine_surfaces(hurst):
    surface = synthetic.self_affine_surface((512, 512), hurst=hurst, rms_um=1.0, seed=3, min_wavelength_px=2.0)
    metrics = roughness.fracture_metrics(surface, pixel_size_um=0.1)
    assert metrics["hurst_exponent"] == pytest.approx(hurst, abs=0.08)
    assert metrics["fractal_dimension"] == pytest.approx(3 - metrics["hurst_exponent"])
    assert metrics["hurst_fit_min_um"] == pytest.approx(0.4, rel=0.3)


def test_profile_parameters_of_a_cosine_on_a_slope():
    # A cosine symmetric about the middle is orthogonal to the line, so de-tilting leaves it whole.
    distance = np.linspace(0, 100, 100001)
    heights = 2.0 * np.cos(2 * np.pi * (distance - 50) / 10) + 0.3 * distance
    values = profiles.profile_parameters(distance, heights)
    assert values["Ra"] == pytest.approx(2 * 2.0 / np.pi, rel=1e-3)  # mean |cos| = 2/pi
    assert values["Rq"] == pytest.approx(2.0 / np.sqrt(2), rel=1e-3)
    assert values["Rz"] == pytest.approx(4.0, rel=1e-3)
    assert values["Rsk"] == pytest.approx(0.0, abs=1e-3)
    assert values["Rku"] == pytest.approx(1.5, rel=1e-3)


def test_polyline_positions_keep_vertices_and_spacing():
    positions, distances = profiles.polyline_positions(np.array([[0, 0], [3, 4], [3, 10]]), spacing_um=0.5)
    assert distances[-1] == pytest.approx(11.0)
    assert [3.0, 4.0] in positions.tolist()
    assert np.diff(distances).max() <= 0.5 + 1e-12
