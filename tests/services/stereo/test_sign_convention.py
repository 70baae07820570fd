"""Which tilt direction makes a peak a peak (docs/measurement.md, "Sign convention"): in the images as given,
with the tilt axis at 90 degrees, a point that stands higher appears further right in the view at
the larger tilt. The real pollen grain comes out standing on its substrate under this convention
(tests/stereo/test_real_series.py); here a synthetic dome seen at 0/5/10 degrees, the
third-party series' tilts, comes out as a dome, and the same images turned by half a turn need
the tilt axis at 270 degrees, or their relief is inverted."""

import numpy as np
import pytest

from fractoscope import synthetic
from fractoscope.sem.image import SemImage
from fractoscope.stereo.pipeline import compute_series_height_map

PIXEL_SIZE_UM = 0.1
pytestmark = pytest.mark.slow


def _dome_series(tilt_deg):
    rows, cols = np.mgrid[0:352, 0:352].astype(np.float64)
    dome = 6.0 * np.exp(-((rows - 176) ** 2 + (cols - 176) ** 2) / (2 * 45.0**2))
    surface = dome + synthetic.self_affine_surface((352, 352), hurst=0.8, rms_um=0.4, seed=12)
    images, truth = synthetic.render_tilt_series(
        surface, pixel_size_um=PIXEL_SIZE_UM, tilt_deg=tilt_deg, output_shape=(320, 320), seed=12
    )
    return images, truth


def _relief_correlation(z_um: np.ndarray, truth: np.ndarray) -> float:
    known = np.isfinite(z_um)
    return float(np.corrcoef(z_um[known], truth[known])[0, 1])


def test_a_dome_seen_at_0_5_10_degrees_is_a_dome():
    tilts = (0.0, 5.0, 10.0)
    images, truth = _dome_series(tilts)
    views = [SemImage(image, tilt, PIXEL_SIZE_UM, 0) for image, tilt in zip(images, tilts)]
    result = compute_series_height_map(views)
    assert _relief_correlation(result.z_um, truth) > 0.95
    centre = np.nanmean(result.z_um[150:170, 150:170]) - np.nanmean(result.z_um[:30, :30])
    assert 4.5 < centre < 7.0


def test_images_turned_by_half_a_turn_need_the_axis_at_270_degrees():
    tilts = (0.0, 10.0)
    images, truth = _dome_series(tilts)
    turned = [
        SemImage(np.ascontiguousarray(np.rot90(image, 2)), tilt, PIXEL_SIZE_UM, 0) for image, tilt in zip(images, tilts)
    ]
    truth_turned = np.rot90(truth, 2)
    inverted = compute_series_height_map(turned)
    assert _relief_correlation(inverted.z_um, truth_turned) < -0.9  # a pit: the tilt runs the other way in these images
    right = compute_series_height_map(turned, tilt_axis_deg=270.0)
    assert _relief_correlation(right.z_um, truth_turned) > 0.95
