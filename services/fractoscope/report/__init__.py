"""Measurement reports a lab can file: an ROI or a region of a specimen as one HTML page or a PDF,
with the SEM images, the height, coverage and uncertainty maps, the calibration and where each
value came from, the ISO 25178-2 parameters with their uncertainties, the Hurst exponent with its
fit range, profiles with their ISO 21920-2 parameters, and every setting used.

The numbers are the API's: the report asks specimen.queries exactly as GetRoughness and GetProfile
do (`content`); `document` lays the report out, `figures` draws it.
"""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.pyplot as plt

from fractoscope.formats.calibration import Calibration
from fractoscope.numbers import measured, uncertainty_text, value_text
from fractoscope.report.content import ReportContent, report_content
from fractoscope.report.document import (
    Cell,
    Document,
    FigureBlock,
    Heading,
    Paragraph,
    Table,
    write_html,
    write_pdf,
)
from fractoscope.specimen.model import RoiEntry, Specimen
from fractoscope.surface.areal_parameters import UNITS
from fractoscope.surface.profile_parameters import UNITS as PROFILE_UNITS
from fractoscope.surface.scaling import MAX_HURST_STDERR

__all__ = ["MEDIA_TYPES", "ReportContent", "report_content", "write_report"]

MEDIA_TYPES = {"html": "text/html; charset=utf-8", "pdf": "application/pdf"}
_METHOD_NAMES = {"hhc": "height-height correlation", "psd": "profile PSD"}


def write_report(
    specimen: Specimen,
    directory: Path,
    *,
    file_format: str = "html",
    roi: str | None = None,
    region_um=None,
    subject: str | None = None,
) -> Path:
    """Writes the report of an ROI (default: the overview) or a region as `file_format` ("html" or
    "pdf") into `directory`; returns its path. `subject` names what is reported (default:
    "specimen ID"; a height map file's report names the file)."""
    if file_format not in MEDIA_TYPES:
        raise ValueError(f"file_format: {file_format!r} is none of {sorted(MEDIA_TYPES)}")
    content = report_content(specimen, roi=roi, region_um=region_um, subject=subject)
    document = build_document(content)
    path = Path(directory) / f"{specimen.id}-report.{file_format}"
    try:
        (write_html if file_format == "html" else write_pdf)(document, path)
    finally:
        for block in document.blocks:
            if isinstance(block, FigureBlock):
                plt.close(block.figure)
    return path


def build_document(content: ReportContent) -> Document:
    from fractoscope.report import figures  # matplotlib's figures only when a report is drawn

    document = Document(f"Measurement report: {content.subject}, {content.area_label}")
    document.add(_summary(content))
    _calibration(document, content)
    document.add(Heading("SEM images", "sem"))
    if content.views:
        document.add(
            FigureBlock(
                figures.views_figure(content.views),
                "The images the heights were measured from, as given (reference first; contrast stretched over the "
                "0.5 to 99.5 percentiles, downsampled for display).",
                "sem-figure",
            )
        )
    else:
        document.add(
            Paragraph(
                "No image files are kept with these heights (a height map file, or a specimen stored before they "
                "were kept); a specimen's reference image on the height map's grid is the texture of its 3D tiles."
            )
        )
    document.add(
        Heading("Height map", "heights"),
        FigureBlock(
            figures.height_figure(content.area),
            f"Heights of {content.area_label}, grid step {content.area.pixel_size_um:.4g} µm; colours span the 0.5 "
            "to 99.5 percentiles.",
            "height-figure",
        ),
        Heading("Coverage and uncertainty", "maps"),
        FigureBlock(
            figures.maps_figure(content.area),
            "Left: the ROI each matched height comes from (finer ROIs win where they have data); filled: heights "
            "interpolated across holes of a few pixels, which the parameters below leave out. Right: the "
            "matching part of each height's one-sigma uncertainty only (the noise neighbouring heights do not "
            "share); the tilt part, "
            + (
                f"ε_z = {_percent(content.area.tilt_rel_uncertainty)} of each height above the "
                + ("datum" if content.area.datum_levelled else "median height")
                if content.area.tilt_rel_uncertainty
                else "not known here"
            )
            + ", scales every height together and adds to it in quadrature (the exports' sigma_um holds both).",
            "maps-figure",
        ),
    )
    _roughness(document, content)
    _scaling(document, content, figures)
    _profiles(document, content, figures)
    _parameters(document, content)
    return document


