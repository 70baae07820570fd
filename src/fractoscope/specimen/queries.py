"""Profiles and roughness of a stored specimen or a height map, validated; shared by the gRPC and HTTP
endpoints and the command line."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.specimen.store import Specimen
from fractoscope.stereo.matching import DEFAULT_WINDOW_PX
from fractoscope.surface import profile_parameters, profiles, roughness, scaling

MAX_REGION_SAMPLES = 2048 * 2048
MAX_PROFILE_SAMPLES = 1_000_000


@dataclass(frozen=True)
class ChainRequest:
    """The surface texture chain a query asks for; None leaves a setting at its default.

    form: roughness.FORMS (default "plane": for profiles the least-squares line).
    s_filter_um, l_filter_um: cut-offs λs and λc, µm, 0 = no such filter (default: none for areal
        roughness; for profiles the ISO 21920-3 defaults for their length).
    direction_deg: of the "along" Hurst exponents (default 0: along x).
    levelling_region_um: (x_min, y_min, x_max, y_max) µm where the form is fitted (default: all).
    window_px: the matcher's smoothing width in the analysed map's pixels (default: the matching
        window, DEFAULT_WINDOW_PX pixels of the data it comes from; 1 for maps of other origin).
    min_windows: the Hurst fit starts this many windows up (default scaling.TRUSTWORTHY_WINDOWS).
    robust_form: fit the form robustly (default: least squares).
    """

    form: str | None = None
    s_filter_um: float | None = None
    l_filter_um: float | None = None
    direction_deg: float | None = None
    levelling_region_um: tuple[float, float, float, float] | None = None
    window_px: float | None = None
    min_windows: float | None = None
    robust_form: bool | None = None


@dataclass(frozen=True)
class SpecimenProfile:
    """Samples along a polyline: (n,) distances and heights µm (NaN unknown), per-sample index into
    `sources` (ROI ids; -1 none); the roughness profile (n,) µm on the samples a whole spacing
    apart (NaN elsewhere and where unknown), the chain that made it and its ISO 21920-2
    parameters (None with fewer than 8 known heights)."""

    distance_um: np.ndarray
    z_um: np.ndarray
    source_index: np.ndarray
    sources: list[str]
    parameters: dict | None
    roughness: profile_parameters.RoughnessProfile | None = None
    r_um: np.ndarray | None = None


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


def profile_along(
    specimen: Specimen, points_um, *, spacing_um: float = 0.0, magnification: float = 0.0, chain: ChainRequest = ChainRequest()
) -> SpecimenProfile:
    """The fused surface along a polyline of (x, y) µm: at the finest pixel size the line meets, or
    at the one a magnification means; samples `spacing_um` apart (default: that pixel size). The
    roughness profile takes `chain`'s form and cut-offs (ISO 21920-3)."""
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
    form = _form(chain.form)
    lambdas = [_cutoff(value, field) for value, field in ((chain.s_filter_um, "s_filter_um"), (chain.l_filter_um, "l_filter_um"))]
    try:
        positions, distances = profiles.polyline_positions(points, spacing_um=spacing_um)
    except ValueError as error:
        raise InvalidInputError("points", str(error)) from None
    samples = specimen.surface.sample(positions[:, 0], positions[:, 1], cell_um=cell_um)
    z_um = samples.z_um.astype(np.float64)
    sources = [roi.id for roi in specimen.surface.rois]
    # The chain needs equal spacing: the vertices between whole spacings are left out of it.
    steps = distances / spacing_um
    regular = np.abs(steps - np.round(steps)) < 1e-6
    if np.isfinite(z_um[regular]).sum() < 8:
        return SpecimenProfile(distances, z_um, samples.source, sources, None)
    try:
        made = profile_parameters.roughness_profile(
            z_um[regular], spacing_um=spacing_um, form=form, lambda_s_um=lambdas[0], lambda_c_um=lambdas[1]
        )
    except ValueError as error:
        raise InvalidInputError("s_filter_um" if "lambda_s" in str(error) else "form", str(error)) from None
    r_um = np.full(z_um.shape, np.nan)
    r_um[regular] = made.r_um
    parameters = profile_parameters.profile_parameters(made.r_um, spacing_um=spacing_um)
    return SpecimenProfile(distances, z_um, samples.source, sources, parameters, made, r_um)


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


