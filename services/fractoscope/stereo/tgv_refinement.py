"""Refinement of a disparity field by second-order total generalized variation (TGV²) over a
small-window ZNCC data term.

A window matcher finds each pixel's disparity as the average over its window, so structure finer
than the window (dimple rims, river steps) is lost, and noise grows as the window shrinks. Here
every pixel's data term comes from a small window (5 × 5 px): the ZNCC parabola through the
scores at −1, 0 and +1 px around the current disparity, weighted by its peak's precision
(1/σ², see `correlation.peak_sigma_px`). TGV² then balances the data against the cost of
departing from a piecewise affine field: slopes cost nothing, kinks and steps cost in proportion
to their size, so rims and steps stay sharp while noise is averaged out where the surface is
smooth. The right image is warped by the current field and the data term taken again (`warps`
times); in between, a diagonally scaled primal-dual scheme minimizes the convex problem.

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).

References
----------
K. Bredies, K. Kunisch, T. Pock, "Total generalized variation", SIAM J. Imaging Sci. 3 (2010)
492-526, doi:10.1137/090769521.
A. Chambolle, T. Pock, "A first-order primal-dual algorithm for convex problems with applications
to imaging", J. Math. Imaging Vis. 40 (2011) 120-145, doi:10.1007/s10851-010-0251-1.
R. Ranftl, S. Gehrig, T. Pock, H. Bischof, "Pushing the limits of stereo using variational stereo
estimation", IEEE Intelligent Vehicles Symposium (2012) 401-407, doi:10.1109/IVS.2012.6232171.
"""

from __future__ import annotations

import numba
import numpy as np

from fractoscope.stereo import correlation

DATA_WINDOW_PX = 5
# Weights of the two TGV² terms, in units of the data term's (dimensionless, χ²-like) cost: first
# order (steps) and second order (kinks). Chosen on the synthetic dimples and self-affine
# surfaces, where the first-order term hardly binds (1 to 5 give the same heights).
STEP_WEIGHT = 3.0
KINK_WEIGHT = 3.0
# A 5 × 5 px window locates its peak no better than this on noise-free texture (its per-pixel
# errors there are 0.1-0.2 px): the data term never claims more, so that TGV² still averages.
SIGMA_FLOOR_PX = 0.2
# Three warps of 50 iterations: 30 per warp cost dimples 0.3 points of RMS error (3.1 % of the
# height range instead of 2.9 %).
WARPS = 3
ITERATIONS_PER_WARP = 50
# Primal step over dual step: small primal steps let the dual (regularizing) variables settle
# first, which converges in a third of the iterations on the synthetic surfaces.
_STEP_RATIO = 0.2
# Iterations run together in one sweep down the rows (`_wavefront`): 8 of them touch 19 rows at a
# time, of 13 float32 arrays each, 1 MB at 1024 columns, about what one core's L2 cache holds.
WAVEFRONT_ITERATIONS = 8


def refine_disparity(
    left: np.ndarray,
    right: np.ndarray,
    initial_px: np.ndarray,
    *,
    window_px: int = DATA_WINDOW_PX,
    step_weight: float = STEP_WEIGHT,
    kink_weight: float = KINK_WEIGHT,
    warps: int = WARPS,
    iterations_per_warp: int = ITERATIONS_PER_WARP,
) -> np.ndarray:
    """Refines `initial_px` (rows, cols float32, finite: a window matcher's disparities before
    masking) for `left` and `right`, (rows, cols) float32 images normalized to zero mean and
    unit variance, rectified so that parallax runs along rows. Returns the refined disparities,
    (rows, cols) float32."""
    left_stats = correlation.window_stats(left, window_px)
    state = _State.starting_at(initial_px)
    for _ in range(warps):
        target, precision = data_term(left, left_stats, right, state.disparity, window_px)
        state.iterate(
            target, precision, step_weight=step_weight, kink_weight=kink_weight, iterations=iterations_per_warp
        )
    return state.disparity


