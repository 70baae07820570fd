"""The side detector's lighting in the images, and what it says about the relief's sign.

An Everhart-Thornley detector beside the column collects more from facets that face it, so the
image looks lit from the detector's side (Goldstein et al., Scanning Electron Microscopy and
X-Ray Microanalysis, 4th ed., doi:10.1007/978-1-4939-6676-9, ch. 7). Regressed on the heights'
slopes, each view's band-passed brightness has a coefficient per slope component:

- along the tilt axis (rows), the detector's lighting alone;
- across it (columns), the detector's lighting plus the yield law's response to the beam's tilt,
  which is k·sin(tilt) to first order for any law of the incidence angle (secant, Lambert...).

With two or more tilts the columns' coefficients c_i = k sin t_i + a_col separate the two. The
detector's part a = (a_col, a_row) flips with the relief (heights and tilts negated), k does not:
so a tells the sign, but only against a known detector place. Without one it is evidence
("the lighting reads as from the image's bottom if the relief is as given"), never a verdict.

Conventions: images (rows, cols) on the reference grid with the tilt axis along the columns
(rectified), heights in pixels; azimuths counter-clockwise from the column axis as displayed
(90: the image's top), "from the tilt axis" = azimuth - 90.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from fractoscope.stereo.relief_sign import MIN_BLOCKS, ReliefSign, sign_test

# Blocks per image side (fewer where a block would be under _MIN_BLOCK_PX).
_BLOCKS_PER_SIDE = 8
_MIN_BLOCK_PX = 32
# Smoothing of the image and the heights before slopes are taken, px: the matcher's noise is
# largest at the pixel scale.
_SMOOTHING_PX = 3.0
# A block votes only with heights over this share of its pixels, in every view.
_MIN_MEASURED_SHARE = 0.5
# A block votes only where its lighting stands out of its noise by this many sigmas.
_MIN_T = 2.0
# A lighting direction is reported where chance would give so concentrated a set of block
# directions with less than this probability (Rayleigh test).
_DIRECTION_P_VALUE = 1e-3


@dataclass(frozen=True)
class Lighting:
    """The detector's part of the lighting per image block, under the heights as given.

    vectors: (blocks, 2) the slope coefficients (col, row) of the detector's lighting, in units
        of the views' band-passed grey standard deviation per unit slope.
    sigmas: (blocks, 2) their one-sigma noise.
    """

    vectors: np.ndarray
    sigmas: np.ndarray

    def direction(self) -> tuple[float, float, float]:
        """(azimuth from the tilt axis, its one-sigma, Rayleigh p-value): where the lighting comes
        from if the relief is as given, degrees in (-180, 180]; NaN azimuth without blocks."""
        if not len(self.vectors):
            return float("nan"), float("nan"), 1.0
        # A facet facing a detector at azimuth φ brightens with slope (−cos φ, sin φ) (col, row).
        angles = np.arctan2(self.vectors[:, 1], -self.vectors[:, 0])
        mean = np.exp(1j * angles).mean()
        count, length = len(angles), abs(mean)
        p_value = float(np.exp(np.sqrt(1 + 4 * count + 4 * (count**2 - (count * length) ** 2)) - (1 + 2 * count)))
        spread = np.sqrt(max(-2.0 * np.log(max(length, 1e-12)), 0.0)) / np.sqrt(count)
        azimuth = (np.degrees(np.angle(mean)) - 90.0 + 180.0) % 360.0 - 180.0
        return float(azimuth), float(np.degrees(spread)), min(max(p_value, 0.0), 1.0)

    def significant_direction(self) -> tuple[float, float] | None:
        """(azimuth from the tilt axis, sigma) where the blocks' directions agree beyond chance."""
        azimuth, sigma, p_value = self.direction()
        return (azimuth, sigma) if np.isfinite(azimuth) and p_value < _DIRECTION_P_VALUE else None


