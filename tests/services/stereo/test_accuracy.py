"""Recovered heights against the known surfaces of synthetic SEM pairs (640², 2 % noise)."""

import numpy as np
import pytest
from conftest import cleavage_pair, dimple_pair, fracture_pair, inner_mask

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo import geometry, matching
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.stereo.pipeline import compute_height_map

pytestmark = pytest.mark.slow  # accuracy on 640² pairs: `pytest -m "not slow"` leaves it out

WINDOW = MatchingOptions(method="window_zncc")
TILT_PAIRS = [(-5.0, 5.0), (0.0, 10.0)]


def _reconstruct(pair, tilt_deg, **kwargs):
    first, second = (SemImage(image, None, None, 0) for image in (pair.first, pair.second))
    return compute_height_map(first, second, tilt_deg=tilt_deg, pixel_size_um=0.1, **kwargs)


def _errors(result, pair):
    errors = synthetic.height_errors(result.z_um, pair.z_seen_um)
    return errors.valid_fraction, errors.rms_of_range, errors.sa_relative


@pytest.mark.parametrize("tilt_deg", TILT_PAIRS)
def test_fracture_surface_heights_meet_the_accuracy_targets(tilt_deg):
    """The default method meets Matching II's targets on the self-affine surface (measured:
    0.53 % and 0.54 % RMS, 100 % valid, Sa within 0.6 %, with the shading's slopes fused in);
    window correlation its first issue's."""
    pair = fracture_pair(tilt_deg=tilt_deg)
    result = _reconstruct(pair, tilt_deg)
    valid_fraction, rms_of_range, sa_relative = _errors(result, pair)
    assert valid_fraction >= 0.98
    assert rms_of_range <= 0.010
    assert abs(sa_relative) <= 0.02
    assert result.z_um.dtype == np.float32 and result.z_um.shape == pair.first.shape
    assert result.report["method"] == "tgv_zncc"
    window_valid, window_rms, window_sa = _errors(_reconstruct(pair, tilt_deg, options=WINDOW), pair)
    assert window_valid >= 0.98 and window_rms <= 0.015 and abs(window_sa) <= 0.02


@pytest.mark.parametrize(
    "make_pair", [fracture_pair, dimple_pair, cleavage_pair], ids=["self-affine", "dimples", "cleavage"]
)
@pytest.mark.parametrize("tilt_deg", TILT_PAIRS)
def test_the_default_method_measures_better_than_window_correlation(make_pair, tilt_deg):
    """TGV² refinement lowers the RMS error on every surface and measures at least as much
    (measured, ±5° and 0/10°: self-affine 0.53 and 0.54 % against 1.12 and 1.11 %; dimples 1.6
    and 1.6 % against 4.2 and 4.1 %, 99.7-99.9 % valid against 98.8-98.9 %; cleavage 1.23 and
    2.60 % against 2.8 and 6.5 %, 88-90 % valid against 78-80 %)."""
    pair = make_pair(tilt_deg=tilt_deg)
    default_valid, default_rms, _ = _errors(_reconstruct(pair, tilt_deg), pair)
    window_valid, window_rms, _ = _errors(_reconstruct(pair, tilt_deg, options=WINDOW), pair)
    assert default_rms < 0.95 * window_rms
    assert default_valid >= window_valid


def _errors_by_default_and_with(options, make_pair, tilt_deg, *, default=None):
    """`_errors` of the pair made by `make_pair` reconstructed with `default`, and with `options`."""
    pair = make_pair(tilt_deg=tilt_deg)
    default = default or MatchingOptions()
    return _errors(_reconstruct(pair, tilt_deg, options=default), pair), _errors(
        _reconstruct(pair, tilt_deg, options=options), pair
    )


def _within(result, pair):
    """Fractions of valid inner heights within one pixel of disparity of the truth and within
    three reported sigmas (after the constant offset)."""
    valid = np.isfinite(result.z_um) & inner_mask(pair.z_seen_um.shape)
    error = result.z_um[valid] - pair.z_seen_um[valid]
    error -= np.median(error)
    one_pixel_um = 0.1 / (2 * np.sin(np.radians(5.0)))
    return np.mean(np.abs(error) < one_pixel_um), np.mean(np.abs(error) < 3 * result.sigma_um[valid])