def data_term(left, left_stats, right, disparity, window_px):
    """The ZNCC parabola's peak (target disparity) and its precision 1/σ² (0 where the scores have
    no peak; σ as `correlation.peak_sigma_px`, at least `SIGMA_FLOOR_PX`), (rows, cols) float32
    each, from the right image warped by `disparity` (finite)."""
    warped = correlation.warp_along_rows(right, disparity)
    scores = correlation.zncc_scores_within_one_px(left, left_stats, warped, window_px)
    sigma_scale = correlation.SIGMA_CALIBRATION**2 / window_px**2
    return _parabola_peaks(np.ascontiguousarray(disparity, np.float32), *scores, np.float32(sigma_scale))


class _State:
    """The primal (disparity d, slope field v) and dual (p for ∇d - v, q for the symmetrized
    gradient of v) variables, with the over-relaxed copies of d and v; (rows, cols) float32 each."""

    def __init__(self, disparity: np.ndarray):
        self.disparity = disparity
        self.relaxed = disparity.copy()
        (
            self.slope_cols,
            self.slope_rows,
            self.relaxed_slope_cols,
            self.relaxed_slope_rows,
            self.dual_cols,
            self.dual_rows,
            self.dual_cc,
            self.dual_rr,
            self.dual_rc,
        ) = (np.zeros_like(disparity) for _ in range(9))

    @classmethod
    def starting_at(cls, disparity_px: np.ndarray) -> _State:
        return cls(np.ascontiguousarray(disparity_px, np.float32).copy())

    def iterate(self, target, precision, *, step_weight, kink_weight, iterations):
        tau = np.float32(_STEP_RATIO / np.sqrt(12.0))  # τσ‖K‖² ≤ 1 with ‖K‖² ≤ 12 for TGV²
        sigma = np.float32(1.0 / (_STEP_RATIO * np.sqrt(12.0)))
        np.copyto(self.relaxed, self.disparity)
        np.copyto(self.relaxed_slope_cols, self.slope_cols)
        np.copyto(self.relaxed_slope_rows, self.slope_rows)
        arrays = (
            self.disparity,
            self.slope_cols,
            self.slope_rows,
            self.relaxed,
            self.relaxed_slope_cols,
            self.relaxed_slope_rows,
            self.dual_cols,
            self.dual_rows,
            self.dual_cc,
            self.dual_rr,
            self.dual_rc,
            target,
            precision,
        )
        weights = (np.float32(step_weight), np.float32(kink_weight), sigma, tau)
        for done in range(0, iterations, WAVEFRONT_ITERATIONS):
            _wavefront(*arrays, *weights, min(WAVEFRONT_ITERATIONS, iterations - done))


# The two half-steps of the primal-dual iteration, row by row.
# Differences are forward for ∇d and backward for the symmetrized gradient of v, so that the
# divergences in the primal step are their exact negative adjoints (Neumann boundaries: the
# differences across the border vanish). Each row is updated by a few loops that each touch
# only a handful of arrays: LLVM then vectorizes them (AVX2), where one loop over all fourteen
# arrays stayed scalar and took 2-4 times as long. The loops handle the last (or first) column
# apart, so that the rest run without branches. Every constant is float32: a float64 literal
# would turn the whole expression into float64. The arithmetic is IEEE (no fastmath): with
# reassociation allowed, code compiled afresh and code loaded from numba's cache rounded
# differently (inlined into its caller or not), so two processes gave heights 1e-6 apart; the
# loops vectorize either way, at the same speed.
_JIT = dict(nogil=True, cache=True, boundscheck=False, error_model="numpy")


@numba.njit(**_JIT)
def _parabola_peaks(disparity, before, centre, after, sigma_scale):  # pragma: no cover
    """`data_term`'s target and precision from the scores at -1, 0, +1 px, in one pass."""
    rows, cols = centre.shape
    target, precision = np.empty_like(centre), np.empty_like(centre)
    zero, half, one, two = np.float32(0.0), np.float32(0.5), np.float32(1.0), np.float32(2.0)
    least_curvature, bias = np.float32(1e-4), np.float32(0.02**2)
    floor = np.float32(SIGMA_FLOOR_PX**2)
    for i in range(rows):
        for j in range(cols):
            b, c, a = before[i, j], centre[i, j], after[i, j]
            curvature = b - two * c + a
            peaked = curvature < -least_curvature and c > zero
            offset = min(max(half * (b - a) / curvature, -one), one) if peaked else zero
            target[i, j] = disparity[i, j] + offset
            variance = sigma_scale * max(one - c, zero) / max(-half * curvature, least_curvature) + bias
            precision[i, j] = one / max(variance, floor) if peaked else zero
    return target, precision