def _summary(content: ReportContent) -> Table:
    """What is reported, where its height zero is, how much of it was measured, when and by what."""
    return Table(
        ["", ""],
        [
            [Cell("source"), Cell(content.subject)],
            [Cell("area"), Cell(content.area_label)],
            [Cell("height zero"), Cell(content.datum_text)],
            [Cell("coverage"), Cell(_coverage_text(content.area.coverage))],
            [Cell("created"), Cell(content.created)],
            [Cell("software"), Cell(content.software)],
        ],
        anchor="summary",
    )


def _calibration(document: Document, content: ReportContent) -> None:
    document.add(Heading("Calibration", "calibration"))
    if not content.tilt_calibrated:
        document.add(
            Paragraph(
                "The tilt was not calibrated: the heights use nominal stage tilts (from the file metadata or the "
                "request), whose assumed uncertainty scales every height by ε_z = δα / tan α = "
                f"{_percent(content.roughness.tilt_rel_uncertainty)}. Calibrating the tilts from a series of three "
                'or more images removes most of it: a manifest ROI\'s "images" with "calibrate": true, '
                "fracto height --calibrate-tilt, or calibrate_tilt in the API.",
                emphasis=True,
            )
        )
    for item in content.rois:
        roi, calibration = item.roi, item.calibration
        if calibration is None:
            document.add(
                Paragraph(
                    f"ROI {roi.id}: stored before the calibration's sources were recorded; tilts "
                    f"{roi.matching.get('tilt_deg')} °, pixel size {roi.pixel_size_um:.6g} µm."
                )
            )
            continue
        nominal = _nominal_tilts(roi, calibration)
        caption = (
            "tilt calibrated from the images, starting from the nominal tilts"
            + (f" {', '.join(f'{tilt:+g}' for tilt in nominal)} °" if nominal else "")
            + " (the reference view keeps its nominal tilt: only differences are observable)"
            if calibration.tilt_calibrated
            else "tilt not calibrated: sigma is the nominal tilt uncertainty"
        )
        document.add(
            Table(
                ["ROI " + roi.id, "value", "unit", "source", "sigma (°)"] + (["nominal (°)"] if nominal else []),
                _calibration_rows(roi, calibration),
                caption=caption,
                anchor=f"calibration-{roi.id}",
            )
        )


def _calibration_rows(roi: RoiEntry, calibration: Calibration) -> list[list[Cell]]:
    """One ROI's calibration table: each view's tilt, the pixel size and, where recorded, the tilt
    axis, as (quantity, value, unit, source, sigma °), and each view's nominal tilt (°) when the
    tilts were calibrated."""
    nominal = _nominal_tilts(roi, calibration)
    rows = [
        [
            Cell(f"tilt of view {index}"),
            Cell(_signed(value_text(tilt, sigma)), tilt, f"{roi.id}.tilt_deg[{index}]"),
            Cell("°"),
            Cell(source),
            Cell(uncertainty_text(sigma), sigma if math.isfinite(sigma) else None, f"{roi.id}.tilt_sigma_deg[{index}]"),
        ]
        + ([Cell(f"{nominal[index]:+.4f}", nominal[index], f"{roi.id}.tilt_deg_nominal[{index}]")] if nominal else [])
        for index, (tilt, source, sigma) in enumerate(
            zip(calibration.tilt_deg, calibration.tilt_source, calibration.tilt_sigma_deg)
        )
    ]
    rows.append(
        [
            Cell("pixel size"),
            Cell(f"{calibration.pixel_size_um:.6g}", calibration.pixel_size_um, f"{roi.id}.pixel_size_um"),
            Cell("µm"),
            Cell(calibration.pixel_size_source),
            Cell(""),
        ]
    )
    axis = roi.matching.get("tilt_axis_deg")
    if axis is not None:
        rows.append(
            [
                Cell("tilt axis"),
                Cell(f"{axis:.4g}", axis, f"{roi.id}.tilt_axis_deg"),
                Cell("°"),
                Cell(roi.matching.get("tilt_axis_source") or "unknown"),
                Cell(""),
            ]
        )
    sign = roi.matching.get("relief_sign")
    if sign:
        rows.append([Cell("relief sign"), Cell(sign), Cell(""), Cell(_relief_sign_source(roi.matching)), Cell("")])
    return [row + [Cell("")] * (len(rows[0]) - len(row)) for row in rows]


