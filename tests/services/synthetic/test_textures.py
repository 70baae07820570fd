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


@pytest.mark.parametrize("texture", ["speckle", "sem"])
def test_a_displaced_texture_is_found_where_its_disparity_says(texture):
    """The second image sampled at (row, col + d) shows the first, d the pair's exact disparity
    (a cosine of 0.5 px and a 12 px period): measured 6.7 grey levels RMS apart for the speckles
    (their sharp edges resample poorly at the images' own pixels) and 2.1 for the SEM-like
    texture, against 25 and 5.9 assuming no displacement."""
    factor, shape = 4, (64, 200)
    fine_shape = (shape[0] * factor, shape[1] * factor)
    if texture == "speckle":
        fine = synthetic.speckle_texture(fine_shape, speckle_px=4.0 * factor, seed=3)
    else:
        fine = synthetic.sem_texture(fine_shape, pixel_size_um=0.1 / factor, seed=3)

    def displacement(row_px, col_px):
        return 0.5 * np.cos(2 * np.pi * col_px / 12.0) + 0.0 * row_px

    first, second, disparity = synthetic.displaced_pair(fine, displacement, factor=factor, noise_fraction=0.0)
    rows, cols = np.mgrid[: shape[0], : shape[1]].astype(np.float32)
    found = cv2.remap(second.astype(np.float32), cols + disparity.astype(np.float32), rows, cv2.INTER_CUBIC)
    inner = (slice(4, -4), slice(4, -4))
    matched_grey = np.sqrt(np.mean((found - first)[inner] ** 2))
    unmoved_grey = np.sqrt(np.mean((second.astype(np.float32) - first)[inner] ** 2))
    assert matched_grey < 0.4 * unmoved_grey
    assert np.abs(disparity - displacement(rows, cols + disparity)).max() < 1e-9
