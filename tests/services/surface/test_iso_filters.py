"""ISO 16610 Gaussian filters: 50 % transmission at the cut-off, holes and edges by normalized
convolution, the ISO 21920-3 default cut-offs."""

from __future__ import annotations

import numpy as np
import pytest

from fractoscope.surface import iso_filters


def _amplitude(values: np.ndarray) -> float:
    """Amplitude of a mean-free sinusoid from its RMS over whole periods."""
    return float(np.sqrt(2.0 * np.mean(values**2)))


# Cut-offs of 20 px (direct convolution) and 200 px (FFT on a padded grid): both code paths.
@pytest.mark.parametrize("cutoff_px", [20.0, 200.0])
def test_profile_filter_transmits_half_the_amplitude_at_the_cutoff(cutoff_px):
    spacing = 0.25
    cutoff = cutoff_px * spacing
    x = np.arange(8192) * spacing
    for wavelength_ratio in (0.5, 1.0, 2.0):
        wavelength = cutoff * wavelength_ratio
        mean_line = iso_filters.gaussian_mean_line(
            np.sin(2 * np.pi * x / wavelength), spacing_um=spacing, cutoff_um=cutoff
        )
        # Away from the ends, over a whole number of periods.
        periods = int(2048 * spacing / wavelength)
        middle = mean_line[2048 : 2048 + int(round(periods * wavelength / spacing))]
        expected = iso_filters.transmission(wavelength, cutoff_um=cutoff)
        assert _amplitude(middle) == pytest.approx(expected, abs=0.002)
    assert iso_filters.transmission(cutoff, cutoff_um=cutoff) == pytest.approx(0.5, rel=1e-12)


@pytest.mark.parametrize("cutoff_px", [16.0, 160.0])
def test_areal_filters_split_an_oblique_wave_in_half_at_the_cutoff(cutoff_px):
    pixel = 0.1
    cutoff = cutoff_px * pixel
    rows, cols = np.indices((1024, 1024))
    angle = np.radians(35.0)
    wave = np.sin(2 * np.pi * (cols * np.cos(angle) + rows * np.sin(angle)) * pixel / cutoff)
    mean = iso_filters.gaussian_mean_surface(wave, pixel_size_um=pixel, cutoff_um=cutoff)
    rest = iso_filters.l_filter(wave, pixel_size_um=pixel, lambda_c_um=cutoff)
    centre = (slice(320, 704), slice(320, 704))
    assert _amplitude(mean[centre]) == pytest.approx(0.5, abs=0.005)
    assert _amplitude(rest[centre]) == pytest.approx(0.5, abs=0.005)
    assert np.allclose(mean + rest, wave)


def test_holes_stay_holes_and_leave_distant_points_alone():
    pixel = 0.1
    rng = np.random.default_rng(2)
    z = rng.standard_normal((300, 400)).cumsum(axis=1) * 0.01
    holes = z.copy()
    holes[140:160, 190:215] = np.nan
    for cutoff in (0.5, 8.0):  # sigma 0.9 px (direct) and 15 px (FFT)
        full = iso_filters.gaussian_mean_surface(z, pixel_size_um=pixel, cutoff_um=cutoff)
        with_holes = iso_filters.gaussian_mean_surface(holes, pixel_size_um=pixel, cutoff_um=cutoff)
        assert np.array_equal(np.isnan(with_holes), np.isnan(holes))
        reach = int(np.ceil(5 * iso_filters.gaussian_sigma_px(cutoff, pixel))) + 1
        far = np.ones(z.shape, dtype=bool)
        far[140 - reach : 160 + reach, 190 - reach : 215 + reach] = False
        assert np.allclose(with_holes[far], full[far], atol=1e-6)


def test_a_level_surface_stays_level_up_to_the_edges_and_around_holes():
    """Normalized convolution: the mean surface of a constant is that constant everywhere known,
    edges and holes included (a zero-padded filter would sag towards zero there), to double
    precision on the direct path and single precision on the FFT path."""
    z = np.full((200, 260), 3.0)
    z[50:70, 80:120] = np.nan
    for cutoff, rtol in ((0.4, 1e-12), (10.0, 1e-6)):
        mean = iso_filters.gaussian_mean_surface(z, pixel_size_um=0.1, cutoff_um=cutoff)
        assert np.allclose(mean[np.isfinite(z)], 3.0, rtol=rtol)


