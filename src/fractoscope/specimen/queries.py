"""Profiles, roughness and the heights of an area of a stored specimen, validated; shared by the
gRPC and HTTP endpoints, the exports and the report."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration
from fractoscope.mesh.grid import area_average
from fractoscope.specimen.store import RoiEntry, Specimen
from fractoscope.stereo import geometry
from fractoscope.stereo.matching import DEFAULT_WINDOW_PX
from fractoscope.surface import areal_parameters, profiles, roughness, uncertainty

MAX_REGION_SAMPLES = 2048 * 2048  # what roughness is computed on, at most
MAX_EXPORT_SAMPLES = 8192 * 8192  # what an export samples, at most (z and sigma: 512 MB)
MAX_PROFILE_SAMPLES = 1_000_000
_SAMPLING_STRIP = 1 << 20  # points sampled at once: bounds the temporaries of a large region


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


def checked_region(region_um, field: str = "region") -> tuple[float, float, float, float]:
    values = tuple(float(v) for v in region_um)
    if not all(math.isfinite(v) for v in values):
        raise InvalidInputError(field, "coordinates must be finite")
    if not (values[0] < values[2] and values[1] < values[3]):
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


@dataclass(frozen=True)
class SurfaceArea:
    """The heights of an ROI or of a region of the fused surface on a regular grid.

    z_um, sigma_um: (rows, cols) float32 heights and their one-sigma uncertainty, µm, NaN unknown
        (sigma all NaN for a specimen stored before it was kept).
    texture: (rows, cols) uint8 grey SEM image on the same grid.
    source: (rows, cols) int16 index into `sources` (ROI ids) of the ROI each point comes from, -1
        where none.
    pixel_size_um: the grid step, µm; origin_um: (x, y) of pixel (0, 0) in the specimen frame, µm.
    roi: the ROI the area shows most of, whose calibration and matching it carries.
    """

    z_um: np.ndarray
    sigma_um: np.ndarray
    texture: np.ndarray
    source: np.ndarray
    sources: list[str]
    pixel_size_um: float
    origin_um: tuple[float, float]
    roi: RoiEntry

    @property
    def calibration(self) -> Calibration | None:
        """Tilts, pixel size and where each came from (None for a specimen stored before the
        sources were recorded)."""
        return Calibration.from_report(self.roi.matching)

    @property
    def window_px(self) -> int:
        """The matching window the heights were measured with: their noise correlates over it."""
        return int((self.roi.matching.get("parameters") or {}).get("window_px") or DEFAULT_WINDOW_PX)


def surface_area(
    specimen: Specimen, *, roi: str | None = None, region_um=None, pixel_size_um: float | None = None,
    max_samples: int = MAX_REGION_SAMPLES,
) -> SurfaceArea:
    """An ROI as measured (`pixel_size_um`, if given, at least its own: area-averaged onto it), or a
    region (x0, y0, x1, y1) µm of the fused surface, clipped to the specimen, sampled at
    `pixel_size_um` (default: the finest there, coarser where that would exceed `max_samples`; a
    given one that exceeds it is an error).
    The default area is the overview ROI."""
    if pixel_size_um is not None:
        positive(pixel_size_um, "pixel_size_um")
    if region_um is not None:
        return _region_area(specimen, checked_region(region_um), pixel_size_um, max_samples)
    entry = specimen.roi(roi) if roi is not None else specimen.rois[0]
    placed = specimen.heights(entry.id)
    z_um = placed.z_um
    sigma_um = placed.sigma_um if placed.sigma_um is not None else np.full(z_um.shape, np.nan, np.float32)
    texture, step = placed.texture, placed.pixel_size_um
    if pixel_size_um is not None and not math.isclose(pixel_size_um, step, rel_tol=1e-9):
        if pixel_size_um < step:
            raise InvalidInputError("pixel_size_um", f"{pixel_size_um} µm is finer than ROI {entry.id!r}'s {step} µm; sample a region instead")
        factor = pixel_size_um / step
        if min(z_um.shape) < factor:
            raise InvalidInputError("pixel_size_um", f"{pixel_size_um} µm leaves no pixel of ROI {entry.id!r}")
        z_um, sigma_um, step = area_average(z_um, factor=factor), area_average(sigma_um, factor=factor), pixel_size_um
        texture = np.clip(np.round(area_average(texture.astype(np.float32), factor=factor)), 0, 255).astype(np.uint8)
    if z_um.size > max_samples:
        raise InvalidInputError("pixel_size_um", f"{z_um.shape[1]} x {z_um.shape[0]} points exceed the limit of {max_samples}; choose a coarser one")
    index = [placed_roi.id for placed_roi in specimen.surface.rois].index(entry.id)
    source = np.where(np.isfinite(z_um), index, -1).astype(np.int16)
    return SurfaceArea(z_um, sigma_um, texture, source, [r.id for r in specimen.surface.rois], step, placed.origin_um, entry)


def _region_area(specimen: Specimen, region, pixel_size_um: float | None, max_samples: int) -> SurfaceArea:
    x0, y0, x1, y1 = _within_specimen(specimen, region)
    if pixel_size_um is None:
        cell_um = max(specimen.finest_pixel_size_um(region), math.sqrt((x1 - x0) * (y1 - y0) / max_samples))
    else:
        cell_um = pixel_size_um
    cols, rows = int((x1 - x0) / cell_um + 1e-9) + 1, int((y1 - y0) / cell_um + 1e-9) + 1
    if rows * cols > max_samples:
        raise InvalidInputError("pixel_size_um", f"{cols} x {rows} points exceed the limit of {max_samples}; choose a coarser one")
    z_um = np.empty((rows, cols), np.float32)
    sigma_um = np.empty((rows, cols), np.float32)
    texture = np.empty((rows, cols), np.uint8)
    source = np.empty((rows, cols), np.int16)
    x_um = x0 + np.arange(cols) * cell_um
    strip = max(1, _SAMPLING_STRIP // cols)
    for start in range(0, rows, strip):
        y_um = y0 + np.arange(start, min(start + strip, rows)) * cell_um
        samples = specimen.surface.sample(*np.meshgrid(x_um, y_um), cell_um=cell_um)
        block = slice(start, start + len(y_um))
        z_um[block], sigma_um[block], source[block] = samples.z_um, samples.sigma_um, samples.source
        texture[block] = np.clip(np.round(samples.texture), 0, 255)
    sources = [roi.id for roi in specimen.surface.rois]
    counts = np.bincount(source[source >= 0].ravel(), minlength=len(sources))
    main = specimen.roi(sources[int(np.argmax(counts))]) if counts.any() else specimen.rois[0]
    return SurfaceArea(z_um, sigma_um, texture, source, sources, cell_um, (x0, y0), main)


def _within_specimen(specimen: Specimen, region) -> tuple[float, float, float, float]:
    """The part of a region that the specimen's ROIs cover (their bounding box)."""
    extents = np.array([roi.region_um for roi in specimen.rois])
    low, high = extents[:, :2].min(axis=0), extents[:, 2:].max(axis=0)
    x0, y0 = max(region[0], low[0]), max(region[1], low[1])
    x1, y1 = min(region[2], high[0]), min(region[3], high[1])
    if not (x0 < x1 and y0 < y1):
        raise InvalidInputError("region", f"does not meet the specimen, which spans x {low[0]:g} to {high[0]:g} µm, y {low[1]:g} to {high[1]:g} µm")
    return float(x0), float(y0), float(x1), float(y1)


