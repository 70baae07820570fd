"""The magnification difference left after alignment, measured densely on the matched images: it
is unbiased and its sigma honest, and a low-magnification overview (2 px of parallax, where an
error of 6e-4 once tilted the heights by 2.4 % of their range) keeps no tilt."""

import cv2
import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo import alignment
from fractoscope.stereo.pipeline import compute_height_map

SIZE_PX = 288
TILTS_DEG = (-5.0, 5.0)


def _overview_pair(seed):
    surface = synthetic.overview_dimple_surface(SIZE_PX + 64, seed=seed)
    return synthetic.render_stereo_pair(
        surface,
        pixel_size_um=synthetic.OVERVIEW_PIXEL_SIZE_UM,
        tilt_deg=TILTS_DEG,
        output_shape=(SIZE_PX, SIZE_PX),
        seed=seed,
    )


@pytest.mark.parametrize(("seed", "epsilon"), [(1, 0.0), (2, 1e-3), (3, -5e-4)])
def test_a_magnification_difference_is_measured_within_its_sigma(seed, epsilon):
    pair = _overview_pair(seed)
    centre = ((SIZE_PX - 1) / 2.0,) * 2
    magnify = cv2.getRotationMatrix2D(centre, 0.0, 1.0 + epsilon)
    second = cv2.warpAffine(
        pair.second.astype(np.float32),
        magnify,
        (SIZE_PX, SIZE_PX),
        flags=cv2.INTER_CUBIC,
        borderMode=cv2.BORDER_REFLECT,
    )
    columns_px = np.arange(SIZE_PX) - (SIZE_PX - 1) / 2.0
    parallax_px = pair.z_seen_um * 2 * np.sin(np.radians(TILTS_DEG[1])) / synthetic.OVERVIEW_PIXEL_SIZE_UM
    disparity_px = (parallax_px + epsilon * columns_px[None, :]).astype(np.float32)
    measured, sigma = alignment.residual_magnification(pair.first, second, disparity_px)
    # Measured 0.5e-4 to 1.6e-4 off at sigma 0.9-1.6e-4; the strip-wise phase correlation used before read
    # 1.5e-3 for 1e-3, and up to 5e-4 for none.
    assert 5e-5 < sigma < 3e-4
    assert abs(measured - epsilon) < 3 * sigma


def test_a_magnification_cannot_be_told_where_too_little_is_matched():
    pair = _overview_pair(1)
    disparity_px = np.full(pair.first.shape, np.nan, np.float32)
    disparity_px[:100] = 0.0
    assert alignment.residual_magnification(pair.first, pair.second, disparity_px) is None


def test_an_overview_keeps_no_tilt():
    pair = _overview_pair(1)
    first, second = (SemImage(image, None, None, 0) for image in (pair.first, pair.second))
    result = compute_height_map(first, second, tilt_deg=TILTS_DEG, pixel_size_um=synthetic.OVERVIEW_PIXEL_SIZE_UM)
    error_um = (result.z_um - pair.z_seen_um)[16:-16, 16:-16]
    rows, cols = np.mgrid[: error_um.shape[0], : error_um.shape[1]]
    known = np.isfinite(error_um)
    design = np.column_stack([cols[known], rows[known], np.ones(known.sum())])
    plane = design @ np.linalg.lstsq(design, error_um[known], rcond=None)[0]
    # The plane's part of the error: 0.5 % of the range (2.4 % with the strips' correction, which
    # left the magnification 6e-4 off); all of it 3.6 % (4.3 %).
    span_um = np.ptp(pair.z_seen_um[16:-16, 16:-16])
    assert np.std(plane) / span_um < 0.012
    assert np.std(error_um[known]) / span_um < 0.04
