"""Flat textures seen displaced: the displacement is what the images show."""

import cv2
import numpy as np
import pytest

from fractoscope import synthetic


@pytest.mark.parametrize("shape", [(96, 400), (400, 96)])
def test_a_shifted_texture_shows_its_shift(shape):
    whole = synthetic.shifted_texture_pair(shape, shift_px=(3.0, -2.0), noise_fraction=0.0, seed=4)
    # The texture is periodic: a whole-pixel shift is a roll, to the grey level.
    rolled = np.roll(whole.first, (-2, 3), axis=(0, 1)).astype(int)
    assert np.abs(rolled - whole.second).max() <= 1
    fraction = synthetic.shifted_texture_pair(shape, shift_px=(3.3, -1.7), noise_fraction=0.0, seed=4)
    # OpenCV's phase correlation locates the peak to a few tenths of a pixel.
    (shift_cols, shift_rows), _ = cv2.phaseCorrelate(
        *(image.astype(np.float64) for image in (fraction.first, fraction.second))
    )
    assert (shift_cols, shift_rows) == pytest.approx((3.3, -1.7), abs=0.3)
    assert whole.first.dtype == np.uint8 and np.ptp(whole.first) > 200 and not whole.z_seen_um.any()