# The RMS target of dimples (1.5 %), cleavage's at 0/10° (2 %) and cleavage's 95 % valid are not
# met (noise and the dimples' shading texture changing with the tilt, see the ideal-image test;
# 4.6 % of cleavage is hidden in the second view and more lies next to its walls); these bounds
# pin what each method achieves so it cannot silently get worse. Measured, default: dimples
# 1.59-1.65 % RMS (2.95-3.03 % before the shading's slopes were fused in), 99.7-99.9 % valid,
# Sa within 0.9 %; cleavage 1.23 % (±5°, within the target) and 2.60 % (0/10°; 4.4 % before
# the hidden bands behind walls were handled, see test_visibility) RMS, 88-90 % valid (84-87 %
# while pixels with a semi-global seed were propagated too, see tgv_zncc), Sa within 0.4 %,
# 96.5-96.7 % within a pixel, 98.6-99.3 % within three sigmas. Since the renderer hides at negative
# tilts what a higher point hides (rendering.visible_sheet_px; before, the −5° view showed its
# walls as seen from below), cleavage at ±5° measures 1.76 % RMS, 86.0 % valid, 91.6 % within a
# pixel and 99.0 % within three sigmas by default, 3.3 %, 77.8 %, 81.4 % and 98.0 % by window
# correlation (0/10° unchanged): matching must now face the reference's own hidden bands.
# Window correlation: dimples 4.1-4.2 %, 98.8-98.9 %, 0.5 %; cleavage 2.8-6.5 %, 78-80 %, 2.0 %.
# The dimples' Sa error scatters with the resampling of the second image: seeds 1-4 at ±5° read
# −1.37, −1.08, −1.22, −1.78 % while the alignment applied the features' rotation and scale, and
# −1.56, −1.25, −1.10, −1.53 % since it removes only what stands out of its sigma (none here).
# See docs/accuracy.md.
BEYOND_TARGETS = {
    ("dimples", "tgv_zncc"): (
        dimple_pair,
        {"valid": 0.99, "rms": 0.019, "sa": 0.018, "one_pixel": 0.99, "three_sigma": 0.99},
    ),
    ("cleavage", "tgv_zncc"): (
        cleavage_pair,
        {"valid": 0.85, "rms": 0.03, "sa": 0.02, "one_pixel": 0.90, "three_sigma": 0.98},
    ),
    ("dimples", "window_zncc"): (
        dimple_pair,
        {"valid": 0.98, "rms": 0.045, "sa": 0.01, "one_pixel": 0.98, "three_sigma": 0.99},
    ),
    ("cleavage", "window_zncc"): (
        cleavage_pair,
        {"valid": 0.75, "rms": 0.07, "sa": 0.025, "one_pixel": 0.80, "three_sigma": 0.95},
    ),
}


@pytest.mark.parametrize("surface", sorted(BEYOND_TARGETS))
@pytest.mark.parametrize("tilt_deg", TILT_PAIRS)
def test_dimples_and_cleavage_keep_their_measured_accuracy(surface, tilt_deg):
    make_pair, bounds = BEYOND_TARGETS[surface]
    pair = make_pair(tilt_deg=tilt_deg)
    result = _reconstruct(pair, tilt_deg, options=MatchingOptions(method=surface[1]))
    valid_fraction, rms_of_range, sa_relative = _errors(result, pair)
    within_one_pixel, within_three_sigma = _within(result, pair)
    assert valid_fraction >= bounds["valid"]
    assert rms_of_range <= bounds["rms"]
    assert abs(sa_relative) <= bounds["sa"]
    assert within_one_pixel >= bounds["one_pixel"] and within_three_sigma >= bounds["three_sigma"]
    if surface == ("cleavage", "tgv_zncc") and tilt_deg == (-5.0, 5.0):
        assert rms_of_range <= 0.02  # Matching II's target, met at ±5°


def test_a_surface_with_few_features_is_searched_over_its_whole_relief():
    """The search range comes from the parallax of the SIFT features the alignment matched. On
    this cleavage surface 8 features on two facets span ±2 px, where the heights span −16 to
    +41 px: a range fitted to them masked the rest (64 % valid, 2.3 % RMS). Too few features to
    bound the parallax leave the range at its default (86 % valid, 1.5 % RMS)."""
    surface = synthetic.reference_surface("cleavage", 640 + 64, seed=4)
    pair = synthetic.render_stereo_pair(
        surface, pixel_size_um=synthetic.REFERENCE_PIXEL_SIZE_UM, tilt_deg=(-5.0, 5.0), output_shape=(640, 640), seed=1
    )
    valid_fraction, rms_of_range, _ = _errors(_reconstruct(pair, (-5.0, 5.0)), pair)
    assert valid_fraction >= 0.8
    assert rms_of_range <= 0.02


