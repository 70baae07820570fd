"""Fine relief from the secondary-electron shading: the two views' brightness at one surface
point tells its slope along the tilt direction, which a correlation window averages away. The
slopes are fused with the stereo disparities along each row.

Physics. Secondary-electron yield depends on the beam's incidence angle θ (the secant law
sec^k θ of our renderer; other laws, detectors and edge contrast elsewhere). For a surface
z(x, y) tilted by t about the y axis, cos θ = (cos t + p sin t) / N with p = ∂z/∂x and
N = √(1 + p² + q²); what both views share (material contrast, edges) cancels in the ratio of
their yields, which depends mostly on p. At a left pixel x matched to x + d in the right image,
with s = ∂d/∂x:

    R(x + d) = L(x) a(s) + b(s),   a and b polynomials in s,

the two images' gains and black levels and the law's form and strength folded into the
coefficients. The law is learned from the pair itself, not assumed: fitted by least squares
against the stereo's slopes, both sides averaged over 4 px, its degree (1 to 4) the one that
best predicts the brightness of image blocks it was not fitted on (two folds of a checkerboard).
The model inverted about the stereo's slope (smoothed over 1.5 px) gives each pixel's
photometric slope, with a variance from the images' noise (J. Immerkær, "Fast noise variance
estimation", Comput. Vis. Image Underst. 64 (1996) 300-302, doi:10.1006/cviu.1996.0060) and
from the stereo's disparity sigma (a mislocated sample of a textured image).

How far to trust it. On the held-out blocks the slopes the brightness alone tells (the model
inverted without the stereo's slope) are compared with the stereo's; the share of the stereo
slopes' variance they explain, clipped to [0, 1], weights the photometric slopes' precision, and
under `MIN_WEIGHT` nothing is fused: flat facets (cleavage), pure material contrast or shading
shaped by something other than the slopes leave the stereo's disparities as they are.

Fusion. Each row's disparities minimise
    Σ_j κ (d_j - ď_j)² / σ_j² + Σ_j (d_{j+1} - d_j - s_{j+½})² / v_{j+½},
ď the stereo's disparities, σ their sigma and κ `_STEREO_WEIGHT`, s the photometric slopes (averaged over σ = 1.4 px,
weighted by precision) and v their variance: the stereo keeps the long wavelengths, the slopes
add the short ones. A tridiagonal system per row.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numba
import numpy as np
from numpy.polynomial import chebyshev
from scipy.linalg import solve_banded

from fractoscope.stereo import correlation

# Below this weight the slopes are not fused at all.
MIN_WEIGHT = 0.05
# The shading law's highest degree in the slope that the cross-validation may choose, and its blocks.
_MAX_DEGREE = 4
_BLOCK_PX = 64
_NEWTON_STEPS = 6
_AGREEMENT_SIGMA_PX = 4.0
# The stereo slope the model is fitted against and inverted about: disparities smoothed over 1.5 px.
_STEREO_SLOPE_SIGMA_PX = 1.5
# Photometric slopes averaged over 1.4 px (precision-weighted) before the fusion.
_SLOPE_SIGMA_PX = 1.4
# Weight of the stereo term over its sigma's: the stereo's errors are correlated over its data
# window, the slopes' are not. RMS error, % of the range, on the synthetic dimples (±5°, 0/10°),
# self-affine surface (±5°) and overview (±5°, 0/10°): weight 3 and slopes averaged over 1.4 px
# 1.61 / 1.64 / 0.53 / 4.32 / 3.89 %; weight 1.5 1.66 / 1.69 / 0.52 / 4.24 / 3.79 %; slopes
# averaged over 1 or 2 px 1.67 / 1.73 / 0.55 / 4.54 / 4.15 and 1.71 / 1.76 / 0.57 / 4.22 / 3.77 %
# (the stereo alone: 2.95 / 3.03 / 0.94 / 6.07 / 5.94 %). A second pass linearized about the
# fused slopes measured worse (dimples 1.78 / 1.89 % against 1.67 / 1.69 % in one pass, before
# the fit was averaged).
# With the magnification measured densely (`alignment.residual_misplacement`) the overview
# measures 3.60 / 3.42 % at weight 3, 3.43 / 3.23 % at weight 1 (dimples then 1.73 / 1.76 %) and
# 3.85 / 3.72 % at 6. Matching again, the left image shaded as the fitted model predicts the right
# view sees it, and fusing anew measured worse (overview 512²: stereo 5.55 % against 5.37 %,
# fused 3.32 % against 3.30 %): its error is the images' noise (3.30 % with 2 % noise, 2.20 % with
# 1 %, 1.43 % without), not the shading.
_STEREO_WEIGHT = 3.0
# The model's fit uses one in this many of the matched pixels, less 8 px of border, and at most
# about `_MAX_FIT_SAMPLES` of them (fitting four laws twice each on more only costs time).
_FIT_STRIDE = 3
_MAX_FIT_SAMPLES = 50_000
# The fit's averaging of brightness and stereo slopes alike.
_FIT_SIGMA_PX = 4.0
_FIT_BORDER_PX = 8
_ROWS_PER_SOLVE = 256
# The fused disparities' sigma is the stereo's times this times the ratio of the posterior's
# standard deviation to the stereo term's alone (at most 1): the model takes the slopes' errors
# for independent, which their averaging and the shared fit make them not. Measured, the share
# of height errors within one and three sigmas: ratio alone 27-38 % and 69-84 %; times 2 50-67 %
# and 95-99 %; times 2.5 60-63 % (self-affine), 76-77 % (dimples, overview) and 98.6-99.9 %.
_POSTERIOR_SCALE = 2.5
# The fused sigma is never under half the stereo's: on renderers the model was not fitted on the
# fusion claimed up to 0.41 of the stereo's error where it gave 0.8-0.96 of it (dimples, secant
# k 1.6 and Lambert laws), and nowhere gave less than 0.52 (measured on 640² pairs at 1-4 % noise).
_MIN_SIGMA_RATIO = 0.5


@dataclass(frozen=True)
class Fusion:
    """disparity_px: (rows, cols) float32, the fused disparities, NaN where the stereo's were.
    sigma_px: (rows, cols) float32, their one-sigma uncertainty: the stereo's, times 2.5 times the
    ratio of the fused posterior's standard deviation to the stereo term's alone, from half the
    stereo's to all of it (`_POSTERIOR_SCALE`, `_MIN_SIGMA_RATIO`).
    agreement: correlation of photometric and stereo slopes over 4 px (NaN: too little matched).
    used: whether the slopes were fused (weight at least MIN_WEIGHT).
    explained: the shading model's cross-validated explained share (`ShadingModel.explained`).
    weight: the factor on the photometric slopes' precision, 0 to 1 (0: the stereo alone)."""

    disparity_px: np.ndarray
    sigma_px: np.ndarray
    agreement: float
    used: bool
    explained: float = float("nan")
    weight: float = 0.0