@numba.njit(**_JIT)
def _wavefront(
    d,
    vc,
    vr,
    d_bar,
    vc_bar,
    vr_bar,
    pc,
    pr,
    qcc,
    qrr,
    qrc,
    target,
    precision,
    step_weight,
    kink_weight,
    sigma,
    tau,
    count,
):  # pragma: no cover
    """`count` primal-dual iterations in one sweep down the rows. Iteration t's position r is the
    dual step of row r, then the primal step of row r - 1 (which reads the dual rows r - 2 to r).
    The dual step of row r reads the over-relaxed primal rows r - 1 to r + 1 of iteration t - 1,
    which that iteration finished at its position r + 2: so iteration t runs 2 positions behind
    iteration t - 1, and each step sees exactly the values it would in sweeps of one iteration
    each, while the 2 count + 3 rows they touch stay in cache."""
    rows = d.shape[0]
    for position in range(rows + 1 + 2 * (count - 1)):
        for t in range(count):
            r = position - 2 * t
            if r < 0 or r > rows:
                continue
            if r < rows:
                _dual_row(d_bar, vc_bar, vr_bar, pc, pr, qcc, qrr, qrc, step_weight, kink_weight, sigma, r)
            if r > 0:
                _primal_row(d, vc, vr, d_bar, vc_bar, vr_bar, pc, pr, qcc, qrr, qrc, target, precision, tau, r - 1)


@numba.njit(**_JIT)
def _dual_row(d, vc, vr, pc, pr, qcc, qrr, qrc, step_weight, kink_weight, sigma, i):  # pragma: no cover
    """The dual half-step of row i, from the over-relaxed primal variables `d`, `vc`, `vr`."""
    rows = d.shape[0]
    below, above = min(i + 1, rows - 1), max(i - 1, 0)
    _dual_step_row_p(d[i], d[below], vc[i], vr[i], pc[i], pr[i], step_weight, sigma)
    _dual_step_row_q(vc[i], vc[above], vr[i], vr[above], qcc[i], qrr[i], qrc[i], kink_weight, sigma)


@numba.njit(**_JIT)
def _dual_step_row_p(d_i, d_below, vc_i, vr_i, pc_i, pr_i, step_weight, sigma):  # pragma: no cover
    """p ← proj_{|p| ≤ step_weight}(p + σ(∇d - v)) along one row."""
    cols = d_i.shape[0]
    for j in range(cols - 1):
        _project_p(pc_i, pr_i, j, d_i[j + 1] - d_i[j] - vc_i[j], d_below[j] - d_i[j] - vr_i[j], step_weight, sigma)
    last = cols - 1
    _project_p(pc_i, pr_i, last, -vc_i[last], d_below[last] - d_i[last] - vr_i[last], step_weight, sigma)


@numba.njit(inline="always", **_JIT)
def _project_p(pc_i, pr_i, j, gradient_c, gradient_r, step_weight, sigma):  # pragma: no cover
    one = np.float32(1.0)
    a = pc_i[j] + sigma * gradient_c
    b = pr_i[j] + sigma * gradient_r
    shrink = one / max(one, np.sqrt(a * a + b * b) / step_weight)
    pc_i[j] = a * shrink
    pr_i[j] = b * shrink


@numba.njit(**_JIT)
def _dual_step_row_q(vc_i, vc_above, vr_i, vr_above, qcc_i, qrr_i, qrc_i, kink_weight, sigma):  # pragma: no cover
    """q ← proj_{|q| ≤ kink_weight}(q + σ ε(v)) along one row, ε the symmetrized gradient."""
    half = np.float32(0.5)
    _project_q(
        qcc_i,
        qrr_i,
        qrc_i,
        0,
        np.float32(0.0),
        vr_i[0] - vr_above[0],
        half * (vc_i[0] - vc_above[0]),
        kink_weight,
        sigma,
    )
    for j in range(1, vc_i.shape[0]):
        _project_q(
            qcc_i,
            qrr_i,
            qrc_i,
            j,
            vc_i[j] - vc_i[j - 1],
            vr_i[j] - vr_above[j],
            half * (vc_i[j] - vc_above[j] + vr_i[j] - vr_i[j - 1]),
            kink_weight,
            sigma,
        )