def _relief_sign_source(matching: dict) -> str:
    """What told the heights' sign, from a matching report, in a few words: the images' cue and
    its premise with the share of the votes that agree with the tilts as given, or the tilts
    where the images could not tell it (the whole verdict: MatchingReport.relief_sign_sentence)."""
    if not matching.get("relief_sign_decided"):
        return "tilts as given (images undecided)"
    agreeing = 100 * (1 + matching.get("relief_sign_strength", 0.0)) / 2
    cue = matching.get("relief_sign_cue")
    if cue == "occlusion":
        return f"occlusion (geometry), {agreeing:.0f} % of walls agree"
    profile = matching.get("instrument_profile")
    premise = f"profile {profile}" if profile else f"detector {matching.get('detector_source', 'given')}"
    return f"{cue} ({premise}), {agreeing:.0f} % of blocks agree"


def _nominal_tilts(roi: RoiEntry, calibration: Calibration) -> list[float]:
    """The nominal tilts (°, one per view) a calibration of the ROI's tilts started from; [] when
    its tilts were not calibrated (or the report does not say)."""
    nominal = list(roi.matching.get("tilt_deg_nominal") or [])
    return nominal if calibration.tilt_calibrated and len(nominal) == len(calibration.tilt_deg) else []


def _roughness(document: Document, content: ReportContent) -> None:
    analysis = content.roughness
    found = analysis.uncertainty
    parts = (
        {"u": found.u_total, "u_tilt": found.u_tilt, "u_noise": found.u_noise}
        if found
        else {"u": {}, "u_tilt": {}, "u_noise": {}}
    )
    rows = []
    for name, unit in UNITS.items():
        value = analysis.parameters.get(name)
        rows.append(
            [
                Cell(name),
                Cell(
                    value_text(value, _finite(parts["u"].get(name))),
                    value if value is not None and math.isfinite(value) else None,
                    name,
                ),
                Cell(unit),
                *(
                    Cell(
                        uncertainty_text(_finite(parts[part].get(name))),
                        _finite(parts[part].get(name)),
                        f"{part}.{name}",
                    )
                    for part in ("u", "u_tilt", "u_noise")
                ),
            ]
        )
    chain = analysis.chain
    document.add(
        Heading("Areal parameters (ISO 25178-2)", "roughness"),
        Table(
            ["parameter", "value", "unit", "u (k = 1)", "tilt part", "matching part"],
            rows,
            anchor="roughness-table",
            caption=(
                f"After removing the form ({chain.form}{', fitted robustly' if chain.robust_form else ''}), on a "
                f"grid of {analysis.pixel_size_um:.4g} µm, from the matched heights only "
                f"({_coverage_text(analysis.coverage) if analysis.coverage else 'coverage unknown'}). "
                f"{content.filters_note}. Values to the decimal of their uncertainty's second significant digit "
                "(three significant digits where none is propagated). Standard uncertainties (k = 1): the "
                "tilt part scales every height by ε_z; the matching part propagates each point's matching sigma, "
                f"correlated over the {content.area.window_px} px window. — : not propagated (Sal, Str, Std, Spd and "
                "Spc have no derivative: their tilt part alone is given) or unknown."
            ),
        ),
    )
    for caveat in analysis.caveats:
        document.add(Paragraph(caveat[:1].upper() + caveat[1:] + ".", emphasis=True))
    bias = {name: _finite(value) for name, value in (found.noise_bias.items() if found else ())}
    if any(value is not None for value in bias.values()):
        document.add(
            Paragraph(
                "Matching noise inflates the height parameters: by an estimated "
                + ", ".join(f"{measured(v, 'µm', digits=2)} for {k}" for k, v in bias.items() if v is not None)
                + " (from the sigma map; not subtracted above)."
            )
        )