def roughness_of(specimen: Specimen, *, roi: str | None = None, region_um=None) -> dict:
    """ISO 25178-2 parameters (areal_parameters' keys: Sa ... Spc, each in its UNITS) after
    least-squares plane de-tilting, and fracture metrics, of one ROI as measured or of a region of
    the fused surface sampled at the finest pixel size there (coarser if that would exceed
    MAX_REGION_SAMPLES), with `uncertainty` (see `areal_uncertainty`)."""
    if region_um is None and roi is None:
        raise InvalidInputError("area", "give an ROI id or a region")
    area = surface_area(specimen, roi=roi, region_um=region_um)
    if np.isfinite(area.z_um).sum() < 64:
        raise InvalidInputError("region", "holds fewer than 64 measured points")
    try:
        detilted = roughness.detilted_heights_um(area.z_um)
        fracture = roughness.fracture_metrics(area.z_um, pixel_size_um=area.pixel_size_um)
        values = areal_parameters.areal_parameters(detilted, pixel_size_um=area.pixel_size_um)
    except ValueError as error:
        raise InvalidInputError("region", str(error)) from None
    return {**values, **fracture, "uncertainty": areal_uncertainty(area, detilted, values)}


def areal_uncertainty(area: SurfaceArea, detilted_um: np.ndarray, values: dict) -> dict:
    """Standard uncertainty of each areal parameter in `values` (its unit), propagated from the
    matching part of the per-pixel sigma (noise correlated over the matching window) and the tilt
    uncertainty (ε_z, which scales every height), with what each part contributes, the bias that
    matching noise adds to Sa and Sq, and ε_z itself. Parameters without a derivative (Sal, Str,
    Std, Spd, Spc) have a tilt part only: their noise part and their total are None, as is every
    part of a specimen stored without sigma or calibration sources."""
    calibration = area.calibration
    known = np.isfinite(detilted_um)
    sigma_known = known & np.isfinite(area.sigma_um)
    empty = {"u": {name: None for name in values}, "u_tilt": {}, "u_noise": {}, "noise_bias": {}, "relative_tilt_error": None}
    if calibration is None or not sigma_known.any():
        return empty
    tilt_sigma = max(s for s in calibration.tilt_sigma_deg if math.isfinite(s)) if any(map(math.isfinite, calibration.tilt_sigma_deg)) else math.nan
    if not math.isfinite(tilt_sigma):
        return empty
    relative = geometry.series_relative_height_error(calibration.tilt_deg, tilt_uncertainty_deg=tilt_sigma)
    sigma = geometry.matching_sigma_um(area.sigma_um, area.z_um, relative_height_error=relative)
    # Points whose sigma is unknown (filled beyond every measured neighbour) take the median one.
    sigma = np.where(sigma_known, sigma, np.median(sigma[sigma_known]))
    found = uncertainty.areal_uncertainty(
        detilted_um, np.where(known, sigma, np.nan), pixel_size_um=area.pixel_size_um, parameters=values,
        tilt_rel_uncertainty=relative, correlation_px=area.window_px,
    )

    def finite(parts: dict) -> dict:
        return {name: float(value) if math.isfinite(value) else None for name, value in parts.items()}

    return {"u": finite(found.u_total), "u_tilt": finite(found.u_tilt), "u_noise": finite(found.u_noise),
            "noise_bias": finite(found.noise_bias), "relative_tilt_error": float(relative)}
