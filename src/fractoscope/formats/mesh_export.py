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
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import trimesh
from scipy import ndimage

from fractoscope.formats._validate import height_grid, positive
from fractoscope.formats.calibration import software

UNITS_PER_UM = {"um": 1.0, "mm": 1e-3}
_TRIMESH_UNITS = {"um": "microns", "mm": "mm"}
FILE_TYPES = ("stl", "ply", "obj")


def area_average(z_um: np.ndarray, *, factor: float) -> np.ndarray:
    """Heights on a grid `factor` (>= 1, any real) times coarser: each output cell is the mean of
    the measured heights it covers, weighted by the area covered (exact for fractional overlaps).

    z_um: (rows, cols) heights, µm, NaN where unknown. Output: (floor(rows / factor),
    floor(cols / factor)) float32, NaN where a cell covers no measured point; cell (i, j) spans
    source pixels [i·factor, (i + 1)·factor) along rows and likewise along columns.
    """
    z_um = np.asarray(z_um)
    if not (np.isfinite(factor) and factor >= 1):
        raise ValueError(f"factor: must be at least 1, got {factor}")
    shape = tuple(int(n // factor) for n in z_um.shape)
    if min(shape) < 1:
        raise ValueError(f"factor: {factor} leaves no cell of a {z_um.shape} map")
    valid = np.isfinite(z_um)
    sums, counts = np.zeros(z_um.shape), valid.astype(np.float64)  # float64: running sums of thousands
    np.copyto(sums, z_um, where=valid)
    for axis, size in enumerate(shape):
        edges = np.arange(size + 1) * float(factor)
        sums, counts = (_integrate_between(values, edges, axis) for values in (sums, counts))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(counts > 1e-6, sums / counts, np.nan).astype(np.float32)


def _integrate_between(values: np.ndarray, edges: np.ndarray, axis: int) -> np.ndarray:
    """Integrals of the piecewise-constant `values` (unit cells along `axis`) between consecutive
    `edges`: differences of their running integral, which is linear within each cell."""
    values = np.moveaxis(values, axis, -1)
    running = np.concatenate([np.zeros(values.shape[:-1] + (1,)), np.cumsum(values, axis=-1)], axis=-1)
    cell = np.minimum(edges.astype(np.int64), values.shape[-1] - 1)
    at_edges = running[..., cell] + (edges - cell) * values[..., cell]
    return np.moveaxis(np.diff(at_edges, axis=-1), -1, axis)


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
    coordinates, faces = _grid_mesh(z_um, pixel_size_um=pixel_size_um, units=units, solid=solid, base_thickness_um=base_thickness_um)
    mesh = trimesh.Trimesh(np.column_stack(coordinates), faces, process=False, validate=False)
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
    PLY and OBJ are trimesh's writers. Binary STL is packed here, streamed in blocks of triangles:
    trimesh's STL writer takes 46 s and several gigabytes of copies for a 4096² grid (33 million
    triangles).
    """
    file_type = Path(path).suffix.lower().lstrip(".")
    if file_type not in FILE_TYPES:
        raise ValueError(f"path: extension {Path(path).suffix!r} is none of {['.' + t for t in FILE_TYPES]}")
    z_um = height_grid(z_um, pixel_size_um)
    if mesh_pixel_size_um is not None:
        positive(mesh_pixel_size_um, "mesh_pixel_size_um")
        if mesh_pixel_size_um < pixel_size_um * (1 - 1e-9):
            raise ValueError(f"mesh_pixel_size_um: {mesh_pixel_size_um} is finer than the map's {pixel_size_um}")
        z_um = area_average(z_um, factor=mesh_pixel_size_um / pixel_size_um)
        pixel_size_um = mesh_pixel_size_um
    statement = f"{software()} height map mesh, units {units}, grid step {pixel_size_um:g} um{', solid' if solid else ''}"
    options = {"pixel_size_um": pixel_size_um, "units": units, "solid": solid, "base_thickness_um": base_thickness_um}
    if file_type == "stl":
        _write_binary_stl(path, *_grid_mesh(z_um, **options), header=statement)
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


_STL_TRIANGLE = np.dtype([("normal", "<f4", (3,)), ("vertices", "<f4", (3, 3)), ("attributes", "<u2")])


def _write_binary_stl(path, coordinates, faces: np.ndarray, *, header: str, block_faces: int = 1 << 20) -> None:
    """Binary STL: an 80-byte header (here the unit statement), the triangle count, then per
    triangle its unit normal, three vertices (float32) and a zero attribute word.

    coordinates: (x, y, z) of the vertices, float32 (N,) each; faces: (M, 3) vertex indices.
    One thread writes a block while the next is packed; memory is two blocks.
    """
    buffers = [np.zeros(min(block_faces, len(faces)), dtype=_STL_TRIANGLE) for _ in range(2)]
    with open(path, "wb") as out, ThreadPoolExecutor(max_workers=1) as writer:
        out.write(header.encode("ascii")[:80].ljust(80, b" "))
        out.write(np.uint32(len(faces)).tobytes())
        written = None
        for number, start in enumerate(range(0, len(faces), block_faces)):
            corners = faces[start : start + block_faces]
            block = buffers[number % 2][: len(corners)]
            # One coordinate at a time: numpy gathers 4-byte items fastest.
            points = [[np.take(axis, corners[:, k]) for axis in coordinates] for k in range(3)]
            for k, point in enumerate(points):
                for axis, values in enumerate(point):
                    block["vertices"][:, k, axis] = values
            (x0, y0, z0), (x1, y1, z1), (x2, y2, z2) = points
            ux, uy, uz, vx, vy, vz = x1 - x0, y1 - y0, z1 - z0, x2 - x0, y2 - y0, z2 - z0
            normal = (uy * vz - uz * vy, uz * vx - ux * vz, ux * vy - uy * vx)
            length = np.sqrt(normal[0] ** 2 + normal[1] ** 2 + normal[2] ** 2)
            np.maximum(length, np.finfo(np.float32).tiny, out=length)
            for axis, component in enumerate(normal):
                block["normal"][:, axis] = component / length
            if written is not None:
                written.result()  # the other buffer is free again
            written = writer.submit(out.write, block)
        if written is not None:
            written.result()


def _grid_mesh(z_um, *, pixel_size_um, units, solid, base_thickness_um):
    """((x, y, z) float32 (N,) each in `units`, faces (M, 3) int32) of `height_map_mesh`."""
    z_um = height_grid(z_um, pixel_size_um)
    if units not in UNITS_PER_UM:
        raise ValueError(f"units: {units!r} is none of {sorted(UNITS_PER_UM)}")
    if min(z_um.shape) < 2:
        raise ValueError(f"z_um: a mesh needs at least 2 x 2 points, got shape {z_um.shape}")
    valid = np.isfinite(z_um)
    if not valid.any():
        raise ValueError("z_um: no measured point")
    if base_thickness_um is not None:
        positive(base_thickness_um, "base_thickness_um")
    rows, cols = z_um.shape
    index_type = np.int32 if 2 * rows * cols < 2**31 else np.int64
    if solid:
        z_um = _nearest_filled(z_um, valid)
        valid = np.ones_like(valid)
    complete = valid[:-1, :-1] & valid[:-1, 1:] & valid[1:, :-1] & valid[1:, 1:]
    if not complete.any():
        raise ValueError("z_um: no quad of four measured points to triangulate")
    # Vertex k is grid point (k // cols, k % cols) until unused ones are dropped. Seen from above,
    # a quad's (top-left, bottom-left, top-right) and (top-right, bottom-left, bottom-right) turn
    # counter-clockwise.
    corner = np.arange(rows - 1, dtype=index_type)[:, None] * cols + np.arange(cols - 1, dtype=index_type)
    corner = corner.reshape(-1) if complete.all() else corner[complete]
    faces = np.empty((len(corner), 6), dtype=index_type)
    np.add(corner[:, None], np.array([0, cols, 1, 1, cols, cols + 1], dtype=index_type), out=faces)
    faces = faces.reshape(-1, 3)
    scale = UNITS_PER_UM[units]
    step = pixel_size_um * scale
    x = np.tile((np.arange(cols) * step).astype(np.float32), rows)
    y = np.repeat(((rows - 1 - np.arange(rows)) * step).astype(np.float32), cols)
    z = z_um.reshape(-1).astype(np.float32) * np.float32(scale)
    used = np.zeros_like(valid)  # a measured point in no complete quad would be a stray vertex
    for corner in (used[:-1, :-1], used[:-1, 1:], used[1:, :-1], used[1:, 1:]):
        corner |= complete
    if not used.all():
        used = used.reshape(-1)
        np.take(np.cumsum(used, dtype=index_type) - 1, faces, out=faces, mode="clip")  # in place: indices are in range
        x, y, z = (np.compress(used, values) for values in (x, y, z))
    if solid:
        z_min, z_max = float(z_um.min()), float(z_um.max())
        thickness = base_thickness_um if base_thickness_um is not None else max(0.1 * (z_max - z_min), pixel_size_um)
        top = len(z)
        walls = _side_walls(rows, cols, top).astype(index_type)
        faces = np.concatenate([faces, faces[:, ::-1] + index_type(top), walls])
        x, y = np.concatenate([x, x]), np.concatenate([y, y])
        z = np.concatenate([z, np.full_like(z, (z_min - thickness) * scale)])
    return (x, y, z), faces


def _side_walls(rows: int, cols: int, top: int) -> np.ndarray:
    """Two triangles per edge of the border of a full (rows, cols) grid (vertex r·cols + c), from
    the surface down to the base (vertex + top), facing outwards."""
    # The border clockwise seen from above: far edge, right, near edge, left, back to the start.
    ring = np.concatenate([
        np.arange(cols - 1),
        np.arange(rows - 1) * cols + cols - 1,
        (rows - 1) * cols + np.arange(cols - 1, 0, -1),
        np.arange(rows - 1, 0, -1) * cols,
    ])
    ring_next = np.roll(ring, -1)
    return np.stack([np.column_stack([ring, ring_next, ring + top]), np.column_stack([ring_next, ring_next + top, ring + top])], axis=1).reshape(-1, 3)


def _nearest_filled(z_um: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`z_um` with each unknown height replaced by the nearest measured one (Euclidean, in pixels)."""
    if valid.all():
        return z_um
    nearest = ndimage.distance_transform_edt(~valid, return_distances=False, return_indices=True)
    return z_um[tuple(nearest)]