@numba.njit(inline="always", **_JIT)
def _project_q(qcc_i, qrr_i, qrc_i, j, strain_cc, strain_rr, strain_rc, kink_weight, sigma):  # pragma: no cover
    one, two = np.float32(1.0), np.float32(2.0)
    c = qcc_i[j] + sigma * strain_cc
    e = qrr_i[j] + sigma * strain_rr
    f = qrc_i[j] + sigma * strain_rc
    shrink = one / max(one, np.sqrt(c * c + e * e + two * f * f) / kink_weight)
    qcc_i[j] = c * shrink
    qrr_i[j] = e * shrink
    qrc_i[j] = f * shrink


@numba.njit(**_JIT)
def _primal_row(d, vc, vr, d_bar, vc_bar, vr_bar, pc, pr, qcc, qrr, qrc, target, precision, tau, i):  # pragma: no cover
    """The primal half-step of row i, with its over-relaxed copies."""
    rows = d.shape[0]
    above, below = max(i - 1, 0), min(i + 1, rows - 1)
    has_above, has_below = np.float32(i > 0), np.float32(i < rows - 1)
    _primal_step_row_d(d[i], d_bar[i], pc[i], pr[i], pr[above], has_above, has_below, target[i], precision[i], tau)
    # v moves along p and the divergence of q (the adjoint of the backward differences).
    _primal_step_row_v(vc[i], vc_bar[i], pc[i], qcc[i], qrc[i], qrc[below], has_below, tau)
    _primal_step_row_v(vr[i], vr_bar[i], pr[i], qrc[i], qrr[i], qrr[below], has_below, tau)


@numba.njit(**_JIT)
def _primal_step_row_d(
    d_i, d_bar_i, pc_i, pr_i, pr_above, has_above, has_below, target_i, precision_i, tau
):  # pragma: no cover
    """d ← (d + τ div p + τ w target) / (1 + τ w), w the data term's precision; d̄ = 2 d_new - d."""
    cols = d_i.shape[0]
    vertical = has_below * pr_i[0] - has_above * pr_above[0]
    _update_d(d_i, d_bar_i, 0, (pc_i[0] if cols > 1 else np.float32(0.0)) + vertical, target_i, precision_i, tau)
    for j in range(1, cols - 1):
        vertical = has_below * pr_i[j] - has_above * pr_above[j]
        _update_d(d_i, d_bar_i, j, pc_i[j] - pc_i[j - 1] + vertical, target_i, precision_i, tau)
    if cols > 1:
        last = cols - 1
        vertical = has_below * pr_i[last] - has_above * pr_above[last]
        _update_d(d_i, d_bar_i, last, vertical - pc_i[last - 1], target_i, precision_i, tau)


@numba.njit(inline="always", **_JIT)
def _update_d(d_i, d_bar_i, j, divergence, target_i, precision_i, tau):  # pragma: no cover
    one, two = np.float32(1.0), np.float32(2.0)
    weight = tau * precision_i[j]
    d_new = (d_i[j] + tau * divergence + weight * target_i[j]) / (one + weight)
    d_bar_i[j] = two * d_new - d_i[j]
    d_i[j] = d_new


@numba.njit(**_JIT)
def _primal_step_row_v(v_i, v_bar_i, p_i, q_across, q_down, q_down_below, has_below, tau):  # pragma: no cover
    """One component of v ← v + τ(p - div q) along one row, div q from the backward differences'
    adjoint: q_across at this column minus the next, q_down at this row minus the next
    (q_down_below)."""
    cols = v_i.shape[0]
    for j in range(cols - 1):
        _update_v(
            v_i, v_bar_i, j, p_i[j] - (q_across[j] - q_across[j + 1] + q_down[j] - has_below * q_down_below[j]), tau
        )
    last = cols - 1
    _update_v(v_i, v_bar_i, last, p_i[last] - (q_across[last] + q_down[last] - has_below * q_down_below[last]), tau)


@numba.njit(inline="always", **_JIT)
def _update_v(v_i, v_bar_i, j, step, tau):  # pragma: no cover
    two = np.float32(2.0)
    v_new = v_i[j] + tau * step
    v_bar_i[j] = two * v_new - v_i[j]
    v_i[j] = v_new
