"""Placing a finer ROI in its parent: position, heights and brightness against known placements."""

import cv2
import numpy as np
import pytest

from fractoscope.errors import InvalidInputError
from fractoscope.specimen.fusion import PlacedRoi
from fractoscope.specimen.registration import align_heights, apply_height_alignment, match_texture, register_child


def _texture(shape, seed=0) -> np.ndarray:
    """Smooth random grey texture (noise blurred over 2 px), float32 0-255."""
    noise = np.random.default_rng(seed).random(shape).astype(np.float32)
    blurred = cv2.GaussianBlur(noise, (0, 0), 2.0)
    return (blurred - blurred.min()) / np.ptp(blurred) * 255


def _sampled(image: np.ndarray, col_px: np.ndarray, row_px: np.ndarray) -> np.ndarray:
    return cv2.remap(image.astype(np.float32), col_px.astype(np.float32), row_px.astype(np.float32), cv2.INTER_CUBIC)


@pytest.mark.parametrize("origin_px, zoom", [((60.0, 45.0), 2), ((83.4, 101.7), 4)])
def test_a_child_image_is_found_where_it_was_cut_from(origin_px, zoom):
    """The child is the parent resampled `zoom` times finer from `origin_px` (col, row): its pixel
    (0, 0) is found there, to a tenth of a parent pixel."""
    parent = _texture((256, 256))
    rows, cols = np.indices((96 * zoom // 2, 96 * zoom // 2), dtype=np.float64)
    child = _sampled(parent, origin_px[0] + cols / zoom, origin_px[1] + rows / zoom)
    found = register_child(parent, child, parent_pixel_size_um=1.0, child_pixel_size_um=1.0 / zoom)
    assert np.hypot(*np.subtract(found.origin_px, origin_px)) < 0.1, found.origin_px
    assert found.score > 0.95


def test_a_child_too_small_or_too_large_is_refused_with_the_field():
    parent = _texture((64, 64))
    with pytest.raises(InvalidInputError) as small:
        register_child(parent, _texture((20, 20)), parent_pixel_size_um=1.0, child_pixel_size_um=0.25)
    assert small.value.field == "rois.center_um"
    with pytest.raises(InvalidInputError) as large:
        register_child(parent, _texture((100, 100)), parent_pixel_size_um=1.0, child_pixel_size_um=1.0)
    assert large.value.field == "rois.pixel_size_um"


def _parent_and_child(offset_um, slope_x, slope_y):
    """A parent at 1 µm/px whose heights are the plane z = 0.01 x + 0.02 y, and a child at
    0.5 µm/px with its pixel (0, 0) at (20, 30) µm whose heights are the parent's there minus
    the plane offset + slope_x x + slope_y y of its own frame (µm)."""
    rows, cols = np.indices((100, 120))
    parent = PlacedRoi(
        "parent", 100.0, 1.0, (0.0, 0.0), (0.01 * cols + 0.02 * rows).astype(np.float32), np.zeros((100, 120), np.uint8)
    )
    rows, cols = np.indices((80, 80))
    x_um, y_um = cols * 0.5, rows * 0.5
    true_um = 0.01 * (20.0 + x_um) + 0.02 * (30.0 + y_um)
    child_z = true_um - (offset_um + slope_x * x_um + slope_y * y_um)
    child = PlacedRoi("child", 200.0, 0.5, (20.0, 30.0), child_z.astype(np.float32), np.zeros((80, 80), np.uint8))
    return parent, child, true_um


def test_the_plane_between_child_and_parent_heights_is_recovered_and_removed():
    parent, child, true_um = _parent_and_child(0.5, 0.001, -0.002)
    fitted = align_heights(parent, child)
    assert fitted.offset_um == pytest.approx(0.5, abs=1e-4)
    assert fitted.slope_x == pytest.approx(0.001, abs=1e-5) and fitted.slope_y == pytest.approx(-0.002, abs=1e-5)
    assert fitted.residual_um < 1e-4 and fitted.overlap_points == 40 * 40
    aligned = apply_height_alignment(child.z_um, fitted, pixel_size_um=child.pixel_size_um)
    assert aligned.dtype == np.float32
    np.testing.assert_allclose(aligned, true_um, atol=2e-4)


def test_a_child_upside_down_against_its_parent_is_told_by_their_reliefs_correlation():
    """Issue 46: a specimen whose ROI alone was inverted kept its overview as it was, silently."""
    rows, cols = np.indices((100, 120))
    relief = lambda x_um, y_um: (np.sin(x_um / 5.0) * np.cos(y_um / 7.0) + 0.01 * x_um).astype(np.float32)  # noqa: E731
    parent = PlacedRoi("parent", 100.0, 1.0, (0.0, 0.0), relief(cols, rows), np.zeros((100, 120), np.uint8))
    rows, cols = np.indices((80, 80))
    child_z = relief(20.0 + cols * 0.5, 30.0 + rows * 0.5)
    for sign in (1.0, -1.0):
        child = PlacedRoi("child", 200.0, 0.5, (20.0, 30.0), sign * child_z, np.zeros((80, 80), np.uint8))
        assert align_heights(parent, child).height_correlation == pytest.approx(sign, abs=0.05)
    flat, _, _ = _parent_and_child(0.0, 0.0, 0.0)  # planes only: no relief to tell by
    assert np.isnan(align_heights(flat, _parent_and_child(0.0, 0.0, 0.0)[1]).height_correlation)


def test_a_child_outside_its_parent_cannot_be_aligned():
    parent, child, _ = _parent_and_child(0.0, 0.0, 0.0)
    away = PlacedRoi(child.id, child.magnification, child.pixel_size_um, (500.0, 500.0), child.z_um, child.texture)
    with pytest.raises(InvalidInputError, match="fewer than 16"):
        align_heights(parent, away)


def test_the_child_texture_gets_the_parents_brightness_and_contrast():
    """The child sees the parent's texture at half its contrast and 40 grey levels brighter: after
    matching, its mean and spread are the parent's on the overlap."""
    parent_texture = _texture((128, 128))
    rows, cols = np.indices((128, 128), dtype=np.float64)
    seen = _sampled(parent_texture, 30.0 + cols / 2, 20.0 + rows / 2)
    parent = PlacedRoi(
        "parent", 100.0, 1.0, (0.0, 0.0), np.zeros((128, 128), np.float32), parent_texture.astype(np.uint8)
    )
    child = PlacedRoi(
        "child",
        200.0,
        0.5,
        (30.0, 20.0),
        np.zeros((128, 128), np.float32),
        np.clip(seen * 0.5 + 40, 0, 255).astype(np.uint8),
    )
    matched = match_texture(parent, child).astype(np.float64)
    assert matched.mean() == pytest.approx(seen.mean(), abs=2.0)
    assert matched.std() == pytest.approx(seen.std(), rel=0.05)
