"""Heights from a tilt series, and the tilt angles themselves, by parallel projection.

A surface point at position x and height z (pixels) appears in view i at u_i = x·cos t_i +
z·sin t_i + o_i, o_i being the view's unknown offset (stage shift, axis position). In terms of
where it appears in the reference view r, u = u_r, its disparity to view i is
d_i = u·a_i + z·b_i + o_i with a_i = cos t_i / cos t_r − 1 and b_i = sin(t_i − t_r) / cos t_r
(for two views this is the general pair formula). With three or more views the tilt differences
are observable: the z terms fix the ratios of the b_i, the u terms (through cos t) their size.
Only differences are: turning every view by one angle turns the (x, z) frame, so the reference
keeps its nominal tilt.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

# Points matched in every view that a tilt fit needs at least (after sampling every 4th pixel).
MIN_CALIBRATION_POINTS = 100


class TooFewPointsError(ValueError):
    """Too few points are matched in every view to estimate the tilts."""


@dataclass(frozen=True)
class TiltEstimate:
    """Estimated tilts (degrees, one per view, the reference's as given), their one-sigma
    uncertainty (degrees, 0 for the reference: the fit's, combined with what the views'
    magnification uncertainties cause), per-view offsets (px, 0 for the reference) and the RMS
    reprojection residual (px)."""

    tilt_deg: np.ndarray
    sigma_deg: np.ndarray
    offsets_px: np.ndarray
    residual_px: float


def coefficients(tilt_deg, *, reference: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(a_i, b_i) per view: disparity d_i = u·a_i + z·b_i + o_i (both 0 for the reference)."""
    angles = np.radians(np.asarray(tilt_deg, np.float64))
    cos_reference = np.cos(angles[reference])
    return np.cos(angles) / cos_reference - 1.0, np.sin(angles - angles[reference]) / cos_reference


def heights_px(
    x_px: np.ndarray, disparities_px: np.ndarray, tilt_deg, *, reference: int = 0, offsets_px=None, sigmas_px=None
) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares heights (px) of points seen at `x_px` in the reference (any shape, from the
    tilt axis) from the disparities of every other view to the reference (views first:
    (N, *shape), the reference's row ignored; NaN = unmatched), and the RMS residual per point
    (px; NaN with fewer than two matched views).

    `sigmas_px` (N of *shape), optional: each disparity's one-sigma uncertainty (the reference's
    never read). Given, each view's equation is weighted by 1/σ², so a view counts by its
    information on the height, b²/σ² (as stereo.geometry.height_sigma_um combines them); a
    disparity whose sigma is not finite and positive is left out. Without, all weigh the same."""
    a, b = coefficients(tilt_deg, reference=reference)
    offsets = np.zeros(len(a)) if offsets_px is None else np.asarray(offsets_px, np.float64)
    others = [view for view in range(len(a)) if view != reference]
    if len(others) == 1 and sigmas_px is None:  # a pair: the one equation solved directly, no residual to speak of
        (view,) = others
        z = (disparities_px[view] - x_px * a[view] - offsets[view]) / b[view]
        return z, np.full(np.shape(x_px), np.nan)
    numerator = np.zeros(np.shape(x_px))
    denominator = np.zeros(np.shape(x_px))
    rests = []
    for view in others:
        rest = disparities_px[view] - x_px * a[view] - offsets[view]
        weight = 1.0 if sigmas_px is None else _weight(sigmas_px[view])
        rest = np.where(np.isfinite(weight), rest, np.nan)
        known = np.isfinite(rest)
        numerator += np.where(known, weight * b[view] * rest, 0.0)
        denominator += np.where(known, weight * b[view] ** 2, 0.0)
        rests.append((b[view], rest))
    with np.errstate(invalid="ignore", divide="ignore"):
        z = np.where(denominator > 0, numerator / denominator, np.nan)
        squares = sum(np.where(np.isfinite(rest), (rest - delta_sin * z) ** 2, 0.0) for delta_sin, rest in rests)
        counts = sum(np.isfinite(rest).astype(int) for _, rest in rests)
        residual = np.where(counts >= 2, np.sqrt(squares / np.maximum(counts, 1)), np.nan)
    return z, residual


def _weight(sigma_px: np.ndarray) -> np.ndarray:
    """1/σ² (1/px²), NaN where the sigma is not finite and positive."""
    sigma = np.asarray(sigma_px, np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(_usable(sigma), 1.0 / sigma**2, np.nan)


def _usable(sigma_px: np.ndarray) -> np.ndarray:
    """Where a disparity's sigma is finite and positive, so that its equation counts."""
    with np.errstate(invalid="ignore"):
        return np.isfinite(sigma_px) & (sigma_px > 0)


def views_used(disparities_px: np.ndarray, *, reference: int = 0, sigmas_px=None) -> np.ndarray:
    """How many views each height rests on, the reference's included, (*shape) uint8: 1 plus the
    other views whose disparity (N, *shape) is known there (and, with `sigmas_px`, its sigma
    finite and positive, as heights_px uses them); 1 means no height."""
    count = np.ones(disparities_px.shape[1:], np.uint8)
    for view in range(len(disparities_px)):
        if view == reference:
            continue
        known = np.isfinite(disparities_px[view])
        if sigmas_px is not None:
            known &= _usable(sigmas_px[view])
        count += known.astype(np.uint8)
    return count


def view_residuals_px(x_px, disparities_px, tilt_deg, z_px, *, reference: int = 0, offsets_px=None) -> np.ndarray:
    """Median absolute deviation of every view's reprojection residual from its median (px,
    (N,): 0 for the reference, NaN for a view with no point matched) given the heights `z_px`,
    shapes as in heights_px. The median is left out: a view's constant offset (a stage that is
    not eucentric) is no inconsistency."""
    a, b = coefficients(tilt_deg, reference=reference)
    offsets = np.zeros(len(a)) if offsets_px is None else np.asarray(offsets_px, np.float64)
    residuals = np.zeros(len(a))
    for view in range(len(a)):
        if view == reference:
            continue
        rest = disparities_px[view] - x_px * a[view] - offsets[view] - z_px * b[view]
        known = np.isfinite(rest)
        residuals[view] = float(np.median(np.abs(rest[known] - np.median(rest[known])))) if known.any() else np.nan
    return residuals


def estimate_tilts(
    x_px: np.ndarray,
    disparities_px: np.ndarray,
    nominal_tilt_deg,
    *,
    reference: int = 0,
    magnification_sigma=None,
    cluster=None,
) -> TiltEstimate:
    """Tilts of every view but the reference that minimize the reprojection residual of points
    matched in all views: x_px (M,) where they appear in the reference, disparities_px (N, M) with
    the reference's row ignored.
    Starts from the nominal tilts. Offsets drop out by centring x and each view's disparities
    (heights are relative), and are recovered afterwards for heights_px.

    `magnification_sigma` (N,): each view's relative magnification uncertainty against the
    reference. A magnification error ε adds ε·x to that view's disparities, which is exactly what
    a change of cos t does, so it moves the tilts: for ±3° views an ε of 1e-4 moves them by
    about 4 %. Its effect enters the sigma next to the fit's own.

    `cluster` (M,) int: a label per point, its block of the reference image. Given, the fit's own
    sigma takes the blocks for the independent samples (`_jackknife_sigma`): matching errors
    correlate over more than a window, and on 256² self-affine series (seeds 1-11) the
    calibrated tilts erred by up to 3.9 of the sigmas that took the points for independent, by
    0.2-2.0 of these (at 512², seeds 1-12: up to 1.6, but 3.9 and 3.4 on two). Without it the points
    are taken for independent."""
    nominal = np.asarray(nominal_tilt_deg, np.float64)
    views = len(nominal)
    if views < 3:
        raise ValueError("tilt angles are observable from three or more views only")
    others = [view for view in range(views) if view != reference]
    known = _matched_in_every_view(disparities_px, others)
    x_mean = float(x_px[known].mean())
    d_mean = disparities_px[:, known].mean(axis=1)
    x = x_px[known] - x_mean
    d = disparities_px[:, known] - d_mean[:, None]

    def residuals_of(disparities, values):
        tilts = _with_others(nominal, others, values)
        z, _ = heights_px(x, disparities, tilts, reference=reference)
        a, b = coefficients(tilts, reference=reference)
        return np.concatenate([disparities[view] - x * a[view] - z * b[view] for view in others])

    fit = least_squares(lambda values: residuals_of(d, values), nominal[others], method="lm")
    tilts = _with_others(nominal, others, fit.x)
    labels = None if cluster is None else np.unique(np.asarray(cluster)[known], return_inverse=True)[1]
    sigma_deg = np.zeros(views)
    sigma_deg[others] = _fit_sigma_deg(fit.jac, fit.fun, heights=x.size, labels=labels)
    if magnification_sigma is not None:
        from_magnification = _magnification_sigma_deg(
            fit.jac, fit.fun, lambda scaled: residuals_of(scaled, fit.x), x, d, magnification_sigma, others
        )
        sigma_deg[others] = np.hypot(sigma_deg[others], from_magnification)
    offsets = d_mean - x_mean * coefficients(tilts, reference=reference)[0]
    offsets[reference] = 0.0
    return TiltEstimate(tilts, sigma_deg, offsets, float(np.sqrt(np.mean(fit.fun**2))))


def _matched_in_every_view(disparities_px: np.ndarray, others: list[int]) -> np.ndarray:
    """Mask (M,) of the points whose disparities (N, M) are finite in every view of `others`;
    TooFewPointsError when fewer than MIN_CALIBRATION_POINTS are."""
    known = np.all(np.isfinite(disparities_px[others]), axis=0)
    if known.sum() < MIN_CALIBRATION_POINTS:
        raise TooFewPointsError(
            f"only {known.sum()} points are matched in every view; at least {MIN_CALIBRATION_POINTS} are needed"
        )
    return known


def _with_others(nominal_deg: np.ndarray, others: list[int], values_deg) -> np.ndarray:
    """The tilts (deg, (N,)): `values_deg` for the views `others`, the nominal one elsewhere."""
    tilts = nominal_deg.copy()
    tilts[others] = values_deg
    return tilts


def _fit_sigma_deg(
    jacobian: np.ndarray, residuals: np.ndarray, *, heights: int, labels: np.ndarray | None
) -> np.ndarray:
    """The tilt fit's own one-sigma uncertainties (deg, (P,)) from its `jacobian` (R, P) and
    `residuals` (R,), R = P·M: taking the points for independent, or given `labels` (M,) int
    0..G-1 (a block per point, the same in every view) by the blocks' jackknife. `heights`: how
    many heights the fit solved inside. inf where the tilts are not determined."""
    try:
        if labels is not None:
            return _jackknife_sigma(jacobian, residuals, np.tile(labels, jacobian.shape[1]))
        # Variable projection: the heights are solved inside, so the Jacobian covers the tilts alone.
        dof = max(residuals.size - jacobian.shape[1] - heights, 1)
        variance = float(residuals @ residuals) / dof
        return np.sqrt(np.clip(np.diag(np.linalg.inv(jacobian.T @ jacobian)) * variance, 0, None))
    except np.linalg.LinAlgError:
        return np.full(jacobian.shape[1], np.inf)


def _magnification_sigma_deg(
    jacobian: np.ndarray, residuals: np.ndarray, residuals_at, x_px, disparities_px, magnification_sigma, others
) -> np.ndarray:
    """One-sigma tilt errors (deg, (len(others),)) that the views' relative magnification
    uncertainties `magnification_sigma` (N,) cause, each view's adding ε·x to its row of
    `disparities_px` (N, M; points at `x_px` (M,), both centred). `residuals_at` gives the fit's
    residuals (R,) at the fitted tilts for other disparities; `jacobian` (R, P) and `residuals`
    are the fit's."""
    # Residuals are linear in the disparities: one Gauss-Newton step gives each view's effect.
    from_magnification = np.zeros(len(others))
    for view in others:
        scaled = disparities_px.copy()
        scaled[view] += magnification_sigma[view] * x_px
        step, *_ = np.linalg.lstsq(jacobian, residuals_at(scaled) - residuals, rcond=None)
        from_magnification += step**2
    return np.sqrt(from_magnification)


def _jackknife_sigma(jacobian: np.ndarray, residuals: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """One-sigma uncertainties of a least-squares fit's parameters by the delete-one-cluster
    jackknife, each deletion one Gauss-Newton step from the fit: δ_g = (JᵀJ - J_gᵀJ_g)⁻¹ J_gᵀ r_g
    over the residuals (R,) labelled g by `labels` (R,) int 0..G-1, covariance (G - 1) / G Σ δ_g δ_gᵀ;
    `jacobian` (R, P). Its leave-one-out weighting keeps the clusters at the edges of the image,
    which carry most of a tilt's information, from shrinking the sigma as the plain cluster
    sandwich does (measured on blocks sharing their errors: 1.65 times too small there, 1.76 for
    the sandwich; taken for independent, 28 times).

    R. M. Bell, D. F. McCaffrey, "Bias reduction in standard errors for linear regression with
    multi-stage samples", Survey Methodology 28 (2002) 169-181."""
    groups, parameters = int(labels.max()) + 1, jacobian.shape[1]
    scores = np.stack(
        [np.bincount(labels, weights=jacobian[:, k] * residuals, minlength=groups) for k in range(parameters)], axis=1
    )
    curvature = np.stack(
        [
            np.bincount(labels, weights=jacobian[:, k] * jacobian[:, m], minlength=groups)
            for k in range(parameters)
            for m in range(parameters)
        ],
        axis=1,
    ).reshape(groups, parameters, parameters)
    left_out = np.linalg.solve((jacobian.T @ jacobian)[None] - curvature, scores[:, :, None])[:, :, 0]
    return np.sqrt(np.diag(left_out.T @ left_out) * (groups - 1) / groups)
