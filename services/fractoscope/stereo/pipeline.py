"""From a stereo pair of SEM images to a calibrated height map on the first image's pixel grid.

Steps: calibration (explicit values over file metadata), data bar crop, rotation of the tilt
axis to vertical, global alignment, dense ZNCC matching, heights by the parallel-projection
formula, uncertainty, and the way back onto the first image's grid as stored.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.progress import ProgressCallback, silent
from fractoscope.sem.image import SemImage
from fractoscope.sem.instruments import InstrumentProfile, detector_place
from fractoscope.stereo import alignment, geometry, matching, orientation, photometric, tilt_series
from fractoscope.stereo.disparity import StripMatcher
from fractoscope.stereo.inputs import (
    ARGUMENT,
    DEFAULT,
    TILT_CALIBRATION,
    MatchingOptions,
    resolve_calibration,
    tilts_against_metadata,
    validate_views,
)
from fractoscope.stereo.relief_sign import ReliefSignMode

# The axis the features' parallax points to scatters by up to 2.3° on synthetic pairs whose axis
# is the one given (dimples: their features crowd on the rims): further off than this is a warning.
AXIS_WARNING_DEG = 3.0
# Tilt axis direction in the image, degrees from the column axis: vertical, parallax along rows.
DEFAULT_TILT_AXIS_DEG = 90.0


# The MatchingOptions a run reports as its parameters (strip_pixels is the server's, not the run's).
PARAMETER_FIELDS = (
    "window_px",
    "max_disparity_px",
    "min_confidence",
    "max_lr_difference_px",
    "normalize_local_contrast",
    "propagate_at_full_resolution",
    "tilt_uncertainty_deg",
    "calibrate_tilt",
    "relief_sign",
    "detector_from_tilt_axis_deg",
)


@dataclass(frozen=True)
class HeightMapResult:
    """A height map on the first image's stored grid (rows, cols), float32.

    z_um: heights in µm, relative (arbitrary constant offset), NaN where unknown.
    sigma_um: one-sigma uncertainty in µm, NaN where z_um is NaN.
    confidence: peak ZNCC, 0 to 1.
    views_used: uint8, how many views each height rests on, the first included (0 where z_um is NaN).
    report: alignment and quality figures (see MatchingReport in the protobuf API).
    """

    z_um: np.ndarray
    sigma_um: np.ndarray
    confidence: np.ndarray
    views_used: np.ndarray
    report: dict = field(default_factory=dict)


def compute_height_map(
    first: SemImage,
    second: SemImage,
    *,
    tilt_deg: tuple[float | None, float | None] = (None, None),
    pixel_size_um: float | None = None,
    tilt_axis_deg: float | None = None,
    options: MatchingOptions = MatchingOptions(),
    progress: ProgressCallback | None = None,
) -> HeightMapResult:
    """Heights of the surface seen in `first`, from `first` and `second` taken at two stage tilts
    (the two-view case of `compute_series_height_map`). Explicit `tilt_deg` entries and
    `pixel_size_um` override what the files say."""
    return compute_series_height_map(
        [first, second],
        tilt_deg=tilt_deg,
        pixel_size_um=pixel_size_um,
        tilt_axis_deg=tilt_axis_deg,
        options=options,
        progress=progress,
    )


def compute_series_height_map(
    images: Sequence[SemImage],
    *,
    tilt_deg: Sequence[float | None] | None = None,
    pixel_size_um: float | None = None,
    tilt_axis_deg: float | None = None,
    options: MatchingOptions = MatchingOptions(),
    strip_matcher: StripMatcher | None = None,
    instruments: Sequence[InstrumentProfile] = (),
    progress: ProgressCallback | None = None,
) -> HeightMapResult:
    """Heights of the surface seen in `images[0]` from a tilt series (two or more views about one
    axis): every view is aligned to and densely matched with the first, and each pixel's height is
    the least-squares solution over all views that matched it, each weighted by its disparity's
    1/σ² (`tilt_series.heights_px`). With `options.calibrate_tilt` and three or more views the
    tilts of all but the first are estimated from the images first (see tilt_series). Explicit
    `tilt_deg` entries and `pixel_size_um` override the files; the tilt axis is DEFAULT_TILT_AXIS_DEG
    unless given. Strips of rows (`options.strip_pixels`) are matched by `strip_matcher` (default:
    here, on strip_workers()). The relief's sign is chosen as `options.relief_sign` says
    (`orientation`), the detector's place from the options, else the `instruments` profile the
    files' metadata names."""
    started, report_progress = time.perf_counter(), progress or silent
    sources = {"tilt_axis_source": DEFAULT if tilt_axis_deg is None else ARGUMENT}
    tilt_axis_deg = DEFAULT_TILT_AXIS_DEG if tilt_axis_deg is None else tilt_axis_deg
    nominal, pixel_size, given_sources = _calibration(images, tilt_deg, pixel_size_um, tilt_axis_deg, options)
    sources |= given_sources
    rectified = _rectify(images, tilt_axis_deg)
    matched = _match_views(rectified.views, options, strip_matcher, report_progress)
    notes = [note for image in images for note in image.notes]  # JPEG, colour (sem.image)
    warnings = notes + tilts_against_metadata(images, tilt_deg) + _matched_enough(matched, rectified)
    tilts, offsets, calibration = _tilts(rectified.x1_px, matched, nominal, options, report_progress)
    if calibration:  # the reference keeps its tilt: only differences are observable
        sources["tilt_source"][1:] = [TILT_CALIBRATION] * (len(images) - 1)
    report_progress(0.92, "heights")
    z_px, views_used = _weighted_heights(rectified.x1_px, matched, tilts, offsets)
    z_px, tilts, sign_report = _oriented(
        images, rectified, matched, z_px, tilts, options, instruments, tilt_axis_deg, warnings
    )
    warnings += _disagreeing_views(rectified.x1_px, matched, tilts, offsets, z_px)
    tilt_uncertainty = _tilt_uncertainty_deg(options, calibration, warnings)
    z_um, sigma_um, confidence, views_used = _stored_maps(
        rectified, images[0], z_px * pixel_size, tilts, pixel_size, tilt_uncertainty, matched, views_used
    )
    axis_estimated = _estimated_tilt_axis_deg(matched.placements, tilt_axis_deg, warnings)
    report = _report(
        tilts=tilts,
        tilt_axis_deg=tilt_axis_deg,
        pixel_size=pixel_size,
        matched=matched,
        z_um=z_um,
        bar_rows=rectified.bar_rows,
        axis_estimated=axis_estimated,
        warnings=warnings,
        calibration=calibration,
        tilt_uncertainty=tilt_uncertainty,
    )
    report.update(sources, **sign_report, **_file_facts(images), parameters=_parameters_used(options))
    report.update(method=options.method, elapsed_s=time.perf_counter() - started)
    report_progress(1.0, "done")
    return HeightMapResult(z_um, sigma_um, confidence, views_used, report)


