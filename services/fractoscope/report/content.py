"""What a measurement report says about an ROI or a region of a specimen: every number comes from
the query the API answers with (specimen.queries), so the report and the API agree."""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np

from fractoscope.errors import FractoscopeError
from fractoscope.formats.calibration import Calibration, software
from fractoscope.sem.image import read_sem_image
from fractoscope.specimen import queries
from fractoscope.specimen.fusion import footprint_um, overlaps
from fractoscope.specimen.model import RoiEntry, Specimen
from fractoscope.surface import iso_filters, roughness, scaling

MAX_VIEW_PX = 1024  # SEM images are shown downsampled to at most this many pixels across


@dataclass(frozen=True)
class View:
    """One SEM image of an ROI as shown: (rows, cols) uint8 grey, its file name and stage tilt."""

    roi: str
    index: int
    name: str
    tilt_deg: float
    pixels: np.ndarray


@dataclass(frozen=True)
class ReportProfile:
    """A profile across the area: its end points (x, y) µm and what queries.profile_along gives
    (samples, the roughness profile by the ISO 21920-3 chain with the default cut-offs for its
    length, its ISO 21920-2 parameters); `note` says why there is no roughness profile, or that the
    cut-offs were extrapolated."""

    name: str
    start_um: tuple[float, float]
    end_um: tuple[float, float]
    found: queries.SpecimenProfile
    note: str

    @property
    def roughness_um(self) -> np.ndarray | None:
        return self.found.r_um

    @property
    def iso(self) -> dict:
        return self.found.parameters or {}

    @property
    def lambda_s_um(self) -> float:
        return self.found.roughness.lambda_s_um if self.found.roughness else math.nan

    @property
    def lambda_c_um(self) -> float:
        return self.found.roughness.lambda_c_um if self.found.roughness else math.nan

    @property
    def spacing_um(self) -> float:
        """The spacing of the profile's samples, µm (the data's, not a table's)."""
        return float(np.median(np.diff(self.found.distance_um))) if len(self.found.distance_um) > 1 else math.nan


@dataclass(frozen=True)
class RoiCalibration:
    """An ROI's calibration and matching as stored (None: built before sources were recorded)."""

    roi: RoiEntry
    calibration: Calibration | None


@dataclass(frozen=True)
class ReportContent:
    specimen_id: str
    subject: str  # what is reported: "specimen ID", or a height map file's name
    datum: dict | None  # where height zero is (surface.datum.Datum.to_dict; None: as measured)
    area_label: str
    region_um: tuple[float, float, float, float] | None
    created: str
    software: str
    area: queries.SurfaceArea
    views: list[View]
    rois: list[RoiCalibration]
    roughness: roughness.SurfaceAnalysis
    trustworthy_range_um: tuple[float, float] | None
    trustworthy_note: str
    profiles: list[ReportProfile]

    @property
    def filters_note(self) -> str:
        """Which S- and L-filters (cut-offs λs, λc) the areal parameters used, in one sentence, and
        what ISO 25178-3 would take for this grid and field."""
        chain, spacing_um = self.roughness.chain, self.roughness.pixel_size_um
        field_um = min(self.area.z_um.shape) * self.area.pixel_size_um
        iso = iso_filters.default_nesting_indices(pixel_size_um=spacing_um, field_um=field_um).reason
        used = ", ".join(
            f"{name} = {f'{value:g} µm' if value else 'none'}"
            for name, value in (("λs", chain.lambda_s_um), ("λc", chain.lambda_c_um))
        )
        why = (
            "as requested"
            if chain.lambda_s_um or chain.lambda_c_um
            else "the API's default for areal parameters, so that they are GetRoughness's"
        )
        return (
            f"Filters: {used} ({why}); ISO 25178-3's nesting indices for the {spacing_um:.4g} µm grid and "
            f"{field_um:.4g} µm field would be: {iso}"
        )

    @property
    def datum_text(self) -> str:
        """Where height zero is, in words, with the figures that tell whether it is a level."""
        datum = self.datum
        if not datum:
            return "as measured (no datum asked for; the offset is arbitrary)"
        if datum["level"] == "none":
            return f"as measured, no plane subtracted: {datum.get('warning') or 'no datum'}"
        places = {
            "plane": "the plane through all heights",
            "substrate": "the substrate",
            "region": "the region's plane",
            "background": "the background plane",
        }
        sigma = datum.get("sigma_um")
        text = (
            f"{places.get(datum['level'], datum['level'])}, tilted {datum['tilt_deg']:.2f}°, fitted on "
            f"{100 * datum['area_fraction']:.1f} % of the map ({100 * (datum['measured_fraction'] or 0):.0f} % of it "
            "matched), residual "
            f"{datum['residual_rms_um']:.2g} µm RMS" + (f" against a sigma of {sigma:.2g} µm" if sigma else "")
        )
        return text + (f"; {datum['warning']}" if datum.get("warning") else "")

    @property
    def tilt_calibrated(self) -> bool:
        """Whether every ROI shown had its tilts calibrated from the images."""
        return all(item.calibration is not None and item.calibration.tilt_calibrated for item in self.rois)

    @property
    def analysis(self) -> dict:
        """The analysis settings, so that the numbers can be computed again."""
        return {
            "area": self.area_label,
            "grid_step_um": self.area.pixel_size_um,
            "form_removal": self.roughness.chain.form + (" (robust)" if self.roughness.chain.robust_form else ""),
            "filters": ", ".join(
                f"{name} {value:g} µm"
                for name, value in (
                    ("lambda_s", self.roughness.chain.lambda_s_um),
                    ("lambda_c", self.roughness.chain.lambda_c_um),
                )
                if value
            )
            or "none (S-L surface = the heights with the form removed)",
            "uncertainty": f"matching part of sigma correlated over the {self.area.window_px} px matching window; "
            "tilt part epsilon_z = delta_alpha / tan alpha of the widest pair",
            "hurst_method": "height-height correlation (second differences) and profile PSD, along x and across, "
            f"from {self.roughness.hurst.min_windows:g} matching windows to a tenth of the field",
            "profiles": "; ".join(f"{p.name}: {_point(p.start_um)} to {_point(p.end_um)} µm" for p in self.profiles),
        }


