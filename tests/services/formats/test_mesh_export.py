"""STL, PLY and OBJ meshes of height maps, loaded back with trimesh."""

from __future__ import annotations

import io
import math

import numpy as np
import pytest
import trimesh

from fractoscope.formats import mesh_export
from fractoscope.formats.mesh_export import height_map_mesh, write_mesh
from fractoscope.mesh.grid import area_average

ROWS, COLS, PIXEL_SIZE_UM = 30, 40, 0.5
FORMATS = ("stl", "ply", "obj")
UNITS_PER_UM = {"um": 1.0, "mm": 1e-3}


def wavy(rows: int = ROWS, cols: int = COLS) -> np.ndarray:
    """A smooth surface, float32 µm, higher towards row 0 so that a mirrored mesh would show."""
    row, col = np.mgrid[0:rows, 0:cols]
    return (np.sin(col / 4.0) + 0.05 * (rows - row) + 10.0).astype(np.float32)


def with_hole(z_um: np.ndarray) -> np.ndarray:
    """A 3 x 4 block of unknown heights away from the border: the (3 + 1) x (4 + 1) quads that touch
    it have an unknown corner."""
    z_um = z_um.copy()
    z_um[10:13, 20:24] = np.nan
    return z_um


def load(path) -> trimesh.Trimesh:
    return trimesh.load(path, force="mesh")  # merges STL's per-triangle corners into shared vertices


def grid_position(mesh: trimesh.Trimesh, *, rows: int, step: float) -> tuple[np.ndarray, np.ndarray]:
    """(row, col) of each vertex from its position in the module's frame (x = col·Δ, y = (R − 1 − row)·Δ)."""
    col = mesh.vertices[:, 0] / step
    row = rows - 1 - mesh.vertices[:, 1] / step
    np.testing.assert_allclose(col, np.round(col), atol=1e-4)
    np.testing.assert_allclose(row, np.round(row), atol=1e-4)
    return np.round(row).astype(int), np.round(col).astype(int)


@pytest.mark.parametrize("file_type", FORMATS)
@pytest.mark.parametrize("units", ["um", "mm"])
def test_surface_mesh_has_the_map_heights_at_the_grid_points(tmp_path, file_type, units):
    z_um = with_hole(wavy())
    path = tmp_path / f"surface.{file_type}"
    write_mesh(path, z_um, pixel_size_um=PIXEL_SIZE_UM, units=units)

    mesh = load(path)

    scale = UNITS_PER_UM[units]
    assert len(mesh.faces) == 2 * ((ROWS - 1) * (COLS - 1) - 4 * 5)
    assert len(mesh.vertices) == np.isfinite(z_um).sum()
    row, col = grid_position(mesh, rows=ROWS, step=PIXEL_SIZE_UM * scale)
    np.testing.assert_allclose(mesh.vertices[:, 2], z_um[row, col] * scale, rtol=1e-6)
    np.testing.assert_allclose(
        mesh.bounds,
        [
            [0, 0, np.nanmin(z_um) * scale],
            [(COLS - 1) * PIXEL_SIZE_UM * scale, (ROWS - 1) * PIXEL_SIZE_UM * scale, np.nanmax(z_um) * scale],
        ],
        rtol=1e-6,
    )
    assert (mesh.face_normals[:, 2] > 0).all()  # counter-clockwise seen from above
    assert not mesh.is_watertight


@pytest.mark.parametrize("file_type", FORMATS)
def test_files_state_their_unit(tmp_path, file_type):
    path = tmp_path / f"surface.{file_type}"
    write_mesh(path, wavy(), pixel_size_um=PIXEL_SIZE_UM, units="mm")
    head = path.read_bytes()[:300]
    statement = b"units mm, grid step 0.5 um"
    if file_type == "stl":
        assert statement in head[:80]
    elif file_type == "ply":
        assert b"\ncomment Fractoscope" in head and statement in head.split(b"end_header")[0]
    else:
        assert head.startswith(b"# Fractoscope") and statement in head.splitlines()[0]


def test_millimetres_are_micrometres_over_a_thousand(tmp_path):
    z_um = with_hole(wavy())
    write_mesh(tmp_path / "um.ply", z_um, pixel_size_um=PIXEL_SIZE_UM, units="um", solid=True)
    write_mesh(tmp_path / "mm.ply", z_um, pixel_size_um=PIXEL_SIZE_UM, units="mm", solid=True)
    in_um, in_mm = load(tmp_path / "um.ply"), load(tmp_path / "mm.ply")
    np.testing.assert_allclose(in_mm.vertices * 1000, in_um.vertices, rtol=1e-6, atol=1e-5)
    assert in_mm.volume * 1e9 == pytest.approx(in_um.volume, rel=1e-5)


