"""Uncertainty propagation against Monte Carlo, and the noise bias of Sa and Sq."""

from __future__ import annotations

import numpy as np
import pytest
from surface_truth import self_affine

from fractoscope.surface import areal_parameters, uncertainty

PIXEL_UM = 0.2
CORRELATION_PX = 5


def _field_parameters(z: np.ndarray) -> dict[str, float]:
    """The parameters with an analytic noise derivative."""
    return (
        areal_parameters.height_parameters(z)
        | areal_parameters.hybrid_parameters(z, pixel_size_um=PIXEL_UM)
        | areal_parameters.functional_parameters(z)
    )


@pytest.fixture(scope="module")
def surface() -> np.ndarray:
    return self_affine((192, 192), hurst=0.8, seed=7, max_wavelength_px=30, min_wavelength_px=4)


@pytest.fixture(scope="module")
def sigma(surface) -> np.ndarray:
    # Matching noise of 3-5 % of Sq, larger on one side (as on a steep flank).
    return 0.03 + 0.02 * np.linspace(0, 1, surface.shape[1])[None, :] * np.ones(surface.shape)


@pytest.fixture(scope="module")
def monte_carlo(surface, sigma) -> dict[str, float]:
    return uncertainty.monte_carlo_uncertainty(
        _field_parameters, surface, sigma, correlation_px=CORRELATION_PX, samples=200, seed=3
    )


@pytest.fixture(scope="module")
def propagated(surface, sigma):
    return uncertainty.areal_uncertainty(
        surface,
        sigma,
        pixel_size_um=PIXEL_UM,
        parameters=_field_parameters(surface),
        tilt_rel_uncertainty=0.02,
        correlation_px=CORRELATION_PX,
    )


@pytest.mark.slow
def test_noise_part_of_the_height_and_slope_families_matches_monte_carlo(monte_carlo, propagated):
    # 200 paired draws estimate a standard deviation to about 5 %.
    for name in ("Sa", "Sq", "Ssk", "Sku", "Sp", "Sv", "Sz", "Sdq", "Sdr"):
        assert propagated.u_noise[name] == pytest.approx(monte_carlo[name], rel=0.15), name


@pytest.mark.slow
def test_noise_part_of_the_material_ratio_family_is_within_its_documented_factor(monte_carlo, propagated):
    assert propagated.u_noise["Sk"] == pytest.approx(monte_carlo["Sk"], rel=0.15)
    for name in ("Spk", "Svk", "Vmp", "Vmc", "Vvc", "Vvv"):
        assert 0.85 <= propagated.u_noise[name] / monte_carlo[name] <= 1.6, name
    for name in ("Smr1", "Smr2"):  # level-crossing counts: first order sees only part of them
        assert 0.45 <= propagated.u_noise[name] / monte_carlo[name] <= 1.0, name


def test_tilt_part_matches_scaling_the_heights(surface):
    rel = 0.02
    base = _field_parameters(surface)
    draws = [_field_parameters(surface * (1 + e)) for e in np.random.default_rng(1).normal(0, rel, 400)]
    result = uncertainty.areal_uncertainty(
        surface, 0.0, pixel_size_um=PIXEL_UM, parameters=base, tilt_rel_uncertainty=rel
    )
    for name in ("Sa", "Sq", "Sz", "Sdq", "Sdr", "Sk", "Spk", "Vmc", "Vvv"):
        spread = np.std([d[name] for d in draws])
        assert result.u_tilt[name] == pytest.approx(spread, rel=0.1), name
        assert result.u_noise[name] == 0.0
    for name in ("Ssk", "Sku", "Smr1", "Smr2"):
        assert result.u_tilt[name] == 0.0
        assert np.std([d[name] for d in draws]) < 1e-6 * max(abs(base[name]), 1.0), name
    # Sdr is not proportional to the height scale: its relative uncertainty differs from the tilt's.
    assert result.u_tilt["Sdr"] / base["Sdr"] != pytest.approx(rel, rel=0.05)


def test_noise_bias_of_sa_and_sq_is_removed_with_the_sigma_map():
    truth = self_affine((256, 256), hurst=0.7, seed=2, max_wavelength_px=40)
    sigma = np.full(truth.shape, 0.15)  # noise of 15 % of Sq inflates it by 1.1 %
    measured = truth + uncertainty.correlated_noise(sigma, correlation_px=3, rng=np.random.default_rng(4))
    parameters = areal_parameters.height_parameters(measured)
    true_values = areal_parameters.height_parameters(truth)
    result = uncertainty.areal_uncertainty(
        measured, sigma, pixel_size_um=PIXEL_UM, parameters=parameters, tilt_rel_uncertainty=0.0, correlation_px=3
    )
    for name in ("Sa", "Sq"):
        assert parameters[name] > true_values[name] * 1.008
        assert result.corrected[name] == pytest.approx(true_values[name], rel=0.003), name
        assert result.noise_bias[name] == pytest.approx(parameters[name] - result.corrected[name])


def test_spatial_and_feature_noise_needs_monte_carlo(surface, sigma):
    parameters = areal_parameters.areal_parameters(surface, pixel_size_um=PIXEL_UM)
    analytic = uncertainty.areal_uncertainty(
        surface,
        sigma,
        pixel_size_um=PIXEL_UM,
        parameters=parameters,
        tilt_rel_uncertainty=0.01,
        correlation_px=CORRELATION_PX,
    )
    assert set(analytic.u_total) == set(parameters)
    for name in uncertainty.NOT_DIFFERENTIABLE:
        assert np.isnan(analytic.u_noise[name]) and np.isnan(analytic.u_total[name]), name
    sampled = uncertainty.areal_uncertainty(
        surface,
        sigma,
        pixel_size_um=PIXEL_UM,
        parameters=parameters,
        tilt_rel_uncertainty=0.01,
        correlation_px=CORRELATION_PX,
        monte_carlo_samples=4,
    )
    for name in uncertainty.NOT_DIFFERENTIABLE:
        assert np.isfinite(sampled.u_total[name]), name
    assert sampled.u_total["Spc"] >= sampled.u_tilt["Spc"]


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"sigma_um": -0.1}, "sigma_um"),
        ({"tilt_rel_uncertainty": -1.0}, "tilt_rel_uncertainty"),
        ({"correlation_px": 0.5}, "correlation_px"),
        ({"parameters": {"Ra": 1.0}}, "not areal parameters: Ra"),
    ],
)
def test_bad_arguments_are_named(surface, options, message):
    arguments = {
        "sigma_um": 0.1,
        "pixel_size_um": PIXEL_UM,
        "parameters": {"Sa": 1.0},
        "tilt_rel_uncertainty": 0.01,
    } | options
    with pytest.raises(ValueError, match=message):
        uncertainty.areal_uncertainty(surface, **arguments)
