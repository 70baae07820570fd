"""Profiles, roughness and the heights of an area of a stored specimen or a height map, validated;
shared by the gRPC and HTTP endpoints, the command line, the exports and the report."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.formats.calibration import Calibration
from fractoscope.mesh.grid import area_average
from fractoscope.progress import checkpoint
from fractoscope.specimen.model import RoiEntry, Specimen
from fractoscope.stereo.matching import DEFAULT_WINDOW_PX
from fractoscope.surface import measurement, profile_parameters, profiles, roughness, scaling

MAX_REGION_SAMPLES = 2048 * 2048  # what roughness is computed on, at most
MAX_EXPORT_SAMPLES = 8192 * 8192  # what an export samples, at most (z and sigma: 512 MB)
MAX_PROFILE_SAMPLES = 1_000_000
_SAMPLING_STRIP = 1 << 20  # points sampled at once: bounds the temporaries of a large region


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


def positive_input(value: float, field: str) -> float:
    if not (math.isfinite(value) and value > 0):
        raise InvalidInputError(field, f"must be a positive number, got {value}")
    return value


def checked_region(region_um, field: str = "region", *, allow_point: bool = False) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) µm as floats: finite, min below max (or equal, with
    `allow_point`)."""
    values = tuple(float(v) for v in region_um)
    if not all(math.isfinite(v) for v in values):
        raise InvalidInputError(field, "coordinates must be finite")
    ordered = (
        (values[0] <= values[2] and values[1] <= values[3])
        if allow_point
        else (values[0] < values[2] and values[1] < values[3])
    )
    if not ordered:
        raise InvalidInputError(field, "min must be smaller than max in x and y")
    return values


