"""A height map written in any export format, chosen by name or by a file's extension: the one
registry of export formats (`EXPORT_FORMATS`), each with its writer, media type and costs: X3P
(`x3p`), float32 TIFF (`tif`), CSV (`csv`), and STL, PLY and OBJ meshes (`mesh_export`). The
API's ExportFormat enum names the same formats (tests/test_registries.py holds them equal)."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from fractoscope.formats import mesh_export
from fractoscope.formats.calibration import Calibration
from fractoscope.formats.surface_export import write_height_csv, write_height_tiff
from fractoscope.formats.x3p import write_x3p


@dataclass(frozen=True)
class Heights:
    """What every writer is given: heights and their one-sigma uncertainty, (rows, cols) µm, NaN
    unknown; the grid step and the (x, y) of pixel (0, 0), µm; the calibration; and for meshes
    whether to close a solid and the units ("um" or "mm")."""

    z_um: np.ndarray
    pixel_size_um: float
    origin_um: tuple[float, float]
    sigma_um: np.ndarray | None
    calibration: Calibration | None
    solid: bool
    units: str


@dataclass(frozen=True)
class ExportFormat:
    """One export format: its writer, its media type, and its sizes per grid point, about: the
    file's bytes, and what the writer holds beyond the heights (measured on 512² maps, see
    EXPORT_FORMATS). `mesh`: a triangle mesh, which alone closes into a solid and takes units."""

    write: Callable[[str | os.PathLike, Heights], None]
    media_type: str
    file_bytes_per_point: int
    writer_bytes_per_point: int
    mesh: bool = False


def _with_calibration(writer: Callable[..., None]) -> Callable[[str | os.PathLike, Heights], None]:
    """A writer of the heights on their grid, with its origin and the calibration (X3P, TIFF)."""

    def write(path: str | os.PathLike, heights: Heights) -> None:
        writer(
            path,
            heights.z_um,
            pixel_size_um=heights.pixel_size_um,
            origin_um=heights.origin_um,
            calibration=heights.calibration,
        )

    return write


def _write_csv(path: str | os.PathLike, heights: Heights) -> None:
    write_height_csv(
        path, heights.z_um, pixel_size_um=heights.pixel_size_um, origin_um=heights.origin_um, sigma_um=heights.sigma_um
    )


def _write_mesh(path: str | os.PathLike, heights: Heights) -> None:
    mesh_export.write_mesh(
        path, heights.z_um, pixel_size_um=heights.pixel_size_um, units=heights.units, solid=heights.solid
    )


# File bytes: two triangles a point for meshes (binary STL 50 B each), which a solid's base and
# walls double (measured: X3P 8, TIFF 4, CSV 34, STL 100, PLY 38, OBJ 82). Writer bytes: trimesh
# builds PLY and OBJ whole, float64 vertices, int64 faces and then the file's text or bytes
# (tracemalloc: X3P 9, CSV 170, STL 380 with its fixed 50 MB blocks, PLY 186, OBJ 473; solids
# about twice that).
EXPORT_FORMATS = {
    "x3p": ExportFormat(_with_calibration(write_x3p), "application/zip", 8, 16),
    "tif": ExportFormat(_with_calibration(write_height_tiff), "image/tiff", 4, 8),
    "csv": ExportFormat(_write_csv, "text/csv", 40, 200),
    "stl": ExportFormat(_write_mesh, "model/stl", 100, 60, mesh=True),
    "ply": ExportFormat(_write_mesh, "application/octet-stream", 40, 250, mesh=True),
    "obj": ExportFormat(_write_mesh, "model/obj", 90, 600, mesh=True),
}
MESH_FORMATS = tuple(name for name, export_format in EXPORT_FORMATS.items() if export_format.mesh)


def file_bytes(file_format: str, points: int, *, solid: bool = False) -> int:
    """The estimated size of a file of `file_format` for a grid of `points` points."""
    return EXPORT_FORMATS[file_format].file_bytes_per_point * points * (2 if solid else 1) + 4096


def writer_bytes(file_format: str, points: int, *, solid: bool = False) -> int:
    """The estimated memory `write_surface` takes beyond the heights for a grid of `points` points."""
    return EXPORT_FORMATS[file_format].writer_bytes_per_point * points * (2 if solid else 1)


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
    """Write heights in `file_format` (a key of EXPORT_FORMATS).

    z_um, sigma_um: (rows, cols) heights and their one-sigma uncertainty, µm, NaN unknown (sigma
        goes into the CSV only). pixel_size_um: the grid step, µm; origin_um: (x, y) of pixel
        (0, 0), µm (X3P offsets, TIFF description, CSV coordinates). calibration: recorded where
        the format has room for it (X3P comment, TIFF description).
    solid, units: meshes only ("um" or "mm"); X3P stores metres, TIFF and CSV micrometres, as
        their definitions say, so other units there are an error.
    """
    if file_format not in EXPORT_FORMATS:
        raise ValueError(f"format: {file_format!r} is none of {list(EXPORT_FORMATS)}")
    export_format = EXPORT_FORMATS[file_format]
    if not export_format.mesh and solid:
        raise ValueError(f"solid: only meshes ({', '.join(MESH_FORMATS)}) close into a solid, not {file_format}")
    if not export_format.mesh and units != "um":
        raise ValueError(
            f"units: {file_format} files have fixed units (X3P metres, TIFF and CSV µm); {units!r} applies to meshes"
        )
    heights = Heights(z_um, pixel_size_um, origin_um, sigma_um, calibration, solid, units)
    export_format.write(path, heights)
