"""Fusion of ROIs into one surface, against surfaces whose values are known everywhere."""

import numpy as np
import pytest

from fractoscope.specimen.fusion import FEATHER_PX, FusedSurface, PlacedRoi, footprint_um, overlaps


def _roi(roi_id, z_um, *, pixel_size_um, origin_um=(0.0, 0.0), texture=None, magnification=0.0):
    z_um = np.asarray(z_um, np.float32)
    texture = np.full(z_um.shape, 100, np.uint8) if texture is None else texture
    return PlacedRoi(roi_id, magnification, pixel_size_um, origin_um, z_um, texture)


def _plane(shape, pixel_size_um, origin_um=(0.0, 0.0)):
    """z = 0.3 x - 0.2 y + 5 (µm) at the ROI's pixel centres."""
    rows, cols = np.indices(shape)
    x_um, y_um = origin_um[0] + cols * pixel_size_um, origin_um[1] + rows * pixel_size_um
    return 0.3 * x_um - 0.2 * y_um + 5.0


def test_the_outermost_pixels_are_sampled_too():
    """Points on an ROI's first and last rows and columns get its heights and texture (they came
    back unknown: a zero blending weight at the edge and a NaN border in the interpolation)."""
    roi = _roi("overview", _plane((40, 60), 0.5), pixel_size_um=0.5, texture=np.full((40, 60), 80, np.uint8))
    surface = FusedSurface([roi])
    x_um = np.concatenate([np.arange(60) * 0.5, np.zeros(40), np.full(40, 29.5), np.arange(60) * 0.5])
    y_um = np.concatenate([np.zeros(60), np.arange(40) * 0.5, np.arange(40) * 0.5, np.full(60, 19.5)])
    samples = surface.sample(x_um, y_um, cell_um=0.5)
    np.testing.assert_allclose(samples.z_um, 0.3 * x_um - 0.2 * y_um + 5.0, atol=1e-4)
    assert np.allclose(samples.texture, 80) and (samples.source == 0).all()
    beyond = surface.sample(np.array([-0.3, 29.8, 5.0]), np.array([5.0, 5.0, 19.8]), cell_um=0.5)
    assert np.isnan(beyond.z_um).all()


def test_footprint_and_overlap_of_rectangles():
    assert footprint_um((10.0, 20.0), (5, 11), 0.5) == (10.0, 20.0, 15.0, 22.0)
    assert overlaps((0, 0, 1, 1), (1, 1, 2, 2)) and overlaps((0, 0, 4, 4), (1, 1, 2, 2))
    assert not overlaps((0, 0, 1, 1), (1.5, 0, 2, 1)) and not overlaps((0, 0, 1, 1), (0, 1.5, 1, 2))


def test_one_roi_is_sampled_exactly_on_a_plane_between_its_pixels():
    """Bilinear sampling reproduces a plane anywhere inside; outside the ROI there is nothing."""
    roi = _roi("overview", _plane((200, 300), 0.5, (10.0, 20.0)), pixel_size_um=0.5, origin_um=(10.0, 20.0))
    surface = FusedSurface([roi])
    rng = np.random.default_rng(0)
    x_um, y_um = rng.uniform(11, 158, 500), rng.uniform(21, 118, 500)
    samples = surface.sample(x_um, y_um, cell_um=0.5)
    np.testing.assert_allclose(samples.z_um, 0.3 * x_um - 0.2 * y_um + 5.0, atol=1e-4)
    assert (samples.source == 0).all() and np.allclose(samples.texture, 100)
    outside = surface.sample(np.array([0.0, 200.0]), np.array([0.0, 50.0]), cell_um=0.5)
    assert np.isnan(outside.z_um).all() and (outside.source == -1).all()