def plane(rows: int = ROWS, cols: int = COLS) -> np.ndarray:
    """z = 0.2 x + 0.1 y + 3 µm at x = col·Δ, y = row·Δ."""
    row, col = np.mgrid[0:rows, 0:cols]
    return (0.2 * col * PIXEL_SIZE_UM + 0.1 * row * PIXEL_SIZE_UM + 3.0).astype(np.float32)


@pytest.mark.parametrize("file_type", FORMATS)
@pytest.mark.parametrize("units", ["um", "mm"])
def test_solid_is_a_watertight_block_of_the_right_volume(tmp_path, file_type, units):
    z_um = plane()
    path = tmp_path / f"solid.{file_type}"
    write_mesh(path, z_um, pixel_size_um=PIXEL_SIZE_UM, units=units, solid=True, base_thickness_um=2.0)

    mesh = load(path)

    scale = UNITS_PER_UM[units]
    assert mesh.is_watertight and mesh.is_winding_consistent and mesh.is_volume
    width, depth = (COLS - 1) * PIXEL_SIZE_UM, (ROWS - 1) * PIXEL_SIZE_UM
    base_um = float(z_um.min()) - 2.0
    # A plane is triangulated exactly: the block's volume is its area times the height of its centre.
    centre_um = 0.2 * width / 2 + 0.1 * depth / 2 + 3.0
    assert mesh.volume == pytest.approx(width * depth * (centre_um - base_um) * scale**3, rel=1e-5)
    np.testing.assert_allclose(
        mesh.bounds, [[0, 0, base_um * scale], [width * scale, depth * scale, float(z_um.max()) * scale]], rtol=1e-6
    )
    bottom = mesh.vertices[:, 2] < (base_um + 1e-3) * scale
    assert bottom.sum() == ROWS * COLS  # the base repeats the grid


def test_solid_fills_holes_with_the_nearest_measured_height():
    row, col = np.mgrid[0:ROWS, 0:COLS]
    z_um = (0.5 * col + 1.0).astype(np.float32)  # height 0.5 c + 1: a filled point shows its source's column
    z_um[:, :3] = np.nan  # the nearest measured point of (r, c < 3) is (r, 3)
    z_um[12:15, 18:21] = np.nan  # filled from the measured ring around it, columns 17 to 21
    mesh = height_map_mesh(z_um, pixel_size_um=PIXEL_SIZE_UM, solid=True, base_thickness_um=1.0)

    assert mesh.is_watertight and mesh.is_volume
    top = mesh.vertices[mesh.vertices[:, 2] > 2.0]  # the base lies at 2.5 - 1 µm, the surface at 2.5 µm and up
    assert len(top) == ROWS * COLS
    surface_row, surface_col = grid_position(trimesh.Trimesh(top, process=False), rows=ROWS, step=PIXEL_SIZE_UM)
    np.testing.assert_allclose(top[surface_col < 3, 2], 0.5 * 3 + 1.0)
    inside = (surface_row >= 12) & (surface_row < 15) & (surface_col >= 18) & (surface_col < 21)
    assert inside.sum() == 9
    assert set(np.round(top[inside, 2], 4)) <= {0.5 * c + 1.0 for c in range(17, 22)}
    measured = ~((surface_col < 3) | inside)
    np.testing.assert_allclose(top[measured, 2], 0.5 * surface_col[measured] + 1.0)


@pytest.mark.parametrize("block_triangles", [1 << 20, 200])
def test_our_stl_packs_what_trimesh_writes(tmp_path, monkeypatch, block_triangles):
    monkeypatch.setattr(mesh_export, "_STL_BLOCK_TRIANGLES", block_triangles)  # 200: strips of 2 rows
    z_um = with_hole(wavy())
    path = tmp_path / "ours.stl"
    write_mesh(path, z_um, pixel_size_um=PIXEL_SIZE_UM, solid=True)
    by_trimesh = height_map_mesh(z_um, pixel_size_um=PIXEL_SIZE_UM, solid=True).export(file_type="stl")

    ours = trimesh.load(path, process=False)
    theirs = trimesh.load(io.BytesIO(by_trimesh), file_type="stl", process=False)

    # The same triangles, each with the same corners in the same turn, in whatever order.
    def ordered(mesh):
        keys = mesh.triangles.reshape(len(mesh.triangles), -1)
        return np.lexsort(keys.T[::-1])

    np.testing.assert_array_equal(ours.triangles[ordered(ours)], theirs.triangles[ordered(theirs)])
    stored = np.frombuffer(
        path.read_bytes()[84:], dtype=[("normal", "<f4", 3), ("vertices", "<f4", (3, 3)), ("attr", "<u2")]
    )
    unit_normals, _ = trimesh.triangles.normals(stored["vertices"].astype(np.float64))
    np.testing.assert_allclose(stored["normal"], unit_normals, atol=1e-6)
    assert load(path).is_watertight


