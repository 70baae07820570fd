"""Levels of detail and their tiles on surfaces whose shape is known exactly."""

import numpy as np
import pytest
from conftest import decode_glb, rough_with_hole, validate_glbs
from matplotlib import tri

from fractoscope.mesh import levels as mesh_levels
from fractoscope.mesh import pipeline
from fractoscope.units import METRES_PER_UM

PIXEL_SIZE_UM = 0.1


def _decode_vertices(glb: bytes) -> np.ndarray:
    """A GLB's vertices back in the height map's frame: (col_px, row_px, z_um)."""
    x_m, y_m, z_m = decode_glb(glb).positions_m.T
    return np.column_stack(
        [x_m / METRES_PER_UM / PIXEL_SIZE_UM, z_m / METRES_PER_UM / PIXEL_SIZE_UM, y_m / METRES_PER_UM]
    )


@pytest.mark.parametrize("method", list(mesh_levels.Simplification))
def test_a_plane_stays_a_plane_at_every_level(method):
    rows, cols = np.mgrid[0:530, 0:610].astype(np.float32)
    plane = 0.02 * rows - 0.01 * cols + 3.0
    tiles = list(
        mesh_levels.iter_tiles(plane, np.zeros(plane.shape, np.uint8), pixel_size_um=PIXEL_SIZE_UM, method=method)
    )
    assert len({tile.level for tile in tiles}) >= 4
    for tile in tiles:
        col_px, row_px, z_um = tile.positions.T
        np.testing.assert_allclose(z_um, 0.02 * row_px - 0.01 * col_px + 3.0, atol=1e-4)
        assert tile.geometric_error_um < 1e-4
        np.testing.assert_allclose(tile.normals, np.tile(tile.normals[0], (len(tile.normals), 1)), atol=1e-4)


def test_sphere_cap_geometric_error_is_the_true_deviation(tmp_path):
    radius_um, size = 30.0, 400
    rows, cols = np.mgrid[0:size, 0:size]
    r2 = ((rows - 199.5) ** 2 + (cols - 199.5) ** 2) * PIXEL_SIZE_UM**2
    sphere = np.sqrt(radius_um**2 - r2).astype(np.float32)
    tiles = mesh_levels.iter_tiles(sphere, np.zeros(sphere.shape, np.uint8), pixel_size_um=PIXEL_SIZE_UM)
    errors = {}
    for tile in tiles:
        if tile.level == 0:
            continue
        # Independent evaluation: matplotlib's triangle interpolation against the analytic sphere.
        x, y, z = tile.positions.T
        surface = tri.LinearTriInterpolator(tri.Triangulation(x, y, tile.triangles), z)(cols, rows)
        deviation = np.abs(np.ma.filled(surface, np.nan) - sphere)
        true_error_um = np.nanmax(deviation)
        assert tile.geometric_error_um == pytest.approx(true_error_um, rel=1e-3, abs=1e-5)
        errors[tile.level] = max(errors.get(tile.level, 0.0), tile.geometric_error_um)
    levels = sorted(errors)
    assert all(errors[a] < errors[b] for a, b in zip(levels, levels[1:]))  # coarser, larger error


@pytest.mark.parametrize("method", list(mesh_levels.Simplification))
def test_tiles_share_borders_and_every_glb_is_valid(method, tmp_path):
    z, texture = rough_with_hole()
    options = pipeline.MeshingOptions(method=method)
    tiles, report = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM, options=options)
    assert report.filtered.holes_filled > 0
    reports = validate_glbs([tile.glb for tile in tiles], tmp_path)
    assert [r["errors"] for r in reports] == [0] * len(tiles), [r["messages"] for r in reports if r["errors"]][:3]
    by_key = {(t.level, t.tile_row, t.tile_col): _decode_vertices(t.glb) for t in tiles}
    shared = 0
    for (level, row, col), vertices in by_key.items():
        right = by_key.get((level, row, col + 1))
        if right is None:
            continue
        border_x = right[:, 0].min()
        mine = {tuple(v) for v in vertices[np.isclose(vertices[:, 0], border_x, atol=1e-6)]}
        theirs = {tuple(v) for v in right[np.isclose(right[:, 0], border_x, atol=1e-6)]}
        assert mine == theirs and len(mine) > 10
        shared += 1
    assert shared >= 2


def test_coarsest_level_is_one_small_tile_and_errors_grow():
    z, texture = rough_with_hole(1100)
    tiles, _ = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    levels = sorted({t.level for t in tiles})
    coarsest = [t for t in tiles if t.level == levels[-1]]
    assert len(coarsest) == 1 and coarsest[0].triangle_count <= mesh_levels.COARSEST_TRIANGLES
    assert len(tiles) == mesh_levels.tile_count(z.shape)
    errors = [max(t.geometric_error_m for t in tiles if t.level == level) for level in levels]
    assert errors[0] == 0.0 and all(a < b for a, b in zip(errors, errors[1:]))
    finest = [t for t in tiles if t.level == 0]
    assert sum(t.vertex_count for t in finest) >= np.isfinite(z).sum()  # shared borders count twice


def test_heights_the_matcher_did_not_locate_are_not_meshed():
    """A plane whose speckle (every 7th point, as 10 % of the pollen substrate) carries heights
    off by up to 9 µm with a sigma of 8 µm, as unlocated matches do: beyond the bound (two pixels
    of disparity, 2 x 9.6 x 0.1 µm) they are left out and filled from their neighbours, so the
    mesh is the plane; with the bound at 0 every height is meshed and the speckle shows."""
    rows, cols = np.mgrid[0:96, 0:96].astype(np.float32)
    plane = 0.01 * rows + 1.0
    speckle = (rows * 96 + cols) % 7 == 0
    z = np.where(speckle, plane + np.random.default_rng(3).uniform(-9, 9, plane.shape), plane).astype(np.float32)
    sigma = np.where(speckle, 8.0, 0.05).astype(np.float32)
    bound = pipeline.MeshingOptions(max_slope=9.6, max_sigma_um=2 * 9.6 * PIXEL_SIZE_UM, level_count=1)
    texture = np.zeros(z.shape, np.uint8)
    tiles, report = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM, options=bound, sigma_um=sigma)
    assert report.uncertain_dropped == speckle.sum()
    col_px, row_px, z_um = _decode_vertices(tiles[0].glb).T
    np.testing.assert_allclose(z_um, 0.01 * row_px + 1.0, atol=0.05)  # a fill is its neighbours' Gaussian mean
    every = pipeline.MeshingOptions(max_slope=9.6, level_count=1)
    tiles, report = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM, options=every, sigma_um=sigma)
    assert report.uncertain_dropped == 0 and np.abs(_decode_vertices(tiles[0].glb)[:, 2] - 1.5).max() > 5
