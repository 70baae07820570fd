"""A height map written in any export format, chosen by name or by a file's extension: X3P (`x3p`),
float32 TIFF (`tif`), CSV (`csv`), and STL, PLY and OBJ meshes (`mesh_export`)."""

from __future__ import annotations

import os

import numpy as np

from fractoscope.formats import mesh_export
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.surface_export import write_height_csv, write_height_tiff
from fractoscope.formats.x3p import write_x3p

MESH_FORMATS = mesh_export.FILE_TYPES
FORMATS = ("x3p", "tif", "csv", *MESH_FORMATS)
MEDIA_TYPES = {
    "x3p": "application/zip",
    "tif": "image/tiff",
    "csv": "text/csv",
    "stl": "model/stl",
    "ply": "application/octet-stream",
    "obj": "model/obj",
}


# A file's bytes per grid point, about: two triangles a point for meshes (binary STL 50 B each),
# which a solid's base and walls double (measured on 512² maps: X3P 8, TIFF 4, CSV 34, STL 100,
# PLY 38, OBJ 82).
_FILE_BYTES_PER_POINT = {"x3p": 8, "tif": 4, "csv": 40, "stl": 100, "ply": 40, "obj": 90}
# What a writer holds beyond the heights per grid point: trimesh builds PLY and OBJ whole, float64
# vertices, int64 faces and then the file's text or bytes (tracemalloc on 512² maps: X3P 9, CSV
# 170, STL 380 with its fixed 50 MB blocks, PLY 186, OBJ 473; solids about twice that).
_WRITER_BYTES_PER_POINT = {"x3p": 16, "tif": 8, "csv": 200, "stl": 60, "ply": 250, "obj": 600}


def file_bytes(file_format: str, points: int, *, solid: bool = False) -> int:
    """The estimated size of a file of `file_format` for a grid of `points` points."""
    return _FILE_BYTES_PER_POINT[file_format] * points * (2 if solid else 1) + 4096


def writer_bytes(file_format: str, points: int, *, solid: bool = False) -> int:
    """The estimated memory `write_surface` takes beyond the heights for a grid of `points` points."""
    return _WRITER_BYTES_PER_POINT[file_format] * points * (2 if solid else 1)


def write_surface(
    path: str | os.PathLike,
    file_format: str,
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    sigma_um: np.ndarray | None = None,
    calibration: Calibration | None = None,
    solid: bool = False,
    units: str = "um",
) -> None:
    """Write heights in `file_format` (one of FORMATS).

    z_um, sigma_um: (rows, cols) heights and their one-sigma uncertainty, µm, NaN unknown (sigma
        goes into the CSV only). pixel_size_um: the grid step, µm; origin_um: (x, y) of pixel
        (0, 0), µm (X3P offsets, TIFF description, CSV coordinates). calibration: recorded where
        the format has room for it (X3P comment, TIFF description).
    solid, units: meshes only ("um" or "mm"); X3P stores metres, TIFF and CSV micrometres, as
        their definitions say, so other units there are an error.
    """
    if file_format not in FORMATS:
        raise ValueError(f"format: {file_format!r} is none of {list(FORMATS)}")
    if file_format in MESH_FORMATS:
        mesh_export.write_mesh(path, z_um, pixel_size_um=pixel_size_um, units=units, solid=solid)
        return
    if solid:
        raise ValueError(f"solid: only meshes ({', '.join(MESH_FORMATS)}) close into a solid, not {file_format}")
    if units != "um":
        raise ValueError(
            f"units: {file_format} files have fixed units (X3P metres, TIFF and CSV µm); {units!r} applies to meshes"
        )
    if file_format == "x3p":
        write_x3p(path, z_um, pixel_size_um=pixel_size_um, origin_um=origin_um, calibration=calibration)
    elif file_format == "tif":
        write_height_tiff(path, z_um, pixel_size_um=pixel_size_um, origin_um=origin_um, calibration=calibration)
    else:
        write_height_csv(path, z_um, pixel_size_um=pixel_size_um, origin_um=origin_um, sigma_um=sigma_um)
