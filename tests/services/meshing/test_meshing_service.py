"""The meshing service over a real gRPC server on loopback."""

import grpc
import numpy as np
import pytest
from conftest import decode_glb, rotated_to_lowest_first, rough_with_hole, validate_glbs

from fractoscope.client import ClientError
from fractoscope.mesh import pipeline
from fractoscope.v1 import meshing_pb2

PIXEL_SIZE_UM = 0.1


def test_plain_glbs_carry_the_float32_mesh_without_extensions(client, tmp_path):
    """plain_glb, for tools without a meshopt decoder: float32 geometry, no glTF extensions, valid
    for the Khronos validator with nothing it cannot check; the same mesh as the compact GLB."""
    z, texture = rough_with_hole(300)
    plain, _ = client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM, level_count=3, plain_glb=True)
    compact, _ = client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM, level_count=3)
    reports = validate_glbs([tile.glb for tile in plain], tmp_path)
    assert [(r["errors"], [m for m in r["messages"] if "UNSUPPORTED_EXTENSION" in m]) for r in reports] == [
        (0, [])
    ] * len(plain)
    for plain_tile, compact_tile in zip(plain, compact):
        assert b"EXT_meshopt_compression" not in plain_tile.glb and b"KHR_mesh_quantization" not in plain_tile.glb
        plain_mesh, compact_mesh = decode_glb(plain_tile.glb), decode_glb(compact_tile.glb)
        np.testing.assert_array_equal(
            rotated_to_lowest_first(plain_mesh.triangles), rotated_to_lowest_first(compact_mesh.triangles)
        )
        step_m = np.ptp(plain_mesh.positions_m, axis=0).max() / 65535 * 10  # the compact grid spans the whole map
        assert np.abs(plain_mesh.positions_m - compact_mesh.positions_m).max() <= step_m
        if plain_tile.triangle_count > 10_000:
            assert len(plain_tile.glb) > 2.5 * len(compact_tile.glb)


def test_meshing_service_streams_tiles_and_rejects_bad_input(client):
    z, texture = rough_with_hole(300)
    tiles, report = client.build_mesh(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    local, local_report = pipeline.mesh_height_map(z, texture, pixel_size_um=PIXEL_SIZE_UM)
    assert [(t.level, t.tile_row, t.tile_col, t.triangle_count) for t in tiles] == [
        (t.level, t.tile_row, t.tile_col, t.triangle_count) for t in local
    ]
    assert report["holes_filled"] == local_report.filtered.holes_filled
    assert report["islands_dropped"] == local_report.islands_dropped
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
    tiles, _ = client.build_mesh(
        z, None, pixel_size_um=PIXEL_SIZE_UM, method=meshing_pb2.SIMPLIFICATION_METHOD_QUADRIC, level_count=2
    )
    assert {t.level for t in tiles} == {0, 1}
