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

from fractoscope.progress import checkpoint
from fractoscope.units import HEIGHT_ROUNDING_UM

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
        raise ValueError(f"{rows.size} usable points (finite heights in the region fitted) are too few to fit a {form}")
    if form == "plane" or form.startswith("poly"):
        degree = 1 if form == "plane" else int(form[4:])
        try:
            return _remove_polynomial(z, rows, cols, degree, form, robust)
        except np.linalg.LinAlgError:
            raise ValueError(
                f"the usable points do not determine a {form} (they lie on too few rows or columns)"
            ) from None
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
    if scale <= HEIGHT_ROUNDING_UM:  # no outliers among rounding errors (a constant map left none to fit)
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
        checkpoint()
        new_weights = _robust_weights(residual_of(params), iteration)
        converged = iteration > _HUBER_ITERATIONS and np.max(np.abs(new_weights - weights)) < 1e-3
        weights = new_weights
        if converged:
            break
        params = solve(weights, params)
    return params, weights


def _remove_polynomial(
    z: np.ndarray, rows: np.ndarray, cols: np.ndarray, degree: int, form: str, robust: bool
) -> FormFit:
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
    """Sphere through the point above the field centre at height a, with normal (-b, -c, 1)/|·| and
    curvature κ there (`_tangent_quadric`): a flat or tilted surface is its κ = 0 limit, which
    the fit reaches as smoothly as any sphere. Started from the least-squares plane with κ = 0 and
    with the quadratic fit's mean curvature."""
    shift = points.mean(axis=0)
    p = points - shift
    a, b, c, curvatures, _ = _plane_and_curvatures(p)
    params, weights = _fit_tangent_quadric(
        p, [np.array([a, b, c, 0.0]), np.array([a, b, c, np.mean(curvatures)])], robust
    )
    quadric = _tangent_quadric(params)
    form_um = _on_grid(quadric, shift, z.shape, pixel_size_um)
    return FormFit(
        residual_um=z - form_um,
        form_um=form_um,
        form="sphere",
        parameters={
            "radius_um": quadric.radius_um,
            "centre_um": (quadric.axis_point_um + shift).tolist(),
            "convex": quadric.convex,
        },
        fit_points=len(points),
        inlier_fraction=float(np.mean(weights > 0)),
    )


def _remove_cylinder(z: np.ndarray, points: np.ndarray, pixel_size_um: float, robust: bool) -> FormFit:
    """Cylinder touching the point above the field centre at height a, with normal (-b, -c, 1)/|·|
    there, its axis along the tangent plane at angle θ, curvature κ across it (`_tangent_quadric`):
    a flat or tilted surface is its κ = 0 limit. Started from the least-squares plane with κ = 0
    and with the quadratic fit's largest curvature, the axis along the least curved direction."""
    shift = points.mean(axis=0)
    p = points - shift
    a, b, c, curvatures, directions = _plane_and_curvatures(p)
    curved = int(np.argmax(np.abs(curvatures)))
    along = directions[:, 1 - curved]
    basis = _tangent_basis(b, c)
    # The least curved direction, lifted into the tangent plane, as an angle from its first axis.
    lifted = np.array([along[0], along[1], b * along[0] + c * along[1]])
    theta0 = float(np.arctan2(lifted @ basis[1], lifted @ basis[0]))
    # Also the axis turned by 90°: on a doubly curved surface either direction may fit best.
    starts = [
        np.array([a, b, c, theta0, 0.0]),
        np.array([a, b, c, theta0, curvatures[curved]]),
        np.array([a, b, c, theta0 + np.pi / 2, curvatures[1 - curved]]),
    ]
    params, weights = _fit_tangent_quadric(p, starts, robust)
    quadric = _tangent_quadric(params)
    form_um = _on_grid(quadric, shift, z.shape, pixel_size_um)
    axis = quadric.axis if quadric.axis[0] >= 0 else -quadric.axis  # the azimuth is taken modulo 180°
    return FormFit(
        residual_um=z - form_um,
        form_um=form_um,
        form="cylinder",
        parameters={
            "radius_um": quadric.radius_um,
            "axis_azimuth_deg": float(np.degrees(np.arctan2(axis[1], axis[0])) % 180.0),
            "axis_elevation_deg": float(np.degrees(np.arcsin(np.clip(axis[2], -1.0, 1.0)))),
            "axis_point_um": (quadric.axis_point_um + shift).tolist(),
            "convex": quadric.convex,
        },
        fit_points=len(points),
        inlier_fraction=float(np.mean(weights > 0)),
    )