def block_lighting(views: Sequence[np.ndarray], tilts_deg: Sequence[float], z_px: np.ndarray) -> Lighting:
    """The detector's lighting per block (`Lighting`) of `views` (each (rows, cols) on the
    reference grid, the reference first, NaN where a view has no pixel), seen at `tilts_deg`, of
    heights `z_px` (rows, cols, as the tilts given say, NaN where unknown)."""
    sines = np.sin(np.radians(np.asarray(tilts_deg, np.float64)))
    slopes, usable = _smoothed_slopes(z_px)
    greys = [_band_passed(view) for view in views]
    usable &= np.all([np.isfinite(grey) for grey in greys], axis=0)
    block = max(_MIN_BLOCK_PX, min(z_px.shape) // _BLOCKS_PER_SIDE)
    vectors, sigmas = [], []
    for top in range(0, z_px.shape[0] - block + 1, block):
        for left in range(0, z_px.shape[1] - block + 1, block):
            window = (slice(top, top + block), slice(left, left + block))
            inside = usable[window]
            if inside.mean() < _MIN_MEASURED_SHARE:
                continue
            fits = [
                _slope_fit(grey[window][inside], slopes[0][window][inside], slopes[1][window][inside]) for grey in greys
            ]
            if any(fit is None for fit in fits):
                continue
            vector, sigma = _detector_part(
                np.array([fit[0] for fit in fits]), np.array([fit[1] for fit in fits]), sines
            )
            vectors.append(vector)
            sigmas.append(sigma)
    return Lighting(np.reshape(vectors, (-1, 2)), np.reshape(sigmas, (-1, 2)))


def relief_sign_from_lighting(lighting: Lighting, *, detector_from_tilt_axis_deg: float) -> ReliefSign:
    """Whether the heights `lighting` was measured under, or their mirror image, is the relief a
    detector at `detector_from_tilt_axis_deg` (known, finite) lights: a sign test over the blocks
    whose lighting along the detector's direction stands out of its noise."""
    azimuth = np.radians(90.0 + detector_from_tilt_axis_deg)
    towards = np.array([-np.cos(azimuth), np.sin(azimuth)])
    along = lighting.vectors @ towards
    noise = np.sqrt((lighting.sigmas**2) @ towards**2)
    voting = np.abs(along) > _MIN_T * noise
    agreeing, disagreeing = int(np.sum(along[voting] > 0)), int(np.sum(along[voting] < 0))
    votes = agreeing + disagreeing
    return sign_test(
        agreeing,
        disagreeing,
        cue="lighting",
        too_few=f"too little of the image shows the detector's lighting ({votes} blocks of {MIN_BLOCKS} needed)",
        ambiguous=f"the lighting is ambiguous ({agreeing} of {votes} image blocks agree with the tilts)",
    )


def _smoothed_slopes(z_px: np.ndarray) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """The heights' slopes (along columns, along rows) after smoothing, and where they are known."""
    known = np.isfinite(z_px)
    weight = cv2.GaussianBlur(known.astype(np.float32), (0, 0), _SMOOTHING_PX)
    z = cv2.GaussianBlur(np.where(known, z_px, 0).astype(np.float32), (0, 0), _SMOOTHING_PX)
    z /= np.maximum(weight, np.float32(1e-3))
    slope_rows, slope_cols = np.gradient(z)
    return (slope_cols, slope_rows), weight > 0.9


def _band_passed(view: np.ndarray) -> np.ndarray:
    """The view's brightness between the smoothing and 8 times it, in units of its own standard
    deviation (views differ in contrast), NaN where the view has no pixel."""
    known = np.isfinite(view)
    grey = cv2.GaussianBlur(np.where(known, view, np.nanmean(view)).astype(np.float32), (0, 0), _SMOOTHING_PX)
    grey -= cv2.GaussianBlur(grey, (0, 0), 8 * _SMOOTHING_PX)
    scale = float(np.std(grey[known])) if known.any() else 0.0
    return np.where(known, grey / max(scale, 1e-6), np.nan)


def _slope_fit(grey: np.ndarray, slope_cols: np.ndarray, slope_rows: np.ndarray):
    """Least squares of `grey` on both slopes and a constant: ((c_col, c_row), their sigmas), the
    variance inflated as if one sample per smoothed area were independent; None if degenerate."""
    design = np.column_stack([slope_cols, slope_rows, np.ones(grey.size)])
    solution, residual, rank, _ = np.linalg.lstsq(design, grey, rcond=None)
    if rank < 3 or not residual.size:
        return None
    count = grey.size
    correlated = count / max(count / (2 * _SMOOTHING_PX) ** 2, 1.0)
    variances = residual[0] / (count - 3) * np.diag(np.linalg.inv(design.T @ design))[:2] * correlated
    return solution[:2], np.sqrt(variances)


def _detector_part(coefficients: np.ndarray, sigmas: np.ndarray, sines: np.ndarray):
    """The detector's (col, row) lighting and its sigma from each view's slope coefficients
    (views, 2): rows' coefficients averaged; columns' fitted as k sin(tilt) + a_col where the
    views' tilts differ (else their mean, the yield law's part then not taken out)."""
    weights = np.full(len(sines), 1.0 / len(sines))
    if np.ptp(sines) > 1e-6:
        design = np.column_stack([sines, np.ones_like(sines)])
        weights = np.linalg.pinv(design)[1]  # a_col = weights @ c_col
    a_col = float(weights @ coefficients[:, 0])
    a_row = float(coefficients[:, 1].mean())
    sigma_col = float(np.sqrt(weights**2 @ sigmas[:, 0] ** 2))
    sigma_row = float(np.sqrt((sigmas[:, 1] ** 2).sum()) / len(sines))
    return (a_col, a_row), (sigma_col, sigma_row)
