"""Slopes from the secondary-electron shading, fused with the stereo disparities (stereo.photometric)."""

import numpy as np
import pytest
from conftest import cleavage_pair, dimple_pair

from fractoscope import synthetic
from fractoscope.rpc import wire
from fractoscope.sem.image import SemImage
from fractoscope.stereo import photometric
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_height_map

ROWS, COLS = 96, 400


def _secant_law_pair(disparity_px, *, slope_gain=1.0, noise_grey=1.0, seed=0):
    """A left texture and the right view of it at (row, col + disparity_px), brightened by
    1 + slope_gain·∂d/∂x as the secant law does; grey levels about 100, with Gaussian noise."""
    rng = np.random.default_rng(seed)
    columns = np.arange(COLS, dtype=np.float64)
    texture = synthetic.self_affine_surface((ROWS, COLS), hurst=0.3, rms_um=1.0, seed=seed, min_wavelength_px=4.0)
    left = 100.0 + 15.0 * texture
    slope = np.gradient(disparity_px, axis=1)
    right = np.empty_like(left)
    for row in range(ROWS):  # the right view's column x + d(x) shows the left's column x
        right[row] = np.interp(columns, columns + disparity_px[row], left[row] * (1.0 + slope_gain * slope[row]))
    noisy = [image + rng.normal(0.0, noise_grey, image.shape) for image in (left, right)]
    return noisy[0].astype(np.float32), noisy[1].astype(np.float32)


def _wavy_disparity_px(ripple_px=0.4):
    """Ripples of 12 px wavelength and `ripple_px` amplitude, too fine for a correlation window,
    on hills of 100 px, (ROWS, COLS)."""
    columns = np.arange(COLS, dtype=np.float64)
    rows = np.arange(ROWS, dtype=np.float64)[:, None]
    hills = 3.0 * np.sin(2 * np.pi * columns / 100.0 + rows / 30.0)
    return hills + ripple_px * np.sin(2 * np.pi * columns / 12.0 + rows / 7.0)


def test_slopes_from_the_shading_restore_relief_finer_than_the_stereo_resolves():
    truth = _wavy_disparity_px()
    left, right = _secant_law_pair(truth)
    # A window matcher's view of it: the hills right, the ripples averaged away to a fifth.
    stereo = _wavy_disparity_px(ripple_px=0.08).astype(np.float32)
    stereo[10:14, 50:60] = np.nan  # a masked patch stays masked
    sigma = np.where(np.isfinite(stereo), np.float32(0.3), np.float32(np.nan))  # as a matcher gives it
    fusion = photometric.fused_disparity(left, right, stereo, sigma, noise_grey=np.sqrt(2.0))
    assert fusion.used and fusion.weight > 0.8 and fusion.weight == pytest.approx(fusion.explained)
    inner = (slice(4, -4), slice(20, -20))
    known = np.isfinite(fusion.disparity_px)
    assert np.array_equal(known, np.isfinite(stereo))
    before = np.sqrt(np.nanmean((stereo - truth)[inner] ** 2))
    after = np.sqrt(np.nanmean((fusion.disparity_px - truth)[inner] ** 2))
    assert before > 0.2  # four fifths of the ripples' RMS, 0.28 px
    assert after < 0.5 * before  # measured 0.08 px
    # The sigma shrinks where the slopes add information, never beyond the stereo's.
    assert np.nanmax(fusion.sigma_px) <= 0.3 + 1e-6 and np.nanmedian(fusion.sigma_px) < 0.25
    assert np.array_equal(np.isfinite(fusion.sigma_px), known)


def test_shading_that_tells_nothing_of_the_slopes_leaves_the_disparities_alone():
    """A right view whose brightness does not change with the slopes (another texture, moved by
    the disparities) tells none: the disparities come back as they were."""
    truth = _wavy_disparity_px()
    left, _ = _secant_law_pair(truth)
    _, unrelated = _secant_law_pair(truth, slope_gain=0.0, seed=7)
    stereo = truth.astype(np.float32)
    fusion = photometric.fused_disparity(left, unrelated, stereo, np.full(truth.shape, 0.3, np.float32), noise_grey=1.4)
    assert not fusion.used and fusion.weight == 0.0 and fusion.explained < photometric.MIN_WEIGHT
    assert fusion.disparity_px is stereo and fusion.sigma_px is not None


def test_too_little_matched_is_left_alone():
    truth = _wavy_disparity_px()
    left, right = _secant_law_pair(truth)
    stereo = np.full(truth.shape, np.nan, np.float32)
    stereo[:2, :100] = 1.0
    fusion = photometric.fused_disparity(left, right, stereo, np.full(truth.shape, 0.3, np.float32), noise_grey=1.4)
    assert not fusion.used and np.isnan(fusion.agreement) and fusion.disparity_px is stereo


