"""Height maps as a float32 TIFF image or a CSV point list, for image tools and spreadsheets.

Both use the specimen's frame: row r, column c is the point x = x0 + c·Δ, y = y0 + r·Δ (y grows
down the image, as in `--region X0,Y0,X1,Y1`), heights in µm.
"""

from __future__ import annotations

import os
from contextlib import nullcontext
from typing import TextIO

import numpy as np
import tifffile

from fractoscope.formats._validate import height_grid, origin
from fractoscope.formats.calibration import Calibration, export_description
from fractoscope.progress import checkpoint

CSV_COLUMNS = ("x_um", "y_um", "z_um", "sigma_um")
UM_PER_CM = 1e4


def write_height_tiff(
    path: str | os.PathLike,
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    calibration: Calibration | None = None,
) -> None:
    """Write heights as a single-page float32 TIFF.

    z_um: (rows, cols) heights, µm, NaN where unknown (stored as NaN).
    pixel_size_um: grid step, µm: stored in the resolution tags as pixels per centimetre (the
        finest unit TIFF has) and in the description.
    origin_um: (x0, y0), µm, the position of pixel (0, 0), in the description.
    calibration: in the ImageDescription, the JSON of `export_description`, with "z_unit": "um".
    """
    z_um = height_grid(z_um, pixel_size_um)
    per_cm = UM_PER_CM / pixel_size_um
    description = export_description(
        calibration, grid_step_um=float(pixel_size_um), origin_um=list(origin(origin_um)), z_unit="um"
    )
    tifffile.imwrite(
        path,
        np.asarray(z_um, dtype=np.float32),
        photometric="minisblack",
        resolution=(per_cm, per_cm),
        resolutionunit="CENTIMETER",
        description=description,
        metadata=None,  # no tifffile description besides ours
    )


def write_height_csv(
    file: str | os.PathLike | TextIO,
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    sigma_um: np.ndarray | None = None,
    origin_um: tuple[float, float] = (0.0, 0.0),
    block_rows: int = 256,
) -> int:
    """Write heights as CSV with the header x_um,y_um,z_um,sigma_um; returns the rows written.

    z_um: (rows, cols) heights, µm; points where z_um is NaN are left out, so every line is a
        measured point that any CSV reader parses as numbers.
    sigma_um: (rows, cols) one-sigma height uncertainty, µm; the field is empty where it is None or
        NaN.
    origin_um: (x0, y0), µm, the position of pixel (0, 0).
    Values are written with 9 significant digits, which recovers float32 exactly. Streamed in blocks
    of `block_rows` image rows.
    """
    z_um = height_grid(z_um, pixel_size_um)
    if sigma_um is not None and np.shape(sigma_um) != z_um.shape:
        raise ValueError(f"sigma_um: shape {np.shape(sigma_um)} differs from z_um's {z_um.shape}")
    if block_rows < 1:
        raise ValueError(f"block_rows: must be at least 1, got {block_rows}")
    x0, y0 = origin(origin_um)
    rows, cols = z_um.shape
    x_um = x0 + np.arange(cols) * float(pixel_size_um)
    written = 0
    opened = (
        open(file, "w", newline="", encoding="ascii") if isinstance(file, (str, os.PathLike)) else nullcontext(file)
    )
    with opened as out:
        out.write(",".join(CSV_COLUMNS) + "\n")
        for start in range(0, rows, block_rows):
            checkpoint()
            z = z_um[start : start + block_rows]
            row, col = np.nonzero(np.isfinite(z))
            sigma = (
                np.full(row.shape, np.nan)
                if sigma_um is None
                else np.asarray(sigma_um[start : start + block_rows])[row, col]
            )
            y = y0 + (start + row) * float(pixel_size_um)
            lines = [
                f"{xv:.9g},{yv:.9g},{zv:.9g},{'' if sv != sv else format(sv, '.9g')}\n"
                for xv, yv, zv, sv in zip(x_um[col].tolist(), y.tolist(), z[row, col].tolist(), sigma.tolist())
            ]
            out.write("".join(lines))
            written += len(lines)
    return written
