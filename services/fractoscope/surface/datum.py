"""Where height zero is: a datum plane fitted to the whole surface, to its substrate, or to a region.

Stereo heights are relative (their offset is arbitrary, and an uneven stage leaves a tilt). A
datum gives them a meaning: with the "substrate" datum, the heights of a grain lying on a flat
substrate are its heights above that substrate. Each datum is a plane fitted by robust least
squares (surface.form_removal) and subtracted; heights are (rows, cols) µm, NaN unknown, and a
region is (x_min, y_min, x_max, y_max) µm with x = col * pixel size, y = row * pixel size.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fractoscope.surface.form_removal import remove_form

LEVELS = ("plane", "substrate")
# The substrate search starts from the lowest fifth of the heights and grows by points within
# this many robust sigmas of its plane.
_SUBSTRATE_START_QUANTILE = 0.2
_SUBSTRATE_SIGMAS = 3.0
_SUBSTRATE_ROUNDS = 4


@dataclass(frozen=True)
class Datum:
    """How heights were levelled: `level` ("plane", "substrate" or "region"), the region (µm) for
    "region", and the plane that was subtracted: z = offset_um + slope_x x + slope_y y (x, y µm),
    with the share of measured points that defined it."""

    level: str
    offset_um: float
    slope_x: float
    slope_y: float
    region_um: tuple[float, float, float, float] | None = None
    fraction: float = 1.0

    def to_dict(self) -> dict:
        return {
            "level": self.level,
            "offset_um": self.offset_um,
            "slope_x": self.slope_x,
            "slope_y": self.slope_y,
            "region_um": list(self.region_um) if self.region_um else None,
            "fraction": self.fraction,
        }


def level_heights(
    z_um: np.ndarray, *, pixel_size_um: float, level: str | tuple[float, float, float, float]
) -> tuple[np.ndarray, Datum]:
    """Heights with the datum plane subtracted (float32) and the datum. `level`: "plane" (a plane
    through all measured heights), "substrate" (through the lowest extensive level: the points
    near a plane grown from the lowest fifth of the heights) or a region (x_min, y_min, x_max,
    y_max) µm. ValueError when the region or substrate holds too few measured points."""
    z = np.asarray(z_um, np.float64)
    measured = np.isfinite(z)
    if isinstance(level, str):
        if level not in LEVELS:
            raise ValueError(f"level must be one of {', '.join(LEVELS)} or a region, not {level!r}")
        region = measured if level == "plane" else _substrate(z, measured, pixel_size_um)
        name, region_um = level, None
    else:
        region_um = tuple(float(v) for v in level)
        x0, y0, x1, y1 = region_um
        if not (x0 < x1 and y0 < y1):
            raise ValueError("the region's minimum must be smaller than its maximum in x and y")
        rows, cols = np.indices(z.shape)
        region = (
            measured
            & (cols * pixel_size_um >= x0)
            & (cols * pixel_size_um <= x1)
            & (rows * pixel_size_um >= y0)
            & (rows * pixel_size_um <= y1)
        )
        name = "region"
    if region.sum() < 3:
        raise ValueError(f"the {name} datum needs at least 3 measured points, found {int(region.sum())}")
    offset, slope_x, slope_y = _plane(z, region, pixel_size_um)
    rows, cols = np.indices(z.shape)
    levelled = z - (offset + slope_x * cols * pixel_size_um + slope_y * rows * pixel_size_um)
    datum = Datum(name, offset, slope_x, slope_y, region_um, float(region.sum() / max(measured.sum(), 1)))
    return levelled.astype(np.float32), datum


def _plane(z: np.ndarray, region: np.ndarray, pixel_size_um: float) -> tuple[float, float, float]:
    """(offset, slope along x, slope along y) of the robust plane through `region`."""
    fit = remove_form(z, pixel_size_um=pixel_size_um, form="plane", region=region)
    form = fit.form_um
    rows, cols = z.shape
    offset = float(form[0, 0])
    slope_x = float((form[0, -1] - form[0, 0]) / ((cols - 1) * pixel_size_um)) if cols > 1 else 0.0
    slope_y = float((form[-1, 0] - form[0, 0]) / ((rows - 1) * pixel_size_um)) if rows > 1 else 0.0
    return offset, slope_x, slope_y


def _substrate(z: np.ndarray, measured: np.ndarray, pixel_size_um: float) -> np.ndarray:
    """The measured points of the lowest extensive level: start from the lowest fifth, fit a
    plane, keep every point within _SUBSTRATE_SIGMAS robust sigmas of it (the substrate's own
    roughness and tilt), and refit."""
    if measured.sum() < 3:
        return measured
    region = measured & (z <= np.quantile(z[measured], _SUBSTRATE_START_QUANTILE))
    rows, cols = np.indices(z.shape)
    for _ in range(_SUBSTRATE_ROUNDS):
        offset, slope_x, slope_y = _plane(z, region, pixel_size_um)
        residual = z - (offset + slope_x * cols * pixel_size_um + slope_y * rows * pixel_size_um)
        inside = residual[region]
        scale = 1.4826 * np.median(np.abs(inside - np.median(inside)))
        grown = measured & (np.abs(residual) <= _SUBSTRATE_SIGMAS * max(scale, 1e-6))
        if grown.sum() < 3 or np.array_equal(grown, region):
            break
        region = grown
    return region