def fused_disparity(
    left: np.ndarray, right: np.ndarray, disparity_px: np.ndarray, sigma_px: np.ndarray, *, noise_grey: float
) -> Fusion:
    """The stereo `disparity_px` ((rows, cols), NaN unknown, sigma `sigma_px`) of `left` against
    `right` ((rows, cols) grey images as taken, right placed on left's grid), with the
    photometric slopes fused in, weighted by how well the pair's learned shading model explains
    the stereo's slopes (see the module docstring).
    `noise_grey`: the standard deviation of both images' noise, grey levels
    (`noise_sigma` of each, combined in quadrature)."""
    valid = np.isfinite(disparity_px)
    unchanged = Fusion(disparity_px, sigma_px, float("nan"), False)
    if valid.sum() < 1000:
        return unchanged
    filled = _filled_along_rows(disparity_px.astype(np.float32), valid)
    left = left.astype(np.float32, copy=False)
    warped = correlation.warp_along_rows(right.astype(np.float32, copy=False), filled)
    stereo_slope = np.gradient(cv2.GaussianBlur(filled, (0, 0), _STEREO_SLOPE_SIGMA_PX), axis=1)
    model = _fitted_model(left, warped, stereo_slope, valid)
    if model is None:
        return unchanged
    agreement = _agreement(_told_slope(left, warped, model), np.gradient(filled, axis=1), valid)
    weight = float(np.clip(model.explained, 0.0, 1.0))
    if not weight >= MIN_WEIGHT:
        return Fusion(disparity_px, sigma_px, agreement, False, model.explained, 0.0)
    stereo_sigma_px = np.nan_to_num(sigma_px, nan=1.0)
    slope, precision = _slopes(left, warped, stereo_slope, model, valid, stereo_sigma_px, noise_grey)
    del warped, stereo_slope
    slope, precision = _averaged(slope, precision * np.float32(weight), _SLOPE_SIGMA_PX)
    stereo_precision = np.where(valid, _STEREO_WEIGHT / np.maximum(stereo_sigma_px, 1e-3) ** 2, 0.0)
    fused, variance_ratio = np.empty_like(filled), np.empty_like(filled)
    for top in range(0, filled.shape[0], _ROWS_PER_SOLVE):
        rows = slice(top, top + _ROWS_PER_SOLVE)
        fused[rows], variance_ratio[rows] = _solved_rows(
            filled[rows], stereo_precision[rows], slope[rows], precision[rows]
        )
    # Rounding can leave a ratio out of (0, 1] where a row's pixels are barely tied (canvas corners).
    variance_ratio = np.where((variance_ratio > 0) & (variance_ratio <= 1), variance_ratio, np.float32(1.0))
    sigma_ratio = np.clip(_POSTERIOR_SCALE * np.sqrt(variance_ratio), np.float32(_MIN_SIGMA_RATIO), np.float32(1.0))
    return Fusion(
        np.where(valid, fused, np.float32(np.nan)), sigma_px * sigma_ratio, agreement, True, model.explained, weight
    )


