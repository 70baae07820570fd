"""The dense matcher on pairs whose disparity is known exactly."""

import tracemalloc

import numpy as np
import pytest

from fractoscope.stereo import correlation, matching, window_zncc
from fractoscope.synthetic import self_affine_surface


def _texture(shape, seed=0):
    values = self_affine_surface(shape, hurst=0.3, rms_um=1.0, seed=seed, min_wavelength_px=3.0)
    return ((values - values.min()) / np.ptp(values) * 200 + 20).astype(np.float32)


@pytest.mark.parametrize("shift_px", [3.3, -7.6, 0.25])
def test_constant_shift_is_recovered_to_a_twentieth_of_a_pixel(shift_px):
    left = _texture((256, 320))
    right = correlation.warp_along_rows(left, np.full(left.shape, -shift_px, np.float32))
    result = matching.match_disparity(left, right, max_disparity_px=16)
    inner = result.disparity_px[20:-20, 20:-20]
    assert np.isfinite(inner).mean() > 0.98
    assert np.nanmedian(np.abs(inner - shift_px)) < 0.05


def test_search_range_as_wide_as_a_small_image_is_searched():
    """The widest allowed range (the image width) on an image too small for a deep pyramid: a
    coarse search of more than 128 candidate shifts."""
    left = _texture((200, 200), seed=2)
    right = correlation.warp_along_rows(left, np.full(left.shape, -3.0, np.float32))
    result = matching.match_disparity(left, right, max_disparity_px=200)
    assert np.nanmedian(np.abs(result.disparity_px[20:-20, 20:-20] - 3.0)) < 0.05


@pytest.mark.parametrize("method", list(matching.METHODS))
def test_no_match_beyond_the_search_range_is_kept(method):
    """A 6.5 px shift searched within ±4 px: window correlation's peak sits at the search's edge
    and the refinement is not bound by it; neither may pass for a measurement."""
    left = _texture((200, 240), seed=3)
    right = correlation.warp_along_rows(left, np.full(left.shape, -6.5, np.float32))
    wide = matching.match_disparity(left, right, max_disparity_px=16, method=method).disparity_px
    narrow = matching.match_disparity(left, right, max_disparity_px=4, method=method).disparity_px
    assert np.isfinite(wide[20:-20, 20:-20]).mean() > 0.98
    assert not np.any(np.abs(narrow[np.isfinite(narrow)]) >= 3.0)


def test_a_full_search_of_a_thin_strip_needs_no_memory_per_shift():
    """A strip too thin for a pyramid is searched at full resolution over every shift; the
    scores come one shift at a time (a 48 × 20000 pair once took 24 GB this way)."""
    left = _texture((24, 3000), seed=4)
    right = correlation.warp_along_rows(left, np.full(left.shape, -2.0, np.float32))
    stats = correlation.window_stats(left, 15)
    tracemalloc.start()
    refined = window_zncc.residual_search(left, stats, right, np.zeros(left.shape, np.float32), 15, 600)
    _, peak_bytes = tracemalloc.get_traced_memory()
    tracemalloc.stop()
    assert np.nanmedian(np.abs(refined.disparity[5:-5, 20:-20] - 2.0)) < 0.1
    assert peak_bytes < 40 * left.nbytes  # all 1201 scores at once: 1201 times


@pytest.mark.parametrize("propagate_at_full_resolution", [False, True])
def test_strips_give_the_same_answer_as_one_piece(propagate_at_full_resolution):
    left = _texture((600, 200), seed=1)
    ramp = np.linspace(-4, 4, 200, dtype=np.float32)[None, :].repeat(600, axis=0)
    right = correlation.warp_along_rows(left, -ramp)
    whole = matching.match_disparity(
        left, right, max_disparity_px=12, propagate_at_full_resolution=propagate_at_full_resolution
    )
    strips = matching.match_disparity(
        left,
        right,
        max_disparity_px=12,
        strip_pixels=200 * 150,
        propagate_at_full_resolution=propagate_at_full_resolution,
    )
    # Away from the side borders (where the pyramids of different heights see different edges)
    # the seams between strips must not show.
    inner = (slice(None), slice(40, 160))
    both = np.isfinite(whole.disparity_px[inner]) & np.isfinite(strips.disparity_px[inner])
    assert both.mean() > 0.95
    assert np.max(np.abs(whole.disparity_px[inner][both] - strips.disparity_px[inner][both])) < 0.05
    assert np.nanmedian(np.abs(strips.disparity_px[inner] - ramp[inner])) < 0.1


def test_small_islands_among_masked_pixels_are_speckles():
    disparity = np.full((100, 100), np.nan, np.float32)
    disparity[:, :60] = 2.0  # a large consistent region
    disparity[40:45, 80:85] = 9.0  # a 25-pixel island
    speckles = window_zncc.speckles(disparity, np.isfinite(disparity), max_pixels=100)
    assert speckles[40:45, 80:85].all()
    assert not speckles[:, :60].any()


def test_textureless_images_are_masked_not_guessed():
    flat = np.full((128, 128), 100.0, np.float32)
    result = matching.match_disparity(flat, flat, max_disparity_px=8)
    assert np.isnan(result.disparity_px).all()


@pytest.mark.parametrize("seed", [0, 1])
def test_a_thin_strip_of_a_flat_surface_stays_flat(seed):
    """48 rows cannot tell a magnification: the features' fit once read 0.981 ± 0.005 there and
    turned a 3 px shift (a flat surface) into a ramp of several µm, and the parallax of a flat
    surface, which has no direction, was read as a tilt axis 20° off."""
    import cv2

    from fractoscope.sem.image import SemImage
    from fractoscope.stereo.pipeline import compute_height_map

    noise = cv2.GaussianBlur(np.random.default_rng(seed).normal(size=(48, 2000)).astype(np.float32), (0, 0), 2.0)
    left = ((noise - noise.min()) / np.ptp(noise) * 255).astype(np.uint8)
    result = compute_height_map(
        SemImage(left, None, None, 0),
        SemImage(np.roll(left, 3, axis=1), None, None, 0),
        tilt_deg=(-5.0, 5.0),
        pixel_size_um=0.1,
    )
    inner = result.z_um[:, 50:-50]
    assert np.isfinite(inner).mean() > 0.9
    assert np.nanpercentile(inner, 95) - np.nanpercentile(inner, 5) < 0.3  # µm; 3 px is 1.72 µm of height
    # No warning of a magnification or a tilt axis; a flat surface cannot tell the relief's sign.
    assert result.report["warnings"] == []
    assert not result.report["relief_sign_decided"]
