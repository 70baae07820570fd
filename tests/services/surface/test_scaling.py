"""Hurst exponents of synthetic self-affine surfaces, with and without a matcher's noise and
smoothing, over the reported (trustworthy) fit range; direction resolution; the PSD as data."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import ndimage
from surface_truth import MATCHING_WINDOW_PX, as_matched, fractional_brownian_sheet, self_affine

from fractoscope.surface import scaling

PIXEL_UM = 0.1
HURSTS = (0.5, 0.6, 0.7, 0.8, 0.9)
METHODS = ("hhc", "psd")


def _errors(z: np.ndarray, hurst: float, window_px: float, method: str) -> list[tuple[float, float]]:
    """(H - hurst, standard error) along rows and along columns."""
    fits = [
        scaling.hurst_exponent(z, pixel_size_um=PIXEL_UM, window_px=window_px, method=method, direction_deg=d)
        for d in (0.0, 90.0)
    ]
    return [(fit.hurst - hurst, fit.hurst_stderr) for fit in fits]


@pytest.mark.slow
@pytest.mark.parametrize("hurst", HURSTS)
def test_hurst_exponent_of_clean_self_affine_surfaces(hurst):
    """2048² maps, a 4 px window: lags 1.6-20 µm (16-205 px). Over twelve maps both methods are
    unbiased to 0.012 with a scatter of 0.025 per map and direction; two maps and two directions
    must average within 0.05 and each estimate lie within three of its standard errors."""
    for method in METHODS:
        errors = []
        for seed in (1, 2):
            errors += _errors(
                self_affine((2048, 2048), hurst=hurst, seed=seed, min_wavelength_px=2.0, isotropic=True),
                hurst,
                4,
                method,
            )
        error, stderr = np.array(errors).T
        assert abs(error.mean()) < 0.05, (method, error)
        assert np.all(np.abs(error) < 3 * stderr + 0.01), (method, error, stderr)


@pytest.mark.slow
@pytest.mark.parametrize("hurst", HURSTS)
def test_hurst_exponent_through_a_matcher(hurst):
    """4096² maps with 2 % white noise averaged over a 15 px window, as a matcher returns them: lags
    6-41 µm (60-410 px). The smoothing biases H by at most 0.035 (h(r)) and 0.04 (PSD) here (see
    fractoscope.surface.scaling), the map-to-map scatter is 0.03: two maps and two directions must
    average within 0.05, each estimate within three standard errors of the truth plus that bias."""
    for method in METHODS:
        errors = []
        for seed in (1, 2):
            matched = as_matched(
                self_affine((4096, 4096), hurst=hurst, seed=seed, min_wavelength_px=2.0, isotropic=True), seed=seed
            )
            errors += _errors(matched, hurst, MATCHING_WINDOW_PX, method)
        error, stderr = np.array(errors).T
        assert abs(error.mean()) < 0.05, (method, error)
        assert np.all(np.abs(error - 0.04) < 3 * stderr + 0.01), (method, error, stderr)


def test_reported_fit_range_is_four_windows_to_a_tenth_of_the_field():
    z = self_affine((1024, 1536), hurst=0.7, seed=3, min_wavelength_px=2.0, isotropic=True)
    hhc = scaling.hurst_exponent(z, pixel_size_um=PIXEL_UM, window_px=10, method="hhc")
    assert (hhc.fit_min_um, hhc.fit_max_um) == pytest.approx((4.0, 10.24), rel=0.03)
    assert hhc.scale_um[hhc.in_fit].min() == hhc.fit_min_um and np.all(np.diff(hhc.scale_um) > 0)
    psd = scaling.hurst_exponent(z, pixel_size_um=PIXEL_UM, window_px=10, method="psd")
    # Wavelengths twice the lags.
    assert psd.fit_min_um >= 8.0 * 0.97 and psd.fit_max_um <= 20.48 * 1.03
    assert scaling.trustworthy_range_um(z.shape, pixel_size_um=PIXEL_UM, window_px=10) == pytest.approx((4.0, 10.24))
    with pytest.raises(ValueError, match="window_px"):
        scaling.trustworthy_range_um((256, 256), pixel_size_um=PIXEL_UM, window_px=10)


@pytest.mark.slow
def test_exponents_along_and_across_a_direction():
    """A fractional Brownian sheet: self-affine with H = 0.8 along x and 0.5 along y. All its profiles
    share the sheet's few longest waves, so one map scatters by up to 0.1 (more than the jackknife,
    which assumes blocks far apart are independent, reports); the two directions stay well apart.
    Turned by 30° counter-clockwise on the map, the exponents follow the turn."""
    sheet = fractional_brownian_sheet((2048, 2048), hurst_x=0.8, hurst_y=0.5, seed=4)
    for method in METHODS:
        fits = scaling.anisotropic_hurst(sheet, pixel_size_um=PIXEL_UM, window_px=4, direction_deg=0.0, method=method)
        assert fits["along"].hurst == pytest.approx(0.8, abs=0.1), method
        assert fits["across"].hurst == pytest.approx(0.5, abs=0.1), method
        assert fits["along"].hurst - fits["across"].hurst > 0.2, method
        assert fits["across"].direction_deg == 90.0
    turned = ndimage.rotate(sheet, 30.0, reshape=False, order=1, mode="constant", cval=np.nan)[362:-362, 362:-362]
    assert np.isfinite(turned).all()
    for direction, (along, across) in ((30.0, (0.8, 0.5)), (120.0, (0.5, 0.8))):
        fits = scaling.anisotropic_hurst(
            turned, pixel_size_um=PIXEL_UM, window_px=3, direction_deg=direction, method="hhc"
        )
        assert fits["along"].hurst == pytest.approx(along, abs=0.1), direction
        assert fits["across"].hurst == pytest.approx(across, abs=0.1), direction
    wrong = scaling.anisotropic_hurst(turned, pixel_size_um=PIXEL_UM, window_px=3, direction_deg=-30.0, method="hhc")
    assert abs(wrong["along"].hurst - wrong["across"].hurst) < 0.15  # 60° off: a mix of both


def test_holes_are_skipped():
    z = self_affine((1024, 1024), hurst=0.7, seed=5, min_wavelength_px=2.0, isotropic=True)
    holes = z.copy()
    rng = np.random.default_rng(1)
    for row, col in rng.integers(0, 1000, size=(100, 2)):
        holes[row : row + 12, col : col + 12] = np.nan
    for method in METHODS:
        full = scaling.hurst_exponent(z, pixel_size_um=PIXEL_UM, window_px=4, method=method)
        partial = scaling.hurst_exponent(holes, pixel_size_um=PIXEL_UM, window_px=4, method=method)
        assert partial.hurst == pytest.approx(full.hurst, abs=0.03), method


def test_radial_psd_is_the_surface_spectrum():
    hurst = 0.7
    slopes = []
    for seed in (0, 1, 2):  # one map's slope over a decade scatters by about 0.1
        q, c = scaling.radial_psd(
            self_affine((1024, 1024), hurst=hurst, seed=seed, min_wavelength_px=2.0, isotropic=True),
            pixel_size_um=PIXEL_UM,
        )
        middle = (q > 1 / (100 * PIXEL_UM)) & (q < 1 / (10 * PIXEL_UM))
        slopes.append(np.polyfit(np.log(q[middle]), np.log(c[middle]), 1)[0])
    assert np.mean(slopes) == pytest.approx(-(2 + 2 * hurst), abs=0.1)
    # Normalised so that its integral over the frequency plane is the mean square height: white
    # noise of variance s² spreads it evenly over the (1 / pixel)² square, C = s² pixel².
    white = np.random.default_rng(2).normal(0.0, 0.3, (512, 512))
    _, c_white = scaling.radial_psd(white, pixel_size_um=PIXEL_UM)
    assert np.median(c_white) == pytest.approx(0.09 * PIXEL_UM**2, rel=0.03)
    # The profile spectrum the same way: its integral over k is the profiles' mean square.
    k, one_d = scaling.profile_psd(white[::4], pixel_size_um=PIXEL_UM)
    assert np.nanmedian(one_d) == pytest.approx(2 * 0.09 * PIXEL_UM, rel=0.05)  # one-sided


def test_bad_arguments_are_named():
    z = self_affine((256, 256), hurst=0.7, seed=1, min_wavelength_px=2.0, isotropic=True)
    with pytest.raises(ValueError, match="method"):
        scaling.hurst_exponent(z, pixel_size_um=PIXEL_UM, window_px=2, method="dfa")
    with pytest.raises(ValueError, match="fit_range_um"):
        scaling.hurst_exponent(z, pixel_size_um=PIXEL_UM, window_px=2, fit_range_um=(2.0, 1.0))
    with pytest.raises(ValueError, match="pixel_size_um"):
        scaling.trustworthy_range_um(z.shape, pixel_size_um=0.0, window_px=2)


@pytest.mark.parametrize(
    ("hurst", "stderr", "why"),
    [
        (0.7, 0.03, ""),
        (-0.102, 0.842, "outside (0, 1)"),  # the profile PSD of a real report, printed without a word
        (1.23, 0.05, "outside (0, 1)"),
        (0.001, 0.001, "cannot be told from 0"),  # white noise by h(r)
        (0.5, 0.2, "standard error above 0.15"),
        (float("nan"), 0.1, "no finite H"),
    ],
)
def test_an_exponent_outside_zero_to_one_or_too_uncertain_is_not_determinable(hurst, stderr, why):
    reason = scaling.hurst_validity(hurst, stderr)
    assert (reason == "") if not why else (reason.startswith("not determinable") and why in reason)


def test_white_noise_has_no_determinable_hurst_exponent_by_either_method():
    z = np.random.default_rng(2).normal(size=(192, 192))
    fits = scaling.hurst_exponents(z, pixel_size_um=0.5, window_px=1.0)
    for fit in fits.values():
        assert fit.not_determinable.startswith("not determinable")
        assert f"fitted over {fit.fit_min_um:.3g} to {fit.fit_max_um:.3g} µm" in fit.not_determinable


def test_a_self_affine_surface_has_a_determinable_hurst_exponent():
    z = self_affine((256, 256), hurst=0.7, seed=3, min_wavelength_px=2.0, isotropic=True)
    fit = scaling.hurst_exponent(z, pixel_size_um=1.0, window_px=1.0)
    assert fit.not_determinable == "" and 0.5 < fit.hurst < 0.9
