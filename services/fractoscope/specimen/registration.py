"""Placing a higher-magnification ROI inside its parent: where (image registration), at what height
(offset and tilt fitted on the overlap) and with what brightness (texture gain and offset)."""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.specimen.fusion import PlacedRoi

# The lowest peak correlation an automatic placement is trusted with: a true match of the demo's
# ROI scores 0.9, a pure-noise ROI 0.04.
MIN_REGISTRATION_SCORE = 0.3


@dataclass(frozen=True)
class Registration:
    """Where a child image's pixel (0, 0) lies in its parent's image, parent pixels (col, row), and
    the peak normalized cross-correlation of that placement (0 to 1)."""

    origin_px: tuple[float, float]
    score: float


def register_child(
    parent_image: np.ndarray, child_image: np.ndarray, *, parent_pixel_size_um: float, child_pixel_size_um: float
) -> Registration:
    """Finds a child SEM image (rows, cols, finer pixels) inside its parent's image by zero-mean
    normalized cross-correlation after averaging the child to the parent's pixel size (which
    also makes brightness and contrast differences irrelevant); sub-pixel by a parabola through the
    peak and its neighbours."""
    scale = child_pixel_size_um / parent_pixel_size_um
    rows, cols = child_image.shape
    if min(round(cols * scale), round(rows * scale)) < 8:
        raise InvalidInputError("rois.center_um", "the ROI covers fewer than 8 x 8 parent pixels; give its centre")
    if round(cols * scale) > parent_image.shape[1] or round(rows * scale) > parent_image.shape[0]:
        raise InvalidInputError("rois.pixel_size_um", "the ROI would be larger than its parent")
    small, achieved = _at_parent_scale(child_image, scale)
    scores = cv2.matchTemplate(parent_image.astype(np.float32), small, cv2.TM_CCOEFF_NORMED)
    _, best, _, (col, row) = cv2.minMaxLoc(scores)
    col_f = col + _parabola_peak(scores[row, col - 1 : col + 2]) if 0 < col < scores.shape[1] - 1 else float(col)
    row_f = row + _parabola_peak(scores[row - 1 : row + 2, col]) if 0 < row < scores.shape[0] - 1 else float(row)
    # Small pixel k is centred on child coordinate (k + 0.5) / s - 0.5, so child pixel 0 sits at
    # small coordinate 0.5 s - 0.5 for the achieved scale s.
    return Registration((col_f + 0.5 * achieved[0] - 0.5, row_f + 0.5 * achieved[1] - 0.5), float(best))


def _at_parent_scale(child_image: np.ndarray, scale: float) -> tuple[np.ndarray, tuple[float, float]]:
    """The child image area-averaged by `scale` (child over parent pixel size), float32, and the
    scale achieved along (cols, rows) after rounding to whole pixels."""
    rows, cols = child_image.shape
    size = (max(round(cols * scale), 1), max(round(rows * scale), 1))
    small = cv2.resize(child_image.astype(np.float32), size, interpolation=cv2.INTER_AREA)
    return small, (size[0] / cols, size[1] / rows)


def _parabola_peak(values: np.ndarray) -> float:
    left, centre, right = (float(v) for v in values)
    curvature = left - 2 * centre + right
    return 0.0 if curvature >= 0 else float(np.clip(0.5 * (left - right) / curvature, -0.5, 0.5))


@dataclass(frozen=True)
class HeightAlignment:
    """Plane z = offset + slope_x·x + slope_y·y (µm, x and y in the child's µm frame) that brings a
    child's heights onto its parent's, the RMS of what remains on the overlap, µm, and how the two
    heights' relief (each without its own plane) correlates there (-1 to 1; negative: one of them is
    upside down; NaN: no relief)."""

    offset_um: float
    slope_x: float
    slope_y: float
    residual_um: float
    overlap_points: int
    height_correlation: float = float("nan")