def _slopes(left, warped, stereo_slope, model, valid, stereo_sigma_px, noise_grey):
    """Each pixel's photometric slope, the model inverted about the stereo's slope, and its
    precision (1 / variance, 0 where unknown): (rows, cols) float32 each. `stereo_sigma_px` has
    no NaN (1 px where the stereo has none)."""
    predicted, derivative = model.predicted(left, stereo_slope)
    residual = warped - predicted
    del predicted
    usable = valid & (np.abs(derivative) > 1e-3)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        slope = np.where(usable, stereo_slope + residual / derivative, np.float32(0.0))
        del residual
        variance = np.gradient(warped, axis=1) ** 2 * stereo_sigma_px**2 + np.float32(noise_grey**2)
        precision = np.where(usable, derivative**2 / variance, np.float32(0.0))
    return slope.astype(np.float32, copy=False), precision.astype(np.float32, copy=False)


def noise_sigma(image: np.ndarray) -> float:
    """Standard deviation of a (rows, cols) grey image's pixel noise, grey levels, by Immerkær's
    Laplacian-difference mask (texture makes it an overestimate, which only weights the
    photometric slopes less)."""
    mask = np.array([[1, -2, 1], [-2, 4, -2], [1, -2, 1]], np.float32)
    response = cv2.filter2D(image.astype(np.float32), -1, mask)[1:-1, 1:-1]
    return float(np.sqrt(np.pi / 2.0) * np.mean(np.abs(response)) / 6.0)