def _weighted_heights(x1_px, matched: _MatchedViews, tilts, offsets) -> tuple[np.ndarray, np.ndarray]:
    """Heights (px) with each view's equation weighted by its disparity's 1/σ², and how many views
    each rests on (uint8), on the rectified grid (`tilt_series.heights_px`, `views_used`)."""
    sigmas = [None, *matched.sigmas]  # the reference's is never read
    z_px, _ = tilt_series.heights_px(x1_px, matched.disparities, tilts, offsets_px=offsets, sigmas_px=sigmas)
    return z_px, tilt_series.views_used(matched.disparities, sigmas_px=sigmas)


def _stored_maps(
    rectified: _Rectified, first: SemImage, z_um, tilts, pixel_size, tilt_uncertainty, matched, views_used
):
    """The result's maps on the first image's grid as stored (`_on_stored_grid`): heights (µm,
    NaN outside the image) and their sigma (`geometry.height_sigma_um`), the best confidence (0
    where unknown) and the views count (uint8, 0 where no height)."""
    z_um = z_um.astype(np.float32)
    z_um[rectified.outside] = np.nan  # the canvas's corners, not the image: not in sigma's reference level either
    sigma_um = geometry.height_sigma_um(
        z_um, matched.sigmas, tilt_deg=tilts, pixel_size_um=pixel_size, tilt_uncertainty_deg=tilt_uncertainty
    )
    z_um, sigma_um, confidence, views_used = _on_stored_grid(
        rectified, first, z_um, sigma_um, matched.best_confidence(), views_used
    )
    views_used = np.where(np.isfinite(z_um), np.nan_to_num(views_used), 0).round().astype(np.uint8)
    return z_um, sigma_um, np.nan_to_num(confidence).astype(np.float32), views_used