def align_heights(parent: PlacedRoi, child: PlacedRoi) -> HeightAlignment:
    """Fits the plane between a child's heights (averaged to the parent's pixel size) and the
    parent's at the same places; two passes, the second without points beyond 3 robust sigma."""
    factor = max(int(round(parent.pixel_size_um / child.pixel_size_um)), 1)
    rows, cols = (child.z_um.shape[0] // factor) * factor, (child.z_um.shape[1] // factor) * factor
    blocks = child.z_um[:rows, :cols].reshape(rows // factor, factor, cols // factor, factor)
    known = np.isfinite(blocks)
    counts = known.sum(axis=(1, 3))
    sums = np.where(known, blocks, 0.0).sum(axis=(1, 3))
    child_z = np.where(counts > factor * factor / 2, sums / np.maximum(counts, 1), np.nan)
    block_rows, block_cols = np.indices(child_z.shape)
    x_child_um = (block_cols * factor + (factor - 1) / 2) * child.pixel_size_um
    y_child_um = (block_rows * factor + (factor - 1) / 2) * child.pixel_size_um
    parent_col = (x_child_um + child.origin_um[0] - parent.origin_um[0]) / parent.pixel_size_um
    parent_row = (y_child_um + child.origin_um[1] - parent.origin_um[1]) / parent.pixel_size_um
    parent_z = cv2.remap(
        parent.z_um.astype(np.float32),
        parent_col.astype(np.float32),
        parent_row.astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    difference = (parent_z - child_z).ravel()
    design = np.column_stack([np.ones(difference.size), x_child_um.ravel(), y_child_um.ravel()])
    use = np.isfinite(difference)
    if use.sum() < 16:
        raise InvalidInputError(
            "rois.center_um",
            f"ROI {child.id!r} placed there overlaps its parent {parent.id!r} in fewer than 16 measured points",
        )
    for _ in range(2):
        coefficients, *_ = np.linalg.lstsq(design[use], difference[use], rcond=None)
        residual = difference - design @ coefficients
        spread = 1.4826 * np.nanmedian(np.abs(residual[use] - np.nanmedian(residual[use])))
        use = np.isfinite(residual) & (np.abs(residual) <= 3 * max(spread, 1e-9))
    final = residual[np.isfinite(residual)]
    both = np.isfinite(difference)
    # Each side's own plane out first: a tilt is what the alignment mends, the relief's shape is not.
    sides = [z[both].astype(np.float64) for z in (parent_z.ravel(), child_z.ravel())]
    pair = [z - design[both] @ np.linalg.lstsq(design[both], z, rcond=None)[0] for z in sides]
    relief = all(np.std(part) > 1e-4 * max(np.ptp(z), 1e-9) for part, z in zip(pair, sides))  # not a plane's rounding
    correlation = float(np.corrcoef(pair)[0, 1]) if relief else float("nan")
    return HeightAlignment(
        offset_um=float(coefficients[0]),
        slope_x=float(coefficients[1]),
        slope_y=float(coefficients[2]),
        residual_um=float(np.sqrt(np.mean(final**2))),
        overlap_points=int(final.size),
        height_correlation=correlation,
    )


def apply_height_alignment(z_um: np.ndarray, alignment: HeightAlignment, *, pixel_size_um: float) -> np.ndarray:
    """Child heights (rows, cols) µm with the fitted plane added, float32."""
    rows, cols = np.indices(z_um.shape)
    plane = alignment.offset_um + alignment.slope_x * cols * pixel_size_um + alignment.slope_y * rows * pixel_size_um
    return (z_um + plane).astype(np.float32)


def match_texture(parent: PlacedRoi, child: PlacedRoi) -> np.ndarray:
    """The child's texture with gain and offset that give it its parent's mean and spread on the
    overlap (both seen at the parent's pixel size), uint8."""
    small, achieved = _at_parent_scale(child.texture, child.pixel_size_um / parent.pixel_size_um)
    small_rows, small_cols = np.indices(small.shape)
    x_um = child.origin_um[0] + ((small_cols + 0.5) / achieved[0] - 0.5) * child.pixel_size_um
    y_um = child.origin_um[1] + ((small_rows + 0.5) / achieved[1] - 0.5) * child.pixel_size_um
    parent_texture = cv2.remap(
        parent.texture.astype(np.float32),
        ((x_um - parent.origin_um[0]) / parent.pixel_size_um).astype(np.float32),
        ((y_um - parent.origin_um[1]) / parent.pixel_size_um).astype(np.float32),
        cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=np.nan,
    )
    overlap = np.isfinite(parent_texture)
    if overlap.sum() < 16 or small[overlap].std() < 1e-6:
        return child.texture
    gain = parent_texture[overlap].std() / small[overlap].std()
    offset = parent_texture[overlap].mean() - gain * small[overlap].mean()
    return np.clip(child.texture.astype(np.float32) * gain + offset, 0, 255).astype(np.uint8)
