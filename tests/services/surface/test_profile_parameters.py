"""ISO 21920-2 profile parameters and the ISO 21920-3 profile chain on profiles with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from fractoscope.surface import iso_filters, profile_parameters

SPACING_UM = 0.05


def test_sine_profile_gives_its_parameters():
    x = np.arange(0, 400, SPACING_UM)
    amplitude, wavelength = 1.5, 12.5
    values = profile_parameters.profile_parameters(
        amplitude * np.sin(2 * np.pi * x / wavelength), spacing_um=SPACING_UM
    )
    assert values["Ra"] == pytest.approx(2 * amplitude / np.pi, rel=1e-4)
    assert values["Rq"] == pytest.approx(amplitude / np.sqrt(2), rel=1e-4)
    assert values["Rsk"] == pytest.approx(0.0, abs=1e-6)
    assert values["Rku"] == pytest.approx(1.5, rel=1e-4)
    assert values["Rp"] == pytest.approx(amplitude, rel=1e-4)
    assert values["Rv"] == pytest.approx(amplitude, rel=1e-4)
    assert values["Rz"] == pytest.approx(2 * amplitude, rel=1e-4)
    assert values["Rt"] == pytest.approx(2 * amplitude, rel=1e-4)
    # The 7-point slope leaves out three samples at each end, where this sine is steepest.
    assert values["Rdq"] == pytest.approx(2 * np.pi * amplitude / wavelength / np.sqrt(2), rel=1e-3)
    assert values["RSm"] == pytest.approx(wavelength, rel=1e-4)


def test_rsm_ignores_ripples_below_the_height_discrimination():
    x = np.arange(0, 400, SPACING_UM)
    z = np.sin(2 * np.pi * x / 20.0) + 0.05 * np.sin(2 * np.pi * x / 1.3)  # ripples 2.5 % of Rz
    assert profile_parameters.profile_parameters(z, spacing_um=SPACING_UM)["RSm"] == pytest.approx(20.0, rel=0.01)


def test_rz_is_the_mean_of_the_section_heights():
    z = np.zeros(1000)
    for section, height in enumerate([1.0, 2.0, 3.0, 4.0, 5.0]):
        z[section * 200 + 100] = height  # one spike per section
    z -= z.mean()
    values = profile_parameters.profile_parameters(z, spacing_um=SPACING_UM)
    assert values["Rz"] == pytest.approx(3.0, rel=1e-9)
    assert values["Rt"] == pytest.approx(5.0, rel=1e-9)


def test_rk_family_of_a_three_piece_material_ratio_curve():
    count = 200_000
    ratio = (np.arange(count) + 0.5) * 100.0 / count
    z = np.random.default_rng(0).permutation(np.interp(ratio, [0, 10, 90, 100], [3.0, 1.0, -1.0, -4.0]))
    values = profile_parameters.profile_parameters(z, spacing_um=SPACING_UM)
    assert values["Rk"] == pytest.approx(2.5, rel=1e-3)
    assert values["Rmr1"] == pytest.approx(8.75, rel=2e-3)
    assert values["Rmr2"] == pytest.approx(90.0 + 0.25 / 0.3, rel=2e-3)
    assert values["Rpk"] == pytest.approx(1.75, rel=2e-3)
    assert values["Rvk"] == pytest.approx(2.75, rel=2e-3)


def test_roughness_profile_removes_form_and_waviness_and_reports_the_defaults():
    x = np.arange(0, 2000, 0.25)  # 2 mm: ISO 21920-3 gives lambda_c 250 µm (Sc2), lambda_s 2.5 µm
    roughness = 0.4 * np.sin(2 * np.pi * x / 25.0)
    z = 0.01 * x + 3.0 * np.sin(2 * np.pi * x / 6000.0) + roughness  # form and a waviness 24 lambda_c long
    result = profile_parameters.roughness_profile(z, spacing_um=0.25)
    assert (result.lambda_c_um, result.lambda_s_um) == (250.0, 2.5)
    assert result.cutoffs == iso_filters.default_nesting_indices(pixel_size_um=0.25, field_um=x[-1] - x[0])
    middle = slice(2000, 6000)
    # The 25 µm wave passes both filters: (1 - T(lambda_c)) T(lambda_s) of its amplitude.
    passed = (1 - iso_filters.transmission(25.0, cutoff_um=250.0)) * iso_filters.transmission(25.0, cutoff_um=2.5)
    assert np.sqrt(2 * np.mean(result.r_um[middle] ** 2)) == pytest.approx(0.4 * passed, rel=0.01)
    assert np.corrcoef(result.r_um[middle], roughness[middle])[0, 1] > 0.999


def test_bad_arguments_are_named():
    with pytest.raises(ValueError, match="spacing_um"):
        profile_parameters.profile_parameters(np.zeros(100), spacing_um=0.0)
    with pytest.raises(ValueError, match="lambda_s_um"):
        profile_parameters.roughness_profile(
            np.random.default_rng(1).random(100), spacing_um=0.1, lambda_s_um=5.0, lambda_c_um=2.0
        )
    with pytest.raises(ValueError, match="sections"):
        profile_parameters.profile_parameters(np.random.default_rng(1).random(100), spacing_um=0.1, sections=0)


def test_a_short_coarse_profile_gets_no_filter_that_would_empty_it():
    """Ten samples 1 µm apart: the ISO series' lambda_c for 9 µm (0.8 µm) is under two samples and
    took every height for the mean line (Ra 2e-11); no L-filter is applied instead, and said."""
    z = np.array([0.0, 1.0, -0.5, 0.7, -1.2, 0.3, 0.9, -0.8, 0.2, -0.4])
    made = profile_parameters.roughness_profile(z, spacing_um=1.0)
    assert made.lambda_c_um == 0.0 and made.lambda_s_um == 0.0
    assert profile_parameters.profile_parameters(made.r_um, spacing_um=1.0)["Ra"] > 0.3


def test_a_given_lambda_c_gets_the_lambda_s_paired_with_it():
    x = np.arange(10000) * 0.02
    z = np.sin(2 * np.pi * x / 1.3) + 0.1 * np.sin(2 * np.pi * x / 0.11)
    made = profile_parameters.roughness_profile(z, spacing_um=0.02, lambda_c_um=2.5)
    assert made.lambda_s_um == pytest.approx(
        0.08
    )  # 2.5 µm with 0.08 µm, as the series pairs them (not the 200 µm length's default, 25 µm with 0.8)


def test_unknown_ends_are_not_part_of_the_evaluation_length():
    """A line drawn past the data (256 measured samples, then 600 unknown) once took its default
    cut-offs from the whole line: lambda_c 8 instead of 2.5 µm, and Rq 4 times as large."""
    rng = np.random.default_rng(4)
    spacing_um = 0.1
    x_um = np.arange(256) * spacing_um
    measured = 0.3 * x_um + 0.5 * np.sin(2 * np.pi * x_um / 6.0) + 0.05 * rng.normal(size=x_um.size)
    alone = profile_parameters.roughness_profile(measured, spacing_um=spacing_um)
    drawn = profile_parameters.roughness_profile(
        np.concatenate([np.full(40, np.nan), measured, np.full(600, np.nan)]), spacing_um=spacing_um
    )
    assert (drawn.lambda_c_um, drawn.lambda_s_um) == (alone.lambda_c_um, alone.lambda_s_um) == (2.5, 0.0)
    np.testing.assert_allclose(drawn.r_um[40:296], alone.r_um)
    assert np.isnan(drawn.r_um[:40]).all() and np.isnan(drawn.r_um[296:]).all()
    figures = profile_parameters.profile_parameters(drawn.r_um, spacing_um=spacing_um)
    for name, value in profile_parameters.profile_parameters(alone.r_um, spacing_um=spacing_um).items():
        assert figures[name] == pytest.approx(value, nan_ok=True), name