@pytest.mark.parametrize("tilt_deg", TILT_PAIRS)
def test_dimples_meet_the_targets_when_the_two_views_differ_only_by_parallax(tilt_deg):
    """What keeps dimples from the targets is the images, not the matcher: rendered without
    noise and with the secondary-electron shading fixed to the surface (the same in both views),
    a 7 px window measures them within the targets (measured: 1.32 % and 1.43 % RMS, 99.9 % and
    99.7 % valid). With the shading changing with the tilt, as in a microscope, no window from
    7 to 15 px does better than 3.4 % (see docs/accuracy.md)."""
    pair = dimple_pair(tilt_deg=tilt_deg, noise_fraction=0.0, shading_tilt_deg=float(np.mean(tilt_deg)))
    options = MatchingOptions(window_px=7, method="window_zncc")
    valid_fraction, rms_of_range, sa_relative = _errors(_reconstruct(pair, tilt_deg, options=options), pair)
    assert valid_fraction >= 0.98
    assert rms_of_range <= 0.015
    assert abs(sa_relative) <= 0.02


# Local contrast normalization (on by default) takes the shading that changes with the tilt out
# before matching. Measured by window correlation without it: dimples 7.2-7.5 % RMS and 95 % valid (4.1-4.2 % and
# 99 % with), the self-affine surface 1.23-1.26 % and 99.8 % (1.11-1.12 % and 100 %).
WITHOUT_LOCAL_CONTRAST = {
    "self-affine": (fracture_pair, {"valid": 0.98, "rms": 0.015}),
    "dimples": (dimple_pair, {"valid": 0.92, "rms": 0.08}),
}


@pytest.mark.parametrize("surface", sorted(WITHOUT_LOCAL_CONTRAST))
@pytest.mark.parametrize("tilt_deg", TILT_PAIRS)
def test_local_contrast_normalization_takes_the_tilt_dependent_shading_out(surface, tilt_deg):
    make_pair, bounds = WITHOUT_LOCAL_CONTRAST[surface]
    with_contrast, (valid_fraction, rms_of_range, _) = _errors_by_default_and_with(
        MatchingOptions(normalize_local_contrast=False, method="window_zncc"),
        make_pair,
        tilt_deg,
        default=WINDOW,
    )
    assert valid_fraction >= bounds["valid"] and rms_of_range <= bounds["rms"]
    assert with_contrast[0] > valid_fraction and with_contrast[1] < rms_of_range
    if surface == "dimples":
        assert with_contrast[1] < 0.65 * rms_of_range


# Propagation at full resolution (an option of window correlation, whose coarser levels always
# propagate) frees more of the pixels next to steps. Measured: cleavage 2.5 % and 6.1 % RMS (2.8 % and 6.5 % by
# default), 80-81 % valid (78-80 %); dimples 4.0-4.1 % (4.1-4.2 %). On cleavage seed 1 at ±5° it
# frees pixels at about the same RMS error: 3.19 % against 3.13 %, 80.7 % valid against 78.9 %
# (seeds 2 and 3: 2.03 % against 2.59 %, 1.95 % against 2.17 %).
WITH_FULL_RESOLUTION_PROPAGATION = {
    "self-affine": (fracture_pair, {"valid": 0.99, "rms": 0.015, "sa": 0.02}),
    "cleavage": (cleavage_pair, {"valid": 0.79, "rms": 0.065, "sa": 0.02}),
    "dimples": (dimple_pair, {"valid": 0.98, "rms": 0.043, "sa": 0.01}),
}