def test_scale_limited_surface_reports_its_cutoffs():
    z = np.random.default_rng(1).standard_normal((64, 64))
    result = iso_filters.scale_limited_surface(z, pixel_size_um=0.5, lambda_s_um=1.5, lambda_c_um=10.0)
    assert (result.lambda_s_um, result.lambda_c_um) == (1.5, 10.0)
    assert np.allclose(
        result.z_um, result.sf_um - iso_filters.gaussian_mean_surface(result.sf_um, pixel_size_um=0.5, cutoff_um=10.0)
    )
    unfiltered = iso_filters.scale_limited_surface(z, pixel_size_um=0.5)
    assert unfiltered.lambda_s_um is None and np.array_equal(unfiltered.z_um, z)
    with pytest.raises(ValueError, match="lambda_s_um"):
        iso_filters.scale_limited_surface(z, pixel_size_um=0.5, lambda_s_um=10.0, lambda_c_um=10.0)
    with pytest.raises(ValueError, match="cutoff_um"):
        iso_filters.gaussian_mean_surface(z, pixel_size_um=0.5, cutoff_um=-1.0)


@pytest.mark.parametrize(
    ("length_um", "lambda_c_um", "lambda_s_um", "from_table"),
    [
        (400.0, 80.0, 2.5, True),  # Sc1: le = 5 lambda_c
        (1249.0, 80.0, 2.5, True),
        (1250.0, 250.0, 2.5, True),  # Sc2
        (4000.0, 800.0, 2.5, True),  # Sc3
        (12500.0, 2500.0, 8.0, True),  # Sc4
        (40000.0, 8000.0, 25.0, True),  # Sc5
        (1e6, 8000.0, 25.0, True),
        (150.0, 25.0, 0.8, False),  # below the table: the series continues
        (50.0, 8.0, 0.25, False),
    ],
)
def test_default_profile_cutoffs_follow_iso_21920_3(length_um, lambda_c_um, lambda_s_um, from_table):
    cutoffs = iso_filters.default_nesting_indices(pixel_size_um=0.01, field_um=length_um)
    assert (cutoffs.lambda_c_um, cutoffs.lambda_s_um, cutoffs.from_iso_table) == (lambda_c_um, lambda_s_um, from_table)
    assert cutoffs.sampling_ok


def test_sampling_coarser_than_the_table_allows_is_flagged():
    assert not iso_filters.default_nesting_indices(pixel_size_um=1.0, field_um=4000.0).sampling_ok
    assert iso_filters.default_nesting_indices(pixel_size_um=0.5, field_um=4000.0).sampling_ok


@pytest.mark.parametrize(
    ("pixel_size_um", "field_um", "lambda_s_um", "lambda_c_um"),
    [
        (1.0, 1020.0, 8.0, 80.0),  # the 1 µm/px overview once got ISO 21920-3's 2.5 µm, 2.5 samples
        (0.25, 140.0, 0.8, 25.0),  # sampled finely enough for the pair the series makes
        (0.05582, 85.0, 0.25, 8.0),  # the real pollen pair's pixel size
        (0.1, 25.5, 0.0, 2.5),  # the lambda_s 0.1 µm resolves would leave no band below 2.5 µm
        (1.0, 9.0, 0.0, 0.0),  # a field too short for either
    ],
)
def test_default_nesting_indices_follow_the_sampling_and_the_field(pixel_size_um, field_um, lambda_s_um, lambda_c_um):
    chosen = iso_filters.default_nesting_indices(pixel_size_um=pixel_size_um, field_um=field_um)
    assert (chosen.lambda_s_um, chosen.lambda_c_um) == (lambda_s_um, lambda_c_um)
    assert not chosen.lambda_s_um or chosen.lambda_s_um >= 3 * pixel_size_um  # ISO 25178-3 Table 1's sampling
    assert not chosen.lambda_c_um or 5 * chosen.lambda_c_um <= field_um
    for value in (chosen.lambda_s_um, chosen.lambda_c_um):
        assert not value or value in iso_filters.PREFERRED_NESTING_INDICES_UM
    assert chosen.spacing_um == pixel_size_um and chosen.reason.count(";") == 1  # one sentence, both filters
    assert (f"λs = {lambda_s_um:g} µm" in chosen.reason) == bool(lambda_s_um)