def _on_grid(quadric: _TangentQuadric, shift: np.ndarray, shape: tuple[int, int], pixel_size_um: float) -> np.ndarray:
    """The quadric's height, µm, at the pixel centres of a (rows, cols) map, for a quadric fitted to
    points less their mean ``shift`` (x, y, z µm)."""
    rows, cols = shape
    return shift[2] + quadric.height(
        (np.arange(cols) * pixel_size_um - shift[0])[None, :], (np.arange(rows) * pixel_size_um - shift[1])[:, None]
    )


def _plane_and_curvatures(p: np.ndarray):
    """For points p (n, 3) centred on their mean: the least-squares plane h = a + b x + c y, and the
    principal curvatures (2,) and directions (2, 2, columns) of a quadratic fit, 1/µm, positive
    for a dome."""
    x, y, h = p.T
    a, b, c = np.linalg.lstsq(np.column_stack([np.ones_like(x), x, y]), h, rcond=None)[0]
    q_xx, q_xy, q_yy = np.linalg.lstsq(np.column_stack([x * x, x * y, y * y, x, y, np.ones_like(x)]), h, rcond=None)[0][
        :3
    ]
    curvatures, directions = np.linalg.eigh(np.array([[2 * q_xx, q_xy], [q_xy, 2 * q_yy]]))
    return a, b, c, -curvatures, directions


def _tangent_basis(b: float, c: float) -> np.ndarray:
    """Orthonormal (2, 3) basis of the plane h = a + b x + c y: its x direction and the one across."""
    along_x = np.array([1.0, 0.0, b]) / np.hypot(1.0, b)
    normal = np.array([-b, -c, 1.0]) / np.sqrt(1.0 + b * b + c * c)
    return np.array([along_x, np.cross(normal, along_x)])


@dataclass(frozen=True)
class _TangentQuadric:
    """A sphere (axis None) or a cylinder (unit axis) through q = (0, 0, a) with unit normal n there
    (n_z > 0) and curvature κ (1/µm, > 0 a dome): its centre, or a point of its axis, is q - n/κ.
    Coordinates are relative to the fitted points' mean."""

    point: np.ndarray
    normal: np.ndarray
    curvature: float
    axis: np.ndarray | None

    def residuals(self, p: np.ndarray) -> np.ndarray:
        """Signed orthogonal distance of the points p (n, 3), µm, written so that it stays exact
        as κ → 0 (where it becomes the distance to the tangent plane): for w = p - q with the axis
        component removed, (κ|w|² + 2 w·n) / (|κ w + n| + 1)."""
        w = p - self.point
        across = w if self.axis is None else w - np.outer(w @ self.axis, self.axis)
        return (self.curvature * np.einsum("ij,ij->i", across, across) + 2.0 * (w @ self.normal)) / (
            np.linalg.norm(self.curvature * across + self.normal, axis=1) + 1.0
        )

    def height(self, x_um: np.ndarray, y_um: np.ndarray) -> np.ndarray:
        """Height of the surface above (x_um, y_um) (broadcast), on the branch through q; NaN where a
        vertical line misses it. The root of A t² + B t + C = 0 for t = h - a, in the form that
        stays exact as κ → 0."""
        u = np.zeros(3) if self.axis is None else self.axis
        lateral = x_um * u[0] + y_um * u[1]
        k, n = self.curvature, self.normal
        a2 = k * (1.0 - u[2] ** 2)
        b1 = 2.0 * n[2] - 2.0 * k * u[2] * lateral
        c0 = k * (x_um**2 + y_um**2 - lateral**2) + 2.0 * (n[0] * x_um + n[1] * y_um)
        with np.errstate(invalid="ignore"):
            return self.point[2] - 2.0 * c0 / (b1 + np.sqrt(b1 * b1 - 4.0 * a2 * c0))

    @property
    def radius_um(self) -> float:
        return float(1.0 / abs(self.curvature)) if self.curvature else float("inf")

    @property
    def convex(self) -> bool:
        return bool(self.curvature >= 0)

    @property
    def axis_point_um(self) -> np.ndarray:
        """The centre (sphere) or the axis point below q (cylinder), µm."""
        return self.point - self.normal / self.curvature if self.curvature else np.full(3, np.inf)