def test_noise_sigma_reads_the_noise_of_a_smooth_image():
    rng = np.random.default_rng(3)
    smooth = 100.0 + 20.0 * np.sin(np.arange(300)[None, :] / 40.0) * np.ones((300, 1))
    assert photometric.noise_sigma(smooth + rng.normal(0.0, 5.0, smooth.shape)) == pytest.approx(5.0, rel=0.05)


def _reconstruct(pair, tilt_deg=(-5.0, 5.0), options=MatchingOptions()):
    first, second = (SemImage(image, None, None, 0) for image in (pair.first, pair.second))
    return compute_height_map(first, second, tilt_deg=tilt_deg, pixel_size_um=0.1, options=options)


@pytest.mark.slow
def test_the_default_method_fuses_dimples_slopes_and_leaves_cleavage_alone(monkeypatch):
    """Dimples' slopes agree with the stereo's (0.95) and bring their RMS error from 2.95 % of
    the range to 1.59 % (±5°); cleavage's do not (0.14: its facets are flat between walls)."""
    dimples = dimple_pair()
    fused = _reconstruct(dimples)
    assert fused.report["photometric_slopes_used"] == [True]
    assert fused.report["photometric_agreement"][0] > 0.9
    weight, explained = fused.report["photometric_weight"][0], fused.report["photometric_explained"][0]
    assert 0.5 < weight <= 1.0 and 0.5 < explained <= 1.0
    sent = wire.report_to_message(fused.report)  # as a gRPC client reads it
    assert list(sent.photometric_weight) == [weight] and list(sent.photometric_explained) == [explained]
    fused_rms = synthetic.height_errors(fused.z_um, dimples.z_seen_um).rms_of_range
    monkeypatch.setattr(photometric, "MIN_WEIGHT", 2.0)  # never reached: the stereo alone
    alone = _reconstruct(dimples)
    assert alone.report["photometric_slopes_used"] == [False]
    assert fused_rms < 0.7 * synthetic.height_errors(alone.z_um, dimples.z_seen_um).rms_of_range
    monkeypatch.undo()
    cleavage = _reconstruct(cleavage_pair())
    assert cleavage.report["photometric_slopes_used"] == [False] and cleavage.report["photometric_weight"] == [0.0]


def _variant_pair(name, size_px=320):
    return dimple_pair(size_px=size_px, physics=synthetic.PHYSICS_VARIANTS[name])


def _errors(pair, name, method="tgv_zncc"):
    """The full height-map request on `pair`, told where the variant's detector is, as a user would."""
    physics = synthetic.PHYSICS_VARIANTS[name]
    options = MatchingOptions(method=method, detector_from_tilt_axis_deg=physics.detector_from_tilt_axis_deg)
    result = _reconstruct(pair, options=options)
    return synthetic.height_errors(result.z_um, pair.z_seen_um).rms_of_range, result.report


@pytest.mark.slow
@pytest.mark.parametrize("name", ["lambert", "secant_k1.6_side_detector"])
def test_on_renderers_it_was_not_tuned_on_the_default_beats_window_correlation(name):
    """Other yield laws and detectors (synthetic.PHYSICS_VARIANTS) on 320² dimples at ±5°: the
    learned shading model is fitted and used (weights 0.87 and 0.62), and the default method's
    RMS error stays under 5 % of the range and under window correlation's (measured: 3.3 % and
    4.3 %; window correlation 4.6 % and 7.5 %; a wrongly fused slope costs several points)."""
    pair = _variant_pair(name)
    default, report = _errors(pair, name)
    window, _ = _errors(pair, name, "window_zncc")
    assert report["photometric_slopes_used"] == [True]
    assert default < window and default < 0.05


def test_shading_without_slope_information_gets_no_weight():
    """A renderer with no yield law (material contrast only): the model explains nothing of the
    stereo's slopes, and the disparities are the stereo's alone."""
    pair = _variant_pair("texture_only", size_px=256)
    left, right = pair.first.astype(np.float32), pair.second.astype(np.float32)
    truth_px = pair.z_seen_um / 0.1 * 2.0 * np.sin(np.radians(5.0))
    stereo = (truth_px - truth_px.mean()).astype(np.float32)
    fusion = photometric.fused_disparity(left, right, stereo, np.full(stereo.shape, 0.3, np.float32), noise_grey=3.0)
    assert fusion.explained < photometric.MIN_WEIGHT and fusion.weight == 0.0 and not fusion.used
    assert fusion.disparity_px is stereo