def _filled_along_rows(disparity_px: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Unknown disparities interpolated linearly along their row between the nearest known ones
    (held constant beyond them; 0 in rows without any)."""
    rows, cols = disparity_px.shape
    columns = np.broadcast_to(np.arange(cols, dtype=np.int32), (rows, cols))
    before, after = correlation.nearest_known_along_rows(valid)
    known = np.where(valid, disparity_px, 0.0)
    at_before = np.take_along_axis(known, np.clip(before, 0, cols - 1), axis=1)
    at_after = np.take_along_axis(known, np.clip(after, 0, cols - 1), axis=1)
    span = np.maximum(after - before, 1)
    between = at_before + (at_after - at_before) * ((columns - before) / span).astype(np.float32)
    filled = np.where(before < 0, at_after, np.where(after >= cols, at_before, between))
    return np.where(valid, disparity_px, np.where((before < 0) & (after >= cols), 0.0, filled)).astype(np.float32)


@dataclass(frozen=True)
class ShadingModel:
    """R = L a(u) + b(u), u = s / slope_scale (the fitted range is ±1), a and b Chebyshev series of
    `degree` (coefficients (2, degree + 1): a's, then b's); `explained`: the cross-validated share
    of the stereo's slopes' variance that the slopes the brightness tells through the model
    explain (1 - mean squared difference / variance, both averaged over `_FIT_SIGMA_PX`)."""

    coefficients: np.ndarray
    slope_scale: float
    explained: float

    def predicted(self, left, slope):
        """The right view's brightness (rows, cols) float32 at `left`'s brightness and `slope`,
        and its derivative in the slope; continued linearly beyond the fitted range (|u| > 1)."""
        u = slope / np.float32(self.slope_scale)
        within = np.clip(u, -1.0, 1.0)
        a, b = self.coefficients.astype(np.float32)
        value = left * chebyshev.chebval(within, a) + chebyshev.chebval(within, b)
        derivative = left * chebyshev.chebval(within, chebyshev.chebder(a)) + chebyshev.chebval(
            within, chebyshev.chebder(b)
        )
        return value + derivative * (u - within), derivative / np.float32(self.slope_scale)


def _fitted_model(left, warped, stereo_slope, valid) -> ShadingModel | None:
    """The shading model of the pair (see `_fit_samples` for the data): of laws of degree 1 to
    `_MAX_DEGREE`, the one that best predicts the right view's brightness on image blocks it was
    not fitted on (two folds of a checkerboard of `_BLOCK_PX` blocks), refitted on all blocks,
    with the share of the stereo slopes' variance that it explains there. None where too little
    is matched."""
    samples = _fit_samples(left, warped, stereo_slope, valid)
    if samples is None:
        return None
    brightness, slope, target, fold = samples
    slope_scale = float(np.percentile(np.abs(slope), 99)) + 1e-6
    u = np.clip(slope / slope_scale, -1.0, 1.0)
    explained, misfit = {}, {}
    for degree in range(1, _MAX_DEGREE + 1):
        design = _design(brightness, u, degree)
        errors, residuals = [], []
        for test in (0, 1):
            coefficients = _robust_lstsq(design[fold != test], target[fold != test])
            residuals.append(target[fold == test] - design[fold == test] @ coefficients)
            told = _inverted(coefficients.reshape(2, degree + 1), brightness[fold == test], target[fold == test])
            errors.append(told - u[fold == test])
        explained[degree] = 1.0 - float(np.mean(np.concatenate(errors) ** 2) / np.var(u))
        misfit[degree] = float(np.mean(np.concatenate(residuals) ** 2))
    degree = min(misfit, key=misfit.get)
    coefficients = _robust_lstsq(_design(brightness, u, degree), target)
    return ShadingModel(coefficients.reshape(2, degree + 1), slope_scale, explained[degree])


def _inverted(coefficients, brightness, target):
    """The scaled slopes u (within ±1) at which the law of `coefficients` (2, degree + 1) takes
    each left `brightness` to its right `target`: Newton's method from a flat surface."""
    a, b = coefficients
    slope_a, slope_b = chebyshev.chebder(a), chebyshev.chebder(b)
    u = np.zeros_like(brightness)
    for _ in range(_NEWTON_STEPS):
        value = brightness * chebyshev.chebval(u, a) + chebyshev.chebval(u, b) - target
        derivative = brightness * chebyshev.chebval(u, slope_a) + chebyshev.chebval(u, slope_b)
        with np.errstate(divide="ignore", invalid="ignore"):
            u = np.clip(np.nan_to_num(u - value / derivative), -1.0, 1.0)
    return u


def _fit_samples(left, warped, stereo_slope, valid):
    """One in `_FIT_STRIDE` (or more, `_MAX_FIT_SAMPLES`) matched pixels away from the border: the left brightness, the
    stereo's slope and the right brightness there, each averaged over `_FIT_SIGMA_PX` (the
    stereo's slopes lack the fine relief that the brightness has, and a fit at full resolution
    would take that lack for a weaker shading: on a surface of 12 px ripples, slopes told 13 %
    too small), and each sample's fold (0 or 1, a checkerboard of `_BLOCK_PX` blocks); None
    where fewer than 100 samples fall in either fold."""
    total = np.maximum(_gaussian(valid.astype(np.float32), _FIT_SIGMA_PX), 1e-6)

    def averaged(values):
        return (_gaussian(np.where(valid, values, 0.0).astype(np.float32), _FIT_SIGMA_PX) / total).ravel()

    inner = valid & (total > 0.9)
    inner[:_FIT_BORDER_PX] = inner[-_FIT_BORDER_PX:] = False
    inner[:, :_FIT_BORDER_PX] = inner[:, -_FIT_BORDER_PX:] = False
    picked = np.flatnonzero(inner.ravel())
    picked = picked[:: max(_FIT_STRIDE, picked.size // _MAX_FIT_SAMPLES)]
    rows, cols = np.divmod(picked, valid.shape[1])
    fold = (rows // _BLOCK_PX + cols // _BLOCK_PX) % 2
    if min(np.sum(fold == 0), np.sum(fold == 1)) < 100:
        return None
    values = [averaged(field)[picked].astype(np.float64) for field in (left, stereo_slope, warped)]
    return (*values, fold)


def _design(brightness, u, degree):
    """Columns L T_k(u) and T_k(u), k = 0 .. degree, of the least-squares fit."""
    powers = chebyshev.chebvander(u, degree)
    return np.hstack([brightness[:, None] * powers, powers])


def _robust_lstsq(design, target):
    """Least squares (by the normal equations: a few columns, many rows), refitted without the
    samples more than three robust sigmas off."""

    def solved(rows):
        return np.linalg.lstsq(design[rows].T @ design[rows], design[rows].T @ target[rows], rcond=None)[0]

    coefficients = solved(slice(None))
    residual = np.abs(target - design @ coefficients)
    return solved(residual <= 3.0 * 1.4826 * np.median(residual) + 1e-12)


def _told_slope(left, warped, model: ShadingModel) -> np.ndarray:
    """The slope the brightness alone tells, the model linearized about a flat surface, (rows,
    cols) float32: independent of the stereo's slope, unlike the fused slopes, which are the
    stereo's plus a correction."""
    flat, derivative = model.predicted(left, np.zeros_like(left))
    with np.errstate(divide="ignore", invalid="ignore"):
        told = (warped - flat) / derivative
    return np.where(np.isfinite(told), told, 0.0).astype(np.float32)


def _gaussian(values, sigma_px, *, squared=False):
    """(rows, cols) float32 `values` convolved with a Gaussian of `sigma_px` (its square with
    `squared`, for the variance of a weighted average), 3 sigma each side."""
    kernel = cv2.getGaussianKernel(int(6 * sigma_px) | 1, sigma_px)
    if squared:
        kernel = kernel**2
    return cv2.sepFilter2D(values, -1, kernel, kernel)


def _averaged(values, weights, sigma_px):
    """Weighted Gaussian average of `values` and its precision (independent values of variance
    1 / weight), 0 where no weight is near."""
    total = _gaussian(weights, sigma_px)
    mean = _gaussian(values * weights, sigma_px) / np.maximum(total, 1e-12)
    square_total = _gaussian(weights, sigma_px, squared=True)
    with np.errstate(divide="ignore"):
        precision = np.where(total > 1e-9, total**2 / np.maximum(square_total, 1e-30), 0.0)
    return mean.astype(np.float32), precision.astype(np.float32)


def _agreement(photometric, stereo, usable) -> float:
    """Correlation of the two slope fields averaged over `_AGREEMENT_SIGMA_PX`, where most of
    the average is usable."""
    weights = usable.astype(np.float32)
    total = _gaussian(weights, _AGREEMENT_SIGMA_PX)
    covered = usable & (total > 0.5)
    if covered.sum() < 100:
        return float("nan")
    photometric_mean, stereo_mean = (
        _gaussian(np.where(usable, field, 0.0).astype(np.float32), _AGREEMENT_SIGMA_PX)[covered] / total[covered]
        for field in (photometric, stereo)
    )
    return float(np.corrcoef(photometric_mean, stereo_mean)[0, 1])


def _solved_rows(stereo_px, stereo_precision, slope, slope_precision) -> tuple[np.ndarray, np.ndarray]:
    """Each row's minimiser of Σ λ (d - ď)² + Σ w (d_{j+1} - d_j - s)², λ = `stereo_precision`
    (a millionth of its mean where 0), s and w the slopes and precisions averaged over
    neighbouring pixels, and each pixel's posterior variance over the stereo term's alone
    (λ times the inverse's diagonal, 0 to 1); (rows, cols) float32 each."""
    rows, cols = stereo_px.shape
    floor = 1e-6 * max(float(stereo_precision.mean()), 1e-12)
    data = np.maximum(stereo_precision, floor).astype(np.float64)
    pair_slope = 0.5 * (slope[:, 1:] + slope[:, :-1]).astype(np.float64)
    with np.errstate(divide="ignore"):
        pair_weight = np.where(
            (slope_precision[:, 1:] > 0) & (slope_precision[:, :-1] > 0),
            2.0 / (1.0 / slope_precision[:, 1:] + 1.0 / slope_precision[:, :-1]),
            0.0,
        )
    # Weight and slope of the link to the right of each pixel (0 for the last column).
    weight_right = np.zeros((rows, cols))
    weight_right[:, :-1] = pair_weight
    slope_right = np.zeros((rows, cols))
    slope_right[:, :-1] = pair_slope * pair_weight
    weight_left = np.zeros((rows, cols))
    weight_left[:, 1:] = pair_weight
    slope_left = np.zeros((rows, cols))
    slope_left[:, 1:] = pair_slope * pair_weight
    diagonal = data + weight_left + weight_right
    banded = np.zeros((3, rows * cols))
    banded[1] = diagonal.ravel()
    coupling = -weight_right.ravel()  # pixel i with i + 1: 0 across the end of a row
    banded[0, 1:] = coupling[:-1]
    banded[2, :-1] = coupling[:-1]
    rhs = data * stereo_px - slope_right + slope_left
    fused = solve_banded((1, 1), banded, rhs.ravel(), check_finite=False).reshape(rows, cols).astype(np.float32)
    return fused, (data * _inverse_diagonal(diagonal, pair_weight)).astype(np.float32)


@numba.njit(nogil=True, cache=True)
def _inverse_diagonal(diagonal, coupling):  # pragma: no cover
    """The diagonal of the inverse of each row's symmetric tridiagonal matrix, given its
    diagonal (rows, cols) and the negated off-diagonal `coupling` (rows, cols - 1): from the
    forward and backward pivots d and e, 1 / (d + e - diagonal)."""
    rows, cols = diagonal.shape
    out = np.empty((rows, cols))
    forward = np.empty(cols)
    for i in range(rows):
        forward[0] = diagonal[i, 0]
        for j in range(1, cols):
            forward[j] = diagonal[i, j] - coupling[i, j - 1] ** 2 / forward[j - 1]
        backward = diagonal[i, cols - 1]
        out[i, cols - 1] = 1.0 / forward[cols - 1]
        for j in range(cols - 2, -1, -1):
            backward = diagonal[i, j] - coupling[i, j] ** 2 / backward
            out[i, j] = 1.0 / (forward[j] + backward - diagonal[i, j])
    return out