def _calibration(images, tilt_deg, pixel_size_um, tilt_axis_deg, options) -> tuple[list[float], float, dict]:
    """The nominal tilt of every view and the pixel size (explicit values over metadata),
    validated with the images and options, and where each came from (the report's tilt_source
    and pixel_size_source: ARGUMENT or METADATA)."""
    if len(images) < 2:
        raise InvalidInputError("images", f"at least two images are needed, got {len(images)}")
    if options.calibrate_tilt and len(images) < 3:
        raise InvalidInputError("calibrate_tilt", "tilt calibration needs three or more images")
    nominal, pixel_size, sources = resolve_calibration(images, tilt_deg, pixel_size_um)
    for index in range(1, len(images)):
        validate_views(images[0], images[index], tilt_axis_deg, options, index=index)
    return nominal, pixel_size, sources


def _parameters_used(options: MatchingOptions) -> dict:
    """The matcher's tuning as MatchingParameters fields, defaults filled in (0: the search range
    the alignment chose), so that a run can be repeated."""
    used = {name: getattr(options, name) for name in PARAMETER_FIELDS}
    used["max_disparity_px"] = used["max_disparity_px"] or 0
    return used


@dataclass(frozen=True)
class _Rectified:
    """The views without data bar, float32, turned so that the tilt axis is vertical (on a larger
    canvas, `outside` marking what no view covers, when the axis was not vertical already), and
    the reference columns' positions from the tilt axis (the image centre), pixels."""

    views: list[np.ndarray]
    bar_rows: int
    to_rectified: np.ndarray
    rotated: bool
    outside: np.ndarray
    x1_px: np.ndarray


def _rectify(images: Sequence[SemImage], tilt_axis_deg: float) -> _Rectified:
    bar_rows = max(image.data_bar_rows for image in images)
    usable_rows = images[0].pixels.shape[0] - bar_rows
    views = [image.pixels[:usable_rows].astype(np.float32) for image in images]
    to_rectified, canvas = alignment.rotation_to_vertical_axis(views[0].shape, tilt_axis_deg)
    rotated = abs(tilt_axis_deg - 90.0) > 1e-9
    outside = np.zeros(views[0].shape, bool)
    if rotated:
        views = [alignment.apply_affine(view, to_rectified, canvas, fill=np.nan) for view in views]
        outside = np.any([np.isnan(view) for view in views], axis=0)
        fill = float(np.nanmean(views[0]))
        views = [np.nan_to_num(view, nan=fill) for view in views]
    columns_px = np.arange(views[0].shape[1], dtype=np.float64) - (views[0].shape[1] - 1) / 2.0
    x1_px = np.broadcast_to(columns_px[None, :], views[0].shape)
    return _Rectified(views, bar_rows, to_rectified, rotated, outside, x1_px)


@dataclass(frozen=True)
class _MatchedViews:
    """Every view matched to the reference: disparities (views, rows, cols) with the reference's
    row zero, and per view but the reference its disparity sigma, confidence, placement and
    photometric fusion's agreement, use, explained share and weight (`photometric.Fusion`); the relative magnification
    uncertainty of every view (0 for the reference); per view but the reference the view resampled onto the
    reference's grid without parallax (`on_first`) and the matcher's disparity to it, before photometric fusion."""

    disparities: np.ndarray
    sigmas: list[np.ndarray]
    confidences: list[np.ndarray]
    placements: list[alignment.Alignment]
    magnification_sigma: list[float]
    strip_count: int
    photometric_agreement: list[float]
    photometric_slopes_used: list[bool]
    photometric_explained: list[float]
    photometric_weight: list[float]
    on_first: list[np.ndarray]
    matched_disparities: list[np.ndarray]

    def best_confidence(self) -> np.ndarray:
        """The highest peak ZNCC any view reached at each pixel (rows, cols)."""
        return self.confidences[0] if len(self.confidences) == 1 else np.nanmax(np.stack(self.confidences), axis=0)