def _finite(value) -> float | None:
    return float(value) if value is not None and math.isfinite(value) else None


def _scaling(document: Document, content: ReportContent, figures) -> None:
    document.add(
        Heading("Scaling", "scaling"),
        _scaling_table(content),
        Paragraph(f"Fit range: {content.trustworthy_note}."),
        FigureBlock(
            figures.hurst_figure(content), "The height-height correlation and its power-law fit.", "hurst-figure"
        ),
    )
    fits = content.roughness.hurst.fits
    if fits:
        document.add(_hurst_fits_table(fits))
    notes = [content.roughness.hurst.note] if content.roughness.hurst.note else []
    notes += [
        f"{_METHOD_NAMES[method]} {side}: H {fit.not_determinable}"
        for method, sides in fits.items()
        for side, fit in sides.items()
        if fit.not_determinable
    ]
    for note in notes:
        document.add(Paragraph(note[:1].upper() + note[1:] + ".", emphasis=not fits))
    document.add(
        FigureBlock(
            figures.psd_figure(content),
            "The power spectral densities of the surface after form removal and S-filter (the API's psd and the PSD "
            "fits' curves), and the power laws fitted.",
            "psd-figure",
        )
    )


def _scaling_table(content: ReportContent) -> Table:
    """The Hurst exponent, its fit range (µm) and the fractal dimension, as the API gives them."""
    values = content.roughness.legacy()
    along = content.roughness.hurst.fits.get("hhc", {}).get("along")
    undetermined = bool(along and along.not_determinable)
    stderr = along.hurst_stderr if along else None
    return Table(
        ["quantity", "value", "unit"],
        [
            [
                Cell("Hurst exponent H"),
                Cell(
                    "not determinable" if undetermined else value_text(values["hurst_exponent"], stderr),
                    _finite(values["hurst_exponent"]),
                    "hurst_exponent",
                ),
                Cell("1"),
            ],
            [
                Cell("fit from"),
                Cell(
                    value_text(values["hurst_fit_min_um"], None),
                    _finite(values["hurst_fit_min_um"]),
                    "hurst_fit_min_um",
                ),
                Cell("µm"),
            ],
            [
                Cell("fit to"),
                Cell(
                    value_text(values["hurst_fit_max_um"], None),
                    _finite(values["hurst_fit_max_um"]),
                    "hurst_fit_max_um",
                ),
                Cell("µm"),
            ],
            [
                Cell("fractal dimension 3 - H"),
                Cell(
                    value_text(values["fractal_dimension"], stderr),
                    _finite(values["fractal_dimension"]),
                    "fractal_dimension",
                ),
                Cell("1"),
            ],
        ],
        anchor="scaling-table",
        caption="The slope of log h(r) against log r, h(r) the height-height correlation (second "
        f"differences) along {content.roughness.chain.direction_deg:g}° from +x, over the fit range below.",
    )


def _hurst_fits_table(fits) -> Table:
    """Each method's Hurst fit ({method: {side: fit}}) along the chain's direction and across it."""
    return Table(
        ["method", "direction (°)", "H", "standard error", "fit from (µm)", "fit to (µm)"],
        [
            [
                Cell(_METHOD_NAMES[method]),
                Cell(f"{fit.direction_deg:g} ({side})"),
                *(
                    Cell(
                        "not determinable"
                        if key == "hurst" and fit.not_determinable
                        else value_text(value, fit.hurst_stderr)
                        if key == "hurst"
                        else uncertainty_text(value)
                        if key == "hurst_stderr"
                        else value_text(value, None),
                        value if math.isfinite(value) else None,
                        f"hurst.{method}.{side}.{key}",
                    )
                    for key, value in (
                        ("hurst", math.nan if fit.not_determinable else fit.hurst),
                        ("hurst_stderr", fit.hurst_stderr),
                        ("fit_min_um", fit.fit_min_um),
                        ("fit_max_um", fit.fit_max_um),
                    )
                ),
            ]
            for method, sides in fits.items()
            for side, fit in sides.items()
        ],
        anchor="hurst-table",
        caption="Both methods along the chain's direction and across it (90° more); standard errors by "
        "jackknife over bands of profiles. The PSD's fit range is in wavelengths (twice the lags). H is not "
        f"determinable outside (0, 1) or with a standard error above {MAX_HURST_STDERR:g} (why: below).",
    )