def _tangent_quadric(params: np.ndarray) -> _TangentQuadric:
    """Parameters (a, b, c, κ) of a sphere or (a, b, c, θ, κ) of a cylinder as a _TangentQuadric."""
    a, b, c = params[:3]
    normal = np.array([-b, -c, 1.0]) / np.sqrt(1.0 + b * b + c * c)
    axis = None
    if len(params) == 5:
        basis = _tangent_basis(b, c)
        axis = np.cos(params[3]) * basis[0] + np.sin(params[3]) * basis[1]
    return _TangentQuadric(np.array([0.0, 0.0, a]), normal, float(params[-1]), axis)


def _fit_tangent_quadric(p: np.ndarray, starts: list[np.ndarray], robust: bool, quadric_of=_tangent_quadric):
    """A tangent quadric (``quadric_of(parameters)``) fitted to points p (n, 3) by IRLS on the
    orthogonal distances from each start; of those fits and the starts themselves (the first is
    the least-squares plane, κ = 0), the one whose heights leave the smallest vertical residuals
    (RMS, or with ``robust`` the median absolute value) is kept, so the form never leaves more
    than the plane does. Returns (parameters, weights)."""

    def residuals(params):
        checkpoint()  # each evaluation takes 0.1 s on a 1024² map, hundreds of them a fit
        return quadric_of(params).residuals(p)

    def vertical_spread(params):
        quadric = quadric_of(params)
        vertical = p[:, 2] - quadric.height(p[:, 0], p[:, 1])
        vertical = np.where(np.isfinite(vertical), vertical, quadric.residuals(p))  # off its footprint
        return np.median(np.abs(vertical)) if robust else np.sqrt(np.mean(vertical**2))

    candidates = [(start, np.ones(len(p))) for start in starts]
    candidates += [_irls(_weighted_least_squares(residuals), residuals, start, robust) for start in starts]
    return min(candidates, key=lambda candidate: vertical_spread(candidate[0]))


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
        shift = np.array([x_um.mean(), 0.0, values.mean()])
        p = np.column_stack([x_um, np.zeros_like(x_um), values]) - shift
        parabola = np.polyfit(p[:, 0], p[:, 2], 2)

        def arc(params):  # (a, b, κ): the circle in the profile's plane, a sphere's section
            return _tangent_quadric(np.array([params[0], params[1], 0.0, params[2]]))

        starts = [
            np.array([p[:, 2].mean(), np.polyfit(p[:, 0], p[:, 2], 1)[0], 0.0]),
            np.array([parabola[2], parabola[1], -2.0 * parabola[0]]),
        ]
        params, _ = _fit_tangent_quadric(p, starts, robust, quadric_of=arc)
        return z - (shift[2] + arc(params).height(np.arange(z.size) * spacing_um - shift[0], 0.0))
    design = legendre.legvander(_normalised(index, z.size), degree)

    def solve(weights, _previous):
        weighted = design if weights is None else design * weights[:, None]
        return np.linalg.solve(weighted.T @ design, weighted.T @ values)

    coefficients, _ = _irls(solve, lambda c: values - design @ c, None, robust)
    return z - legendre.legvander(_normalised(np.arange(z.size), z.size), degree) @ coefficients
