"""Form removal (the F-operator of ISO 25178-3): a plane, a polynomial of total degree 2-6, a sphere or
a cylinder fitted by robust least squares and subtracted from a height map.

Heights are (rows, cols) float arrays in µm on a square grid of ``pixel_size_um``; NaN marks unknown
points, which are left out of the fit and stay NaN in the residual. Lateral coordinates are
x = col * pixel_size_um, y = row * pixel_size_um. The residual is the vertical distance from the
fitted form (what a profilometer reports), so that positive features stay positive.

Robustness: iteratively reweighted least squares, first with Huber weights (k = 1.345) to get away
from a least-squares start that outliers may have pulled, then with Tukey's biweight (c = 4.685),
which gives gross outliers zero weight; the scale is 1.4826 x the median absolute residual.
Holland & Welsch (1977), doi:10.1080/03610927708827533.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.polynomial import legendre
from scipy import optimize

FORMS = ("plane", "poly2", "poly3", "poly4", "poly5", "poly6", "sphere", "cylinder")
_HUBER_K = 1.345
_TUKEY_C = 4.685
_HUBER_ITERATIONS = 3
_TUKEY_ITERATIONS = 8


@dataclass(frozen=True)
class FormFit:
    """A fitted form and what is left when it is removed.

    residual_um: (rows, cols) heights minus the form, µm (NaN where the input was NaN or where the
        form is undefined, e.g. outside a sphere's footprint).
    form_um: (rows, cols) the fitted form's height at every pixel, µm.
    form: one of FORMS.
    parameters: the form's geometry: polynomial coefficients (Legendre basis over the normalised
        field) or ``radius_um`` and centre / axis for a sphere or cylinder, all µm and degrees.
    fit_points: how many points entered the fit (a regular subsample once there are more than
        ``max_fit_points``).
    inlier_fraction: share of fitted points with non-zero Tukey weight at the end.
    """

    residual_um: np.ndarray
    form_um: np.ndarray
    form: str
    parameters: dict[str, float | int | bool | list[float]] = field(default_factory=dict)
    fit_points: int = 0
    inlier_fraction: float = 1.0


def remove_form(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    form: str = "plane",
    region: np.ndarray | None = None,
    robust: bool = True,
    max_fit_points: int = 262_144,
) -> FormFit:
    """Fit ``form`` to the finite heights (inside ``region`` if given, a (rows, cols) bool mask: levelling
    on a reference area such as the substrate) and subtract it everywhere.

    ``max_fit_points``: fits use a regular grid subsample of at most this many points (a form has at
    most 28 coefficients; a quarter of a million points pins them down and keeps 4096² maps fast).
    """
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 3:
        raise ValueError("z_um must be a (rows, cols) array with at least 3 rows and columns")
    if not pixel_size_um > 0:
        raise ValueError("pixel_size_um must be positive")
    if form not in FORMS:
        raise ValueError(f"form must be one of {', '.join(FORMS)}, not {form!r}")
    if max_fit_points < 16:
        raise ValueError("max_fit_points must be at least 16")
    usable = np.isfinite(z)
    if region is not None:
        region = np.asarray(region, dtype=bool)
        if region.shape != z.shape:
            raise ValueError(f"region has shape {region.shape}, z_um has {z.shape}")
        usable &= region
    rows, cols = _fit_sample(usable, max_fit_points)
    needed = {"plane": 3, "sphere": 4, "cylinder": 5}.get(form) or _poly_terms(int(form[4:]))
    if rows.size < 2 * needed:
        raise ValueError(f"region: {rows.size} usable points are too few to fit a {form}")
    if form == "plane" or form.startswith("poly"):
        degree = 1 if form == "plane" else int(form[4:])
        return _remove_polynomial(z, rows, cols, degree, form, robust)
    x_um, y_um = cols * pixel_size_um, rows * pixel_size_um
    points = np.column_stack([x_um, y_um, z[rows, cols]])
    if form == "sphere":
        return _remove_sphere(z, points, pixel_size_um, robust)
    return _remove_cylinder(z, points, pixel_size_um, robust)


def _fit_sample(usable: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """(rows, cols) of the usable pixels on a regular grid with at most max_points of them."""
    count = int(usable.sum())
    stride = max(1, int(np.ceil(np.sqrt(count / max_points))))
    sub = usable[::stride, ::stride]
    rows, cols = np.nonzero(sub)
    return rows * stride, cols * stride


def _poly_terms(degree: int) -> int:
    return (degree + 1) * (degree + 2) // 2


def _normalised(index: np.ndarray, length: int) -> np.ndarray:
    """Pixel index -> [-1, 1] over the field, where Legendre polynomials are well conditioned."""
    return 2.0 * index / max(length - 1, 1) - 1.0


def _robust_weights(residual: np.ndarray, iteration: int) -> np.ndarray:
    scale = 1.4826 * np.median(np.abs(residual - np.median(residual)))
    if scale <= 0:
        return np.ones_like(residual)
    u = residual / scale
    if iteration < _HUBER_ITERATIONS:
        return np.minimum(1.0, _HUBER_K / np.maximum(np.abs(u), 1e-12))
    return np.where(np.abs(u) < _TUKEY_C, (1.0 - (u / _TUKEY_C) ** 2) ** 2, 0.0)


def _irls(solve, residual_of, start, robust: bool) -> tuple[np.ndarray, np.ndarray]:
    """Iteratively reweighted least squares: ``solve(weights, previous)`` returns the model parameters
    fitted with those weights (None: unweighted), ``residual_of(params)`` the residuals at the fit
    points. Returns the parameters and the final weights."""
    params = solve(None, start)
    weights = np.ones_like(residual_of(params))
    if not robust:
        return params, weights
    for iteration in range(_HUBER_ITERATIONS + _TUKEY_ITERATIONS):
        new_weights = _robust_weights(residual_of(params), iteration)
        converged = iteration > _HUBER_ITERATIONS and np.max(np.abs(new_weights - weights)) < 1e-3
        weights = new_weights
        if converged:
            break
        params = solve(weights, params)
    return params, weights


def _remove_polynomial(z: np.ndarray, rows: np.ndarray, cols: np.ndarray, degree: int, form: str, robust: bool) -> FormFit:
    """Total-degree polynomial sum c_ij P_i(x) P_j(y), i + j <= degree, in Legendre polynomials."""
    n_rows, n_cols = z.shape
    terms = [(i, j) for i in range(degree + 1) for j in range(degree + 1 - i)]
    vx = legendre.legvander(_normalised(cols, n_cols), degree)
    vy = legendre.legvander(_normalised(rows, n_rows), degree)
    design = np.column_stack([vx[:, i] * vy[:, j] for i, j in terms])
    values = z[rows, cols]

    def solve(weights, _previous):
        # Normal equations: the Legendre basis on [-1, 1] keeps them well conditioned, and a 28 x 28
        # system is far cheaper than a QR of the (points x 28) design matrix at every iteration.
        weighted = design if weights is None else design * weights[:, None]
        return np.linalg.solve(weighted.T @ design, weighted.T @ values)

    coefficients, weights = _irls(solve, lambda c: values - design @ c, None, robust)
    grid = np.zeros((degree + 1, degree + 1))
    for (i, j), c in zip(terms, coefficients):
        grid[j, i] = c
    # Separable evaluation: form = Vy @ C @ Vx^T, a few small matrix products instead of a full design matrix.
    full_vy = legendre.legvander(_normalised(np.arange(n_rows), n_rows), degree)
    full_vx = legendre.legvander(_normalised(np.arange(n_cols), n_cols), degree)
    form_um = full_vy @ grid @ full_vx.T
    return FormFit(
        residual_um=z - form_um,
        form_um=form_um,
        form=form,
        parameters={"legendre_coefficients": coefficients.tolist(), "degree": degree},
        fit_points=int(values.size),
        inlier_fraction=float(np.mean(weights > 0)),
    )


def _weighted_least_squares(residuals):
    """An IRLS ``solve`` for a nonlinear model: Levenberg-Marquardt on the weighted residuals."""

    def solve(weights, start):
        root = None if weights is None else np.sqrt(weights)
        fun = residuals if root is None else (lambda params: root * residuals(params))
        return optimize.least_squares(fun, start, method="lm", x_scale="jac").x

    return solve


def _remove_sphere(z: np.ndarray, points: np.ndarray, pixel_size_um: float, robust: bool) -> FormFit:
    """Sphere by orthogonal distance |p - c| - R, started from the algebraic (linear) fit
    x² + y² + z² + D x + E y + F z + G = 0."""
    shift = points.mean(axis=0)
    p = points - shift
    algebraic = np.column_stack([p, np.ones(len(p))])
    d, e, f, g = np.linalg.lstsq(algebraic, -(p**2).sum(axis=1), rcond=None)[0]
    centre0 = -0.5 * np.array([d, e, f])
    radius0 = np.sqrt(max(centre0 @ centre0 - g, 1e-12))
    start = np.concatenate([centre0, [radius0]])

    def residuals(params):
        return np.linalg.norm(p - params[:3], axis=1) - params[3]

    params, weights = _irls(_weighted_least_squares(residuals), residuals, start, robust)
    centre = params[:3] + shift
    radius = abs(params[3])
    # The measured cap is the upper half of the sphere if the data lies above its centre (a dome).
    branch = 1.0 if np.median(points[:, 2]) >= centre[2] else -1.0
    n_rows, n_cols = z.shape
    gx = np.arange(n_cols) * pixel_size_um - centre[0]
    gy = np.arange(n_rows) * pixel_size_um - centre[1]
    under = radius**2 - gy[:, None] ** 2 - gx[None, :] ** 2
    with np.errstate(invalid="ignore"):
        form_um = centre[2] + branch * np.sqrt(under)
    return FormFit(
        residual_um=z - form_um,
        form_um=form_um,
        form="sphere",
        parameters={"radius_um": float(radius), "centre_um": centre.tolist(), "convex": bool(branch > 0)},
        fit_points=len(points),
        inlier_fraction=float(np.mean(weights > 0)),
    )


def _axis_direction(azimuth: float, elevation: float) -> np.ndarray:
    return np.array([np.cos(azimuth) * np.cos(elevation), np.sin(azimuth) * np.cos(elevation), np.sin(elevation)])


def _remove_cylinder(z: np.ndarray, points: np.ndarray, pixel_size_um: float, robust: bool) -> FormFit:
    """Cylinder with its axis near the image plane: axis azimuth and elevation, the axis point's offset
    across the axis from the field centre and its height, and the radius, by orthogonal distance
    |(p - a) x u| - R. Started from a quadratic fit: the axis runs along its direction of least
    curvature and the radius is the inverse of the largest."""
    shift = points.mean(axis=0)
    p = points - shift
    x, y, h = p.T
    quad = np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)])
    a, b, c, d, e, f = np.linalg.lstsq(quad, h, rcond=None)[0]
    eigenvalues, eigenvectors = np.linalg.eigh(np.array([[2 * a, b], [b, 2 * c]]))
    curved = int(np.argmax(np.abs(eigenvalues)))
    curvature = eigenvalues[curved]
    if abs(curvature) < 1e-15:
        raise ValueError("form: the surface has no curvature to fit a cylinder to")
    across = eigenvectors[:, curved]
    along = eigenvectors[:, 1 - curved]
    radius0 = 1.0 / abs(curvature)
    azimuth0 = np.arctan2(along[1], along[0])
    # The quadratic's vertex along the curved direction is where the axis passes below a dome (a
    # positive-up bulge, negative curvature) or above a trough.
    slope = np.array([d, e]) @ across
    vertex = -slope / curvature
    apex = f + slope * vertex + 0.5 * curvature * vertex**2
    height0 = apex + radius0 if curvature > 0 else apex - radius0
    offset0 = vertex * (across @ np.array([-np.sin(azimuth0), np.cos(azimuth0)]))
    start = np.array([azimuth0, 0.0, offset0, height0, radius0])

    def axis_point(params):
        azimuth, _, offset, height, _ = params
        return np.array([-np.sin(azimuth) * offset, np.cos(azimuth) * offset, height])

    def residuals(params):
        u = _axis_direction(params[0], params[1])
        return np.linalg.norm(np.cross(p - axis_point(params), u), axis=1) - params[4]

    params, weights = _irls(_weighted_least_squares(residuals), residuals, start, robust)
    u = _axis_direction(params[0], params[1])
    anchor = axis_point(params) + shift
    radius = abs(params[4])
    convex = bool(np.median(points[:, 2] - (anchor[2] + (points[:, :2] - anchor[:2]) @ u[:2] * u[2])) >= 0)
    n_rows, n_cols = z.shape
    dx = (np.arange(n_cols) * pixel_size_um - anchor[0])[None, :]
    dy = (np.arange(n_rows) * pixel_size_um - anchor[1])[:, None]
    # Vertical line through (x, y) meets the cylinder where |w x u|² = |w|² - (w.u)² = R², w = (dx, dy, dz):
    # dz² (1 - uz²) - 2 dz uz (dx ux + dy uy) + dx² + dy² - (dx ux + dy uy)² - R² = 0.
    lateral = dx * u[0] + dy * u[1]
    qa = 1.0 - u[2] ** 2
    qb = -2.0 * u[2] * lateral
    qc = dx**2 + dy**2 - lateral**2 - radius**2
    with np.errstate(invalid="ignore"):
        root = np.sqrt(qb**2 - 4 * qa * qc)
    dz = (-qb + (1.0 if convex else -1.0) * root) / (2 * qa)
    form_um = anchor[2] + dz
    return FormFit(
        residual_um=z - form_um,
        form_um=form_um,
        form="cylinder",
        parameters={
            "radius_um": float(radius),
            "axis_azimuth_deg": float(np.degrees(params[0]) % 180.0),
            "axis_elevation_deg": float(np.degrees(params[1])),
            "axis_point_um": anchor.tolist(),
            "convex": convex,
        },
        fit_points=len(points),
        inlier_fraction=float(np.mean(weights > 0)),
    )


def remove_profile_form(z_um: np.ndarray, *, spacing_um: float, form: str = "plane", robust: bool = True) -> np.ndarray:
    """A profile (n,) µm sampled every ``spacing_um`` minus its form, fitted as ``remove_form`` fits
    a map: "plane" is the least-squares line (the ISO 21920-3 default F-operator), "polyN" a
    polynomial of degree N, and "sphere" or "cylinder" a circular arc (a sphere's section, or a
    cylinder's across its axis), by orthogonal distance. NaN samples are left out of the fit and
    stay NaN."""
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 1:
        raise ValueError("z_um must be a profile (n,)")
    if not spacing_um > 0:
        raise ValueError("spacing_um must be positive")
    if form not in FORMS:
        raise ValueError(f"form must be one of {', '.join(FORMS)}, not {form!r}")
    index = np.flatnonzero(np.isfinite(z))
    degree = 1 if form == "plane" else int(form[4:]) if form.startswith("poly") else 2
    if index.size < 2 * (degree + 1):
        raise ValueError(f"z_um: {index.size} known heights are too few to fit a {form}")
    values = z[index]
    if form in ("sphere", "cylinder"):
        x_um = index * spacing_um
        shift = np.array([x_um.mean(), values.mean()])
        p = np.column_stack([x_um, values]) - shift
        d, e, g = np.linalg.lstsq(np.column_stack([p, np.ones(len(p))]), -(p**2).sum(axis=1), rcond=None)[0]
        centre0 = -0.5 * np.array([d, e])
        start = np.concatenate([centre0, [np.sqrt(max(centre0 @ centre0 - g, 1e-12))]])

        def residuals(params):
            return np.linalg.norm(p - params[:2], axis=1) - params[2]

        params, _ = _irls(_weighted_least_squares(residuals), residuals, start, robust)
        centre = params[:2] + shift
        branch = 1.0 if np.median(values) >= centre[1] else -1.0
        with np.errstate(invalid="ignore"):
            form_um = centre[1] + branch * np.sqrt(params[2] ** 2 - (np.arange(z.size) * spacing_um - centre[0]) ** 2)
        return z - form_um
    design = legendre.legvander(_normalised(index, z.size), degree)

    def solve(weights, _previous):
        weighted = design if weights is None else design * weights[:, None]
        return np.linalg.solve(weighted.T @ design, weighted.T @ values)

    coefficients, _ = _irls(solve, lambda c: values - design @ c, None, robust)
    return z - legendre.legvander(_normalised(np.arange(z.size), z.size), degree) @ coefficients