def _profiles(document: Document, content: ReportContent, figures) -> None:
    document.add(Heading("Profiles (ISO 21920-2)", "profiles"))
    for profile in content.profiles:
        document.add(
            FigureBlock(
                figures.profile_figure(profile),
                f"{profile.name.capitalize()} profile through the middle of the area.",
                f"profile-{profile.name}",
            )
        )
        if profile.iso:
            iso = [
                [
                    Cell(name),
                    Cell(
                        value_text(value, None),
                        value if math.isfinite(value) else None,
                        f"{profile.name}.roughness.{name}",
                    ),
                    Cell(PROFILE_UNITS[name]),
                ]
                for name, value in profile.iso.items()
            ]
            document.add(
                Table(
                    ["parameter", "roughness profile", "unit"],
                    iso,
                    anchor=f"profile-{profile.name}-iso",
                    caption=(
                        f"As GetProfile gives them, from samples {profile.spacing_um:.4g} µm apart. ISO 21920-3 "
                        f"chain: least-squares line, Gaussian S-filter λs = {profile.lambda_s_um:.3g} µm, L-filter λc "
                        f"= {profile.lambda_c_um:.3g} µm (0: not applied): {profile.found.roughness.cutoffs.reason}"
                        f"{'; ' + profile.note if profile.note else ''}."
                    ),
                )
            )
        else:
            document.add(Paragraph(f"No roughness profile: {profile.note}."))


def _parameters(document: Document, content: ReportContent) -> None:
    document.add(Heading("Parameters used", "parameters"))
    for item in content.rois:
        roi = item.roi
        rows = [[Cell(key), Cell(str(value))] for key, value in sorted((roi.matching.get("parameters") or {}).items())]
        rows += [
            [Cell(key), Cell(_shown(roi.matching.get(key)))]
            for key in (
                "method",
                "valid_fraction",
                "residual_vertical_parallax_px",
                "data_bar_rows",
                "magnification_ratio",
                "tilt_axis_deg_estimated",
                "strip_count",
                "tilt_residual_px",
                "photometric_slopes_used",
                "photometric_agreement",
                "photometric_weight",
                "warnings",
            )
            if key in roi.matching
        ]
        rows += [
            [Cell("magnification"), Cell(f"{roi.magnification:g}")],
            [Cell("parent"), Cell(roi.parent or "(overview)")],
            [Cell("alignment residual (µm)"), Cell(f"{roi.alignment_residual_um:.4g}")],
            [Cell("registration score"), Cell(f"{roi.registration_score:.4g}")],
            [Cell("image files"), Cell(", ".join(view["name"] for view in roi.views) or "(not kept)")],
        ]
        document.add(Table([f"ROI {roi.id}: matching", "value"], rows, anchor=f"parameters-{roi.id}"))
    document.add(
        Table(
            ["analysis", "value"],
            [[Cell(key), Cell(str(value))] for key, value in content.analysis.items()],
            anchor="analysis",
        )
    )


def _percent(value: float | None) -> str:
    return "unknown" if value is None else f"{100 * value:.3g} %"


def _signed(text: str) -> str:
    """A number's text with its sign, + included (tilts)."""
    return text if text.startswith(("-", "n/a")) else f"+{text}"


def _coverage_text(covered) -> str:
    """A Coverage (surface.measurement) in words: what share was matched, filled and unknown."""
    return (
        f"{100 * covered.measured:.1f} % of the points matched, {100 * covered.filled:.1f} % filled, "
        f"{100 * covered.unknown:.1f} % unknown"
    )


def _shown(value) -> str:
    if isinstance(value, float):
        return f"{value:.6g}"
    if isinstance(value, list):
        return "; ".join(map(_shown, value)) or "none"
    return str(value)
