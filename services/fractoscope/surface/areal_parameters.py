"""ISO 25178-2:2021 areal field and feature parameters of a scale-limited surface.

Input: (rows, cols) float heights in µm on a square grid of ``pixel_size_um`` (the S-L or S-F surface:
form removed, filtered), NaN for unknown points, which every parameter leaves out. Heights are
referenced to their mean. Parameter names are the standard's; ``UNITS`` gives each one's unit.
Angles (Std) are counter-clockwise from the column axis (+x) with y pointing up the map (towards
row 0), in [0, 180).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import ndimage

from fractoscope.surface import _filter_kernels, _kernels
from fractoscope.units import HEIGHT_ROUNDING_UM

UNITS = {
    "Sa": "µm",
    "Sq": "µm",
    "Ssk": "1",
    "Sku": "1",
    "Sp": "µm",
    "Sv": "µm",
    "Sz": "µm",
    "Sdq": "1",
    "Sdr": "%",
    "Sal": "µm",
    "Str": "1",
    "Std": "deg",
    "Sk": "µm",
    "Spk": "µm",
    "Svk": "µm",
    "Smr1": "%",
    "Smr2": "%",
    "Vmp": "µm³/µm²",
    "Vmc": "µm³/µm²",
    "Vvc": "µm³/µm²",
    "Vvv": "µm³/µm²",
    "Spd": "1/µm²",
    "Spc": "1/µm",
}

ACF_THRESHOLD = 0.2  # s of ISO 25178-3 for Sal and Str
SPATIAL_MAX_PX = 2048  # larger maps' spatial parameters come from block means (see spatial_parameters)
SPATIAL_MIN_DECAY_BLOCKS = 8.0
STD_ANGLE_STEP_DEG = 0.5
MATERIAL_RATIO_CLASSES = 10_001  # material ratio 0 ... 100 % in steps of 0.01 %
EQUIVALENT_LINE_WIDTH_PERCENT = 40.0
VOLUME_P_PERCENT = 10.0  # ISO 25178-3 defaults for Vmp, Vmc, Vvc, Vvv
VOLUME_Q_PERCENT = 80.0
WOLF_PRUNING_PERCENT = 5.0  # of Sz, ISO 25178-3 default for the feature parameters
_HISTOGRAM_BINS = 65_536


def areal_parameters(
    z_um: np.ndarray, *, pixel_size_um: float, features: bool = True, max_lag_px: int | None = None
) -> dict[str, float]:
    """Every parameter of this module (see ``UNITS`` for the keys); ``features=False`` leaves out Spd
    and Spc, whose watershed segmentation costs about as much as all the others together;
    ``max_lag_px`` bounds the autocorrelation (see ``spatial_parameters``)."""
    z = _validated(z_um, pixel_size_um)
    values = height_parameters(z)
    values |= hybrid_parameters(z, pixel_size_um=pixel_size_um)
    values |= spatial_parameters(z, pixel_size_um=pixel_size_um, max_lag_px=max_lag_px)
    values |= functional_parameters(z)
    if features:
        values |= feature_parameters(z, pixel_size_um=pixel_size_um)
    return values


def _validated(z_um: np.ndarray, pixel_size_um: float | None = None) -> np.ndarray:
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 3:
        raise ValueError("z_um must be a (rows, cols) array with at least 3 rows and columns")
    if pixel_size_um is not None and not (np.isfinite(pixel_size_um) and pixel_size_um > 0):
        raise ValueError("pixel_size_um must be positive")
    if np.count_nonzero(np.isfinite(z)) < 9:
        raise ValueError("z_um has fewer than 9 finite heights")
    return z


def height_parameters(z_um: np.ndarray) -> dict[str, float]:
    """Sa, Sq, Sp, Sv, Sz (µm), Ssk, Sku (1) about the mean height (ISO 25178-2 4.1)."""
    z = _validated(z_um)
    n, mean, _, _ = _kernels.finite_height_summary(z)
    absolute, squares, cubes, fourths, _, sp, lowest = _kernels.central_moments(z, mean)
    sq = float(np.sqrt(squares / n))
    sv = -float(lowest)
    return {
        "Sa": float(absolute / n),
        "Sq": sq,
        # A flat field (its spread only rounding) has no skewness or kurtosis.
        "Ssk": float(cubes / n / sq**3) if sq > HEIGHT_ROUNDING_UM else float("nan"),
        "Sku": float(fourths / n / sq**4) if sq > HEIGHT_ROUNDING_UM else float("nan"),
        "Sp": float(sp),
        "Sv": sv,
        "Sz": float(sp) + sv,
    }


def hybrid_parameters(z_um: np.ndarray, *, pixel_size_um: float) -> dict[str, float]:
    """Sdq (root mean square gradient, 1) and Sdr (developed interfacial area ratio, %), ISO 25178-2
    4.3. Sdq averages each axis over its own finite differences; Sdr takes each grid cell's area as the
    mean of its two triangulations (2021, D.3), half the summed areas of the four triangles spanned at
    its corners, over the cells with four known corners. A corner triangle with slopes gx, gy along
    its two edges has area sqrt(gx² + gy² + 1) / 2 px²."""
    z = _validated(z_um, pixel_size_um)
    sx, nx, sy, ny, corners, cells = _kernels.slope_sums(z, 1.0 / pixel_size_um)
    # Scattered known points may have no known neighbour along an axis, or no cell of four.
    sdq = float(np.sqrt(sx / nx + sy / ny)) if nx and ny else float("nan")
    return {"Sdq": sdq, "Sdr": float((0.25 * corners / cells - 1.0) * 100.0) if cells else float("nan")}


# Spatial parameters ##################################################################################


def autocorrelation(z_um: np.ndarray, *, max_lag_px: int | None = None) -> np.ndarray:
    """Normalised autocorrelation f_ACF of the mean-removed heights for lags up to ``max_lag_px``
    (default: half the shorter side) along both axes: (2 L + 1, 2 L + 1), zero lag at [L, L],
    f_ACF(0) = 1; row lag first. Each lag is the mean over the pairs of known points that it joins
    (the unbiased estimator), by FFT on a grid padded by L so that no lag wraps around."""
    z = _validated(z_um)
    known = np.isfinite(z)
    lag = min(z.shape) // 2 if max_lag_px is None else int(max_lag_px)
    if not 1 <= lag < min(z.shape):
        raise ValueError(f"max_lag_px must be between 1 and {min(z.shape) - 1}")
    # Single precision: f_ACF is needed to about 1e-6, and the padded transforms are the costliest step.
    centred = np.where(known, z - z[known].mean(), 0.0).astype(np.float32)
    shape = tuple(scipy.fft.next_fast_len(n + lag, real=True) for n in z.shape)
    products = _circular_autocorrelation(centred, shape)
    if known.all():
        rows, cols = z.shape
        lags = np.arange(-lag, lag + 1)
        counts = np.outer(rows - np.abs(lags), cols - np.abs(lags)).astype(np.float64)
    else:
        counts = np.rint(_circular_autocorrelation(known.astype(np.float32), shape).astype(np.float64))
    products = _lag_window(products, lag).astype(np.float64)
    if not known.all():
        counts = _lag_window(counts, lag)
    with np.errstate(invalid="ignore", divide="ignore"):
        acf = np.where(counts > 0, products / counts, np.nan)
        return acf / acf[lag, lag]  # NaN on a flat field


def _circular_autocorrelation(values: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    spectrum = scipy.fft.rfft2(values, s=shape, workers=-1)
    return scipy.fft.irfft2(spectrum.real**2 + spectrum.imag**2, s=shape, workers=-1)


def _lag_window(circular: np.ndarray, lag: int) -> np.ndarray:
    """Lags -L..L of a circular correlation (whose negative lags sit at the far end)."""
    index = np.r_[np.arange(-lag, 0), np.arange(0, lag + 1)]
    return circular[np.ix_(index, index)]


def spatial_parameters(
    z_um: np.ndarray, *, pixel_size_um: float, threshold: float = ACF_THRESHOLD, max_lag_px: int | None = None
) -> dict[str, float]:
    """Sal (µm), Str (1) and Std (deg), ISO 25178-2 4.2.

    Sal is the shortest lag at which f_ACF decays to ``threshold``, Str the ratio of that to the
    longest such decay over all directions: NaN when f_ACF does not decay within ``max_lag_px``
    (default half the field) in some direction, as along a lay longer than that. After an L-filter,
    lambda_c / pixel_size_um is a cheaper bound: no longer correlation survives it. Each direction
    is a ray through the ACF every 0.5°, sampled every half pixel, its first crossing interpolated
    linearly. Std is the direction of the largest angular amplitude density of the Fourier spectrum
    (a Hann window keeps the field's edges from putting a false lay at 0° and 90°): the direction in
    which heights vary fastest, perpendicular to the lay.

    Maps larger than SPATIAL_MAX_PX a side are averaged over blocks of b x b pixels first (b the
    smallest that brings them within it) and their autocovariance normalised by the full map's
    variance: for lags of several blocks the block means' autocovariance is the map's, smoothed
    over a block. Where Sal comes out shorter than SPATIAL_MIN_DECAY_BLOCKS blocks the full map is
    used after all. On the benchmark's 4096² S-L surface (blocks of 2) Sal and Str came out within
    0.02 % of the full map's and Std the same, in a quarter of the time.
    """
    z = _validated(z_um, pixel_size_um)
    if not 0 < threshold < 1:
        raise ValueError("threshold must be between 0 and 1")
    block = -(-max(z.shape) // SPATIAL_MAX_PX)
    if block > 1 and min(z.shape) >= SPATIAL_MIN_DECAY_BLOCKS * block:  # a long, narrow strip stays whole
        coarse, variance_ratio = _block_means(z, block)
        lag = None if max_lag_px is None else max(1, min(int(np.ceil(max_lag_px / block)), min(coarse.shape) - 1))
        found = _decay(autocorrelation(coarse, max_lag_px=lag) * variance_ratio, threshold)
        if found is not None and found[0] >= SPATIAL_MIN_DECAY_BLOCKS:
            return {"Sal": found[0] * block * pixel_size_um, "Str": found[1], "Std": texture_direction_deg(coarse)}
    found = _decay(autocorrelation(z, max_lag_px=max_lag_px), threshold)
    sal_px, str_ = found if found is not None else (float("nan"), float("nan"))
    return {"Sal": sal_px * pixel_size_um, "Str": str_, "Std": texture_direction_deg(z)}


def _block_means(z: np.ndarray, block: int) -> tuple[np.ndarray, float]:
    """Means of the known heights over block x block pixels (NaN where fewer than half are known;
    the map cropped to whole blocks), and the ratio of their variance to the map's."""
    rows, cols = (z.shape[0] // block) * block, (z.shape[1] // block) * block
    sums, counts = _filter_kernels.block_sums_and_counts(np.ascontiguousarray(z[:rows, :cols]), block, 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        means = np.where(counts >= block * block / 2, sums / counts, np.nan)
    return means, _variance(means) / _variance(z)


def _variance(z: np.ndarray) -> float:
    """The variance of the known heights (np.nanvar)."""
    n, mean, _, _ = _kernels.finite_height_summary(z)
    return float(_kernels.central_moments(z, mean)[1] / n)


def _decay(acf: np.ndarray, threshold: float) -> tuple[float, float] | None:
    """(Sal in pixels, Str) of an autocorrelation (2 L + 1, 2 L + 1) by rays every 0.5°, or None
    where it decays to the threshold in no direction (Str NaN where it does not in some)."""
    lag = (acf.shape[0] - 1) // 2
    angles = np.radians(np.arange(0.0, 180.0, STD_ANGLE_STEP_DEG))
    radii = np.arange(0.0, lag + 1e-9, 0.5)
    # Lag (rows, cols) along a direction theta counter-clockwise from +x with y up: (-sin, cos).
    ray_rows = lag - np.sin(angles)[:, None] * radii[None, :]
    ray_cols = lag + np.cos(angles)[:, None] * radii[None, :]
    along = ndimage.map_coordinates(np.nan_to_num(acf, nan=1.0), [ray_rows, ray_cols], order=1, mode="nearest")
    below = along <= threshold
    crossed = below.any(axis=1)
    if not crossed.any():
        return None
    first = np.argmax(below, axis=1)[crossed]
    before = along[crossed, first - 1]
    after = along[crossed, first]
    fraction = (before - threshold) / (before - after)
    decay_px = radii[first - 1] + fraction * (radii[1] - radii[0])
    return float(decay_px.min()), float(decay_px.min() / decay_px.max()) if crossed.all() else float("nan")


def texture_direction_deg(z_um: np.ndarray) -> float:
    """Std: the angle (deg, [0, 180) in 0.5° steps, counter-clockwise from +x, y up) of the largest
    angular amplitude density, the integral of |F| along each ray from the origin of the spatial
    frequency plane (ISO 25178-2 4.2.3), sampled by linear interpolation out to the Nyquist frequency.
    Rays rather than angular bins of the frequency grid, whose points crowd onto 0°, 45° and 90°."""
    z = _validated(z_um)
    rows, cols = z.shape
    known = np.isfinite(z)
    centred = np.where(known, z - z[known].mean(), 0.0).astype(np.float32)
    centred *= np.outer(np.hanning(rows).astype(np.float32), np.hanning(cols).astype(np.float32))
    amplitude = np.fft.fftshift(np.abs(scipy.fft.rfft2(centred, workers=-1)), axes=0)
    angles = np.radians(np.arange(0.0, 180.0, STD_ANGLE_STEP_DEG))
    # Spatial frequency (cycles per pixel) from one frequency step to Nyquist, in half steps.
    radius = np.arange(1.0 / min(rows, cols), 0.5, 0.5 / max(rows, cols))
    k_cols = np.cos(angles)[:, None] * radius[None, :] * cols
    k_rows = -np.sin(angles)[:, None] * radius[None, :] * rows  # row frequency points down
    # Rays left of the column axis are read from their point mirror, which the rfft half-plane holds.
    mirror = k_cols < 0
    k_cols = np.where(mirror, -k_cols, k_cols)
    k_rows = np.where(mirror, -k_rows, k_rows)
    density = ndimage.map_coordinates(amplitude, [k_rows + rows // 2, k_cols], order=1, mode="nearest").sum(axis=1)
    return float(np.argmax(density) * STD_ANGLE_STEP_DEG)


# Functional parameters ###############################################################################


@dataclass(frozen=True)
class MaterialRatioCurve:
    """The areal material ratio (Abbott-Firestone) curve: ``height_um[k]`` is the height c at which a
    share ``material_ratio_percent[k]`` of the (known) surface lies at or above c; heights about the
    mean, decreasing."""

    material_ratio_percent: np.ndarray
    height_um: np.ndarray


def material_ratio_curve(z_um: np.ndarray, *, classes: int = MATERIAL_RATIO_CLASSES) -> MaterialRatioCurve:
    """Material ratio curve at ``classes`` equally spaced material ratios 0 ... 100 %, from a
    65 536-class height histogram (heights resolved to Sz / 65 536; no sort of every height). Any
    shape of ``z_um`` (a profile too); NaN left out."""
    if classes < 101:
        raise ValueError("classes must be at least 101")
    z = np.ascontiguousarray(z_um, dtype=np.float64)
    z = z if z.ndim == 2 else z.reshape(1, -1)  # rows of a map go to threads
    n, mean, highest, lowest = _kernels.finite_height_summary(z)
    if n < 9:
        raise ValueError("z_um has fewer than 9 finite heights")
    high, low = highest - mean, lowest - mean  # rounding keeps the order: the extremes of z - mean
    ratio = np.linspace(0.0, 100.0, classes)
    if high <= low:
        return MaterialRatioCurve(ratio, np.full(classes, low))
    width = (high - low) / _HISTOGRAM_BINS
    counts = _kernels.height_histogram(z, mean, low, width, _HISTOGRAM_BINS)
    # Share at or above each bin edge, from the top edge (0 %) down to the lowest (100 %).
    above = np.concatenate([[0], np.cumsum(counts[::-1])]) * (100.0 / n)
    edges = high - width * np.arange(_HISTOGRAM_BINS + 1)
    return MaterialRatioCurve(ratio, np.interp(ratio, above, edges))


def functional_parameters(
    z_um: np.ndarray, *, p_percent: float = VOLUME_P_PERCENT, q_percent: float = VOLUME_Q_PERCENT
) -> dict[str, float]:
    """Sk family (Sk, Spk, Svk µm; Smr1, Smr2 %) and volume parameters (Vmp, Vmc, Vvc, Vvv, µm³/µm²,
    i.e. ml/m²) from the material ratio curve (ISO 25178-2 4.4 and Annex B, ISO 13565-2)."""
    if not 0 < p_percent < q_percent < 100:
        raise ValueError("p_percent and q_percent must satisfy 0 < p < q < 100")
    return functional_parameters_of_curve(material_ratio_curve(z_um), p_percent=p_percent, q_percent=q_percent)


def functional_parameters_of_curve(
    curve: MaterialRatioCurve, *, p_percent: float = VOLUME_P_PERCENT, q_percent: float = VOLUME_Q_PERCENT
) -> dict[str, float]:
    """The functional parameters of a material ratio curve sampled at equal material-ratio steps.

    The central region is the 40 % wide window whose secant has the smallest gradient (the first one
    on ties); the equivalent straight line is the least-squares line through the curve in that window
    (ISO 25178-2:2021 B.1). Its heights at 0 % and 100 % bound the core: Sk is their difference,
    Smr1 and Smr2 the material ratios at them, and Spk (Svk) the height of the triangle with the area
    of the peaks above (dales below) the core over base Smr1 (100 % - Smr2).
    """
    ratio, height = curve.material_ratio_percent, curve.height_um
    step = ratio[1] - ratio[0]
    span = int(round(EQUIVALENT_LINE_WIDTH_PERCENT / step))
    secant = height[span:] - height[:-span]  # <= 0; the smallest gradient is the largest value
    start = int(np.argmax(secant))
    window = slice(start, start + span + 1)
    slope, intercept = np.polyfit(ratio[window], height[window], 1)
    upper, lower = intercept, intercept + 100.0 * slope
    increasing_height = height[::-1]
    smr1 = float(np.interp(upper, increasing_height, ratio[::-1], left=100.0, right=0.0))
    smr2 = float(np.interp(lower, increasing_height, ratio[::-1], left=100.0, right=0.0))
    peak_area = np.trapezoid(np.clip(height - upper, 0.0, None), ratio)  # µm %
    dale_area = np.trapezoid(np.clip(lower - height, 0.0, None), ratio)
    at_p, at_q = np.interp([p_percent, q_percent], ratio, height)

    def material_volume(level):
        return np.trapezoid(np.clip(height - level, 0.0, None), ratio) / 100.0

    def void_volume(level):
        return np.trapezoid(np.clip(level - height, 0.0, None), ratio) / 100.0

    return {
        "Sk": float(upper - lower),
        "Spk": float(2.0 * peak_area / smr1) if smr1 > 0 else 0.0,
        "Svk": float(2.0 * dale_area / (100.0 - smr2)) if smr2 < 100 else 0.0,
        "Smr1": smr1,
        "Smr2": smr2,
        "Vmp": float(material_volume(at_p)),
        "Vmc": float(material_volume(at_q) - material_volume(at_p)),
        "Vvc": float(void_volume(at_p) - void_volume(at_q)),
        "Vvv": float(void_volume(at_q)),
    }


# Feature parameters ##################################################################################


def feature_parameters(
    z_um: np.ndarray, *, pixel_size_um: float, pruning_percent: float = WOLF_PRUNING_PERCENT
) -> dict[str, float]:
    """Spd (density of significant peaks, 1/µm²) and Spc (their arithmetic mean peak curvature, 1/µm),
    ISO 25178-2 5.8, from a watershed segmentation into hills with Wolf pruning at
    ``pruning_percent`` of Sz (ISO 25178-3 default 5 %).

    Hills are the catchment areas of steepest ascent (8-connected); a hill whose height above its
    highest saddle is below the threshold merges across that saddle into its neighbour. Hills that
    touch the field's border or an unknown point are incomplete and left out. The area is the known
    points' count times pixel_size_um². Curvature is -(d²z/dx² + d²z/dy²) / 2 by central differences
    at the peak. Wolf (1991), doi:10.1016/0098-3004(91)90018-G; Scott (2004),
    doi:10.1016/j.wear.2003.09.008.
    """
    z = _validated(z_um, pixel_size_um)
    if not 0 <= pruning_percent < 100:
        raise ValueError("pruning_percent must be in [0, 100)")
    n, mean, highest, lowest = _kernels.finite_height_summary(z)
    heights = _kernels.centred_heights(z, mean)
    threshold = pruning_percent / 100.0 * float((highest - mean) - (lowest - mean))
    labels, peak_index = _ascent_watershed(heights)
    count = peak_index.size - 1
    peak_height = heights.ravel()[peak_index]
    peak_height[0] = -np.inf
    low, high, saddle = _saddles(labels, heights, count)
    with np.errstate(invalid="ignore"):  # hills of unknown points only: -inf peaks and saddles
        root = _wolf_pruning(peak_height, low, high, saddle, threshold)
    incomplete = np.zeros(count + 1, dtype=bool)
    incomplete[root[_kernels.labels_at_gaps(labels, heights, count)]] = True
    survivors = np.unique(root[1:])
    survivors = survivors[~incomplete[survivors]]
    rows, cols = np.unravel_index(peak_index[survivors], z.shape)
    area_um2 = n * pixel_size_um**2
    inside = (rows > 0) & (rows < z.shape[0] - 1) & (cols > 0) & (cols < z.shape[1] - 1)
    r, c = rows[inside], cols[inside]
    d2x = (heights[r, c + 1] - 2 * heights[r, c] + heights[r, c - 1]) / pixel_size_um**2
    d2y = (heights[r + 1, c] - 2 * heights[r, c] + heights[r - 1, c]) / pixel_size_um**2
    curvature = -0.5 * (d2x + d2y)
    curvature = curvature[np.isfinite(curvature)]
    return {
        "Spd": float(survivors.size / area_um2),
        "Spc": float(curvature.mean()) if curvature.size else float("nan"),
    }


def _ascent_watershed(heights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Label each pixel 1..n with the local maximum (plateau) that steepest ascent reaches from it.
    Returns the labels and, for each label (index 0 unused), the flat index of one pixel of its
    maximum."""
    index_type = np.int32 if heights.size < 2**31 else np.int64
    return _kernels.ascent_labels(np.ascontiguousarray(heights), np.zeros(heights.size, dtype=index_type))


def _saddles(labels: np.ndarray, heights: np.ndarray, count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Adjacent hill pairs (low < high label) and the height of the highest pass between them: the
    largest over their shared 8-connected boundary of the lower of the two heights."""
    low, high, pass_height = _kernels.hill_boundaries(labels, heights)
    return _highest_per_pair(low, high, pass_height, count)


def _highest_per_pair(low, high, value, count):
    """Unique (low, high) pairs with the largest value of each."""
    if low.size == 0:
        return low, high, value
    key = low * (count + 1) + high
    # Boundaries come in runs of the same pair: fold those first, then sort what is left.
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    key, value = key[starts], np.maximum.reduceat(value, starts)
    order = np.argsort(key)
    key, value = key[order], value[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    key, value = key[starts], np.maximum.reduceat(value, starts)
    return key // (count + 1), key % (count + 1), value


def _wolf_pruning(peak, low, high, saddle, threshold):
    """Root hill of every hill (index 0 unused) after Wolf pruning. In rounds, every hill whose height
    above its highest saddle is below the threshold, and whose neighbour across that saddle is
    higher, merges into it: the same hills survive as when merging one at a time, smallest first,
    since a hill's highest saddle does not change until it merges itself."""
    count = peak.size - 1
    root = np.arange(count + 1)
    peak = peak.copy()
    while low.size:
        best = np.full(count + 1, -np.inf)
        np.maximum.at(best, low, saddle)
        np.maximum.at(best, high, saddle)
        partner = np.zeros(count + 1, dtype=np.int64)
        for this, other in ((low, high), (high, low)):
            at_best = saddle == best[this]
            partner[this[at_best]] = other[at_best]
        hills = np.unique(np.concatenate([low, high]))
        mate = partner[hills]
        higher = (peak[mate] > peak[hills]) | ((peak[mate] == peak[hills]) & (mate > hills))
        merging = hills[(peak[hills] - best[hills] < threshold) & higher]
        if merging.size == 0:
            break
        root[merging] = partner[merging]
        while True:
            jumped = root[root]
            if np.array_equal(jumped, root):
                break
            root = jumped
        low, high = root[low], root[high]
        keep = low != high
        low, high, saddle = _highest_per_pair(
            np.minimum(low[keep], high[keep]), np.maximum(low[keep], high[keep]), saddle[keep], count
        )
    return root