def roughness_of(specimen: Specimen, *, roi: str | None = None, region_um=None, chain: ChainRequest = ChainRequest()) -> roughness.SurfaceAnalysis:
    """The surface texture chain on one ROI as measured, or on a region of the fused surface
    sampled at the finest pixel size there (coarser if that would exceed MAX_REGION_SAMPLES). The
    matching noise is each ROI's stored sigma map (for a region: the median of the ROI each
    sample comes from), the tilt uncertainty that of the ROI (for a region: the largest of those it
    draws on)."""
    if region_um is not None:
        x0, y0, x1, y1 = checked_region(region_um)
        finest_um = specimen.finest_pixel_size_um((x0, y0, x1, y1))
        cell_um = max(finest_um, math.sqrt((x1 - x0) * (y1 - y0) / MAX_REGION_SAMPLES))
        x_um, y_um = np.meshgrid(np.arange(x0, x1 + 1e-9, cell_um), np.arange(y0, y1 + 1e-9, cell_um))
        samples = specimen.surface.sample(x_um, y_um, cell_um=cell_um)
        z_um, pixel_size_um, origin_um = samples.z_um, cell_um, (x0, y0)
        used = [specimen.surface.rois[i] for i in np.unique(samples.source[samples.source >= 0])]
        window_px = DEFAULT_WINDOW_PX * finest_um / cell_um
        sigma_um = None
        if used and all(placed.sigma_um is not None for placed in used):
            medians = np.array([np.nanmedian(placed.sigma_um) if placed.sigma_um is not None else np.nan for placed in specimen.surface.rois])
            # Samples that no ROI contributes half of take the largest of the medians.
            sigma_um = np.append(medians, np.nanmax(medians))[samples.source]
        tilt = [specimen.roi(placed.id).tilt_rel_uncertainty for placed in used]
        tilt_rel = max(tilt) if tilt and None not in tilt else None
    else:
        if roi is None:
            raise InvalidInputError("area", "give an ROI id or a region")
        entry = specimen.roi(roi)
        placed = specimen.heights(roi)
        z_um, pixel_size_um, origin_um = placed.z_um, placed.pixel_size_um, placed.origin_um
        window_px, sigma_um, tilt_rel = DEFAULT_WINDOW_PX, placed.sigma_um, entry.tilt_rel_uncertainty
    return roughness_of_map(
        z_um, pixel_size_um=pixel_size_um, origin_um=origin_um, sigma_um=sigma_um, tilt_rel_uncertainty=tilt_rel,
        chain=chain, default_window_px=max(1.0, window_px),
    )  # fmt: skip


def roughness_of_map(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    sigma_um: np.ndarray | None = None,
    tilt_rel_uncertainty: float | None = None,
    chain: ChainRequest = ChainRequest(),
    default_window_px: float = 1.0,
) -> roughness.SurfaceAnalysis:
    """The chain on a height map (rows, cols) µm whose pixel (0, 0) lies at `origin_um` (x, y): the
    request's settings checked (errors name its fields), the defaults filled in."""
    if np.isfinite(z_um).sum() < 64:
        raise InvalidInputError("region", "holds fewer than 64 measured points")
    settings = roughness.surface_chain(
        form=_form(chain.form),
        lambda_s_um=_cutoff(chain.s_filter_um, "s_filter_um") or 0.0,
        lambda_c_um=_cutoff(chain.l_filter_um, "l_filter_um") or 0.0,
        direction_deg=0.0 if chain.direction_deg is None else chain.direction_deg,
        window_px=default_window_px if chain.window_px is None else chain.window_px,
        min_windows=scaling.TRUSTWORTHY_WINDOWS if chain.min_windows is None else chain.min_windows,
        robust_form=bool(chain.robust_form),
    )  # fmt: skip
    levelling = None
    if chain.levelling_region_um is not None:
        x0, y0, x1, y1 = checked_region(chain.levelling_region_um, "levelling_region")
        rows, cols = np.shape(z_um)
        x_um = origin_um[0] + np.arange(cols) * pixel_size_um
        y_um = origin_um[1] + np.arange(rows) * pixel_size_um
        levelling = ((y_um >= y0) & (y_um <= y1))[:, None] & ((x_um >= x0) & (x_um <= x1))[None, :]
        if not levelling.any():
            raise InvalidInputError("levelling_region", "does not meet the analysed area")
    return roughness.analyse(
        z_um, pixel_size_um=pixel_size_um, chain=settings, levelling_region=levelling, sigma_um=sigma_um,
        tilt_rel_uncertainty=tilt_rel_uncertainty,
    )  # fmt: skip


def _form(form: str | None) -> str:
    if form is None:
        return "plane"
    if form not in roughness.FORMS:
        raise InvalidInputError("form", f"must be one of {', '.join(roughness.FORMS)}, not {form!r}")
    return form


def _cutoff(value: float | None, field: str) -> float | None:
    if value is not None and not (math.isfinite(value) and value >= 0):
        raise InvalidInputError(field, f"must be a cut-off in µm >= 0 (0: no filter), got {value}")
    return value
