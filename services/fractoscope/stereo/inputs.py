"""A height map request's inputs before any work: the matcher's options (`MatchingOptions`) and
the checks of options, tilts, pixel size and images, with where each calibration value came from.
Errors are InvalidInputError naming the argument (`images[1].tilt_deg`, `window_px`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.sem.image import SemImage
from fractoscope.stereo import geometry, matching
from fractoscope.stereo.disparity import DEFAULT_METHOD
from fractoscope.stereo.relief_sign import ReliefSignMode

# Where a calibration value came from (the report's tilt_source and pixel_size_source).
METADATA, ARGUMENT, TILT_CALIBRATION, DEFAULT = "metadata", "argument", "tilt_calibration", "default"


@dataclass(frozen=True)
class MatchingOptions:
    """Tuning of the matcher; see `matching.match_disparity` for the meaning of each."""

    window_px: int = matching.DEFAULT_WINDOW_PX
    max_disparity_px: int | None = None
    min_confidence: float = matching.DEFAULT_MIN_CONFIDENCE
    max_lr_difference_px: float = matching.DEFAULT_MAX_LR_DIFFERENCE_PX
    normalize_local_contrast: bool = True
    propagate_at_full_resolution: bool = False
    method: str = DEFAULT_METHOD  # a key of matching.METHODS
    tilt_uncertainty_deg: float = 0.5
    calibrate_tilt: bool = False
    strip_pixels: int = matching.DEFAULT_STRIP_PIXELS
    relief_sign: ReliefSignMode = ReliefSignMode.AUTO
    detector_from_tilt_axis_deg: float = float("nan")  # not known: no place is assumed


def resolve_calibration(images, tilt_deg, pixel_size_um) -> tuple[list[float], float, dict]:
    """The nominal tilts and the pixel size (explicit values over the files' metadata; `images`
    are SemImage or anything with their tilt_deg and pixel_size_um), validated, and their sources."""
    given = list(tilt_deg) if tilt_deg is not None else [None] * len(images)
    if len(given) != len(images):
        raise InvalidInputError("images[].tilt_deg", f"{len(given)} tilts for {len(images)} images")
    nominal = [_resolve_tilt(image, explicit, index) for index, (image, explicit) in enumerate(zip(images, given))]
    for index in range(1, len(images)):
        # A tilt read from a file is the file's fault, not the caller's tilt_deg.
        from_files = given[0] is None or given[index] is None
        geometry.validate_tilts(
            (nominal[0], nominal[index]), field=f"images[{index}]" if from_files else f"images[{index}].tilt_deg"
        )
    sources = {
        "tilt_source": [ARGUMENT if explicit is not None else METADATA for explicit in given],
        "pixel_size_source": ARGUMENT if pixel_size_um is not None else METADATA,
    }
    return nominal, _resolve_pixel_size(images[0], pixel_size_um), sources


def tilts_against_metadata(images, tilt_deg) -> list[str]:
    """Warnings where tilts given explicitly run the other way from the stage tilts the files
    record (each view's step from the first, given against recorded): the sign the heights get
    then rests on the typed tilts, which the metadata contradicts."""
    given = list(tilt_deg) if tilt_deg is not None else [None] * len(images)
    warnings = []
    for index in range(1, len(images)):
        pair = (given[0], given[index])
        recorded = (images[0].tilt_deg, images[index].tilt_deg)
        if None in pair or None in recorded or not all(np.isfinite(recorded)):
            continue
        step_given, step_recorded = pair[1] - pair[0], recorded[1] - recorded[0]
        if step_given * step_recorded < 0:
            warnings.append(
                f"the tilts given for images[0] and images[{index}] ({pair[0]:g}°, {pair[1]:g}°) run the other way "
                f"from the stage tilts their files record ({recorded[0]:g}°, {recorded[1]:g}°): the heights follow "
                "the tilts given; check the image order and the tilt signs"
            )
    return warnings


def _resolve_tilt(image: SemImage, explicit: float | None, index: int) -> float:
    if explicit is not None:
        return float(explicit)
    if image.tilt_deg is None:
        raise InvalidInputError(
            f"images[{index}].tilt_deg", "no tilt given and the image file carries no stage tilt metadata"
        )
    if not (np.isfinite(image.tilt_deg) and abs(image.tilt_deg) < 90.0):
        raise InvalidInputError(
            f"images[{index}]",
            f"the stage tilt in its metadata, {image.tilt_deg}°, is not an angle within ±90°; give the tilts",
        )
    return float(image.tilt_deg)


def _resolve_pixel_size(first: SemImage, pixel_size_um: float | None) -> float:
    if pixel_size_um is not None:
        return geometry.validate_pixel_size_um(pixel_size_um)
    if first.pixel_size_um is None:
        raise InvalidInputError("pixel_size_um", "no pixel size given and the image file carries no calibration")
    try:
        return geometry.validate_pixel_size_um(first.pixel_size_um)
    except InvalidInputError as error:  # the file's fault, not the caller's pixel_size_um
        raise InvalidInputError(
            "images[0]", f"the pixel size in its metadata {error.message}; give the pixel size"
        ) from None


def validate_same_size(first: tuple[int, int], other: tuple[int, int], *, index: int) -> None:
    """InvalidInputError naming images[index] unless its (rows, cols) `other` is the first image's."""
    if tuple(other) != tuple(first):
        raise InvalidInputError(
            f"images[{index}]", f"size {tuple(other)[::-1]} differs from the first image's {tuple(first)[::-1]}"
        )


def validate_views(
    first: SemImage, second: SemImage, tilt_axis_deg: float, options: MatchingOptions, *, index: int = 1
) -> None:
    validate_same_size(first.pixels.shape, second.pixels.shape, index=index)
    for view, image in ((0, first), (index, second)):
        data = image.image
        if data.min() == data.max():
            raise InvalidInputError(
                f"images[{view}]", f"is one grey level ({data.flat[0]}) throughout: it has no texture to match"
            )
    validate_tilt_axis_deg(tilt_axis_deg)
    validate_options(options, image_cols=first.pixels.shape[1])


def validate_tilt_axis_deg(tilt_axis_deg: float) -> None:
    """Raises InvalidInputError naming tilt_axis_deg unless it is within ±360° (1e300 is finite,
    but no angle a float can turn by)."""
    if not (np.isfinite(tilt_axis_deg) and abs(tilt_axis_deg) <= 360.0):
        raise InvalidInputError("tilt_axis_deg", f"must be an angle within ±360°, got {tilt_axis_deg}")


def validate_options(options: MatchingOptions, *, image_cols: int) -> None:
    """Raises InvalidInputError naming the first out-of-range setting by its MatchingOptions name."""
    if options.method not in matching.METHODS:
        raise InvalidInputError("method", f"must be one of {', '.join(matching.METHODS)}, got {options.method!r}")
    if options.window_px < 5 or options.window_px % 2 == 0 or options.window_px > 101:
        raise InvalidInputError("window_px", f"must be odd, 5 to 101, got {options.window_px}")
    if not 0.0 <= options.min_confidence < 1.0:
        raise InvalidInputError("min_confidence", f"must be in [0, 1), got {options.min_confidence}")
    if not options.max_lr_difference_px > 0:
        raise InvalidInputError("max_lr_difference_px", f"must be > 0, got {options.max_lr_difference_px}")
    if options.strip_pixels < 1:
        raise InvalidInputError("strip_pixels", f"must be positive, got {options.strip_pixels}")
    if options.max_disparity_px is not None and not 1 <= options.max_disparity_px <= image_cols:
        raise InvalidInputError("max_disparity_px", f"must be 1 to the image width, got {options.max_disparity_px}")
    if not 0.0 <= options.tilt_uncertainty_deg < 45.0:
        raise InvalidInputError("tilt_uncertainty_deg", f"must be in [0, 45), got {options.tilt_uncertainty_deg}")
    if abs(options.detector_from_tilt_axis_deg) > 360.0:  # NaN (not known) passes
        raise InvalidInputError(
            "detector_from_tilt_axis_deg", "must be degrees within ±360°, or absent (NaN) where not known"
        )
