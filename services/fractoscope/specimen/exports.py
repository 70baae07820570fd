"""Exports of a specimen's ROI or region, or of a height map given as arrays, written to a file of
any export format (formats.exports) in a folder the caller owns; the endpoints stream it out."""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats import exports
from fractoscope.formats._validate import height_grid
from fractoscope.formats.calibration import Calibration
from fractoscope.mesh.grid import area_average
from fractoscope.specimen import queries
from fractoscope.specimen.model import Specimen


@dataclass(frozen=True)
class ExportedFile:
    """A written export: its path, format, grid (rows, cols), step µm and origin (x, y) µm."""

    path: Path
    file_format: str
    shape: tuple[int, int]
    pixel_size_um: float
    origin_um: tuple[float, float]


def export_area(
    specimen: Specimen,
    directory: Path,
    *,
    file_format: str,
    roi: str | None = None,
    region_um=None,
    pixel_size_um: float | None = None,
    solid: bool = False,
    units: str = "um",
) -> ExportedFile:
    """An ROI (default the overview) or a region of the specimen in `directory`, at `pixel_size_um`
    (see queries.surface_area), with the calibration of the ROI it shows most of and the heights'
    whole sigma (matching and tilt, as `fracto height` writes it: SurfaceArea.total_sigma_um).
    Regions are sampled in strips and bounded by queries.MAX_EXPORT_SAMPLES."""
    area = queries.surface_area(
        specimen, roi=roi, region_um=region_um, pixel_size_um=pixel_size_um, max_samples=queries.MAX_EXPORT_SAMPLES
    )
    name = f"{specimen.id}-{area.roi.id if region_um is None else 'region'}"
    return _write(
        directory,
        name,
        file_format,
        area.z_um,
        area.total_sigma_um,
        area.pixel_size_um,
        area.origin_um,
        area.calibration,
        solid,
        units,
        heights_field="region" if region_um is not None else "roi",
    )


def export_height_map(
    directory: Path,
    z_um: np.ndarray,
    *,
    file_format: str,
    pixel_size_um: float,
    sigma_um: np.ndarray | None = None,
    calibration: Calibration | None = None,
    export_pixel_size_um: float | None = None,
    solid: bool = False,
    units: str = "um",
) -> ExportedFile:
    """A height map ((rows, cols) µm, NaN unknown, grid step `pixel_size_um`) in `directory`,
    area-averaged onto `export_pixel_size_um` when that is coarser."""
    try:
        z_um = height_grid(z_um, pixel_size_um)
    except ValueError as error:
        raise _invalid(error, heights_field="height_map.z_um") from None
    if sigma_um is not None and np.shape(sigma_um) != z_um.shape:
        raise InvalidInputError(
            "height_map.sigma_um", f"{np.shape(sigma_um)[::-1]} (width, height) differs from z_um's {z_um.shape[::-1]}"
        )
    if sigma_um is not None and np.any(np.asarray(sigma_um) < 0):
        raise InvalidInputError(
            "height_map.sigma_um", f"must be >= 0 µm (NaN where unknown), got {np.nanmin(sigma_um)}"
        )
    if export_pixel_size_um is not None and not math.isclose(export_pixel_size_um, pixel_size_um, rel_tol=1e-9):
        queries.positive_input(export_pixel_size_um, "pixel_size_um")
        if export_pixel_size_um < pixel_size_um or min(z_um.shape) < export_pixel_size_um / pixel_size_um:
            raise InvalidInputError(
                "pixel_size_um",
                f"must be at least the map's {pixel_size_um} µm and leave a pixel of its "
                f"{z_um.shape[1]} x {z_um.shape[0]}",
            )
        factor = export_pixel_size_um / pixel_size_um
        z_um = area_average(z_um, factor=factor)
        sigma_um = area_average(sigma_um, factor=factor) if sigma_um is not None else None
        pixel_size_um = export_pixel_size_um
    return _write(
        directory,
        "height-map",
        file_format,
        z_um,
        sigma_um,
        pixel_size_um,
        (0.0, 0.0),
        calibration,
        solid,
        units,
        heights_field="height_map.z_um",
    )


def _write(
    directory: Path,
    name: str,
    file_format: str,
    z_um,
    sigma_um,
    pixel_size_um,
    origin_um,
    calibration,
    solid,
    units,
    *,
    heights_field: str,
) -> ExportedFile:
    if file_format not in exports.EXPORT_FORMATS:
        raise InvalidInputError("format", f"{file_format!r} is none of {list(exports.EXPORT_FORMATS)}")
    path = Path(directory) / f"{name}.{file_format}"
    try:
        exports.write_surface(
            path,
            file_format,
            z_um,
            pixel_size_um=pixel_size_um,
            origin_um=origin_um,
            sigma_um=sigma_um,
            calibration=calibration,
            solid=solid,
            units=units,
        )
    except ValueError as error:
        raise _invalid(error, heights_field=heights_field) from None
    return ExportedFile(path, file_format, tuple(z_um.shape), float(pixel_size_um), tuple(origin_um))


def _invalid(error: ValueError, *, heights_field: str) -> InvalidInputError:
    """A writer's ValueError ("argument: problem") as InvalidInputError naming the request's field:
    the heights' problems (too few points, ...) are `heights_field`'s."""
    argument, _, message = str(error).partition(": ")
    if not message:
        return InvalidInputError(heights_field, argument)
    return InvalidInputError(heights_field if argument == "z_um" else argument, message)
