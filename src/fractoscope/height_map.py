"""From a stereo pair of SEM images to a calibrated height map on the first image's pixel grid.

Steps: calibration (explicit values over file metadata), data bar crop, rotation of the tilt
axis to vertical, global alignment, dense ZNCC matching, heights by the parallel-projection
formula, uncertainty, and the way back onto the first image's grid as stored.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from fractoscope import alignment, dense_matching, stereo_geometry
from fractoscope.errors import InvalidInputError
from fractoscope.sem_image import SemImage


@dataclass(frozen=True)
class MatchingOptions:
    """Tuning of the matcher; see `dense_matching.match_disparity` for the meaning of each."""

    window_px: int = 15
    max_disparity_px: int | None = None
    min_confidence: float = 0.5
    max_lr_difference_px: float = 1.0
    tilt_uncertainty_deg: float = 0.5


@dataclass(frozen=True)
class HeightMapResult:
    """A height map on the first image's stored grid (rows, cols), float32.

    z_um: heights in µm, relative (arbitrary constant offset), NaN where unknown.
    sigma_um: one-sigma uncertainty in µm, NaN where z_um is NaN.
    confidence: peak ZNCC, 0 to 1.
    report: alignment and quality figures (see MatchingReport in the protobuf API).
    """

    z_um: np.ndarray
    sigma_um: np.ndarray
    confidence: np.ndarray
    report: dict = field(default_factory=dict)


def compute_height_map(
    first: SemImage,
    second: SemImage,
    *,
    tilt_deg: tuple[float | None, float | None] = (None, None),
    pixel_size_um: float | None = None,
    tilt_axis_deg: float = 90.0,
    options: MatchingOptions = MatchingOptions(),
    progress: dense_matching.ProgressCallback | None = None,
) -> HeightMapResult:
    """Heights of the surface seen in `first`, from `first` and `second` taken at two stage tilts.

    Explicit `tilt_deg` entries and `pixel_size_um` override what the files say.
    """
    started = time.perf_counter()
    report_progress = progress or (lambda fraction, message: None)
    tilts = _resolve_tilts(first, second, tilt_deg)
    pixel_size = _resolve_pixel_size(first, pixel_size_um)
    _validate(first, second, tilt_axis_deg, options)

    bar_rows = max(first.data_bar_rows, second.data_bar_rows)
    usable_rows = first.pixels.shape[0] - bar_rows
    first_image = first.pixels[:usable_rows].astype(np.float32)
    second_image = second.pixels[:usable_rows].astype(np.float32)

    to_rectified, canvas = alignment.rotation_to_vertical_axis(first_image.shape, tilt_axis_deg)
    rotated = abs(tilt_axis_deg - 90.0) > 1e-9
    if rotated:
        first_image = alignment.apply_affine(first_image, to_rectified, canvas, fill=np.nan)
        second_image = alignment.apply_affine(second_image, to_rectified, canvas, fill=np.nan)
        outside = np.isnan(first_image) | np.isnan(second_image)
        fill = float(np.nanmean(first_image))
        first_image, second_image = np.nan_to_num(first_image, nan=fill), np.nan_to_num(second_image, nan=fill)
    report_progress(0.05, "aligning the pair")

    placement = alignment.estimate_alignment(first_image, second_image)
    second_on_first = alignment.apply_affine(
        second_image, alignment.second_to_first_matrix(placement, first_image.shape), first_image.shape, inverse=True
    )
    max_disparity = options.max_disparity_px
    if max_disparity is None:
        spread = placement.parallax_spread_px if np.isfinite(placement.parallax_spread_px) else first_image.shape[1] / 8
        max_disparity = int(np.ceil(1.5 * spread + 8))

    def matching_progress(fraction: float, message: str) -> None:
        report_progress(0.1 + 0.8 * fraction, message)

    matched = dense_matching.match_disparity(
        first_image,
        second_on_first,
        window_px=options.window_px,
        max_disparity_px=max_disparity,
        min_confidence=options.min_confidence,
        max_lr_difference_px=options.max_lr_difference_px,
        progress=matching_progress,
    )
    report_progress(0.92, "heights")
    disparity = matched.disparity_px + placement.shift_parallel_px
    x1_px = np.arange(first_image.shape[1], dtype=np.float64)[None, :] - (first_image.shape[1] - 1) / 2.0
    z_um = stereo_geometry.heights_um(x1_px, disparity, tilt_deg=tilts, pixel_size_um=pixel_size)
    sigma_um = stereo_geometry.height_sigma_um(
        z_um,
        matched.sigma_px,
        tilt_deg=tilts,
        pixel_size_um=pixel_size,
        tilt_uncertainty_deg=options.tilt_uncertainty_deg,
    )
    confidence = matched.confidence
    if rotated:
        z_um[outside] = np.nan
        back = (first.pixels.shape[0] - bar_rows, first.pixels.shape[1])
        z_um, sigma_um, confidence = (
            alignment.apply_affine(values.astype(np.float32), to_rectified, back, inverse=True, fill=np.nan)
            for values in (z_um, sigma_um, confidence)
        )
    z_um, sigma_um, confidence = (_pad_rows(values, bar_rows) for values in (z_um, sigma_um, confidence))
    valid = np.isfinite(z_um)
    report = {
        "tilt_deg": list(tilts),
        "tilt_axis_deg": float(tilt_axis_deg),
        "pixel_size_um": pixel_size,
        "shift_parallel_px": placement.shift_parallel_px,
        "shift_across_px": placement.shift_across_px,
        "rotation_deg": placement.rotation_deg,
        "residual_vertical_parallax_px": placement.residual_vertical_parallax_px,
        "valid_fraction": float(valid.mean()),
        "min_disparity_px": float(np.nanmin(disparity)) if np.isfinite(disparity).any() else float("nan"),
        "max_disparity_px": float(np.nanmax(disparity)) if np.isfinite(disparity).any() else float("nan"),
        "data_bar_rows": int(bar_rows),
        "elapsed_s": time.perf_counter() - started,
    }
    report_progress(1.0, "done")
    return HeightMapResult(z_um, sigma_um, np.nan_to_num(confidence).astype(np.float32), report)


def _resolve_tilts(first: SemImage, second: SemImage, tilt_deg) -> tuple[float, float]:
    resolved = []
    for index, (explicit, image) in enumerate(zip(tilt_deg, (first, second))):
        value = explicit if explicit is not None else image.tilt_deg
        if value is None:
            raise InvalidInputError(
                f"images[{index}].tilt_deg", "no tilt given and the image file carries no stage tilt metadata"
            )
        resolved.append(float(value))
    stereo_geometry.validate_tilts(tuple(resolved), field="images[].tilt_deg")
    return resolved[0], resolved[1]


def _resolve_pixel_size(first: SemImage, pixel_size_um: float | None) -> float:
    value = pixel_size_um if pixel_size_um is not None else first.pixel_size_um
    if value is None:
        raise InvalidInputError("pixel_size_um", "no pixel size given and the image file carries no calibration")
    return stereo_geometry.validate_pixel_size_um(value)


def _validate(first: SemImage, second: SemImage, tilt_axis_deg: float, options: MatchingOptions) -> None:
    if first.pixels.shape != second.pixels.shape:
        raise InvalidInputError(
            "images[1]", f"size {second.pixels.shape[::-1]} differs from the first image's {first.pixels.shape[::-1]}"
        )
    if not np.isfinite(tilt_axis_deg):
        raise InvalidInputError("tilt_axis_deg", f"must be finite, got {tilt_axis_deg}")
    if options.window_px < 5 or options.window_px % 2 == 0 or options.window_px > 101:
        raise InvalidInputError("parameters.window_px", f"must be odd, 5 to 101, got {options.window_px}")
    if not 0.0 <= options.min_confidence < 1.0:
        raise InvalidInputError("parameters.min_confidence", f"must be in [0, 1), got {options.min_confidence}")
    if not options.max_lr_difference_px > 0:
        raise InvalidInputError("parameters.max_lr_difference_px", f"must be > 0, got {options.max_lr_difference_px}")
    if options.max_disparity_px is not None and not 1 <= options.max_disparity_px <= first.pixels.shape[1]:
        raise InvalidInputError("parameters.max_disparity_px", f"must be 1 to the image width, got {options.max_disparity_px}")
    if not 0.0 <= options.tilt_uncertainty_deg < 45.0:
        raise InvalidInputError("parameters.tilt_uncertainty_deg", f"must be in [0, 45), got {options.tilt_uncertainty_deg}")


def _pad_rows(values: np.ndarray, rows: int) -> np.ndarray:
    """Adds `rows` NaN rows at the bottom, where the data bar was."""
    if rows == 0:
        return values.astype(np.float32)
    padding = np.full((rows, values.shape[1]), np.nan, np.float32)
    return np.vstack([values.astype(np.float32), padding])
