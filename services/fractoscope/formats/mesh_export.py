"""Triangle meshes of a height map for CAD and finite element tools: binary STL, binary PLY and
OBJ. trimesh builds the mesh and writes PLY and OBJ; binary STL is packed here (`write_mesh` says
why).

The mesh frame is right-handed with z up, so that seen from above the mesh looks like the SEM
image: vertex (r, c) of an (R, C) grid of step Δ lies at x = c·Δ, y = (R − 1 − r)·Δ (row 0 at the
far edge, y max), z = its height. Coordinates are in micrometres or millimetres (`units`); the file
states the unit in its header or comments, since none of the three formats has a unit field.

The grid gives two triangles per quad of measured points, turning counter-clockwise seen from
above; quads with an unknown (NaN) corner are left out. A `solid` mesh closes the surface into a
watertight block for finite element meshers: unknown heights are first filled with the nearest
measured one, then vertical side walls run from the surface's edge down to a flat base
`base_thickness_um` below the lowest point, and the base repeats the surface's grid (normals
down), so the solid's triangles keep the grid's proportions.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from fractoscope.formats._validate import height_grid, require_positive
from fractoscope.formats.calibration import software
from fractoscope.mesh.grid import area_average, quad_triangles
from fractoscope.progress import checkpoint

UNITS_PER_UM = {"um": 1.0, "mm": 1e-3}
_TRIMESH_UNITS = {"um": "microns", "mm": "mm"}
FILE_TYPES = ("stl", "ply", "obj")
_STL_BLOCK_TRIANGLES = 1 << 20  # 50 MB a block


def height_map_mesh(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    units: str = "um",
    solid: bool = False,
    base_thickness_um: float | None = None,
) -> trimesh.Trimesh:
    """The grid mesh of a height map, in the module's frame.

    z_um: (rows, cols) heights, µm, NaN where unknown; at least 2 x 2.
    pixel_size_um: grid step, µm. units: "um" or "mm", the unit of the mesh coordinates.
    solid: close into a watertight block (see the module docstring); base_thickness_um defaults to
        a tenth of the height range, at least one grid step.
    """
    grid = _Grid.of(z_um, pixel_size_um=pixel_size_um, units=units, solid=solid, base_thickness_um=base_thickness_um)
    rows, cols = grid.z.shape
    faces = quad_triangles(grid.complete, cols)
    vertices = grid.points(0, rows)
    used = np.zeros(grid.z.shape, dtype=bool)  # a measured point in no complete quad would be a stray vertex
    for corner in (used[:-1, :-1], used[:-1, 1:], used[1:, :-1], used[1:, 1:]):
        corner |= grid.complete
    if not used.all():
        used = used.reshape(-1)
        np.take(np.cumsum(used, dtype=faces.dtype) - 1, faces, out=faces, mode="clip")  # in place: indices are in range
        vertices = np.compress(used, vertices, axis=0)
    if grid.base_z is not None:  # solid: every point is used
        top = len(vertices)
        faces = np.concatenate([faces, faces[:, ::-1] + top, _side_walls(_border(rows, cols), top)])
        base = vertices.copy()
        base[:, 2] = grid.base_z
        vertices = np.concatenate([vertices, base])
    mesh = trimesh.Trimesh(vertices, faces, process=False, validate=False)
    mesh.units = _TRIMESH_UNITS[units]
    return mesh


def write_mesh(
    path: str | os.PathLike,
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    mesh_pixel_size_um: float | None = None,
    units: str = "um",
    solid: bool = False,
    base_thickness_um: float | None = None,
) -> None:
    """Write the mesh of a height map as STL, PLY or OBJ, chosen by the extension of `path`.

    z_um: (rows, cols) heights, µm, NaN where unknown; pixel_size_um: its grid step, µm.
    mesh_pixel_size_um: the mesh's grid step, µm, at least `pixel_size_um`: the heights are
        area-averaged onto it first (`area_average`); None keeps the map's grid.
    units, solid, base_thickness_um: as in `height_map_mesh`.
    PLY and OBJ are trimesh's writers, from the whole mesh. Binary STL, a list of triangles, is
    packed here from strips of grid rows, in bounded memory: trimesh's STL writer takes 35 to 53 s
    and 10 GB for a 4096² grid (33 million triangles).
    """
    file_type = Path(path).suffix.lower().lstrip(".")
    if file_type not in FILE_TYPES:
        raise ValueError(f"path: extension {Path(path).suffix!r} is none of {['.' + t for t in FILE_TYPES]}")
    z_um = height_grid(z_um, pixel_size_um)
    if mesh_pixel_size_um is not None:
        require_positive(mesh_pixel_size_um, "mesh_pixel_size_um")
        if mesh_pixel_size_um < pixel_size_um * (1 - 1e-9):
            raise ValueError(f"mesh_pixel_size_um: {mesh_pixel_size_um} is finer than the map's {pixel_size_um}")
        z_um = area_average(z_um, factor=mesh_pixel_size_um / pixel_size_um)
        pixel_size_um = mesh_pixel_size_um
    statement = (
        f"{software()} height map mesh, units {units}, grid step {pixel_size_um:g} um{', solid' if solid else ''}"
    )
    options = {"pixel_size_um": pixel_size_um, "units": units, "solid": solid, "base_thickness_um": base_thickness_um}
    if file_type == "stl":
        _write_binary_stl(
            path, _triangle_strips(_Grid.of(z_um, **options), triangles=_STL_BLOCK_TRIANGLES), header=statement
        )
        return
    mesh = height_map_mesh(z_um, **options)
    if file_type == "obj":
        mesh.export(path, file_type="obj", header=statement, include_normals=False)
        return
    exported = mesh.export(file_type="ply")
    body = exported.index(b"\n", exported.index(b"format")) + 1
    with open(path, "wb") as out:  # trimesh's PLY header has no unit: a comment line states it
        out.write(memoryview(exported)[:body])
        out.write(f"comment {statement}\n".encode("ascii"))
        out.write(memoryview(exported)[body:])


@dataclass(frozen=True)
class _Grid:
    """A height map ready to mesh, in the mesh's unit.

    z: (rows, cols) float32 heights, NaN where unknown (none for a solid: holes filled);
    complete: (rows - 1, cols - 1) True for quads with four known corners; step: the grid step;
    base_z: the solid's base level, None for an open surface.
    """

    z: np.ndarray
    complete: np.ndarray
    step: float
    base_z: float | None

    @classmethod
    def of(cls, z_um, *, pixel_size_um, units, solid, base_thickness_um) -> _Grid:
        z_um = height_grid(z_um, pixel_size_um)
        if units not in UNITS_PER_UM:
            raise ValueError(f"units: {units!r} is none of {sorted(UNITS_PER_UM)}")
        if min(z_um.shape) < 2:
            raise ValueError(f"z_um: a mesh needs at least 2 x 2 points, got shape {z_um.shape}")
        if 2 * z_um.size >= 2**31:
            raise ValueError(f"z_um: {z_um.shape} is too many points for one mesh; choose a coarser mesh_pixel_size_um")
        valid = np.isfinite(z_um)
        if not valid.any():
            raise ValueError("z_um: no measured point")
        if base_thickness_um is not None:
            require_positive(base_thickness_um, "base_thickness_um")
        scale = UNITS_PER_UM[units]
        base_z = None
        if solid:
            z_um = _nearest_filled(z_um, valid)
            valid = np.ones_like(valid)
            z_min, z_max = float(z_um.min()), float(z_um.max())
            thickness = (
                base_thickness_um if base_thickness_um is not None else max(0.1 * (z_max - z_min), pixel_size_um)
            )
            base_z = (z_min - thickness) * scale
        complete = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
        if not complete.any():
            raise ValueError("z_um: no quad of four measured points to triangulate")
        return cls(np.multiply(z_um, scale, dtype=np.float32), complete, pixel_size_um * scale, base_z)

    def points(self, start: int, stop: int) -> np.ndarray:
        """(N, 3) float32 (x, y, z) of the grid points of rows start to stop - 1, row-major."""
        rows, cols = self.z.shape
        points = np.empty((stop - start, cols, 3), dtype=np.float32)
        points[..., 0] = (np.arange(cols) * self.step).astype(np.float32)
        points[..., 1] = ((rows - 1 - np.arange(start, stop)) * self.step).astype(np.float32)[:, None]
        points[..., 2] = self.z[start:stop]
        return points.reshape(-1, 3)


def _border(rows: int, cols: int) -> np.ndarray:
    """The grid's border points (numbered r·cols + c), clockwise seen from above: far edge, right,
    near edge, left."""
    return np.concatenate(
        [
            np.arange(cols - 1),
            np.arange(rows - 1) * cols + cols - 1,
            (rows - 1) * cols + np.arange(cols - 1, 0, -1),
            np.arange(rows - 1, 0, -1) * cols,
        ]
    ).astype(np.int32)


def _side_walls(border: np.ndarray, top: int) -> np.ndarray:
    """(M, 3) int32: two triangles per edge of the closed `border`, from the surface (vertex i) down
    to the base (vertex i + top), facing outwards."""
    following = np.roll(border, -1)
    return np.stack(
        [
            np.column_stack([border, following, border + top]),
            np.column_stack([following, following + top, border + top]),
        ],
        axis=1,
    ).reshape(-1, 3)


def _triangle_strips(grid: _Grid, *, triangles: int) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """The triangles of `height_map_mesh` as blocks of (local vertices (N, 3) float32, faces into
    them) of about `triangles` each: strips of grid rows for the surface and the base, then the
    side walls. Vertices repeat between blocks, which a triangle list does not mind."""
    rows, cols = grid.z.shape
    strip_rows = max(1, triangles // (2 * (cols - 1)))
    for start in range(0, rows - 1, strip_rows):
        stop = min(start + strip_rows, rows - 1)  # quads of rows start to stop - 1, points to stop
        faces = quad_triangles(grid.complete[start:stop], cols)
        points = grid.points(start, stop + 1)
        yield points, faces
        if grid.base_z is not None:
            base = points.copy()
            base[:, 2] = grid.base_z
            yield base, faces[:, ::-1]
    if grid.base_z is not None:
        border = _border(rows, cols)
        ring = np.empty((2, len(border), 3), dtype=np.float32)
        ring[:, :, 0] = (border % cols) * grid.step
        ring[:, :, 1] = (rows - 1 - border // cols) * grid.step
        ring[0, :, 2], ring[1, :, 2] = grid.z.reshape(-1)[border], grid.base_z
        yield ring.reshape(-1, 3), _side_walls(np.arange(len(border), dtype=np.int32), len(border))


_STL_TRIANGLE = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attributes", "<u2")])


def _write_binary_stl(path, blocks, *, header: str) -> None:
    """Binary STL: an 80-byte header (here the unit statement), the triangle count, then per
    triangle its unit normal, three vertices (float32) and a zero attribute word.

    blocks: (vertices (N, 3) float32, faces (M, 3) into them), as `_triangle_strips` yields.
    One thread writes a block while the next is packed.
    """
    buffers, written, count = [np.zeros(0, dtype=_STL_TRIANGLE)] * 2, None, 0
    with open(path, "wb") as out, ThreadPoolExecutor(max_workers=1) as writer:
        out.write(header.encode("ascii")[:80].ljust(80, b" ") + bytes(4))  # the count follows at the end
        for number, (vertices, faces) in enumerate(blocks):
            checkpoint()  # a block a checkpoint: a 6 GB file is written by the hundred
            if len(buffers[number % 2]) < len(faces):
                buffers[number % 2] = np.zeros(len(faces), dtype=_STL_TRIANGLE)
            block = buffers[number % 2][: len(faces)]
            corners = np.take(vertices, faces, axis=0).reshape(len(faces), 9)  # numpy gathers whole rows fast
            x0, y0, z0, x1, y1, z1, x2, y2, z2 = corners.T.copy()  # and computes on contiguous rows fast
            ux, uy, uz, vx, vy, vz = x1 - x0, y1 - y0, z1 - z0, x2 - x0, y2 - y0, z2 - z0
            normal = np.stack([uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx], axis=1)
            normal /= np.maximum(np.sqrt(np.einsum("ij,ij->i", normal, normal)), np.finfo(np.float32).tiny)[:, None]
            # Copied as bytes: 50-byte records leave the floats unaligned, which numpy writes slowly.
            record = block.view(np.uint8).reshape(len(faces), _STL_TRIANGLE.itemsize)
            record[:, :12] = normal.view(np.uint8)
            record[:, 12:48] = corners.view(np.uint8)
            if written is not None:
                written.result()  # the other buffer is free again
            written = writer.submit(out.write, block)
            count += len(faces)
        if written is not None:
            written.result()
        out.seek(80)
        out.write(np.uint32(count).tobytes())


def _nearest_filled(z_um: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`z_um` with each unknown height replaced by the nearest measured one (Euclidean, in pixels)."""
    if valid.all():
        return z_um
    nearest = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return z_um[tuple(nearest)]