@pytest.mark.parametrize("factor", [4, 2.5])
def test_coarser_mesh_averages_the_map_over_each_cell(tmp_path, factor):
    rows, cols = 41, 62
    z_um = np.random.default_rng(2).normal(size=(rows, cols)).astype(np.float32)
    z_um[7:9, 30:33] = np.nan
    step_um = PIXEL_SIZE_UM * factor
    path = tmp_path / "coarse.ply"
    write_mesh(path, z_um, pixel_size_um=PIXEL_SIZE_UM, mesh_pixel_size_um=step_um)

    mesh = load(path)

    out_rows, out_cols = int(rows // factor), int(cols // factor)
    np.testing.assert_allclose(mesh.bounds[1, :2], [(out_cols - 1) * step_um, (out_rows - 1) * step_um], rtol=1e-6)
    row, col = grid_position(mesh, rows=out_rows, step=step_um)
    # Each vertex height lies within the heights of the source pixels its cell touches.
    for z, r, c in zip(mesh.vertices[:, 2], row, col):
        cell = z_um[int(r * factor) : math.ceil((r + 1) * factor), int(c * factor) : math.ceil((c + 1) * factor)]
        assert np.nanmin(cell) - 1e-5 <= z <= np.nanmax(cell) + 1e-5


def test_coarser_mesh_of_a_plane_is_the_plane_at_the_cell_centres(tmp_path):
    factor, rows, cols = 4, 40, 60
    z_um = plane(rows, cols)
    mesh = height_map_mesh(area_average(z_um, factor=factor), pixel_size_um=PIXEL_SIZE_UM * factor)
    out_rows = rows // factor
    row, col = grid_position(mesh, rows=out_rows, step=PIXEL_SIZE_UM * factor)
    # Cell (r, c) covers source pixels [r·f, (r + 1)·f): its centre is pixel r·f + (f − 1) / 2.
    centre_row, centre_col = row * factor + (factor - 1) / 2, col * factor + (factor - 1) / 2
    expected = 0.2 * centre_col * PIXEL_SIZE_UM + 0.1 * centre_row * PIXEL_SIZE_UM + 3.0
    np.testing.assert_allclose(mesh.vertices[:, 2], expected, rtol=1e-6)


def test_area_average_weights_partial_overlaps_and_skips_unknown_points():
    np.testing.assert_allclose(
        area_average(np.array([[1.0, 2.0, 3.0]] * 3), factor=1.5), [[4 / 3, 8 / 3]] * 2, rtol=1e-6
    )
    np.testing.assert_allclose(area_average(np.array([[1.0, np.nan], [3.0, 4.0]]), factor=2), [[8 / 3]], rtol=1e-6)
    assert np.isnan(area_average(np.full((2, 2), np.nan), factor=2)).all()
    z_um = with_hole(wavy())
    np.testing.assert_array_equal(area_average(z_um, factor=1), z_um)


@pytest.mark.parametrize(
    ("path", "z_um", "options", "named"),
    [
        ("mesh.stl", wavy(), {"units": "cm"}, "units"),
        ("mesh.xyz", wavy(), {}, "path"),
        ("mesh.stl", wavy(), {"mesh_pixel_size_um": 0.1}, "mesh_pixel_size_um"),
        ("mesh.stl", wavy(), {"base_thickness_um": -1.0, "solid": True}, "base_thickness_um"),
        ("mesh.stl", wavy(1, COLS), {}, "z_um"),
        ("mesh.stl", np.full((5, 5), np.nan), {}, "z_um"),
    ],
)
def test_bad_arguments_are_named(tmp_path, path, z_um, options, named):
    with pytest.raises(ValueError, match=f"^{named}:"):
        write_mesh(tmp_path / path, z_um, pixel_size_um=PIXEL_SIZE_UM, **options)
