"""ISO 21920-2:2021 profile parameters of a roughness profile, and the profile chain of ISO 21920-3:
least-squares line removal (the default F-operator), then the Gaussian S- and L-filters of
ISO 16610-21 with the default cut-offs chosen by the profile's length.

Profiles are (n,) float heights in µm sampled every ``spacing_um``; NaN samples are left out of every
parameter (and bridged by normalized convolution in the filters).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fractoscope.surface import areal_parameters, form_removal, iso_filters

UNITS = {
    "Ra": "µm",
    "Rq": "µm",
    "Rsk": "1",
    "Rku": "1",
    "Rp": "µm",
    "Rv": "µm",
    "Rz": "µm",
    "Rt": "µm",
    "Rdq": "1",
    "RSm": "µm",
    "Rk": "µm",
    "Rpk": "µm",
    "Rvk": "µm",
    "Rmr1": "%",
    "Rmr2": "%",
}

SECTIONS = iso_filters.ISO_21920_3_SECTIONS
HEIGHT_DISCRIMINATION_PERCENT = 10.0  # of Rz, for the profile elements of RSm
WIDTH_DISCRIMINATION_PERCENT = 1.0  # of the section (sampling) length


@dataclass(frozen=True)
class RoughnessProfile:
    """A roughness profile and the operators that made it: ``r_um`` (n,) µm (NaN where the primary
    profile was unknown), the form removed (form_removal.FORMS or "none"), the cut-offs used (µm; 0
    where that filter was not applied) and the defaults for this length and spacing (``cutoffs``:
    iso_filters.default_nesting_indices, with why they are what they are)."""

    r_um: np.ndarray
    form: str
    lambda_s_um: float
    lambda_c_um: float
    cutoffs: iso_filters.NestingIndices


def roughness_profile(
    z_um: np.ndarray,
    *,
    spacing_um: float,
    form: str = "plane",
    lambda_s_um: float | None = None,
    lambda_c_um: float | None = None,
) -> RoughnessProfile:
    """Primary profile -> roughness profile: remove the form (default the least-squares line, ISO
    21920-3's F-operator; "none" keeps it), apply the S-filter (lambda_s) and subtract the
    L-filter's mean line (lambda_c). The evaluation length is the measured one, from the first
    known height to the last (unknown ends stay NaN). A cut-off of None is the ISO 21920-3 default
    for that length (with lambda_c given, lambda_s is the one paired with it), 0 leaves that
    filter out."""
    profile = _validated(z_um, spacing_um)
    span = _measured_span(profile)
    z = profile[span]
    defaults = iso_filters.default_nesting_indices(pixel_size_um=spacing_um, field_um=spacing_um * (z.size - 1))
    lambda_c = defaults.lambda_c_um if lambda_c_um is None else float(lambda_c_um)
    lambda_s = defaults.lambda_s_um if lambda_s_um is None else float(lambda_s_um)
    if lambda_s_um is None and lambda_c_um and np.isfinite(lambda_c) and lambda_c > 0:
        lambda_s = iso_filters.paired_lambda_s_um(lambda_c, spacing_um=spacing_um)  # the S-filter that goes with it
    if not (np.isfinite(lambda_s) and lambda_s >= 0 and np.isfinite(lambda_c) and lambda_c >= 0):
        raise ValueError(f"lambda_s_um ({lambda_s}) and lambda_c_um ({lambda_c}) must be finite and >= 0")
    if lambda_s and lambda_c and not lambda_s < lambda_c:
        raise ValueError(f"lambda_s_um ({lambda_s}) must be below lambda_c_um ({lambda_c})")
    iso_filters.check_cutoffs_fit(z.size * spacing_um, step_um=spacing_um, lambda_s_um=lambda_s, lambda_c_um=lambda_c)
    primary = z if form == "none" else form_removal.remove_profile_form(z, spacing_um=spacing_um, form=form)
    smoothed = (
        iso_filters.gaussian_mean_line(primary, spacing_um=spacing_um, cutoff_um=lambda_s) if lambda_s else primary
    )
    if lambda_c:
        smoothed = smoothed - iso_filters.gaussian_mean_line(smoothed, spacing_um=spacing_um, cutoff_um=lambda_c)
    r_um = np.full(profile.shape, np.nan)
    r_um[span] = smoothed
    return RoughnessProfile(r_um=r_um, form=form, lambda_s_um=lambda_s, lambda_c_um=lambda_c, cutoffs=defaults)


def _validated(z_um: np.ndarray, spacing_um: float) -> np.ndarray:
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 1 or np.count_nonzero(np.isfinite(z)) < 8:
        raise ValueError("z_um must be a profile (n,) with at least 8 finite heights")
    if not (np.isfinite(spacing_um) and spacing_um > 0):
        raise ValueError("spacing_um must be positive")
    return z


def _measured_span(z: np.ndarray) -> slice:
    """From the first finite height of `z` to the last: a line drawn past the data ends in NaN,
    which is not part of the evaluation length."""
    known = np.flatnonzero(np.isfinite(z))
    return slice(int(known[0]), int(known[-1]) + 1)


def profile_parameters(z_um: np.ndarray, *, spacing_um: float, sections: int = SECTIONS) -> dict[str, float]:
    """ISO 21920-2 parameters of a roughness (or primary) profile, about its mean line (see ``UNITS``).

    Ra, Rq, Rsk, Rku, Rt and the Rk family are over the evaluation length; Rp, Rv and Rz are the means
    over ``sections`` equal sections (np.array_split, 5 by default) of each section's highest peak,
    deepest valley and their sum. Rdq uses the standard's 7-point derivative
    (z[i+3] - 9 z[i+2] + 45 z[i+1] - 45 z[i-1] + 9 z[i-2] - z[i-3]) / (60 dx). RSm is the mean width
    of the profile elements (a peak above and a valley below the mean line, each at least 10 % of Rz
    high; narrower than 1 % of a section they join their neighbour). The Rk family comes from the
    material ratio curve exactly as the areal Sk family (ISO 21920-2 / ISO 13565-2). Unknown
    heights (NaN) at the ends are not part of the evaluation length.
    """
    z = _validated(z_um, spacing_um)
    z = z[_measured_span(z)]
    if sections < 1 or sections > z.size // 2:
        raise ValueError(f"sections must be between 1 and {z.size // 2}")
    known = np.isfinite(z)
    mean = z[known].mean()
    centred = z - mean
    heights = centred[known]
    squares = heights * heights
    rq = float(np.sqrt(squares.mean()))
    parts = [part[np.isfinite(part)] for part in np.array_split(centred, sections)]
    parts = [part for part in parts if part.size]
    rp = float(np.mean([part.max() for part in parts]))
    rv = float(np.mean([-part.min() for part in parts]))
    rz = float(np.mean([part.max() - part.min() for part in parts]))
    slope = (
        centred[6:] - 9 * centred[5:-1] + 45 * centred[4:-2] - 45 * centred[2:-4] + 9 * centred[1:-5] - centred[:-6]
    ) / (60.0 * spacing_um)
    curve = areal_parameters.material_ratio_curve(heights)
    functional = areal_parameters.functional_parameters_of_curve(curve)
    return {
        "Ra": float(np.abs(heights).mean()),
        "Rq": rq,
        "Rsk": float((squares * heights).mean() / rq**3) if rq > 0 else 0.0,
        "Rku": float((squares * squares).mean() / rq**4) if rq > 0 else 0.0,
        "Rp": rp,
        "Rv": rv,
        "Rz": rz,
        "Rt": float(heights.max() - heights.min()),
        "Rdq": float(np.sqrt(np.nanmean(slope**2))),
        "RSm": mean_element_width_um(
            centred,
            spacing_um=spacing_um,
            min_height_um=HEIGHT_DISCRIMINATION_PERCENT / 100.0 * rz,
            min_width_um=WIDTH_DISCRIMINATION_PERCENT / 100.0 * spacing_um * z.size / sections,
        ),
        "Rk": functional["Sk"],
        "Rpk": functional["Spk"],
        "Rvk": functional["Svk"],
        "Rmr1": functional["Smr1"],
        "Rmr2": functional["Smr2"],
    }


def mean_element_width_um(z_um: np.ndarray, *, spacing_um: float, min_height_um: float, min_width_um: float) -> float:
    """RSm: mean width (µm) of the profile elements of a mean-line-centred profile. The profile is
    read as a sequence of excursions above (peaks) and below (valleys) the mean line, each as high as
    its largest |z|; excursions lower than ``min_height_um`` or narrower than ``min_width_um`` are
    merged into their neighbours, and each element (peak plus the following valley) spans from one
    upward crossing of the mean line to the next. NaN without a complete element."""
    z = np.asarray(z_um, dtype=np.float64)
    known = np.isfinite(z)
    x = np.arange(z.size)[known] * spacing_um
    z = z[known]
    above = z > 0
    starts = np.flatnonzero(np.r_[True, above[1:] != above[:-1]])
    # Crossing positions by linear interpolation between the samples either side.
    crossing = np.r_[
        x[0],
        x[starts[1:] - 1]
        + (x[starts[1:]] - x[starts[1:] - 1]) * z[starts[1:] - 1] / (z[starts[1:] - 1] - z[starts[1:]]),
        x[-1],
    ]
    sign = np.where(above[starts], 1, -1)
    extent = np.maximum.reduceat(np.abs(z), starts)
    width = np.diff(crossing)
    # The first excursion starts at the profile's start, not at a crossing.
    is_crossing = np.r_[False, np.ones(starts.size - 1, dtype=bool)]
    # Insignificant excursions go; what they separated joins up, consecutive excursions of the same
    # sign being one excursion.
    significant = np.flatnonzero((extent >= min_height_um) & (width >= min_width_um))
    sign, start_at, is_crossing = sign[significant], crossing[significant], is_crossing[significant]
    first = np.r_[True, sign[1:] != sign[:-1]]
    upward = start_at[first & (sign > 0) & is_crossing]
    if upward.size < 2:
        return float("nan")
    return float(np.mean(np.diff(upward)))