def _match_views(views, options: MatchingOptions, strip_matcher, report_progress) -> _MatchedViews:
    disparities = [np.zeros(views[0].shape, np.float32)]
    sigmas, confidences, placements, magnification_sigma, fusions, on_first, matched_disparities = (
        [],
        [],
        [],
        [0.0],
        [],
        [],
        [],
    )
    for index in range(1, len(views)):

        def matching_progress(fraction: float, message: str, index=index) -> None:
            report_progress(0.05 + 0.8 * (index - 1 + fraction) / (len(views) - 1), f"view {index}: {message}")

        report_progress(0.05 + 0.8 * (index - 1) / (len(views) - 1), f"view {index}: aligning")
        disparity, matched, placement, epsilon_sigma, strip_count, fusion, (resampled, unfused_px) = _match_view(
            views[0], views[index], options, strip_matcher, matching_progress
        )
        fusions.append(fusion)
        on_first.append(resampled)
        matched_disparities.append(unfused_px)
        disparities.append(disparity)
        magnification_sigma.append(epsilon_sigma)
        sigmas.append(matched.sigma_px)
        confidences.append(matched.confidence)
        placements.append(placement)
    return _MatchedViews(
        np.stack(disparities),
        sigmas,
        confidences,
        placements,
        magnification_sigma,
        strip_count,
        [fusion.agreement for fusion in fusions],
        [fusion.used for fusion in fusions],
        [fusion.explained for fusion in fusions],
        [fusion.weight for fusion in fusions],
        on_first,
        matched_disparities,
    )


def _match_view(reference: np.ndarray, view: np.ndarray, options: MatchingOptions, strip_matcher, progress):
    """One view aligned to and matched with the reference: its disparity to the reference (the
    global shift and the magnification error the alignment left taken out), the matcher's result
    (with the default method, the shading's slopes fused in where they agree, `photometric`), the
    placement, the magnification's uncertainty, the number of strips, the photometric fusion, and the
    view resampled onto the reference's grid without parallax with the matcher's disparity to it
    before fusion."""
    placement = alignment.estimate_alignment(reference, view)
    on_first = alignment.apply_affine(
        view, alignment.second_to_first_matrix(placement, reference.shape), reference.shape, inverse=True
    )
    spread = placement.parallax_spread_px if np.isfinite(placement.parallax_spread_px) else reference.shape[1] / 8
    max_disparity_px = options.max_disparity_px or int(np.ceil(1.5 * spread + 8))
    matched = matching.match_disparity(
        reference,
        on_first,
        window_px=options.window_px,
        max_disparity_px=max_disparity_px,
        min_confidence=options.min_confidence,
        max_lr_difference_px=options.max_lr_difference_px,
        normalize_local_contrast=options.normalize_local_contrast,
        propagate_at_full_resolution=options.propagate_at_full_resolution,
        method=options.method,
        strip_pixels=options.strip_pixels,
        strip_matcher=strip_matcher,
        progress=progress,
    )
    strip_count = len(
        matching.strip_bounds(
            reference.shape,
            window_px=options.window_px,
            max_disparity_px=max_disparity_px,
            strip_pixels=options.strip_pixels,
        )
    )
    unfused_px = matched.disparity_px  # the images' own match, which the relief sign's cues read
    fusion = photometric.Fusion(matched.disparity_px, matched.sigma_px, float("nan"), False)
    if options.method == "tgv_zncc":  # window correlation stays the paper's method, FAST quick
        noise_grey = float(np.hypot(photometric.noise_sigma(reference), photometric.noise_sigma(view)))
        fusion = photometric.fused_disparity(
            reference, on_first, matched.disparity_px, matched.sigma_px, noise_grey=noise_grey
        )
        matched = dataclasses.replace(matched, disparity_px=fusion.disparity_px, sigma_px=fusion.sigma_px)
    # A magnification error ε and a rotation θ the alignment left make disparities err by ε·x − θ·y:
    # measured on the matched images, they are taken out here rather than by matching again.
    measured = alignment.residual_misplacement(reference, on_first, matched.disparity_px)
    placement, parallax_px = alignment.with_misplacement(placement, measured, reference.shape)
    disparity = matched.disparity_px + placement.shift_parallel_px - parallax_px
    return disparity, matched, placement, placement.scale_sigma, strip_count, fusion, (on_first, unfused_px)


