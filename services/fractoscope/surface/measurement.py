"""A matched height map as every route keeps it: one function (`measurement`) makes, from what
matching returns, the heights, their uncertainty, the datum and what was measured, for the npz
of `fracto height` and for each ROI of a specimen alike, so that the roughness, coverage, sigma
and datum of one pair are one answer whichever way they are asked for.

In order: the matching noise is taken out of the pipeline's sigma on the heights as matched
(`stereo.geometry.matching_sigma_um`: the tilt part about the pipeline's own reference level; on
heights cleaned or levelled first, the two parts no longer cancel and the noise came out zero on
75 % of a grain); isolated peaks and spikes steeper than the pair measures go and holes of up to
8 px are filled (`surface.filtering`),
the filled points marked; the heights are levelled on the datum asked for (`surface.datum`; the
filled points carry no weight). The total sigma is then the matching noise and the tilt part
ε_z |z - z_ref| in quadrature (`total_sigma_um`), z_ref the datum (a tilt error scales the
heights about the level they are measured from) or, with none, the median height.

Arrays are (rows, cols) float32 µm on the reference image's grid, NaN unknown.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from fractoscope.stereo import geometry
from fractoscope.stereo.inputs import MatchingOptions
from fractoscope.surface import datum, filtering


@dataclass(frozen=True)
class Measurement:
    """A pair's heights as kept.

    z_um: cleaned heights, levelled on `datum` when one was asked for; NaN unknown.
    filled: (rows, cols) bool, True where a height was interpolated rather than matched.
    local_sigma_um: the matching noise's one sigma (the part neighbouring heights do not share),
        known wherever z_um is (filled points: their neighbours' weighted mean); None when the
        matching gave no sigma.
    tilt_rel_uncertainty: ε_z, the relative height error the tilts' uncertainty makes (None:
        the tilts are not known).
    datum: where zero is (None: not levelled).
    filter_report: what cleaning changed.
    """

    z_um: np.ndarray
    filled: np.ndarray
    local_sigma_um: np.ndarray | None
    tilt_rel_uncertainty: float | None
    datum: datum.Datum | None
    filter_report: filtering.FilterReport

    @property
    def sigma_um(self) -> np.ndarray | None:
        """The heights' total one-sigma uncertainty, µm (see `total_sigma_um`; None: unknown)."""
        if self.local_sigma_um is None:
            return None
        return total_sigma_um(
            self.z_um,
            self.local_sigma_um,
            tilt_rel_uncertainty=self.tilt_rel_uncertainty,
            levelled=self.datum is not None and self.datum.level != "none",
        )


def measurement(
    z_um: np.ndarray,
    sigma_um: np.ndarray | None,
    *,
    pixel_size_um: float,
    tilt_deg: Sequence[float],
    tilt_uncertainty_deg: float | None,
    level: str | tuple[float, float, float, float] | None = None,
    strict_level: bool = False,
) -> Measurement:
    """The Measurement of heights as matching returns them: `z_um` and its total `sigma_um` (the
    pipeline's, tilt part included; None: unknown, then no sigma is kept), the pair's `tilt_deg`
    and the `tilt_uncertainty_deg` that sigma was computed with (see `tilt_share`); `level`: None
    or a datum (surface.datum.level_heights; ValueError as it raises)."""
    z = np.asarray(z_um, np.float32)
    tilt_rel = tilt_share(tilt_deg, tilt_uncertainty_deg=tilt_uncertainty_deg)
    local = None
    if sigma_um is not None:
        local = geometry.matching_sigma_um(z, sigma_um, relative_height_error=tilt_rel or 0.0)
    max_slope = geometry.max_measurable_slope(tilt_deg) if len(tilt_deg) >= 2 else None
    filtered = filtering.filter_heights(z, sigma_um=local, max_slope=max_slope, pixel_size_um=pixel_size_um)
    local = _everywhere(filtered.sigma_um, filtered.z_um) if filtered.sigma_um is not None else None
    levelled, found = filtered.z_um, None
    if level is not None:
        levelled, found = datum.level_heights(
            filtered.z_um,
            pixel_size_um=pixel_size_um,
            level=level,
            sigma_um=local,
            filled=filtered.filled,
            strict=strict_level,
        )
    return Measurement(levelled, filtered.filled, local, tilt_rel, found, filtered.report)


