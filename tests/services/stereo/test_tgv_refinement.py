"""TGV² refinement on pairs whose disparity is known exactly: it keeps slopes, and recovers kinks
and steps that a window rounds."""

import os
import subprocess
import sys

import numpy as np
import pytest

from fractoscope.stereo import correlation, matching, tgv_refinement, tgv_zncc, window_zncc
from fractoscope.stereo.disparity import StripTask
from fractoscope.synthetic import self_affine_surface

SHAPE = (160, 256)
COLUMNS = np.arange(SHAPE[1], dtype=np.float32)[None, :].repeat(SHAPE[0], axis=0)


def _pair(disparity_px, *, noise=2.0, seed=0):
    """A textured left image and the right image it matches under `disparity_px` (left pixel
    (r, c) seen at right (r, c + d)), grey levels 20-220 with Gaussian noise of `noise` levels."""
    rng = np.random.default_rng(seed)
    texture = self_affine_surface((SHAPE[0], 3 * SHAPE[1]), hurst=0.3, rms_um=1.0, seed=seed, min_wavelength_px=3.0)
    texture = ((texture - texture.min()) / np.ptp(texture) * 200 + 20).astype(np.float32)
    # Sample the texture densely: left at x, right at x' where x' + d(x) = x (inverted numerically).
    fine_x = np.arange(texture.shape[1] // 3, dtype=np.float32)
    left = texture[:, : SHAPE[1]]
    right = np.empty(SHAPE, np.float32)
    for row in range(SHAPE[0]):
        seen_at = fine_x + disparity_px[row]  # right position of every left pixel
        right[row] = np.interp(np.arange(SHAPE[1]), seen_at, left[row])
    return left + rng.normal(0, noise, SHAPE).astype(np.float32), right + rng.normal(0, noise, SHAPE).astype(np.float32)


def _window_and_refined(disparity_px):
    left, right = (matching.local_contrast(image) for image in _pair(disparity_px))
    directions = window_zncc.match_directions(StripTask(left, right, 15, 16, 0.3, 1.0))
    refined = tgv_refinement.refine_disparity(directions.left, directions.right, directions.forward.disparity)
    return directions.forward.disparity, refined


INNER = (slice(20, -20), slice(24, -24))


def test_slopes_are_kept():
    """A tilted plane costs TGV² nothing: the refinement does not flatten it."""
    ramp = np.float32(-3.0) + COLUMNS * np.float32(6.0 / SHAPE[1])
    _, refined = _window_and_refined(ramp)
    assert np.median(np.abs(refined - ramp)[INNER]) < 0.05


def test_a_rim_is_recovered_that_a_window_rounds():
    """A ridge (slopes of ±0.2 px per px meeting in a kink, as at the rim between two dimples):
    the 15 px window averages its top off; the refinement keeps it."""
    ridge = np.float32(6.0) - np.float32(0.2) * np.abs(COLUMNS - SHAPE[1] / 2)
    window, refined = _window_and_refined(ridge)
    near = (slice(20, -20), slice(SHAPE[1] // 2 - 8, SHAPE[1] // 2 + 9))
    window_error = np.sqrt(np.mean((window - ridge)[near] ** 2))
    refined_error = np.sqrt(np.mean((refined - ridge)[near] ** 2))
    assert refined_error < 0.6 * window_error


def test_a_step_stays_sharp():
    """A 3 px step: fewer pixels beside it are off by more than half a pixel after refinement."""
    step = np.where(COLUMNS < SHAPE[1] / 2, np.float32(-1.5), np.float32(1.5))
    window, refined = _window_and_refined(step)
    assert np.sum(np.abs(refined - step)[INNER] > 0.5) < 0.7 * np.sum(np.abs(window - step)[INNER] > 0.5)


def test_strips_give_the_same_answer_as_one_piece():
    left, right = _pair(np.float32(-4.0) + COLUMNS * np.float32(8.0 / SHAPE[1]), seed=3)
    left, right = np.vstack([left] * 4), np.vstack([right] * 4)  # 640 rows
    whole = matching.match_disparity(left, right, max_disparity_px=12, method="tgv_zncc")
    strips = matching.match_disparity(left, right, max_disparity_px=12, strip_pixels=SHAPE[1] * 200, method="tgv_zncc")
    inner = (slice(None), slice(40, -40))
    both = np.isfinite(whole.disparity_px[inner]) & np.isfinite(strips.disparity_px[inner])
    assert both.mean() > 0.95
    assert np.max(np.abs(whole.disparity_px[inner][both] - strips.disparity_px[inner][both])) < 0.05


@pytest.mark.parametrize("shift_px", [2.5, -3.25])
def test_constant_shift_is_recovered_to_a_twentieth_of_a_pixel(shift_px):
    """Also where the data windows claim most (noise-free images, half-pixel shifts)."""
    left, right = _pair(np.full(SHAPE, shift_px, np.float32), noise=0.0)
    result = matching.match_disparity(left, right, max_disparity_px=8, method="tgv_zncc")
    assert np.isfinite(result.disparity_px[INNER]).mean() > 0.98
    assert np.nanmedian(np.abs(result.disparity_px - shift_px)[INNER]) < 0.05


_REFINE_IN_A_PROCESS = """
import sys
import numpy as np
from fractoscope.stereo import tgv_refinement
rng = np.random.default_rng(0)
left = rng.standard_normal((48, 96)).astype(np.float32)
right = np.roll(left, 3, axis=1) + 0.1 * rng.standard_normal((48, 96)).astype(np.float32)
np.save(sys.argv[1], tgv_refinement.refine_disparity(left, right, np.full((48, 96), 2.5, np.float32)))
"""


@pytest.mark.slow
def test_code_compiled_afresh_and_code_from_the_cache_agree_to_the_bit(tmp_path):
    """Processes share numba's cache: the first compiles the refinement and stores it, the next
    loads it. Both must give the same disparities, or a farmed-out strip differs from one
    matched at home (it did, by 1e-5 px, while the kernels allowed fastmath reassociation)."""
    env = {**os.environ, "NUMBA_CACHE_DIR": str(tmp_path / "numba-cache")}
    outputs = [tmp_path / "compiled.npy", tmp_path / "cached.npy"]
    for output in outputs:
        subprocess.run([sys.executable, "-c", _REFINE_IN_A_PROCESS, str(output)], env=env, check=True, timeout=600)
    assert any((tmp_path / "numba-cache").rglob("*.nbi")), "the first process stored no compiled code"
    compiled, cached = (np.load(output) for output in outputs)
    np.testing.assert_array_equal(compiled, cached)


def test_the_data_term_trusts_cleaner_images_more():
    """The data term's weight is its peak's precision from the images' measured decorrelation
    (noise): the same texture with a quarter of the noise is weighted several times as much, so
    the refinement smooths less where the images are cleaner."""
    shift = np.full(SHAPE, 2.0, np.float32)
    precisions = []
    for noise in (2.0, 8.0):
        left, right = (matching.local_contrast(image) for image in _pair(shift, noise=noise, seed=5))
        left, right = correlation.normalized(left), correlation.normalized(right)
        stats = correlation.window_stats(left, tgv_refinement.DATA_WINDOW_PX)
        _, precision = tgv_refinement.data_term(left, stats, right, shift, tgv_refinement.DATA_WINDOW_PX)
        precisions.append(float(np.median(precision[INNER])))
    assert precisions[0] > 4.0 * precisions[1]


def test_the_sigma_grows_with_the_directions_disagreement():
    """Known answers of `tgv_zncc.calibrated_sigma_px`: the window's sigma scaled where the two
    refined directions agree, and the strip's robust disagreement added in quadrature."""

    window_sigma = np.full((8, 8), 0.5, np.float32)
    valid = np.ones((8, 8), bool)
    agreeing = tgv_zncc.calibrated_sigma_px(window_sigma, np.zeros((8, 8), np.float32), valid)
    assert np.allclose(agreeing, 0.6 * 0.5)
    # Half of a 0.2 px disagreement everywhere, as a normal's RMS from its median: 0.1 / sqrt(0.455).
    disagreeing = tgv_zncc.calibrated_sigma_px(window_sigma, np.full((8, 8), 0.2, np.float32), valid)
    assert np.allclose(disagreeing, np.hypot(0.3, 4.0 * 0.1 / np.sqrt(0.455)), rtol=1e-5)
    # Pixels not kept do not count.
    wild = np.where(np.arange(8)[None, :] < 2, np.float32(50.0), np.float32(0.0)) * np.ones((8, 1), np.float32)
    assert np.allclose(tgv_zncc.calibrated_sigma_px(window_sigma, wild, wild == 0), 0.3)