# Views of which less than the first share is matched with the first view are refused (what
# matches of a noise, mirrored or unrelated view is chance), less than the second reported.
_TOO_FEW_MATCHED = 0.01
_FEW_MATCHED = 0.05


def _matched_enough(matched: _MatchedViews, rectified: _Rectified) -> list[str]:
    """Refuses views of which almost nothing could be matched with the first (such a map is not
    a measurement); the warnings for views of which little could be."""
    area = ~rectified.outside
    warnings = []
    for view in range(1, len(matched.disparities)):
        share = float(np.isfinite(matched.disparities[view][area]).mean()) if area.any() else 0.0
        if share < _TOO_FEW_MATCHED:
            raise InvalidInputError(
                f"images[{view}]",
                f"almost nothing of it could be matched with the first view ({100 * share:.2f} % of the pixels, as "
                "chance matches): the two share no texture (a constant or noise image), do not show one area tilted "
                "about the tilt axis (another area, a mirrored or rotated view), or differ by more parallax than "
                "the maximum disparity (max_disparity_px) lets the matcher search",
            )
        if share < _FEW_MATCHED:
            warnings.append(
                f"only {100 * share:.1f} % of images[{view}] could be matched with the first view; are they one area "
                "tilted about the tilt axis?"
            )
    return warnings


# Views whose parallax the series' heights miss by more than this (median deviation) are
# reported: views consistent with their tilts miss by 0.02-0.04 px (synthetic series), a repeated
# one by 0.6-1.2 px (±5°), the pollen series' by 0.46 and 0.70 px (±3°, ±6°: its nominal tilt
# steps are 5 % off, which the tilt calibration finds).
_DISAGREEING_PX = 0.4


def _disagreeing_views(x1_px, matched: _MatchedViews, tilts, offsets, z_px) -> list[str]:
    """A warning when the parallax of some view of a series of three or more is not what the
    heights of all of them give (a wrong tilt, a view repeated or of another area: a series
    whose third view repeated the first once gave a fifth of the relief, silently). Which view
    is at fault least squares cannot tell from three, so the misses of all are given."""
    if len(matched.disparities) < 3:
        return []
    residuals = tilt_series.view_residuals_px(x1_px, matched.disparities, tilts, z_px, offsets_px=offsets)
    if not np.nanmax(residuals) > _DISAGREEING_PX:
        return []
    misses = ", ".join(f"images[{view}]'s by {residual:.2f} px" for view, residual in enumerate(residuals) if view)
    stated = ", ".join(f"{tilt:g}" for tilt in tilts)
    return [
        f"the views disagree with their tilts ({stated}°): the heights miss the parallax of {misses} (median "
        "deviation; views consistent with their tilts: under 0.1 px); a tilt may be wrong or a view show another "
        "area: check them, or calibrate the tilts from the images"
    ]


