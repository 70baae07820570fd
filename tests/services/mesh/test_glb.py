"""GLB tiles: glTF's axes and units, and what a client decodes from the compressed geometry."""

import numpy as np
import pytest
from conftest import decode_glb, rotated_to_lowest_first, rough_with_hole

from fractoscope.mesh import glb as glb_format
from fractoscope.mesh import levels as mesh_levels
from fractoscope.mesh import pipeline

PIXEL_SIZE_UM = 0.1


def test_glb_is_y_up_in_metres():
    rows, cols = np.mgrid[0:64, 0:80]
    z = (5.0 * np.exp(-((rows - 10) ** 2 + (cols - 70) ** 2) / 8.0)).astype(np.float32)  # top at row 10, column 70
    tiles, _ = pipeline.mesh_height_map(z, np.zeros(z.shape, np.uint8), pixel_size_um=PIXEL_SIZE_UM)
    positions_m = decode_glb(tiles[0].glb).positions_m
    top = positions_m[np.argmax(positions_m[:, 1])]
    np.testing.assert_allclose(top, [70 * PIXEL_SIZE_UM * 1e-6, 5e-6, 10 * PIXEL_SIZE_UM * 1e-6], rtol=1e-4)


@pytest.mark.parametrize("method", list(mesh_levels.Simplification))
def test_glb_decodes_to_the_tile_within_its_quantization(method):
    """What a client decodes (meshoptimizer, then the dequantizing node transform) is the tile's
    mesh: the same triangles, positions within half a step of a 16-bit grid over the whole map,
    normals and texture coordinates within half their 8- and 16-bit steps; and a full tile is
    several times smaller than its mesh as float32."""
    z, texture = rough_with_hole(300)
    low_m, high_m = (
        (0.0, np.nanmin(z) * 1e-6, 0.0),
        (299 * PIXEL_SIZE_UM * 1e-6, np.nanmax(z) * 1e-6, 299 * PIXEL_SIZE_UM * 1e-6),
    )
    grid = glb_format.PositionGrid.spanning(low_m, high_m)
    step_m = (np.array(high_m) - np.array(low_m)) / 65535
    for tile in mesh_levels.iter_tiles(z, texture, pixel_size_um=PIXEL_SIZE_UM, method=method, level_count=3):
        glb = glb_format.tile_glb(tile, pixel_size_um=PIXEL_SIZE_UM, grid=grid)
        decoded = decode_glb(glb)
        np.testing.assert_array_equal(
            rotated_to_lowest_first(decoded.triangles), rotated_to_lowest_first(tile.triangles)
        )
        positions_m = glb_format.to_gltf_positions_m(tile.positions, pixel_size_um=PIXEL_SIZE_UM)
        assert (np.abs(decoded.positions_m - positions_m) <= 0.5 * step_m + 1e-15).all()
        assert np.abs(decoded.normals - tile.normals).max() <= 0.5 / 127 + 1e-6
        assert np.abs(decoded.uvs - tile.uvs).max() <= 0.5 / 65535 + 1e-7
        if len(tile.triangles) > 10_000:
            float32_bytes = len(tile.positions) * 32 + tile.triangles.size * 2
            assert len(glb) < float32_bytes / 2.5, (len(glb), float32_bytes)