def tilt_share(tilt_deg: Sequence[float], *, tilt_uncertainty_deg: float | None) -> float | None:
    """ε_z, the tilt's share of a sigma: the relative height error the tilts' uncertainty makes,
    which scales all heights together, apart from the matching noise (None with fewer than two
    tilts). `tilt_uncertainty_deg`: the one the matching's sigma was computed with, as its report
    states it (None: the matching's default, stereo.inputs.MatchingOptions)."""
    if len(tilt_deg) < 2:
        return None
    if tilt_uncertainty_deg is None:
        tilt_uncertainty_deg = MatchingOptions().tilt_uncertainty_deg
    return geometry.series_relative_height_error(tilt_deg, tilt_uncertainty_deg=tilt_uncertainty_deg)


def _everywhere(sigma_um: np.ndarray, z_um: np.ndarray) -> np.ndarray:
    """Sigma wherever there is a height (the median where a height has none), NaN elsewhere."""
    known = np.isfinite(sigma_um) & np.isfinite(z_um)
    fill = np.float32(np.median(sigma_um[known])) if known.any() else np.float32(np.nan)
    return np.where(np.isfinite(z_um), np.where(known, sigma_um, fill), np.nan).astype(np.float32)


def total_sigma_um(
    z_um: np.ndarray, local_sigma_um: np.ndarray, *, tilt_rel_uncertainty: float | None, levelled: bool
) -> np.ndarray:
    """The one-sigma uncertainty of heights `z_um` whose matching noise is `local_sigma_um` (µm,
    float32): that noise and the tilt part ε_z |z - z_ref| in quadrature, z_ref 0 for `levelled`
    heights (heights above a datum scale about it) else their median; the noise alone when ε_z is
    not known (None)."""
    z = np.asarray(z_um, np.float32)
    local = np.asarray(local_sigma_um, np.float32)
    if not tilt_rel_uncertainty:
        return local.copy()
    known = z[np.isfinite(z)]
    reference = np.float32(0.0 if levelled or not known.size else np.median(known))
    return np.hypot(local, np.float32(tilt_rel_uncertainty) * np.abs(z - reference)).astype(np.float32)


@dataclass(frozen=True)
class Coverage:
    """What share of an area's points (0 to 1) were matched (`measured`), interpolated
    (`filled`) or are unknown; `points` counts them all."""

    measured: float
    filled: float
    unknown: float
    points: int

    def to_dict(self) -> dict:
        return {
            "measured_fraction": self.measured,
            "filled_fraction": self.filled,
            "unknown_fraction": self.unknown,
            "points": self.points,
        }


def coverage(z_um: np.ndarray, filled: np.ndarray | None) -> Coverage:
    """The Coverage of heights `z_um` (NaN unknown) of which `filled` ((rows, cols) bool; None:
    none) were interpolated: a filled point is never counted as measured."""
    known = np.isfinite(z_um)
    interpolated = known & np.asarray(filled, bool) if filled is not None else np.zeros(known.shape, bool)
    points = max(int(known.size), 1)
    measured = int(known.sum() - interpolated.sum())
    return Coverage(measured / points, int(interpolated.sum()) / points, 1 - known.sum() / points, int(known.size))


def measured_only(z_um: np.ndarray, filled: np.ndarray | None) -> np.ndarray:
    """The heights with the filled points unknown (NaN): what surface analysis is run on, since a
    fill bridges a hole smoothly (across a grain's rim it doubled Sdq)."""
    if filled is None:
        return z_um
    return np.where(np.asarray(filled, bool), np.float32(np.nan), z_um).astype(np.asarray(z_um).dtype, copy=False)