def report_content(
    specimen: Specimen, *, roi: str | None = None, region_um=None, subject: str | None = None
) -> ReportContent:
    """Gathers the report of an ROI (default: the overview) or a region (x0, y0, x1, y1) µm;
    `subject` names what is reported (default "specimen ID")."""
    analysis = queries.roughness_of(
        specimen, roi=None if region_um is not None else (roi or specimen.rois[0].id), region_um=region_um
    )
    area = queries.surface_area(specimen, roi=roi, region_um=region_um)
    if region_um is not None:
        bounds = footprint_um(
            area.origin_um, area.z_um.shape, area.pixel_size_um
        )  # the region as clipped to the specimen
        label = f"region x {bounds[0]:.6g} to {bounds[2]:.6g} µm, y {bounds[1]:.6g} to {bounds[3]:.6g} µm"
        shown = [entry for entry in specimen.rois if overlaps(entry.region_um, bounds)]
    else:
        label = f"ROI {area.roi.id}"
        shown = [area.roi]
        bounds = area.roi.region_um
    trustworthy, note = _trustworthy(area)
    return ReportContent(
        specimen_id=specimen.id,
        subject=subject or f"specimen {specimen.id}",
        datum=specimen.rois[0].datum,
        area_label=label,
        region_um=None if region_um is None else bounds,
        created=datetime.now(UTC).isoformat(timespec="seconds"),
        software=software(),
        area=area,
        views=[view for entry in shown for view in _views(specimen, entry)],
        rois=[RoiCalibration(entry, Calibration.from_report(entry.matching)) for entry in shown],
        roughness=analysis,
        trustworthy_range_um=trustworthy,
        trustworthy_note=note,
        profiles=_profiles(specimen, bounds),
    )


def _views(specimen: Specimen, entry: RoiEntry) -> list[View]:
    """The ROI's stored image files, decoded and downsampled; none for specimens built before
    they were kept (the report then shows the reference image on the height map's grid)."""
    tilts = list(entry.matching.get("tilt_deg") or [])
    views = []
    for index, view in enumerate(entry.views):
        try:
            image = read_sem_image(specimen.view_bytes(entry.id, index), field=f"rois.{entry.id}.views[{index}]")
        except FractoscopeError:
            continue
        pixels = image.pixels[: image.pixels.shape[0] - image.data_bar_rows]
        step = max(1, math.ceil(max(pixels.shape) / MAX_VIEW_PX))
        grey = pixels[::step, ::step].astype(np.float32)
        low, high = np.percentile(grey, (0.5, 99.5))
        grey = np.clip((grey - low) * 255.0 / max(high - low, 1e-6), 0, 255).astype(np.uint8)
        views.append(
            View(
                entry.id, index, view["name"] or f"view {index}", tilts[index] if index < len(tilts) else math.nan, grey
            )
        )
    return views


def _trustworthy(area: queries.SurfaceArea) -> tuple[tuple[float, float] | None, str]:
    """The lags a Hurst fit can be trusted over for this field and matching window (scaling)."""
    try:
        low, high = scaling.trustworthy_range_um(
            area.z_um.shape, pixel_size_um=area.pixel_size_um, window_px=area.window_px
        )
    except ValueError:
        field_px = min(area.z_um.shape)
        return None, (
            f"the field ({field_px} px) is too small for a trustworthy range: it starts at "
            f"{scaling.TRUSTWORTHY_WINDOWS:g} matching windows ({scaling.TRUSTWORTHY_WINDOWS * area.window_px:g} px) "
            f"and ends at a tenth of the field ({field_px * scaling.FIELD_FRACTION:g} px)"
        )
    return (low, high), (
        f"lags from {scaling.TRUSTWORTHY_WINDOWS:g} matching windows ({low:.3g} µm) to a tenth of the field "
        f"({high:.3g} µm) are trustworthy; below, the {area.window_px} px window steepens the curve"
    )


def _profiles(specimen: Specimen, bounds) -> list[ReportProfile]:
    """A horizontal and a vertical profile through the middle of the area."""
    x0, y0, x1, y1 = bounds
    middle_x, middle_y = (x0 + x1) / 2, (y0 + y1) / 2
    lines = [("horizontal", (x0, middle_y), (x1, middle_y)), ("vertical", (middle_x, y0), (middle_x, y1))]
    return [_profile(specimen, name, start, end) for name, start, end in lines]


def _profile(specimen: Specimen, name: str, start, end) -> ReportProfile:
    found = queries.profile_along(specimen, [start, end])
    made = found.roughness
    if made is None:
        note = "fewer than 8 heights are measured along it"
    elif not made.cutoffs.from_iso_table:
        length_um = made.cutoffs.evaluation_length_um
        note = f"the profile ({length_um:.3g} µm) is shorter than ISO 21920-3's table: cut-offs extrapolated"
    else:
        note = ""
    return ReportProfile(name, start, end, found, note)


def _point(point) -> str:
    return f"({point[0]:.4g}, {point[1]:.4g})"