def _tilts(x1_px, matched: _MatchedViews, nominal, options: MatchingOptions, report_progress):
    """The tilts heights are computed with: the nominal ones, or with `options.calibrate_tilt`
    those estimated from the disparities, with the views' offsets and the calibration report."""
    if not options.calibrate_tilt:
        return np.array(nominal), None, {}
    report_progress(0.87, "calibrating tilts")
    sample = (slice(None, None, 4), slice(None, None, 4))  # sparse points: neighbours' errors correlate
    disparities = matched.disparities[(slice(None), *sample)].reshape(len(matched.disparities), -1)
    for view in range(1, len(disparities)):
        if np.isfinite(disparities[view]).sum() < tilt_series.MIN_CALIBRATION_POINTS:
            raise InvalidInputError(
                f"images[{view}]", "too little of this view could be matched with the first to calibrate the tilts"
            )
    try:
        # The fit's sigma takes blocks of the sampled points as independent, at least 2 × 2 of them.
        block_px = max(min(alignment.INDEPENDENT_BLOCK_PX, min(x1_px.shape) // 2), 1)
        block_rows, block_cols = (np.arange(size)[step] // block_px for size, step in zip(x1_px.shape, sample))
        cluster = (block_rows[:, None] * (x1_px.shape[1] // block_px + 1) + block_cols[None, :]).ravel()
        estimate = tilt_series.estimate_tilts(
            x1_px[sample].ravel(),
            disparities,
            nominal,
            magnification_sigma=matched.magnification_sigma,
            cluster=cluster,
        )
    except tilt_series.TooFewPointsError as error:
        raise InvalidInputError(
            "images", f"{error}: the views share too little texture to calibrate the tilts"
        ) from None
    _check_calibrated(estimate, nominal)
    calibration = {
        "tilt_deg_nominal": list(nominal),
        "tilt_sigma_deg": estimate.sigma_deg.tolist(),
        "tilt_residual_px": estimate.residual_px,
    }
    return estimate.tilt_deg, estimate.offsets_px, calibration


def _oriented(images, rectified: _Rectified, matched: _MatchedViews, z_px, tilts, options, instruments, axis, warnings):
    """The heights (px) and tilts with the relief's sign chosen (`orientation.oriented`; the
    mirror image: both negated), and the report's relief_sign fields; its warnings added."""
    place = detector_place([image.instrument for image in images], options.detector_from_tilt_axis_deg, instruments)
    chosen = orientation.oriented(
        rectified.views[0],
        list(zip(matched.on_first, matched.matched_disparities)),
        z_px,
        tilts,
        mode=ReliefSignMode(options.relief_sign),
        detector=place,
        tilt_axis_deg=axis,
    )
    warnings += chosen.warnings
    sign = -1.0 if chosen.inverted else 1.0
    return z_px * sign, np.asarray(tilts, np.float64) * sign, chosen.fields


def _file_facts(images) -> dict:
    """The report's instrument and acquisition time: what the first image's file says (empty
    where it says nothing)."""
    key, acquired_at = images[0].instrument, images[0].acquired_at or ""
    if key is None:
        return {"acquired_at": acquired_at}
    instrument = {"vendor": key.vendor, "model": key.model, "detector": key.detector}
    return {"instrument": instrument | {"scan_rotation_deg": key.scan_rotation_deg}, "acquired_at": acquired_at}


def _check_calibrated(estimate: tilt_series.TiltEstimate, nominal) -> None:
    """Refuses calibrated tilts that are not corrections of the nominal ones: calibration mends a
    stage's errors of a few percent, while a tilt step moved by half its size or more (or beyond
    ±90°, or not determined) means a view that shows another area or repeats one. Which view is
    at fault the fit cannot always tell, so every view it moved so far is named."""
    moved = []
    for view in range(1, len(nominal)):
        tilt, sigma, step = float(estimate.tilt_deg[view]), float(estimate.sigma_deg[view]), nominal[view] - nominal[0]
        undetermined = np.isinf(sigma) or sigma > 45.0  # NaN: the magnification's part is unknown, the fit's is not
        if undetermined or not (abs(tilt) < 90.0 and abs(tilt - nominal[view]) < 0.5 * abs(step)):
            moved.append((view, f"images[{view}] at {tilt:.2f} ± {sigma:.2g}° against the nominal {nominal[view]:g}°"))
    if moved:
        raise InvalidInputError(
            f"images[{moved[0][0]}].tilt_deg" if len(moved) == 1 else "images",
            f"the views do not show the first view's area tilted as stated (first view at {nominal[0]:g}°): the "
            f"images put {'; '.join(text for _, text in moved)}",
        )


def _tilt_uncertainty_deg(options: MatchingOptions, calibration: dict, warnings: list[str]) -> float:
    """The tilt uncertainty sigma_um uses: the calibrated tilts' where known, else the nominal one."""
    if not calibration:
        return options.tilt_uncertainty_deg
    calibrated_sigma = float(np.max(calibration["tilt_sigma_deg"]))
    if np.isfinite(calibrated_sigma):
        return calibrated_sigma
    # A view's magnification could be measured neither on the matched images nor from features.
    warnings.append(
        "the calibrated tilts' uncertainty is unknown (a view's magnification could not be measured); sigma_um uses "
        f"the nominal tilt uncertainty of {options.tilt_uncertainty_deg:g} degrees"
    )
    return options.tilt_uncertainty_deg


def _on_stored_grid(rectified: _Rectified, first: SemImage, *maps):
    """The maps (rows, cols) turned back onto the first image's grid as stored, float32, NaN rows
    where its data bar was."""
    if rectified.rotated:
        back = (first.pixels.shape[0] - rectified.bar_rows, first.pixels.shape[1])
        maps = [
            alignment.apply_affine(values.astype(np.float32), rectified.to_rectified, back, inverse=True, fill=np.nan)
            for values in maps
        ]
    return tuple(_pad_rows(values, rectified.bar_rows) for values in maps)


def _estimated_tilt_axis_deg(placements: list[alignment.Alignment], tilt_axis_deg: float, warnings: list[str]) -> float:
    """The tilt axis the features' parallax points to (NaN when none tells); a warning when it is
    more than AXIS_WARNING_DEG from the one used."""
    directions = [p.parallax_direction_deg for p in placements if np.isfinite(p.parallax_direction_deg)]
    axis_estimated = float(tilt_axis_deg + np.median(directions)) if directions else float("nan")
    if directions and abs(axis_estimated - tilt_axis_deg) > AXIS_WARNING_DEG:
        warnings.append(
            f"the parallax points to a tilt axis at {axis_estimated:.1f} degrees, "
            f"{abs(axis_estimated - tilt_axis_deg):.1f} from the {tilt_axis_deg:g} used; heights may be wrong (give "
            "the tilt axis)"
        )
    return axis_estimated


def _report(
    *,
    tilts,
    tilt_axis_deg,
    pixel_size,
    matched: _MatchedViews,
    z_um,
    bar_rows,
    axis_estimated,
    warnings,
    calibration,
    tilt_uncertainty,
) -> dict:
    """The MatchingReport's figures (see the protobuf API), but for the elapsed time."""
    first_placement = matched.placements[0]
    first_disparity = matched.disparities[1]
    measured = np.isfinite(first_disparity).any()
    return {
        "tilt_deg": [float(t) for t in tilts],
        "tilt_axis_deg": float(tilt_axis_deg),
        "pixel_size_um": pixel_size,
        "shift_parallel_px": first_placement.shift_parallel_px,
        "shift_across_px": first_placement.shift_across_px,
        "rotation_deg": first_placement.rotation_deg,
        "rotation_sigma_deg": first_placement.rotation_sigma_deg,
        "magnification_ratio": first_placement.scale,
        "magnification_sigma": first_placement.scale_sigma,
        "residual_vertical_parallax_px": max(p.residual_vertical_parallax_px for p in matched.placements),
        "valid_fraction": float(np.isfinite(z_um).mean()),
        "min_disparity_px": float(np.nanmin(first_disparity)) if measured else float("nan"),
        "max_disparity_px": float(np.nanmax(first_disparity)) if measured else float("nan"),
        "data_bar_rows": int(bar_rows),
        "tilt_axis_deg_estimated": axis_estimated,
        "warnings": warnings,
        "strip_count": matched.strip_count,
        "photometric_agreement": matched.photometric_agreement,
        "photometric_slopes_used": matched.photometric_slopes_used,
        "photometric_explained": matched.photometric_explained,
        "photometric_weight": matched.photometric_weight,
        "tilt_uncertainty_deg": float(tilt_uncertainty),
        **calibration,
    }


def _pad_rows(values: np.ndarray, rows: int) -> np.ndarray:
    """Adds `rows` NaN rows at the bottom, where the data bar was."""
    if rows == 0:
        return values.astype(np.float32, copy=False)
    padding = np.full((rows, values.shape[1]), np.nan, np.float32)
    return np.vstack([values.astype(np.float32), padding])
