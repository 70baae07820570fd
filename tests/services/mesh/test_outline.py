"""What a tile set shows where measurement ends, between tiles and of islands, read back from the
GLBs the builds write: seamless texture and shading across tile borders, no island below the
minimum, unmeasured areas absent or a flat floor at zero, and valid glTF throughout."""

import cv2
import numpy as np
import pytest
import trimesh
from conftest import decode_glb, glb_texture, mesh_component_areas_um2, tile_seams_grey_levels, validate_glbs

from fractoscope.mesh import outline, pipeline

PIXEL_SIZE_UM = 0.1
MIN_ISLAND_PX = outline.DEFAULT_MIN_ISLAND_PX


def _surface_with_islands() -> tuple[np.ndarray, np.ndarray, int]:
    """(heights µm, texture, islands planted): a rough 600 x 600 map with a large unmeasured disc
    and three 8 x 8 px patches inside it, far from everything else."""
    rng = np.random.default_rng(3)
    z = cv2.GaussianBlur(rng.normal(0, 2.0, (600, 600)).astype(np.float32), (0, 0), 6) + 5.0
    texture = np.clip(128 + 40 * rng.standard_normal(z.shape), 0, 255).astype(np.uint8)
    rows, cols = np.indices(z.shape)
    z[np.hypot(rows - 300, cols - 300) < 180] = np.nan
    for row, col in ((250, 250), (300, 330), (340, 260)):
        z[row : row + 8, col : col + 8] = 5.0
    return z, texture, 3


def _tiles(unmeasured=outline.Unmeasured.ABSENT, **options):
    z, texture, _ = _surface_with_islands()
    settings = pipeline.MeshingOptions(unmeasured=unmeasured, max_fill_distance_px=2, **options)
    return pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM, options=settings)


def test_islands_below_the_minimum_are_dropped_and_counted():
    tiles, report = _tiles()
    assert report.islands_dropped == 3
    areas_px = mesh_component_areas_um2(tile.glb for tile in tiles if tile.level == 0) / PIXEL_SIZE_UM**2
    assert (areas_px >= MIN_ISLAND_PX).all(), areas_px
    kept, report = _tiles(min_island_px=0.0)
    assert report.islands_dropped == 0 and sum(t.triangle_count for t in kept) > sum(t.triangle_count for t in tiles)


def test_a_map_smaller_than_the_minimum_is_kept_whole():
    """The largest patch is the surface, never an island: a small map is meshed, not emptied."""
    z = np.zeros((8, 8), np.float32)
    z[0, 0] = np.nan
    kept, dropped = outline.drop_islands(z, min_area_cells=MIN_ISLAND_PX)
    assert dropped == 0 and np.array_equal(np.isfinite(kept), np.isfinite(z))
    z[5:, :] = np.nan  # a 1-row gap splits a 3-row patch (which stays) from a smaller 2-row one
    z[4, :] = np.nan
    z[6:, :] = 1.0
    kept, dropped = outline.drop_islands(z, min_area_cells=MIN_ISLAND_PX)
    assert dropped == 1 and np.isfinite(kept[:4, 1:]).all() and not np.isfinite(kept[6:]).any()


def test_neighbouring_tiles_share_texture_and_normals_at_their_border():
    tiles, _ = _tiles()
    level0 = {(t.tile_row, t.tile_col): t.glb for t in tiles if t.level == 0}
    assert (0, 1) in level0 and (1, 0) in level0
    for (row, col), glb in level0.items():
        right, below = level0.get((row, col + 1)), level0.get((row + 1, col))
        if right is not None:
            assert np.abs(glb_texture(glb)[:, -1].astype(int) - glb_texture(right)[:, 0]).max() <= 2
            mine, theirs = decode_glb(glb), decode_glb(right)
            border = mine.positions_m[:, 0].max()
            a = np.isclose(mine.positions_m[:, 0], border, atol=1e-9)
            b = np.isclose(theirs.positions_m[:, 0], border, atol=1e-9)
            order_a, order_b = np.argsort(mine.positions_m[a, 2]), np.argsort(theirs.positions_m[b, 2])
            np.testing.assert_allclose(mine.normals[a][order_a], theirs.normals[b][order_b], atol=0.02)
        if below is not None:
            assert np.abs(glb_texture(glb)[-1].astype(int) - glb_texture(below)[0]).max() <= 2


def test_unmeasured_areas_absent_or_flat_at_zero(tmp_path):
    absent, _ = _tiles(plain_glb=True)
    flat, _ = _tiles(outline.Unmeasured.FLAT, plain_glb=True)
    assert all(len(decode_glb(t.glb).floor_triangles) == 0 for t in absent)
    floor_area_m2 = surface_area_m2 = 0.0
    for tile in (t for t in flat if t.level == 0):
        decoded = decode_glb(tile.glb)
        floor = decoded.floor_triangles
        assert np.all(decoded.positions_m[np.unique(floor), 1] == 0.0)  # glTF Y is the height
        floor_area_m2 += trimesh.Trimesh(decoded.positions_m, floor, process=False).area
        top = decoded.positions_m.copy()
        top[:, 1] = 0.0
        surface_area_m2 += trimesh.Trimesh(top, np.concatenate([decoded.triangles, decoded.wall_triangles])).area
    assert floor_area_m2 > 0
    # Surface and floor tile the map's plane exactly: 599 x 599 quads of 0.1 µm.
    assert floor_area_m2 + surface_area_m2 == pytest.approx((599 * PIXEL_SIZE_UM * 1e-6) ** 2, rel=1e-6)
    assert floor_area_m2 == pytest.approx(np.pi * (180 * PIXEL_SIZE_UM * 1e-6) ** 2, rel=0.05)
    reports = validate_glbs(
        [t.glb for t in flat[:4]] + [t.glb for t in _tiles(outline.Unmeasured.FLAT)[0][:4]], tmp_path
    )
    assert [r["errors"] for r in reports] == [0] * len(reports), [r["messages"] for r in reports if r["errors"]][:3]


def test_chamfers_follow_an_oblique_mask_edge():
    z = np.full((40, 40), 1.0, np.float32)
    rows, cols = np.indices(z.shape)
    z[cols > rows] = np.nan  # a 45° edge: a staircase of whole quads without chamfers
    settings = pipeline.MeshingOptions(max_fill_distance_px=0, min_island_px=0.0, plain_glb=True)
    (tile,), _ = pipeline.mesh_height_map(z, np.zeros(z.shape, np.uint8), pixel_size_um=1.0, options=settings)
    decoded = decode_glb(tile.glb)
    area_um2 = trimesh.Trimesh(decoded.positions_m, decoded.triangles, process=False).area / 1e-12
    assert area_um2 == pytest.approx(39 * 39 / 2, rel=1e-6)  # the triangle under the diagonal, exactly


def test_the_demo_specimen_has_no_texture_seams(built):
    _, _, data, summary = built
    worst = tile_seams_grey_levels(data / "specimens" / summary["id"])
    assert len(worst) > 20 and max(worst) <= 2
