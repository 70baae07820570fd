"""Semi-global matching's wrapper keeps our disparity convention, and the default matcher's seed
places a step between two textured planes where the pixels put it, on both sides."""

import cv2
import numpy as np
import pytest

from fractoscope.stereo import correlation
from fractoscope.stereo.matching import local_contrast
from fractoscope.stereo.semi_global import seed_disparity, sgbm_disparity


def _texture(shape, seed):
    noise = np.random.default_rng(seed).normal(size=shape).astype(np.float32)
    return cv2.GaussianBlur(noise, (0, 0), 1.2)


def _grey(values):
    return np.clip(128 + 40 * values / values.std(), 0, 255).astype(np.uint8)


@pytest.mark.parametrize("shift_px", [6, -9])
def test_sgbm_disparity_follows_our_convention(shift_px):
    left = _grey(_texture((160, 200), seed=1))
    right = np.roll(left, shift_px, axis=1)  # right[col + shift] = left[col]: disparity +shift
    disparity = sgbm_disparity(left, right, min_px=-16, max_px=16, block_px=5)
    inner = disparity[10:-10, 30:-30]
    assert np.isfinite(inner).mean() > 0.9
    assert np.nanmedian(inner) == pytest.approx(shift_px, abs=0.25)


@pytest.mark.parametrize("min_px, max_px", [(-125, 5), (-200, -150)])
def test_a_search_as_wide_as_the_image_is_cut_to_what_opencv_can_score(min_px, max_px):
    """OpenCV refuses a search that leaves no block inside the image (a 128 px strip searched to
    ±128 px came back INTERNAL from MatchStrip): what is left of it is searched."""
    left = _grey(_texture((64, 128), seed=1))
    right = np.roll(left, -9, axis=1)
    disparity = sgbm_disparity(left, right, min_px=min_px, max_px=max_px, block_px=5)
    assert disparity.shape == left.shape
    found = disparity[np.isfinite(disparity)]
    assert np.all((found >= min_px - 16) & (found <= max_px))


def test_the_seed_places_a_step_where_the_pixels_put_it():
    rows, cols, step_col = 200, 320, 160
    near_px, far_px = 10, 2  # the left plane is nearer: it hides the right one's first 8 px
    left = _texture((rows, cols), seed=2)
    right = _texture((rows, cols), seed=3)  # what neither plane covers in the right view
    columns = np.arange(cols)
    for first, stop, disparity in ((step_col, cols - far_px, far_px), (0, step_col, near_px)):  # far plane first
        right[:, columns[first:stop] + disparity] = left[:, first:stop]
    left_n, right_n = (correlation.normalized(local_contrast(image)) for image in (left, right))
    guide = np.where(columns < step_col, near_px, far_px).astype(np.float32)[None, :].repeat(rows, axis=0)
    seed = seed_disparity(left_n, right_n, guide)
    band = slice(20, rows - 20)
    near_side = seed[band, step_col - 30 : step_col - 2]
    hidden = seed[band, step_col : step_col + near_px - far_px]  # the far plane's strip the near one hides
    far_side = seed[band, step_col + near_px - far_px : step_col + 25]  # visible in both views
    assert np.mean(np.abs(near_side - near_px) <= 1.0) > 0.9
    assert np.mean(np.abs(far_side - far_px) <= 1.0) > 0.9  # window correlation: 0.74, it fattens the step
    assert np.mean(np.abs(hidden - near_px) <= 1.0) < 0.2


def test_images_too_small_for_a_seed_get_none():
    tiny = correlation.normalized(_texture((20, 300), seed=4))  # fewer rows than a seed needs
    assert np.isnan(seed_disparity(tiny, tiny, np.zeros_like(tiny))).all()