def profile_along(
    specimen: Specimen,
    points_um,
    *,
    spacing_um: float = 0.0,
    magnification: float = 0.0,
    chain: ChainRequest = ChainRequest(),
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
        cell_um = specimen.pixel_size_at_magnification(positive_input(magnification, "magnification"))
    else:
        cell_um = specimen.finest_pixel_size_um(
            (points[:, 0].min(), points[:, 1].min(), points[:, 0].max(), points[:, 1].max())
        )
    spacing_um = _profile_spacing(points, positive_input(spacing_um, "spacing_um") if spacing_um else None, cell_um)
    form = _form(chain.form)
    lambdas = [
        _cutoff(value, field)
        for value, field in ((chain.s_filter_um, "s_filter_um"), (chain.l_filter_um, "l_filter_um"))
    ]
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
    # ISO 21920-2's five sections need two samples each.
    if np.isfinite(z_um[regular]).sum() < 2 * profile_parameters.SECTIONS:
        return SpecimenProfile(distances, z_um, samples.source, sources, None)
    made = _roughness_profile(z_um[regular], spacing_um, form, lambdas[0], lambdas[1])
    r_um = np.full(z_um.shape, np.nan)
    r_um[regular] = made.r_um
    parameters = profile_parameters.profile_parameters(made.r_um, spacing_um=spacing_um)
    return SpecimenProfile(distances, z_um, samples.source, sources, parameters, made, r_um)


def _profile_spacing(points: np.ndarray, spacing_um: float | None, cell_um: float) -> float:
    """The spacing of a profile's samples, µm: `spacing_um` if given, else the pixel size `cell_um`.
    Too many samples (MAX_PROFILE_SAMPLES, the vertices among them) blame the spacing only where
    a given one is finer than the default and the default would do; else the points (too many,
    too far apart: a line of 1e308 µm, or one far beyond the specimen)."""
    with np.errstate(over="ignore"):  # coordinates of ±1e308 make a line of infinite length, refused below
        length_um = float(np.hypot(*np.diff(points, axis=0).T).sum())

    def sample_count(spacing: float) -> float:
        return np.floor(length_um / spacing) + 1 + len(points)  # both ends and every vertex

    chosen_um = spacing_um or cell_um
    if sample_count(chosen_um) <= MAX_PROFILE_SAMPLES:
        return chosen_um
    if spacing_um is not None and sample_count(cell_um) <= MAX_PROFILE_SAMPLES:
        raise InvalidInputError(
            "spacing_um",
            f"{spacing_um:g} µm gives more than {MAX_PROFILE_SAMPLES} samples along the {length_um:g} µm line; "
            f"use a larger spacing (default: {cell_um:g} µm)",
        )
    raise InvalidInputError(
        "points",
        f"{len(points)} points making a line of {length_um:g} µm give more than {MAX_PROFILE_SAMPLES} samples "
        f"{chosen_um:g} µm apart; give a shorter line of fewer points",
    )


def _roughness_profile(
    z_um: np.ndarray, spacing_um: float, form: str, lambda_s_um: float | None, lambda_c_um: float | None
) -> profile_parameters.RoughnessProfile:
    """The ISO 21920-3 chain on equally spaced heights (n,) µm; a setting it rejects is an error
    naming the request's field."""
    try:
        return profile_parameters.roughness_profile(
            z_um, spacing_um=spacing_um, form=form, lambda_s_um=lambda_s_um, lambda_c_um=lambda_c_um
        )
    except ValueError as error:
        message = str(error)
        field = (
            "s_filter_um"
            if message.startswith("lambda_s")
            else "l_filter_um"
            if message.startswith("lambda_c")
            else "form"
        )
        raise InvalidInputError(field, message) from None


def height_statistics(specimen: Specimen, region_um) -> dict:
    """Statistics of the fused surface's measured heights in a region (x_min, y_min, x_max, y_max)
    µm, sampled at the finest pixel size there (coarser if that would exceed MAX_REGION_SAMPLES):
    mean, median, std, min, max (µm; None when nothing is measured), the number of measured
    samples, their share of all samples and the sampling pixel size."""
    area = surface_area(specimen, region_um=region_um, allow_point=True)
    z_um, cell_um = area.z_um, area.pixel_size_um
    known = z_um[np.isfinite(z_um)].astype(np.float64)
    figures = (known.mean(), np.median(known), known.std(), known.min(), known.max()) if known.size else (None,) * 5
    names = ("mean_um", "median_um", "std_um", "min_um", "max_um")
    return {
        **{name: None if value is None else float(value) for name, value in zip(names, figures)},
        "count": int(known.size),
        "measured_fraction": known.size / z_um.size,
        "pixel_size_um": cell_um,
    }


def roughness_of(
    specimen: Specimen, *, roi: str | None = None, region_um=None, chain: ChainRequest = ChainRequest()
) -> roughness.SurfaceAnalysis:
    """The surface texture chain on the measured points of one ROI (the overview when neither is
    given), or of a region of the fused surface (clipped to the specimen) sampled at the finest
    pixel size of the ROIs that hold all of it (coarser if that would exceed MAX_REGION_SAMPLES),
    not at that of a finer ROI that meets a part of it, which would upsample the rest: see
    `roughness_of_map`. The matching noise is each ROI's stored sigma map (for a region: fused as
    the heights are), the tilt uncertainty that of the ROI (for a region: the largest of those it
    draws on)."""
    if region_um is not None:
        area = surface_area(specimen, region_um=region_um, pixel_size_um=_holding_cell_um(specimen, region_um))
        x0, y0 = area.origin_um
        rows, cols = area.z_um.shape
        finest_um = specimen.finest_pixel_size_um(
            (x0, y0, x0 + (cols - 1) * area.pixel_size_um, y0 + (rows - 1) * area.pixel_size_um)
        )
        window_px = DEFAULT_WINDOW_PX * finest_um / area.pixel_size_um
    else:
        area = surface_area(specimen, roi=roi)
        window_px = DEFAULT_WINDOW_PX
    sigma_um = area.sigma_um if np.isfinite(area.sigma_um).any() else None
    return roughness_of_map(
        area.z_um,
        pixel_size_um=area.pixel_size_um,
        origin_um=area.origin_um,
        sigma_um=sigma_um,
        filled=area.filled,
        tilt_rel_uncertainty=area.tilt_rel_uncertainty,
        chain=chain,
        default_window_px=max(1.0, window_px),
    )


def _holding_cell_um(specimen: Specimen, region_um) -> float:
    """The finest pixel size of the ROIs whose regions hold all of a region (clipped to the
    specimen; the overview's if none does), coarser where that would exceed MAX_REGION_SAMPLES, µm."""
    x0, y0, x1, y1 = _within_specimen(specimen, checked_region(region_um))
    cell_um = specimen.finest_pixel_size_um((x0, y0, x1, y1), holding=True)
    return max(cell_um, math.sqrt((x1 - x0) * (y1 - y0) / MAX_REGION_SAMPLES))


def roughness_of_map(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    origin_um: tuple[float, float] = (0.0, 0.0),
    sigma_um: np.ndarray | None = None,
    filled: np.ndarray | None = None,
    tilt_rel_uncertainty: float | None = None,
    chain: ChainRequest = ChainRequest(),
    default_window_px: float = 1.0,
) -> roughness.SurfaceAnalysis:
    """The chain on a height map (rows, cols) µm whose pixel (0, 0) lies at `origin_um` (x, y): on
    its measured points only, the `filled` ones (bool, interpolated rather than matched) left out
    (surface.measurement.measured_only), every route's one way (the npz of `fracto height`, a
    specimen's ROI or region, the report); `sigma_um` the matching noise (the median where a
    measured point has none). The request's settings checked (errors name its fields), the
    defaults filled in; the result's `coverage` says what share of the map was measured."""
    covered = measurement.coverage(z_um, filled)
    z_um = measurement.measured_only(z_um, filled)
    if sigma_um is not None:
        with_sigma = np.isfinite(sigma_um) & np.isfinite(z_um)
        if not with_sigma.any():
            sigma_um = None
        else:
            sigma_um = np.where(np.isfinite(z_um) & ~with_sigma, np.median(sigma_um[with_sigma]), sigma_um)
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
    )
    levelling = None
    if chain.levelling_region_um is not None:
        x0, y0, x1, y1 = checked_region(chain.levelling_region_um, "levelling_region")
        rows, cols = np.shape(z_um)
        x_um = origin_um[0] + np.arange(cols) * pixel_size_um
        y_um = origin_um[1] + np.arange(rows) * pixel_size_um
        levelling = ((y_um >= y0) & (y_um <= y1))[:, None] & ((x_um >= x0) & (x_um <= x1))[None, :]
        if not levelling.any():
            raise InvalidInputError("levelling_region", "does not meet the analysed area")
    analysis = roughness.analyse(
        z_um,
        pixel_size_um=pixel_size_um,
        chain=settings,
        levelling_region=levelling,
        sigma_um=sigma_um,
        tilt_rel_uncertainty=tilt_rel_uncertainty,
    )
    return dataclasses.replace(analysis, coverage=covered)


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
    filled: (rows, cols) bool, True where a height was interpolated rather than matched.
    tilt_rel_uncertainty: ε_z of the heights (for a region the largest of the ROIs it draws on;
        None: not known).
    datum_levelled: whether its heights are above a datum (the overview's), about which ε_z scales
        them.
    """

    z_um: np.ndarray
    sigma_um: np.ndarray
    texture: np.ndarray
    source: np.ndarray
    sources: list[str]
    pixel_size_um: float
    origin_um: tuple[float, float]
    roi: RoiEntry
    filled: np.ndarray
    tilt_rel_uncertainty: float | None = None
    datum_levelled: bool = False

    @property
    def coverage(self) -> measurement.Coverage:
        return measurement.coverage(self.z_um, self.filled)

    @property
    def total_sigma_um(self) -> np.ndarray:
        """The heights' whole one-sigma uncertainty, matching noise and tilt part (µm; see
        surface.measurement.total_sigma_um), as `fracto height` writes its sigma_um."""
        return measurement.total_sigma_um(
            self.z_um, self.sigma_um, tilt_rel_uncertainty=self.tilt_rel_uncertainty, levelled=self.datum_levelled
        )

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
    specimen: Specimen,
    *,
    roi: str | None = None,
    region_um=None,
    pixel_size_um: float | None = None,
    max_samples: int = MAX_REGION_SAMPLES,
    allow_point: bool = False,
) -> SurfaceArea:
    """An ROI as measured (`pixel_size_um`, if given, at least its own: area-averaged onto it), or a
    region (x0, y0, x1, y1) µm of the fused surface, clipped to the specimen, sampled at
    `pixel_size_um` (default: the finest there, coarser where that would exceed `max_samples`; a
    given one that exceeds it is an error).
    The default area is the overview ROI; `allow_point` takes a region of no extent (a point)."""
    if pixel_size_um is not None:
        positive_input(pixel_size_um, "pixel_size_um")
    if region_um is not None:
        return _region_area(
            specimen, checked_region(region_um, allow_point=allow_point), pixel_size_um, max_samples, allow_point
        )
    entry = specimen.roi(roi) if roi is not None else specimen.rois[0]
    placed = specimen.heights(entry.id)
    z_um = placed.z_um
    sigma_um = placed.sigma_um if placed.sigma_um is not None else np.full(z_um.shape, np.nan, np.float32)
    filled = placed.filled if placed.filled is not None else np.zeros(z_um.shape, bool)
    texture, step = placed.texture, placed.pixel_size_um
    if pixel_size_um is not None and not math.isclose(pixel_size_um, step, rel_tol=1e-9):
        if pixel_size_um < step:
            raise InvalidInputError(
                "pixel_size_um",
                f"{pixel_size_um} µm is finer than ROI {entry.id!r}'s {step} µm; sample a region instead",
            )
        factor = pixel_size_um / step
        if min(z_um.shape) < factor:
            raise InvalidInputError("pixel_size_um", f"{pixel_size_um} µm leaves no pixel of ROI {entry.id!r}")
        share = area_average(np.where(np.isfinite(z_um), filled, np.nan).astype(np.float32), factor=factor)
        z_um, sigma_um, step = area_average(z_um, factor=factor), area_average(sigma_um, factor=factor), pixel_size_um
        filled = np.isfinite(z_um) & (np.nan_to_num(share) >= 0.5)
        texture = np.clip(np.round(area_average(texture.astype(np.float32), factor=factor)), 0, 255).astype(np.uint8)
    if z_um.size > max_samples:
        raise InvalidInputError(
            "pixel_size_um",
            f"{z_um.shape[1]} x {z_um.shape[0]} points exceed the limit of {max_samples}; choose a coarser one",
        )
    index = [placed_roi.id for placed_roi in specimen.surface.rois].index(entry.id)
    source = np.where(np.isfinite(z_um), index, -1).astype(np.int16)
    sources = [r.id for r in specimen.surface.rois]
    return SurfaceArea(
        z_um, sigma_um, texture, source, sources, step, placed.origin_um, entry, filled, *_tilt_part(specimen, [entry])
    )


def _tilt_part(specimen: Specimen, used: list[RoiEntry]) -> tuple[float | None, bool]:
    """ε_z of heights drawn from the ROIs `used` (the largest; None when one's is not known) and
    whether they are above a datum (the overview's: its children are aligned to it)."""
    tilts = [entry.tilt_rel_uncertainty for entry in used]
    datum = specimen.rois[0].datum or {}
    return (max(tilts) if tilts and None not in tilts else None), datum.get("level", "none") != "none"


def area_shape(
    specimen: Specimen,
    *,
    roi: str | None = None,
    region_um=None,
    pixel_size_um: float | None = None,
    max_samples: int = MAX_REGION_SAMPLES,
    allow_point: bool = False,
) -> tuple[int, int]:
    """The (rows, cols) of what surface_area would sample, from the specimen's description alone
    (no heights read), for estimates before any work; its inputs checked as surface_area checks
    them, but for a pixel size too coarse for an ROI, which surface_area refuses."""
    if pixel_size_um is not None:
        positive_input(pixel_size_um, "pixel_size_um")
    if region_um is not None:
        region = checked_region(region_um, allow_point=allow_point)
        *_, rows, cols = _region_grid(specimen, region, pixel_size_um, max_samples, allow_point)
        return rows, cols
    entry = specimen.roi(roi) if roi is not None else specimen.rois[0]
    factor = max(1.0, (pixel_size_um or entry.pixel_size_um) / entry.pixel_size_um)
    return max(1, int(entry.shape[0] / factor)), max(1, int(entry.shape[1] / factor))


def roughness_shape(specimen: Specimen, *, roi: str | None = None, region_um=None) -> tuple[int, int]:
    """The (rows, cols) of the map roughness_of analyses (see area_shape)."""
    if region_um is None:
        return area_shape(specimen, roi=roi or specimen.rois[0].id)
    return area_shape(specimen, region_um=region_um, pixel_size_um=_holding_cell_um(specimen, region_um))


def _region_grid(
    specimen: Specimen, region, pixel_size_um: float | None, max_samples: int, allow_point: bool
) -> tuple[float, float, float, int, int]:
    """(x0, y0, cell_um, rows, cols) of the grid a region is sampled on (see surface_area)."""
    x0, y0, x1, y1 = _within_specimen(specimen, region, allow_point=allow_point)
    if pixel_size_um is None:
        cell_um = max(specimen.finest_pixel_size_um(region), math.sqrt((x1 - x0) * (y1 - y0) / max_samples))
    else:
        cell_um = pixel_size_um
    cols, rows = int((x1 - x0) / cell_um + 1e-9) + 1, int((y1 - y0) / cell_um + 1e-9) + 1
    if rows * cols > max_samples:
        raise InvalidInputError(
            "pixel_size_um", f"{cols} x {rows} points exceed the limit of {max_samples}; choose a coarser one"
        )
    return x0, y0, cell_um, rows, cols


def _region_area(
    specimen: Specimen, region, pixel_size_um: float | None, max_samples: int, allow_point: bool
) -> SurfaceArea:
    x0, y0, cell_um, rows, cols = _region_grid(specimen, region, pixel_size_um, max_samples, allow_point)
    z_um = np.empty((rows, cols), np.float32)
    sigma_um = np.empty((rows, cols), np.float32)
    texture = np.empty((rows, cols), np.uint8)
    source = np.empty((rows, cols), np.int16)
    filled = np.empty((rows, cols), bool)
    x_um = x0 + np.arange(cols) * cell_um
    strip = max(1, _SAMPLING_STRIP // cols)
    for start in range(0, rows, strip):
        checkpoint()
        y_um = y0 + np.arange(start, min(start + strip, rows)) * cell_um
        samples = specimen.surface.sample(*np.meshgrid(x_um, y_um), cell_um=cell_um)
        block = slice(start, start + len(y_um))
        z_um[block], sigma_um[block], source[block] = samples.z_um, samples.sigma_um, samples.source
        filled[block] = samples.filled
        texture[block] = np.clip(np.round(samples.texture), 0, 255)
    sources = [roi.id for roi in specimen.surface.rois]
    counts = np.bincount(source[source >= 0].ravel(), minlength=len(sources))
    main = specimen.roi(sources[int(np.argmax(counts))]) if counts.any() else specimen.rois[0]
    used = [specimen.roi(sources[index]) for index in np.flatnonzero(counts)]
    tilt_part = _tilt_part(specimen, used)
    return SurfaceArea(z_um, sigma_um, texture, source, sources, cell_um, (x0, y0), main, filled, *tilt_part)


def _within_specimen(specimen: Specimen, region, *, allow_point: bool = False) -> tuple[float, float, float, float]:
    """The part of a region that the specimen's ROIs cover (their bounding box); with
    `allow_point`, a point or a line in it too."""
    extents = np.array([roi.region_um for roi in specimen.rois])
    low, high = extents[:, :2].min(axis=0), extents[:, 2:].max(axis=0)
    x0, y0 = max(region[0], low[0]), max(region[1], low[1])
    x1, y1 = min(region[2], high[0]), min(region[3], high[1])
    if not ((x0 <= x1 and y0 <= y1) if allow_point else (x0 < x1 and y0 < y1)):
        raise InvalidInputError(
            "region",
            f"does not meet the specimen, which spans x {low[0]:g} to {high[0]:g} µm, y {low[1]:g} to {high[1]:g} µm",
        )
    return float(x0), float(y0), float(x1), float(y1)
