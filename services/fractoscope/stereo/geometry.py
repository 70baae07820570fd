"""Parallel-projection stereo geometry of SEM tilt pairs and its error model.

A surface point at lateral position x (perpendicular to the tilt axis) and height z is seen at
``x_i = x cos t_i + z sin t_i`` in the image taken at stage tilt t_i. Two views give
``z = (x2 cos t1 - x1 cos t2) / sin(t2 - t1)``; for eucentric ±α this is ``z = d p / (2 sin α)``
with disparity d = x2 - x1 in pixels of size p. Positions are measured from the tilt axis.
Heights are solved by tilt_series (for any number of views); this module checks the inputs and
holds the error model.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from fractoscope.errors import InvalidInputError
from fractoscope.stereo import tilt_series


def validate_tilts(tilt_deg: tuple[float, float], *, field: str = "tilt_deg") -> None:
    """Rejects tilts that are not finite, beyond ±90°, or too close to give heights."""
    t1, t2 = tilt_deg
    if not (np.isfinite(t1) and np.isfinite(t2)) or max(abs(t1), abs(t2)) >= 90.0:
        raise InvalidInputError(field, f"tilts must be finite and within ±90°, got {t1} and {t2}")
    if abs(t2 - t1) < 0.1:
        raise InvalidInputError(field, f"the two tilts must differ by at least 0.1°, got {t1} and {t2}")


def validate_pixel_size_um(value: float, *, field: str = "pixel_size_um") -> float:
    """The pixel size as float, or InvalidInputError unless finite and within 1e-5 to 1e4 µm."""
    if not np.isfinite(value) or not 1e-5 <= value <= 1e4:
        raise InvalidInputError(field, f"must be between 1e-5 and 1e4 µm, got {value}")
    return float(value)


def relative_height_error_from_tilt(*, tilt_deg: tuple[float, float], tilt_uncertainty_deg: float) -> float:
    """Relative height error ε_z = δα / tan α for a half tilt difference α known to ±δα
    (0.0999 for α = 5°, δα = 0.5°: the paper's 10 %)."""
    half_difference = np.radians(abs(tilt_deg[1] - tilt_deg[0]) / 2.0)
    return float(np.radians(tilt_uncertainty_deg) / np.tan(half_difference))


def height_sigma_um(
    z_um: np.ndarray,
    disparity_sigma_px: Sequence[np.ndarray],
    *,
    tilt_deg: Sequence[float],
    pixel_size_um: float,
    tilt_uncertainty_deg: float,
) -> np.ndarray:
    """One-sigma height uncertainty per pixel, µm, float32 (NaN where z_um is NaN), as the
    pipeline reports it. z_um: (rows, cols) float32 heights; disparity_sigma_px: each view's
    disparity uncertainty to the reference view (tilt_deg[0]), (rows, cols), NaN where unmatched,
    one per view but the reference.

    Each view's disparity error becomes a height error through its height per pixel of
    disparity (p cos t_r / sin(t_i - t_r): 0.0287 µm at 0.005 µm/px and 5.74 µm at 1 µm/px for
    ±5°); the views combine by their information. The tilt error adds ε_z |z - z_ref| for the
    widest pair (`series_relative_height_error`) about a reference level (`_tilt_sigma_um`)."""
    _, b = tilt_series.coefficients(tilt_deg)
    with np.errstate(invalid="ignore", divide="ignore"):
        # Information on the height from each view's disparity, 1/px² (none where unmatched).
        information = sum(
            np.where(np.isfinite(sigma), (np.float32(b[index + 1]) / sigma) ** 2, np.float32(0))
            for index, sigma in enumerate(disparity_sigma_px)
        )
        disparity_sigma_um = np.float32(pixel_size_um) / np.sqrt(information)
    relative = series_relative_height_error(tilt_deg, tilt_uncertainty_deg=tilt_uncertainty_deg)
    sigma_um = np.hypot(disparity_sigma_um, _tilt_sigma_um(z_um, relative))
    sigma_um[~np.isfinite(z_um)] = np.nan
    return sigma_um


def series_relative_height_error(tilt_deg: Sequence[float], *, tilt_uncertainty_deg: float) -> float:
    """ε_z of a tilt series: that of its widest pair with the reference view (tilt_deg[0])."""
    _, b = tilt_series.coefficients(tilt_deg)
    widest = (float(tilt_deg[0]), float(tilt_deg[np.argmax(np.abs(b))]))
    return relative_height_error_from_tilt(tilt_deg=widest, tilt_uncertainty_deg=tilt_uncertainty_deg)


def matching_sigma_um(z_um: np.ndarray, sigma_um: np.ndarray, *, relative_height_error: float) -> np.ndarray:
    """The disparity (matching noise) part of `height_sigma_um`'s sigma, µm float32: the tilt part
    ε_z |z - z_ref| taken out again (NaN where either is NaN). Surface analysis propagates the two
    apart: the tilt part scales every height together, the matching part varies from window to
    window."""
    tilt = _tilt_sigma_um(np.asarray(z_um, np.float32), relative_height_error)
    sigma = np.asarray(sigma_um, np.float32)
    return np.sqrt(np.maximum(sigma * sigma - tilt * tilt, np.float32(0)))


def _tilt_sigma_um(z_um: np.ndarray, relative: float) -> np.ndarray:
    """ε_z |z - z_ref|: a tilt error scales heights about a reference level, the median height (of
    every 4th row and column, which tell it well enough)."""
    sample = z_um[::4, ::4]
    sample = sample[np.isfinite(sample)]
    reference_um = np.float32(np.median(sample)) if sample.size else np.float32(0)
    return np.float32(relative) * np.abs(z_um - reference_um)


def max_measurable_slope(tilt_deg: Sequence[float]) -> float:
    """The steepest slope (height over horizontal distance) a matcher can measure between
    neighbouring points: a disparity that changes by more than one pixel per pixel is an
    occlusion (the disparity gradient limit; one view sees what the other cannot), and one pixel
    of disparity is cos t_r / |sin(t_i - t_r)| pixels of height for the widest pair (9.6 for
    ±3°, 2.9 for ±10°)."""
    _, b = tilt_series.coefficients(tilt_deg)
    return float(1.0 / np.max(np.abs(b)))