@pytest.mark.parametrize("surface", sorted(WITH_FULL_RESOLUTION_PROPAGATION))
@pytest.mark.parametrize("tilt_deg", TILT_PAIRS)
def test_propagation_at_full_resolution_recovers_more_steps(surface, tilt_deg):
    make_pair, bounds = WITH_FULL_RESOLUTION_PROPAGATION[surface]
    default, (valid_fraction, rms_of_range, sa_relative) = _errors_by_default_and_with(
        MatchingOptions(propagate_at_full_resolution=True, method="window_zncc"),
        make_pair,
        tilt_deg,
        default=WINDOW,
    )
    assert valid_fraction >= bounds["valid"] and rms_of_range <= bounds["rms"] and abs(sa_relative) <= bounds["sa"]
    if surface != "self-affine":
        assert rms_of_range < default[1] + (0.001 if surface == "cleavage" else 0.0)
    if surface == "cleavage":  # more pixels next to steps, and the step errors go, not only the masks
        assert valid_fraction > default[0]


def test_misaligned_pair_is_aligned_and_reported():
    pair = fracture_pair(shift_px=(7.5, -3.2), rotation_deg=0.4)
    result = _reconstruct(pair, (-5.0, 5.0))
    assert result.report["shift_across_px"] == pytest.approx(-3.2, abs=0.2)
    # Counter-clockwise on screen is a negative angle in (column, row-down) coordinates.
    assert result.report["rotation_deg"] == pytest.approx(-0.4, abs=0.05)
    assert result.report["residual_vertical_parallax_px"] < 0.5
    valid_fraction, rms_of_range, _ = _errors(result, pair)
    assert valid_fraction >= 0.95
    assert rms_of_range <= 0.02


def test_oblique_tilt_axis():
    pair = fracture_pair(tilt_axis_deg=30.0)
    result = _reconstruct(pair, (-5.0, 5.0), tilt_axis_deg=30.0)
    valid_fraction, rms_of_range, _ = _errors(result, pair)
    assert valid_fraction >= 0.95
    assert rms_of_range <= 0.02
    # The matching part of sigma, the tilt part taken out about the stored map's median height:
    # sigma's own reference level once took in the rotated canvas's corners, and the matching
    # part came out 0 on a fifth of a map (here on 0.2 %; measured now: at least 0.47 of its median).
    relative = geometry.series_relative_height_error((-5.0, 5.0), tilt_uncertainty_deg=0.5)
    local = geometry.matching_sigma_um(result.z_um, result.sigma_um, relative_height_error=relative)[
        np.isfinite(result.z_um)
    ]
    assert local.min() > 0.2 * np.median(local)


@pytest.mark.parametrize("method", list(matching.METHODS))
def test_uncertainty_is_calibrated(method):
    """About two thirds of the actual errors lie within one reported sigma (measured: 0.60 by
    the default method, whose sigma the fused slopes narrow; 0.63 before they were fused)."""
    pair = fracture_pair(seed=5)
    result = _reconstruct(pair, (-5.0, 5.0), options=MatchingOptions(tilt_uncertainty_deg=0.0, method=method))
    valid = np.isfinite(result.z_um) & inner_mask(pair.first.shape)
    error = result.z_um[valid] - pair.z_seen_um[valid]
    error -= np.median(error)
    within = np.mean(np.abs(error) <= result.sigma_um[valid])
    assert 0.5 <= within <= 0.9


def test_data_bar_rows_come_back_as_nan_on_the_stored_grid():
    pair = fracture_pair(size_px=320)
    bar = np.zeros((24, 320), np.uint8)
    bar[8:12, 10:200:4] = 255
    first, second = (
        SemImage(np.vstack([image, bar]), -5.0 + 10.0 * k, 0.1, 24) for k, image in enumerate((pair.first, pair.second))
    )
    result = compute_height_map(first, second)
    assert result.z_um.shape == (344, 320)
    assert np.isnan(result.z_um[-24:]).all()
    assert np.isfinite(result.z_um[100:200, 100:200]).mean() > 0.95
    assert result.report["data_bar_rows"] == 24


def test_explicit_tilts_and_pixel_size_override_metadata():
    pair = fracture_pair(size_px=256)
    wrong = (SemImage(pair.first, 30.0, 5.0, 0), SemImage(pair.second, 30.0, 5.0, 0))  # equal, wrong tilts
    result = compute_height_map(*wrong, tilt_deg=(-5.0, 5.0), pixel_size_um=0.1)
    assert result.report["tilt_deg"] == [-5.0, 5.0] and result.report["pixel_size_um"] == 0.1
    from_metadata = compute_height_map(SemImage(pair.first, -5.0, 0.1, 0), SemImage(pair.second, 5.0, 0.1, 0))
    np.testing.assert_allclose(from_metadata.z_um, result.z_um, equal_nan=True)
