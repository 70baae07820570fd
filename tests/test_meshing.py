"""Filtering, levels of detail and GLB tiles on surfaces whose shape is known exactly."""

import grpc
import numpy as np
import pytest
from matplotlib import tri

from conftest import decode_glb, validate_glbs
from fractoscope.client import ClientError
from fractoscope.formats import glb as glb_format
from fractoscope.mesh import levels as mesh_levels
from fractoscope.mesh import pipeline
from fractoscope.surface import filtering
from fractoscope.synthetic import self_affine_surface
from fractoscope.units import METRES_PER_UM
from fractoscope.v1 import meshing_pb2

PIXEL_SIZE_UM = 0.1


def _decode_vertices(glb: bytes) -> np.ndarray:
    """A GLB's vertices back in the height map's frame: (col_px, row_px, z_um)."""
    x_m, y_m, z_m = decode_glb(glb).positions_m.T
    return np.column_stack([x_m / METRES_PER_UM / PIXEL_SIZE_UM, z_m / METRES_PER_UM / PIXEL_SIZE_UM, y_m / METRES_PER_UM])


def _rough_with_hole(size=600):
    z = self_affine_surface((size, size), hurst=0.8, rms_um=2.0, seed=4).astype(np.float32)
    z[200:260, 300:380] = np.nan
    texture = np.clip((z - np.nanmin(z)) / (np.nanmax(z) - np.nanmin(z)) * 255, 0, 255)
    return z, np.nan_to_num(texture).astype(np.uint8)


def test_isolated_spike_is_removed_and_a_step_is_kept():
    rng = np.random.default_rng(0)
    z = np.where(np.arange(100)[None, :] < 50, 0.0, 2.0) + rng.normal(0, 0.01, (100, 100))
    z = z.astype(np.float32)
    z[20, 20] += 30.0
    result = filtering.filter_heights(z, smoothing_um=0.05)
    assert result.report.outliers_removed == 1
    assert abs(result.z_um[20, 20]) < 0.1 and result.filled[20, 20]
    step = np.median(result.z_um[:, 52:60]) - np.median(result.z_um[:, 40:48])
    assert step == pytest.approx(2.0, abs=0.02)
    assert np.abs(result.z_um[:, 51] - 2.0).max() < 0.1 and np.abs(result.z_um[:, 48] - 0.0).max() < 0.1
    assert result.report.points_smoothed > 5000
    assert np.std(result.z_um[:, 5:45]) < np.std(z[:, 5:45][np.abs(z[:, 5:45]) < 1])


def test_holes_are_filled_only_near_measured_points():
    z = np.zeros((120, 120), np.float32)
    z[10:14, 10:14] = np.nan  # small hole: filled
    z[50:100, 50:100] = np.nan  # large hole: only its rim is filled
    result = filtering.filter_heights(z, max_fill_distance_px=8)
    assert np.isfinite(result.z_um[10:14, 10:14]).all()
    assert np.isnan(result.z_um[60:90, 60:90]).all()
    assert np.isfinite(result.z_um[50:58, 50:100]).all()
    assert result.report.holes_filled == int(result.filled.sum())
    assert result.report.outliers_removed == 0


@pytest.mark.parametrize("method", list(mesh_levels.Simplification))
def test_a_plane_stays_a_plane_at_every_level(method):
    rows, cols = np.mgrid[0:530, 0:610].astype(np.float32)
    plane = 0.02 * rows - 0.01 * cols + 3.0
    tiles = list(mesh_levels.iter_tiles(plane, np.zeros(plane.shape, np.uint8), pixel_size_um=PIXEL_SIZE_UM, method=method))
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
    z, texture = _rough_with_hole()
    options = pipeline.MeshingOptions(method=method)
    tiles, report = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM, options=options)
    assert report.holes_filled > 0
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
    z, texture = _rough_with_hole(1100)
    tiles, _ = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    levels = sorted({t.level for t in tiles})
    coarsest = [t for t in tiles if t.level == levels[-1]]
    assert len(coarsest) == 1 and coarsest[0].triangle_count <= mesh_levels.COARSEST_TRIANGLES
    assert len(tiles) == mesh_levels.tile_count(z.shape)
    errors = [max(t.geometric_error_m for t in tiles if t.level == level) for level in levels]
    assert errors[0] == 0.0 and all(a < b for a, b in zip(errors, errors[1:]))
    finest = [t for t in tiles if t.level == 0]
    assert sum(t.vertex_count for t in finest) >= np.isfinite(z).sum()  # shared borders count twice


def test_glb_is_y_up_in_metres():
    rows, cols = np.mgrid[0:64, 0:80]
    z = (5.0 * np.exp(-((rows - 10) ** 2 + (cols - 70) ** 2) / 8.0)).astype(np.float32)  # top at row 10, column 70
    tiles, _ = pipeline.mesh_height_map(z, np.zeros(z.shape, np.uint8), pixel_size_um=PIXEL_SIZE_UM)
    positions_m = decode_glb(tiles[0].glb).positions_m
    top = positions_m[np.argmax(positions_m[:, 1])]
    np.testing.assert_allclose(top, [70 * PIXEL_SIZE_UM * 1e-6, 5e-6, 10 * PIXEL_SIZE_UM * 1e-6], rtol=1e-4)