def test_the_finer_roi_wins_inside_and_ramps_in_over_its_feather():
    """An overview at 0 µm and a 4x finer ROI at 1 µm inside it: the ROI's value deep inside, the
    overview's outside, and a monotone ramp from one to the other over FEATHER_PX of ROI pixels."""
    overview = _roi("overview", np.zeros((200, 200)), pixel_size_um=1.0, texture=np.full((200, 200), 50, np.uint8))
    zoom = _roi(
        "zoom",
        np.ones((400, 400)),
        pixel_size_um=0.25,
        origin_um=(50.0, 50.0),
        texture=np.full((400, 400), 150, np.uint8),
    )
    surface = FusedSurface([zoom, overview])  # any order: coarse to fine inside
    assert [roi.id for roi in surface.rois] == ["overview", "zoom"] and surface.finest_pixel_size_um == 0.25
    centre = surface.sample(np.array([100.0]), np.array([100.0]), cell_um=0.25)
    assert centre.z_um[0] == pytest.approx(1.0) and centre.texture[0] == pytest.approx(150.0) and centre.source[0] == 1
    far = surface.sample(np.array([20.0]), np.array([100.0]), cell_um=0.25)
    assert far.z_um[0] == pytest.approx(0.0) and far.source[0] == 0
    # Along a row into the ROI from its left border at x = 50 µm: the feather spans 32 ROI pixels (8 µm).
    x_um = np.linspace(49.0, 50.0 + FEATHER_PX * 0.25 + 1.0, 200)
    line = surface.sample(x_um, np.full_like(x_um, 100.0), cell_um=0.25).z_um
    assert line[0] == pytest.approx(0.0) and line[-1] == pytest.approx(1.0)
    assert np.all(np.diff(line) >= -1e-6) and ((line > 0.05) & (line < 0.95)).sum() > 100


def test_a_coarse_cell_averages_the_finer_data():
    """A ±1 µm checkerboard seen with cells four pixels wide averages to its mean; with cells of
    its own pixel size it keeps its values."""
    board = np.where((np.indices((256, 256)).sum(axis=0) % 2) == 0, 1.0, -1.0)
    surface = FusedSurface([_roi("board", board, pixel_size_um=1.0)])
    x_um, y_um = np.meshgrid(np.arange(40.0, 200.0, 7.3), np.arange(40.0, 200.0, 7.3))
    coarse = surface.sample(x_um, y_um, cell_um=4.0).z_um
    assert np.abs(coarse).max() < 0.05
    at_pixels = surface.sample(np.array([40.0, 41.0]), np.array([40.0, 40.0]), cell_um=1.0).z_um
    np.testing.assert_allclose(at_pixels, [1.0, -1.0], atol=1e-6)


def test_holes_in_the_finer_roi_show_the_coarser_data():
    overview = _roi("overview", np.full((100, 100), 2.0), pixel_size_um=1.0)
    fine = np.ones((200, 200))
    fine[80:120, 80:120] = np.nan
    surface = FusedSurface([overview, _roi("zoom", fine, pixel_size_um=0.5, origin_um=(25.0, 25.0))])
    hole = surface.sample(np.array([75.0]), np.array([75.0]), cell_um=0.5)  # the hole's centre
    assert hole.z_um[0] == pytest.approx(2.0) and hole.source[0] == 0


def test_a_surface_needs_an_roi():
    with pytest.raises(ValueError):
        FusedSurface([])


def test_the_sem_image_shows_where_heights_are_unknown():
    """Heights unknown over a patch of the only ROI (what matching could not measure): the fused
    texture there is still the image's, not black, while the heights stay unknown."""
    z = np.full((120, 120), 3.0)
    z[40:80, 40:80] = np.nan
    texture = np.full((120, 120), 180, np.uint8)
    surface = FusedSurface([_roi("overview", z, pixel_size_um=1.0, texture=texture)])
    inside = surface.sample(np.array([60.0, 45.0]), np.array([60.0, 70.0]), cell_um=1.0)
    assert np.isnan(inside.z_um).all() and np.allclose(inside.texture, 180)
