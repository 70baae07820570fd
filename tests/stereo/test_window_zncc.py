"""The dense matcher on pairs whose disparity is known exactly."""

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


@pytest.mark.parametrize("propagate_at_full_resolution", [False, True])
def test_strips_give_the_same_answer_as_one_piece(propagate_at_full_resolution):
    left = _texture((600, 200), seed=1)
    ramp = np.linspace(-4, 4, 200, dtype=np.float32)[None, :].repeat(600, axis=0)
    right = correlation.warp_along_rows(left, -ramp)
    whole = matching.match_disparity(left, right, max_disparity_px=12, propagate_at_full_resolution=propagate_at_full_resolution)
    strips = matching.match_disparity(left, right, max_disparity_px=12, strip_pixels=200 * 150, propagate_at_full_resolution=propagate_at_full_resolution)
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
