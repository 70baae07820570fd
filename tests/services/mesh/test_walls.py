"""Walls ("curtains"): triangles across a jump steeper than stereo can measure are marked, kept out
of the geometric error, and written as their own primitive; tiles with nothing measured are skipped."""

import numpy as np
import pytest
from conftest import decode_glb, fracture_pair, validate_glbs

from fractoscope.mesh import levels as mesh_levels
from fractoscope.mesh import pipeline, walls
from fractoscope.sem.image import SemImage
from fractoscope.stereo.geometry import matching_sigma_um, max_measurable_slope, series_relative_height_error
from fractoscope.stereo.pipeline import compute_height_map

PIXEL_SIZE_UM = 0.1


def _plateau(size=600, height_um=30.0):
    """A gently rolling surface with a 30 µm plateau (a grain on a substrate) whose rim rises over
    2 px: far steeper than a ±3° pair can measure (slope 9.6)."""
    rows, cols = np.mgrid[0:size, 0:size].astype(np.float32)
    base = 0.3 * np.sin(cols / 37.0) * np.cos(rows / 23.0)
    radius = np.hypot(rows - size / 2, cols - size / 2)
    plateau = height_um * np.clip((size / 4 - radius) / 2.0, 0, 1)
    return (base + plateau).astype(np.float32)


def test_the_slope_limit_is_one_pixel_of_disparity_per_pixel():
    assert max_measurable_slope((-3.0, 3.0)) == pytest.approx(1 / np.sin(np.radians(6)) * np.cos(np.radians(3)))
    assert max_measurable_slope((-10.0, 10.0)) == pytest.approx(2.88, abs=0.01)
    assert max_measurable_slope((0.0, 5.0, 10.0)) == pytest.approx(1 / np.sin(np.radians(10)))  # the widest pair


def test_grid_walls_follow_the_jump_and_its_uncertainty():
    z = np.zeros((4, 4))
    z[:, 2:] = 5.0  # a 5 µm step between columns 1 and 2
    x, y = np.meshgrid(np.arange(4) * 0.1, np.arange(4) * 0.1)
    upper, lower = walls.grid_wall_triangles(x, y, z, max_slope=9.6)
    assert (upper | lower)[:, 1].all() and not (upper | lower)[:, [0, 2]].any()
    upper, lower = walls.grid_wall_triangles(x, y, z, max_slope=9.6, sigma_um=2.0)  # 3 sigma of the difference: 8.5 µm
    assert not (upper | lower).any()
    assert not np.concatenate(walls.grid_wall_triangles(x, y, z, max_slope=None)).any()


def test_cliffs_become_walls_and_leave_the_geometric_error_alone(tmp_path):
    z = _plateau()
    texture = np.full(z.shape, 128, np.uint8)
    options = pipeline.MeshingOptions(max_slope=max_measurable_slope((-3.0, 3.0)))
    marked, _ = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM, options=options)
    plain, _ = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    assert all(tile.wall_triangle_count == 0 for tile in plain)
    coarse = [t for t in marked if t.level >= 2]
    assert coarse and all(t.wall_triangle_count > 0 for t in coarse)
    # The rim (30 µm) dominated every coarse level's error; without it the error is the
    # rolling surface's and the rounding of the plateau's top.
    for with_walls, without in zip(marked, plain):
        assert with_walls.triangle_count == without.triangle_count
        if with_walls.level >= 2:
            assert without.geometric_error_m > 10e-6 and with_walls.geometric_error_m < 0.3 * without.geometric_error_m
    # Walls are their own primitive ("wall"), and no triangle spans the rim outside them.
    decoded = decode_glb(marked[0].glb)
    assert len(decoded.wall_triangles) > 0
    heights = decoded.positions_m[:, 1] * 1e6
    spans = np.ptp(heights[decoded.triangles], axis=1)
    assert spans.max() < 1.0 and np.ptp(heights[decoded.wall_triangles], axis=1).min() > 0.9  # 9.6 x 0.1 µm
    assert all(r["errors"] == 0 for r in validate_glbs([t.glb for t in marked[-3:]], tmp_path))


def test_a_coarser_level_is_never_said_to_be_better_than_the_finer_one():
    """Leaving out more around the walls at coarser levels must not make a parent's error smaller
    than its children's (a viewer that refines it would find them worse): on a matched synthetic
    pair the levels' errors were 0, 0.21, 0.15 and 0.18 µm."""
    pair = fracture_pair(size_px=256, seed=11)
    matched = compute_height_map(
        SemImage(pair.first, None, None, 0), SemImage(pair.second, None, None, 0), tilt_deg=(-5, 5), pixel_size_um=0.1
    )
    local = matching_sigma_um(
        matched.z_um,
        matched.sigma_um,
        relative_height_error=series_relative_height_error((-5, 5), tilt_uncertainty_deg=0.5),
    )
    options = pipeline.MeshingOptions(max_slope=max_measurable_slope((-5.0, 5.0)))
    tiles, _ = pipeline.mesh_height_map(matched.z_um, pair.first, pixel_size_um=0.1, options=options, sigma_um=local)
    by_level = [
        max(t.geometric_error_m for t in tiles if t.level == level) for level in range(max(t.level for t in tiles) + 1)
    ]
    assert len(by_level) >= 3 and by_level[-1] > 0 and by_level == sorted(by_level)


@pytest.mark.parametrize("method", list(mesh_levels.Simplification))
def test_tiles_with_no_measured_point_are_skipped(method):
    """A map whose right half is unknown (the real pollen pair's upper corner was): its tiles
    there are left out instead of failing the whole mesh."""
    z = _plateau(600)
    z[:, 250:] = np.nan
    z[:5, :5] = np.nan
    tiles, _ = pipeline.mesh_height_map(
        z,
        np.zeros(z.shape, np.uint8),
        pixel_size_um=PIXEL_SIZE_UM,
        options=pipeline.MeshingOptions(method=method, max_fill_distance_px=0),
    )
    finest = [(t.tile_row, t.tile_col) for t in tiles if t.level == 0]
    assert finest == [(0, 0), (1, 0), (2, 0)] and len(tiles) < mesh_levels.tile_count(z.shape)
    assert all(t.triangle_count > 0 for t in tiles)