def _rotated_to_lowest_first(triangles: np.ndarray) -> np.ndarray:
    """Each triangle rotated (winding kept) to start at its lowest index: the index codec may
    rotate triangles."""
    shift = np.argmin(triangles, axis=1)[:, None]
    return np.take_along_axis(triangles, (shift + np.arange(3)) % 3, axis=1)


@pytest.mark.parametrize("method", list(mesh_levels.Simplification))
def test_glb_decodes_to_the_tile_within_its_quantization(method):
    """What a client decodes (meshoptimizer, then the dequantizing node transform) is the tile's
    mesh: the same triangles, positions within half a step of a 16-bit grid over the whole map,
    normals and texture coordinates within half their 8- and 16-bit steps; and a full tile is
    several times smaller than its mesh as float32."""
    z, texture = _rough_with_hole(300)
    low_m, high_m = (0.0, np.nanmin(z) * 1e-6, 0.0), (299 * PIXEL_SIZE_UM * 1e-6, np.nanmax(z) * 1e-6, 299 * PIXEL_SIZE_UM * 1e-6)
    grid = glb_format.PositionGrid.spanning(low_m, high_m)
    step_m = (np.array(high_m) - np.array(low_m)) / 65535
    for tile in mesh_levels.iter_tiles(z, texture, pixel_size_um=PIXEL_SIZE_UM, method=method, level_count=3):
        glb = glb_format.tile_glb(tile, pixel_size_um=PIXEL_SIZE_UM, grid=grid)
        decoded = decode_glb(glb)
        np.testing.assert_array_equal(_rotated_to_lowest_first(decoded.triangles), _rotated_to_lowest_first(tile.triangles))
        positions_m = glb_format.to_gltf_positions_m(tile.positions, pixel_size_um=PIXEL_SIZE_UM)
        assert (np.abs(decoded.positions_m - positions_m) <= 0.5 * step_m + 1e-15).all()
        assert np.abs(decoded.normals - tile.normals).max() <= 0.5 / 127 + 1e-6
        assert np.abs(decoded.uvs - tile.uvs).max() <= 0.5 / 65535 + 1e-7
        if len(tile.triangles) > 10_000:
            float32_bytes = len(tile.positions) * 32 + tile.triangles.size * 2
            assert len(glb) < float32_bytes / 2.5, (len(glb), float32_bytes)


def test_plain_glbs_carry_the_float32_mesh_without_extensions(client, tmp_path):
    """plain_glb, for tools without a meshopt decoder: float32 geometry, no glTF extensions, valid
    for the Khronos validator with nothing it cannot check; the same mesh as the compact GLB."""
    z, texture = _rough_with_hole(300)
    plain, _ = client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM, level_count=3, plain_glb=True)
    compact, _ = client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM, level_count=3)
    reports = validate_glbs([tile.glb for tile in plain], tmp_path)
    assert [(r["errors"], [m for m in r["messages"] if "UNSUPPORTED_EXTENSION" in m]) for r in reports] == [(0, [])] * len(plain)
    for plain_tile, compact_tile in zip(plain, compact):
        assert b"EXT_meshopt_compression" not in plain_tile.glb and b"KHR_mesh_quantization" not in plain_tile.glb
        plain_mesh, compact_mesh = decode_glb(plain_tile.glb), decode_glb(compact_tile.glb)
        np.testing.assert_array_equal(_rotated_to_lowest_first(plain_mesh.triangles), _rotated_to_lowest_first(compact_mesh.triangles))
        step_m = np.ptp(plain_mesh.positions_m, axis=0).max() / 65535 * 10  # the compact grid spans the whole map
        assert np.abs(plain_mesh.positions_m - compact_mesh.positions_m).max() <= step_m
        if plain_tile.triangle_count > 10_000:
            assert len(plain_tile.glb) > 2.5 * len(compact_tile.glb)


def test_meshing_service_streams_tiles_and_rejects_bad_input(client):
    z, texture = _rough_with_hole(300)
    tiles, report = client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    local, local_report = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    assert [(t.level, t.tile_row, t.tile_col, t.triangle_count) for t in tiles] == [
        (t.level, t.tile_row, t.tile_col, t.triangle_count) for t in local
    ]
    assert report["holes_filled"] == local_report.holes_filled
    with pytest.raises(ClientError) as error:
        client.build_mesh(z, texture[:100], pixel_size_um=PIXEL_SIZE_UM)
    assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT and error.value.field == "height_map.texture"
    with pytest.raises(ClientError) as error:
        client.build_mesh(z, texture, pixel_size_um=float("nan"))
    assert error.value.field == "height_map.pixel_size_um"
    with pytest.raises(ClientError) as error:
        client.build_mesh(np.full_like(z, np.nan), texture, pixel_size_um=PIXEL_SIZE_UM)
    assert error.value.code == grpc.StatusCode.INVALID_ARGUMENT and error.value.field == "height_map.z_um"
    with pytest.raises(ClientError) as error:
        client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM, method=7)
    assert error.value.field == "method"
    tiles, _ = client.build_mesh(z, None, pixel_size_um=PIXEL_SIZE_UM, method=meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC, level_count=2)
    assert {t.level for t in tiles} == {0, 1}
