"""Profiles and roughness of a stored specimen, validated; shared by the gRPC and HTTP endpoints."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.specimen.store import Specimen
from fractoscope.surface import profiles, roughness

MAX_REGION_SAMPLES = 2048 * 2048
MAX_PROFILE_SAMPLES = 1_000_000


@dataclass(frozen=True)
class SpecimenProfile:
    """Samples along a polyline: (n,) distances and heights µm (NaN unknown), per-sample index into
    `sources` (ROI ids; -1 none), and the ISO 21920-2 parameters (None with < 3 known heights)."""

    distance_um: np.ndarray
    z_um: np.ndarray
    source_index: np.ndarray
    sources: list[str]
    parameters: dict | None


def positive(value: float, field: str) -> float:
    if not (math.isfinite(value) and value > 0):
        raise InvalidInputError(field, f"must be a positive number, got {value}")
    return value


def checked_region(region_um, field: str = "region", *, allow_point: bool = False) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) µm as floats: finite, min below max (or equal, with
    `allow_point`)."""
    values = tuple(float(v) for v in region_um)
    if not all(math.isfinite(v) for v in values):
        raise InvalidInputError(field, "coordinates must be finite")
    ordered = (values[0] <= values[2] and values[1] <= values[3]) if allow_point else (values[0] < values[2] and values[1] < values[3])
    if not ordered:
        raise InvalidInputError(field, "min must be smaller than max in x and y")
    return values


def profile_along(specimen: Specimen, points_um, *, spacing_um: float = 0.0, magnification: float = 0.0) -> SpecimenProfile:
    """The fused surface along a polyline of (x, y) µm: at the finest pixel size the line meets, or
    at the one a magnification means; samples `spacing_um` apart (default: that pixel size)."""
    points = np.asarray(points_um, np.float64).reshape(-1, 2)
    if len(points) < 2:
        raise InvalidInputError("points", f"a profile needs at least two points, got {len(points)}")
    if not np.all(np.isfinite(points)):
        raise InvalidInputError("points", "coordinates must be finite")
    if magnification:
        cell_um = specimen.pixel_size_at_magnification(positive(magnification, "magnification"))
    else:
        cell_um = specimen.finest_pixel_size_um((points[:, 0].min(), points[:, 1].min(), points[:, 0].max(), points[:, 1].max()))
    spacing_um = positive(spacing_um, "spacing_um") if spacing_um else cell_um
    length_um = float(np.hypot(*np.diff(points, axis=0).T).sum())
    if length_um / spacing_um > MAX_PROFILE_SAMPLES:
        raise InvalidInputError("spacing_um", f"gives more than {MAX_PROFILE_SAMPLES} samples; use a larger spacing")
    try:
        positions, distances = profiles.polyline_positions(points, spacing_um=spacing_um)
    except ValueError as error:
        raise InvalidInputError("points", str(error)) from None
    samples = specimen.surface.sample(positions[:, 0], positions[:, 1], cell_um=cell_um)
    z_um = samples.z_um.astype(np.float64)
    parameters = profiles.profile_parameters(distances, z_um) if np.isfinite(z_um).sum() >= 3 else None
    return SpecimenProfile(distances, z_um, samples.source, [roi.id for roi in specimen.surface.rois], parameters)


def height_statistics(specimen: Specimen, region_um) -> dict:
    """Statistics of the fused surface's measured heights in a region (x_min, y_min, x_max, y_max)
    µm, sampled at the finest pixel size there (coarser if that would exceed MAX_REGION_SAMPLES):
    mean, median, std, min, max (µm; None when nothing is measured), the number of measured
    samples, their share of all samples and the sampling pixel size."""
    x0, y0, x1, y1 = checked_region(region_um, allow_point=True)
    cell_um = specimen.finest_pixel_size_um((x0, y0, x1, y1))
    cell_um = max(cell_um, math.sqrt((x1 - x0) * (y1 - y0) / MAX_REGION_SAMPLES))
    x_um, y_um = np.meshgrid(np.arange(x0, x1 + 1e-9, cell_um), np.arange(y0, y1 + 1e-9, cell_um))
    z_um = specimen.surface.sample(x_um, y_um, cell_um=cell_um).z_um
    known = z_um[np.isfinite(z_um)].astype(np.float64)
    figures = (known.mean(), np.median(known), known.std(), known.min(), known.max()) if known.size else (None,) * 5
    names = ("mean_um", "median_um", "std_um", "min_um", "max_um")
    return {**{name: None if value is None else float(value) for name, value in zip(names, figures)},
            "count": int(known.size), "measured_fraction": known.size / z_um.size, "pixel_size_um": cell_um}


def roughness_of(specimen: Specimen, *, roi: str | None = None, region_um=None) -> dict:
    """ISO 25178-2 parameters (keys Sa ... Sdr) and fracture metrics of one ROI as measured, or of a
    region of the fused surface sampled at the finest pixel size there (coarser if that would exceed
    MAX_REGION_SAMPLES)."""
    if region_um is not None:
        x0, y0, x1, y1 = checked_region(region_um)
        cell_um = specimen.finest_pixel_size_um((x0, y0, x1, y1))
        cell_um = max(cell_um, math.sqrt((x1 - x0) * (y1 - y0) / MAX_REGION_SAMPLES))
        x_um, y_um = np.meshgrid(np.arange(x0, x1 + 1e-9, cell_um), np.arange(y0, y1 + 1e-9, cell_um))
        z_um, pixel_size_um = specimen.surface.sample(x_um, y_um, cell_um=cell_um).z_um, cell_um
    else:
        if roi is None:
            raise InvalidInputError("area", "give an ROI id or a region")
        specimen.roi(roi)
        placed = specimen.heights(roi)
        z_um, pixel_size_um = placed.z_um, placed.pixel_size_um
    if np.isfinite(z_um).sum() < 64:
        raise InvalidInputError("region", "holds fewer than 64 measured points")
    try:
        fracture = roughness.fracture_metrics(z_um, pixel_size_um=pixel_size_um)
    except ValueError as error:
        raise InvalidInputError("region", str(error)) from None
    return {**roughness.areal_parameters(z_um, pixel_size_um=pixel_size_um), **fracture}
