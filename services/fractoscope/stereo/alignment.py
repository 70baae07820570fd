"""Rectification of SEM stereo pairs: tilt axis to vertical, then global shift and rotation removed.

Coordinates are pixels, x along columns and y along rows. After `rotation_to_vertical_axis` the tilt
axis is vertical and parallax runs along x. `estimate_alignment` then measures how the second
image sits against the first from matched SIFT features: rows must agree (up to a rotation, a
magnification and an across shift), while x differences are parallax plus a global shift.

What rows tell of the second image's linear misplacement is two numbers: how the row shift grows
along x (a rotation θ, or a shear of the rows: they differ only in the columns) and along y (a
magnification ε). The columns' own linear part is the surface's mean slope plus any shear of the
columns, which no pair can tell apart: it is left in the heights, as the surface's. A rotation is
taken to move columns by −θ·y and a magnification by ε·x, so either, misjudged, tilts the heights
(a 4000 × 501 frame once got 0.037° that was not there: 2.6 px of ramp). Each is therefore
measured with its one-sigma uncertainty and applied only where it stands out of it by
`SIGNIFICANT_SIGMAS` (`significant`): first from features (`estimate_alignment`), then what is
left densely over the matched pixels (`residual_misplacement`), whose sigma is far smaller.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import cv2
import numpy as np


@dataclass(frozen=True)
class Alignment:
    """How the second image is placed against the first, pixels and degrees.

    A point at (x, y) of the first image (relative to the image centre) lies at
    ``scale * rotate(rotation_deg) @ (x, y) + (shift_parallel_px + parallax, shift_across_px)``
    in the second one. The scale is a magnification difference, measured across the parallax
    (along the tilt axis, where tilting changes nothing). `rotation_deg` and `scale` are what is
    removed: 0 and 1 where the measurement did not stand out of its sigma (`significant`);
    `rotation_sigma_deg` and `scale_sigma` are the one-sigma uncertainties of what is removed
    (NaN where nothing tells it), the value left in counted as error where it was not removed.
    """

    shift_parallel_px: float
    shift_across_px: float
    rotation_deg: float
    residual_vertical_parallax_px: float
    parallax_spread_px: float
    matched_features: int
    scale: float = 1.0
    parallax_direction_deg: float = float("nan")
    scale_sigma: float = float("nan")
    rotation_sigma_deg: float = float("nan")


_NO_ALIGNMENT = Alignment(0.0, 0.0, 0.0, float("nan"), float("nan"), 0)


def rotation_to_vertical_axis(shape: tuple[int, int], tilt_axis_deg: float) -> tuple[np.ndarray, tuple[int, int]]:
    """Affine map (2x3) from an image of `shape` (rows, cols) to a canvas in which the tilt axis
    (at `tilt_axis_deg` from the column axis, counter-clockwise as displayed) is vertical, and the
    canvas shape (rows, cols) holding the whole rotated image."""
    rows, cols = shape
    angle = 90.0 - tilt_axis_deg
    matrix = cv2.getRotationMatrix2D(((cols - 1) / 2.0, (rows - 1) / 2.0), angle, 1.0)
    cos, sin = abs(matrix[0, 0]), abs(matrix[0, 1])
    out_cols = int(np.ceil(rows * sin + cols * cos - 1e-6))
    out_rows = int(np.ceil(rows * cos + cols * sin - 1e-6))
    matrix[0, 2] += (out_cols - cols) / 2.0
    matrix[1, 2] += (out_rows - rows) / 2.0
    return matrix, (out_rows, out_cols)


def apply_affine(image: np.ndarray, matrix: np.ndarray, shape: tuple[int, int], *, inverse: bool = False, fill=0.0):
    """Warps `image` by `matrix` (source to destination, or destination to source with
    `inverse`) onto a canvas of `shape` (rows, cols), bilinear, `fill` outside."""
    flags = cv2.INTER_LINEAR | (cv2.WARP_INVERSE_MAP if inverse else 0)
    return cv2.warpAffine(
        image, matrix, (shape[1], shape[0]), flags=flags, borderMode=cv2.BORDER_CONSTANT, borderValue=fill
    )


# Row spread (standard deviation, full-resolution pixels) the matched features need for a magnification.
_MIN_ROW_SPREAD_PX = 32.0
# Features the parallax's spread needs (else it is NaN, unknown).
_MIN_SPREAD_FEATURES = 50
# Features are located no better than this, px: the scatter of identical images' features (0)
# tells nothing finer.
_LOCATION_FLOOR_PX = 0.05
# A component of the misplacement is removed only where it is this many of its sigmas from none:
# by chance a pure translation then gets one in about 400 pairs (and the dense fit takes it out).
SIGNIFICANT_SIGMAS = 3.0
# Features are found on a copy of about this many pixels, whatever the frame's shape: a copy at
# most 512 px wide left a 4000 × 501 frame 64 px across, whose features could not tell a
# rotation (0.037° ± 0.02° that was not there); at 512² px the 4000 × 501 frame keeps 181 px.
FEATURE_PIXELS = 512 * 512
_MAX_FEATURES = 1000


def estimate_alignment(
    first: np.ndarray, second: np.ndarray, *, max_features: int = _MAX_FEATURES, feature_pixels: int = FEATURE_PIXELS
) -> Alignment:
    """Global placement of `second` against `first` (both (rows, cols), parallax along x), from
    SIFT features found on copies of at most `feature_pixels` pixels; returns zeros when fewer
    than 12 features match. The rotation and the magnification are removed where they stand out
    of their sigmas (`significant`)."""
    points = _matched_feature_points(first, second, max_features=max_features, feature_pixels=feature_pixels)
    if points is None:
        return _NO_ALIGNMENT
    points1, points2 = points
    # Rows: y2 - y1 = sin(θ) x1 + (scale - 1) y1 + shift_across (small rotation and magnification
    # change), fitted with outlier trimming. Features within a few dozen rows cannot tell a
    # magnification (a 48-row strip once got 0.981 ± 0.005 and a 20 µm ramp): it is then left at 1.
    fit_scale = float(np.std(points1[:, 1])) >= _MIN_ROW_SPREAD_PX
    design = np.column_stack(
        [points1[:, 0], points1[:, 1] if fit_scale else np.zeros(len(points1)), np.ones(len(points1))]
    )
    row_fit = _trimmed_row_fit(design, points2[:, 1] - points1[:, 1])
    if row_fit is None:
        return _NO_ALIGNMENT
    (sin_rotation, scale_change, shift_across), residual, inliers = row_fit
    sigma = _row_fit_sigma(design, residual, inliers)
    scale_change, scale_sigma = significant(scale_change, sigma[1] if fit_scale else float("nan"))
    magnification = 1.0 + scale_change
    rotation, rotation_sigma = significant(np.arcsin(np.clip(sin_rotation / magnification, -1.0, 1.0)), sigma[0])
    rotated_x = magnification * (np.cos(rotation) * points1[:, 0] - np.sin(rotation) * points1[:, 1])
    shift_parallel_px, spread_px = _parallax_median_and_spread_px((points2[:, 0] - rotated_x)[inliers])
    return Alignment(
        parallax_direction_deg=_parallax_direction_deg(points1[inliers], points2[inliers]),
        shift_parallel_px=shift_parallel_px,
        shift_across_px=float(shift_across),
        rotation_deg=float(np.degrees(rotation)),
        residual_vertical_parallax_px=float(np.sqrt(np.mean(residual[inliers] ** 2))),
        parallax_spread_px=spread_px,
        matched_features=int(inliers.sum()),
        scale=float(magnification),
        scale_sigma=scale_sigma,
        rotation_sigma_deg=float(np.degrees(rotation_sigma)),
    )


def significant(value: float, sigma: float) -> tuple[float, float]:
    """A measured component of the misplacement as removed, with the one-sigma uncertainty of what
    is removed: itself where it is more than SIGNIFICANT_SIGMAS of its `sigma` from none, else none
    (0.0), the value left in then counted as error (hypot(value, sigma)). NaN sigma: unknown,
    nothing removed."""
    if not abs(value) > SIGNIFICANT_SIGMAS * sigma:  # also where sigma is NaN
        return 0.0, float(np.hypot(value, sigma))
    return float(value), float(sigma)


def _matched_feature_points(
    first: np.ndarray, second: np.ndarray, *, max_features: int, feature_pixels: int
) -> tuple[np.ndarray, np.ndarray] | None:
    """Where the SIFT features that match lie in `first` and in `second` ((K, 2) each: col, row,
    full-resolution px from the first image's centre), found on copies of at most
    `feature_pixels` pixels; None when either image has fewer than 12 features or fewer than 12
    match."""
    scale = min(1.0, float(np.sqrt(feature_pixels / first.size)))
    first8, second8 = (
        _to_uint8(cv2.resize(image, None, fx=scale, fy=scale, interpolation=cv2.INTER_AREA) if scale < 1 else image)
        for image in (first, second)
    )
    sift = cv2.SIFT_create(nfeatures=max_features)
    keys1, desc1 = sift.detectAndCompute(first8, None)
    keys2, desc2 = sift.detectAndCompute(second8, None)
    if desc1 is None or desc2 is None or len(keys1) < 12 or len(keys2) < 12:
        return None
    # Lowe's ratio test: keep matches clearly better than the second-best candidate.
    candidates = cv2.BFMatcher(cv2.NORM_L2).knnMatch(desc1, desc2, k=2)
    matches = [pair[0] for pair in candidates if len(pair) == 2 and pair[0].distance < 0.8 * pair[1].distance]
    if len(matches) < 12:
        return None
    centre = np.array([(first.shape[1] - 1) / 2.0, (first.shape[0] - 1) / 2.0])
    # Keypoints of the scaled copy, back in full-resolution pixel coordinates.
    points1 = (np.array([keys1[m.queryIdx].pt for m in matches]) + 0.5) / scale - 0.5 - centre
    points2 = (np.array([keys2[m.trainIdx].pt for m in matches]) + 0.5) / scale - 0.5 - centre
    return points1, points2


def _trimmed_row_fit(design: np.ndarray, across_px: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """Least-squares coefficients of the features' row differences `across_px` (K,) on `design`
    (K, 3), trimmed of outliers over five rounds, with the residuals (K,, px) and the inliers
    (K,, bool); None when fewer than 8 features stay inliers."""
    inliers = np.abs(across_px - np.median(across_px)) < 3.0
    for _ in range(5):
        if inliers.sum() < 8:
            return None
        coef, *_ = np.linalg.lstsq(design[inliers], across_px[inliers], rcond=None)
        residual = across_px - design @ coef
        residual_scale = max(1.4826 * np.median(np.abs(residual[inliers])), 0.3)
        inliers = np.abs(residual) < 3.0 * residual_scale
    return coef, residual, inliers


def _row_fit_sigma(design: np.ndarray, residual_px: np.ndarray, inliers: np.ndarray) -> np.ndarray:
    """One-sigma uncertainties (3,) of the row fit's coefficients from its residuals over the
    inliers (features err independently: measured, their z-scores on pure translations scatter as
    a unit normal's), at least `_LOCATION_FLOOR_PX` each; NaN for a column of zeros (a coefficient
    not fitted)."""
    dof = max(int(inliers.sum()) - 3, 1)
    normal = design[inliers].T @ design[inliers]
    variance = max(float(residual_px[inliers] @ residual_px[inliers]) / dof, _LOCATION_FLOOR_PX**2)
    covariance = np.linalg.pinv(normal) * variance
    fitted = np.any(design[inliers] != 0.0, axis=0)
    return np.where(fitted, np.sqrt(np.diag(covariance)), np.nan)


def _parallax_median_and_spread_px(parallax_px: np.ndarray) -> tuple[float, float]:
    """Median of the features' parallaxes (K,, px) and how far their 2nd and 98th percentiles
    reach from it (px, NaN with fewer than _MIN_SPREAD_FEATURES), far outliers left out."""
    # Mismatched features can claim absurd parallaxes; far outliers would inflate the search range.
    spread = max(1.4826 * np.median(np.abs(parallax_px - np.median(parallax_px))), 1.0)
    parallax_px = parallax_px[np.abs(parallax_px - np.median(parallax_px)) < 8.0 * spread]
    low, median, high = np.percentile(parallax_px, [2, 50, 98])
    # A few dozen features sample the parallax too thinly to bound it: on a cleavage surface 8
    # features on two facets gave ±2 px where the heights span −16 to +41 px.
    spread_px = float(max(median - low, high - median)) if len(parallax_px) >= _MIN_SPREAD_FEATURES else float("nan")
    return float(median), spread_px


def _parallax_direction_deg(points1: np.ndarray, points2: np.ndarray) -> float:
    """Direction of the parallax between matched features (N, 2: col, row, about the centre),
    degrees from the first image's column axis counter-clockwise as displayed, in (-45, 45): 0
    when the tilt axis is vertical as assumed; NaN with fewer than 8 features or where the
    parallax varies no more than three times the scatter across it.

    The second view is the first turned, scaled and shifted, each point moved by its own height
    along the parallax direction. Across that direction only the similarity moves points, so
    the direction is the one across which a similarity fits the displacements best (scanned in
    steps of 0.25°, robustly by the median of the absolute residuals), turned back by the
    similarity's rotation: the second view's parallax runs along its own, rotated, columns. The
    displacements' principal direction, used before, took a 3° rotation for an axis 22° off."""
    if len(points1) < 8:
        return float("nan")
    x, y = points1.T
    displacement = points2 - points1
    design_x = np.column_stack(
        [x, -y, np.ones_like(x), np.zeros_like(x)]
    )  # (scale cos - 1, scale sin, shift col, shift row)
    design_y = np.column_stack([y, x, np.zeros_like(x), np.ones_like(x)])
    angles = np.radians(np.arange(-44.75, 45.0, 0.25))
    spreads, rotations = [], []
    for angle in angles:
        across = np.array([np.sin(angle), np.cos(angle)])  # the normal of the direction (cos, -sin) in (col, row)
        design = across[0] * design_x + across[1] * design_y
        target = displacement @ across
        coef, *_ = np.linalg.lstsq(design, target, rcond=None)
        spreads.append(np.median(np.abs(target - design @ coef)))
        rotations.append(np.arctan2(coef[1], 1.0 + coef[0]))
    best = int(np.argmin(spreads))
    along = np.array([np.cos(angles[best]), -np.sin(angles[best])])
    design = along[0] * design_x + along[1] * design_y
    target = displacement @ along
    coef, *_ = np.linalg.lstsq(design, target, rcond=None)
    if np.median(np.abs(target - design @ coef)) < 3.0 * max(spreads[best], _LOCATION_FLOOR_PX):
        return float("nan")  # no parallax to speak of (a flat surface): no direction either
    return float(np.degrees(angles[best] + rotations[best]))


def second_to_first_matrix(alignment: Alignment, shape: tuple[int, int]) -> np.ndarray:
    """Affine map (2x3) from the first image's pixel grid to the second's, without parallax: used
    with `apply_affine(..., inverse=True)` to resample the second image onto the first's grid."""
    rows, cols = shape
    centre = np.array([(cols - 1) / 2.0, (rows - 1) / 2.0])
    theta = np.radians(alignment.rotation_deg)
    rotation = alignment.scale * np.array([[np.cos(theta), -np.sin(theta)], [np.sin(theta), np.cos(theta)]])
    offset = centre - rotation @ centre + np.array([alignment.shift_parallel_px, alignment.shift_across_px])
    return np.column_stack([rotation, offset])


def _to_uint8(image: np.ndarray) -> np.ndarray:
    low, high = np.percentile(image, [0.5, 99.5])
    scaled = (image.astype(np.float32) - low) * (255.0 / max(high - low, 1e-6))
    return np.clip(scaled, 0, 255).astype(np.uint8)


# Matched images' residuals correlate beyond a matching window: squares of this side are taken as
# the independent samples of the fits on them (here and in the tilt calibration's).
INDEPENDENT_BLOCK_PX = 64


@dataclass(frozen=True)
class Misplacement:
    """What alignment left of the second image's linear misplacement, measured densely
    (`residual_misplacement`): a magnification error `epsilon` (the second image 1 + ε times
    larger about the centre) and a rotation `rotation_rad` (its rows shifted by θ·x), each with
    its one-sigma uncertainty."""

    epsilon: float
    epsilon_sigma: float
    rotation_rad: float
    rotation_sigma_rad: float


def residual_misplacement(
    first: np.ndarray, second_on_first: np.ndarray, disparity_px: np.ndarray, *, block_px: int = INDEPENDENT_BLOCK_PX
) -> Misplacement | None:
    """Magnification error ε and rotation θ left after alignment, from the second image resampled
    onto the first and moved back by the matched disparity, so only misplacement remains: rows
    then shift by ε·y + θ·x + c, fitted densely by Gauss-Newton (Lucas-Kanade) over every matched
    pixel, with a gain and an offset between the images, trimmed at three robust sigmas. SIFT on
    a reduced copy leaves ~1e-4 of ε, which tilt calibration cannot tolerate, and a 288² overview's
    heights (2 px of parallax) took a tilt of 2.4 % of their range from an ε of 6e-4 that
    strip-wise phase correlation left (it read 1.5e-3 for 1e-3); features on a 4000 × 501 frame
    tell θ to ±0.005°, 0.3 px over its 4000 rows. The sigmas are cluster-robust, `block_px`
    square blocks taken as independent: with 16 px blocks the real pollen series' ±3° and ±6°
    tilt steps disagreed by three of their sigmas, its residuals being correlated beyond a
    matching window. None when it cannot be measured (under half of the pixels matched, or the
    image under four blocks a side).

    B. D. Lucas, T. Kanade, "An iterative image registration technique with an application to
    stereo vision", Proc. IJCAI (1981) 674-679."""
    rows, cols = first.shape
    known = np.isfinite(disparity_px)
    if min(rows, cols) < 4 * block_px or known.mean() < 0.5:
        return None
    fill = np.where(known, disparity_px, float(np.median(disparity_px[known]))).astype(np.float32)
    map_cols = np.arange(cols, dtype=np.float32)[None, :] + fill
    y_px = np.broadcast_to(np.arange(rows, dtype=np.float32)[:, None] - np.float32((rows - 1) / 2), (rows, cols))
    x_px = np.broadcast_to(np.arange(cols, dtype=np.float32)[None, :] - np.float32((cols - 1) / 2), (rows, cols))
    first = first.astype(np.float32)
    second = second_on_first.astype(np.float32)
    # Unmatched pixels, their neighbours (the gradient reaches them) and an 8 px border are left out.
    used = cv2.erode(known.astype(np.uint8), np.ones((5, 5), np.uint8), borderValue=0).astype(bool)
    used[:8], used[-8:], used[:, :8], used[:, -8:] = False, False, False, False
    shift = np.zeros(3)  # ε, θ, c: the second image's rows lie at y + ε·y + θ·x + c
    for _ in range(_MISPLACEMENT_ITERATIONS):
        map_rows = y_px + np.float32((rows - 1) / 2) + (shift[0] * y_px + shift[1] * x_px + shift[2]).astype(np.float32)
        matched = cv2.remap(second, map_cols, map_rows, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
        gradient = cv2.Sobel(0.5 * (matched + first), cv2.CV_32F, 0, 1, ksize=3) / np.float32(8.0)
        # Rows lying at t where v = shift is assumed: matched ≈ gain·first + offset + gradient·(v - t),
        # linear in the five unknowns.
        design = [first, np.ones_like(first), gradient * y_px, gradient * x_px, gradient]
        weights = used
        for _ in range(2):
            coefficients, residual = _weighted_fit(design, matched, weights)
            scale = 1.4826 * float(np.median(np.abs(residual[used])))
            weights = used & (np.abs(residual) < 3.0 * scale)
        shift -= coefficients[2:]
    sigma = _cluster_sigma(design, residual, weights, block_px)
    return Misplacement(float(shift[0]), float(sigma[2]), float(shift[1]), float(sigma[3]))


def with_misplacement(
    placement: Alignment, misplacement: Misplacement | None, shape: tuple[int, int]
) -> tuple[Alignment, np.ndarray]:
    """The placement decided with the dense fit: the scale and rotation that the features' (as
    applied in resampling the second image) and `misplacement` (what the dense fit found left on
    it) add up to, each removed only where it stands out of the dense fit's sigma (`significant`:
    the features' own decision only served the matcher's rows), with the parallax the change
    puts into the matched disparities, (rows, cols) float32 px, ε·x − θ·y about the centre (a
    rotation moves columns by −θ·y, a magnification by ε·x). With no misplacement measured,
    `placement` as it is and no parallax."""
    rows, cols = shape
    if misplacement is None:
        return placement, np.zeros(shape, np.float32)
    scale_change, scale_sigma = significant(
        placement.scale * (1.0 + misplacement.epsilon) - 1.0, misplacement.epsilon_sigma
    )
    rotation, rotation_sigma = significant(
        np.radians(placement.rotation_deg) + misplacement.rotation_rad, misplacement.rotation_sigma_rad
    )
    epsilon = (1.0 + scale_change) / placement.scale - 1.0
    theta = rotation - np.radians(placement.rotation_deg)
    x_px = np.arange(cols, dtype=np.float32) - np.float32((cols - 1) / 2)
    y_px = np.arange(rows, dtype=np.float32)[:, None] - np.float32((rows - 1) / 2)
    parallax_px = np.float32(epsilon) * x_px[None, :] - np.float32(theta) * y_px
    placed = dataclasses.replace(
        placement,
        scale=1.0 + scale_change,
        scale_sigma=scale_sigma,
        rotation_deg=float(np.degrees(rotation)),
        rotation_sigma_deg=float(np.degrees(rotation_sigma)),
    )
    return placed, parallax_px


# Gauss-Newton steps of `residual_misplacement`: the shifts are a small fraction of a pixel, so
# the second step changes ε by ~1e-6 and the third by nothing measurable.
_MISPLACEMENT_ITERATIONS = 3


def _weighted_fit(design: list[np.ndarray], target: np.ndarray, weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Least-squares coefficients of `target` on the `design` images over the `weights` pixels
    (bool), and the residual image, float64 normal equations of (rows, cols) float32 images."""
    columns = [np.where(weights, column, np.float32(0.0)) for column in design]
    normal = np.array([[float(np.sum(a * b, dtype=np.float64)) for b in columns] for a in columns])
    right = np.array([float(np.sum(a * target, dtype=np.float64)) for a in columns])
    coefficients = np.linalg.solve(normal, right)
    residual = target - sum(np.float32(c) * column for c, column in zip(coefficients, design))
    return coefficients, residual


def _cluster_sigma(design: list[np.ndarray], residual: np.ndarray, weights: np.ndarray, block_px: int) -> np.ndarray:
    """One-sigma uncertainties of `_weighted_fit`'s coefficients, cluster-robust: residuals are
    correlated within a matching window, so sums over `block_px` blocks are taken as the
    independent samples (the sandwich estimate)."""
    rows, cols = residual.shape
    blocks_rows, blocks_cols = rows // block_px, cols // block_px
    columns = [
        np.where(weights, column, np.float32(0.0))[: blocks_rows * block_px, : blocks_cols * block_px]
        for column in design
    ]
    scores = np.stack(
        [
            (column * residual[: blocks_rows * block_px, : blocks_cols * block_px])
            .reshape(blocks_rows, block_px, blocks_cols, block_px)
            .sum(axis=(1, 3), dtype=np.float64)
            .ravel()
            for column in columns
        ],
        axis=1,
    )
    bread = np.linalg.inv(np.array([[float(np.sum(a * b, dtype=np.float64)) for b in columns] for a in columns]))
    return np.sqrt(np.diag(bread @ (scores.T @ scores) @ bread))
