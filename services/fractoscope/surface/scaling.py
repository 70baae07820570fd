"""Scaling analysis of fracture surfaces: the Hurst (roughness) exponent H of a self-affine surface,
from the height-height correlation h(r) ~ r^H and from the profile power spectrum P(k) ~ k^-(1 + 2H),
fitted only over the scales the data can be trusted at, along and across a chosen direction.

Trustworthy scales. A stereo height map is averaged over its matching window w, in both directions,
which steepens both curves well above w. On 4096² isotropic self-affine surfaces seen through a
15 px box (H = 0.5 / 0.7 / 0.9, eight maps and directions each) a fit from lags of 2 windows
overestimates H by 0.07 / 0.04 / 0.03 (h(r)) and 0.09 / 0.08 / 0.08 (PSD); from 4 windows by 0.035 /
0.016 / 0.007 and 0.04 / 0.03 / 0.03, with a scatter from map to map of 0.025-0.035: the
standard error reported for h(r) matches it, the PSD's is 0.65-0.85 of it. Without the smoothing
(2048², a 4 px window) h(r) reads 0.02 high and the PSD 0.005 low. The default fit range is therefore lags from four
windows to a tenth of the field (``trustworthy_range_um``), and wavelengths twice that for the PSD (a lag r is
most sensitive to wavelengths near 2r). Above a tenth of the field too few independent samples
remain.

The height-height correlation is taken of second differences, h(r) = sqrt(<(z(x+r) - 2 z(x) +
z(x-r))²>): it scales as r^H like the first-difference one for 0 < H < 1, but wavelengths longer than
r enter it as r⁴ instead of r², so it does not flatten towards H = 1 at lags approaching the field
(first differences give 0.80 for H = 0.9 over the same range). Kent & Wood (1997), J. R. Stat. Soc.
B 59, 679; Schmittbuhl, Vilotte & Roux (1995), doi:10.1103/PhysRevE.51.131.

The standard error comes from a delete-one jackknife over blocks of the field (bands across the
direction, times segments along it for h(r)), so it holds the map-to-map scatter that a
regression's own error leaves out (not the bias above), as long as blocks a quarter of the field
apart are nearly independent: a field whose profiles all share a few waves as long as the field
scatters more than it reports. Along and
across a direction: Ponson, Bonamy & Bouchaud (2006), doi:10.1103/PhysRevLett.96.035506.

Directions are degrees counter-clockwise from the column axis (+x) with y pointing up the map.
Heights (rows, cols) µm, NaN unknown; the form should be removed first, and no L-filter applied
(it removes exactly the large scales the exponent is fitted over).
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
import scipy.fft

from fractoscope.surface import _filter_kernels

JACKKNIFE_BANDS = 4  # jackknife blocks: bands of profiles across the direction (8 for the PSD) ...
JACKKNIFE_SEGMENTS = 4  # ... times segments along it for h(r) (spectra need whole profiles)
LAGS_PER_DECADE = 12
TRUSTWORTHY_WINDOWS = 4.0  # the fit range starts this many matching windows up (see above)
FIELD_FRACTION = 0.1  # and ends at this fraction of the field
# A standard error above this leaves H undetermined: 0.15 spans most of the range 0.3-0.9 that
# fracture surfaces are reported in at two sigma.
MAX_HURST_STDERR = 0.15
# Below this or two standard errors H cannot be told from 0, uncorrelated heights: on white noise
# (192² to 640², windows of 1 to 15 px, 36 maps) h(r) gave |H| up to 0.07, never above both.
MIN_HURST = 0.02


@dataclass(frozen=True)
class ScalingFit:
    """A power-law fit. ``hurst``: H; ``hurst_stderr``: its jackknife standard error;
    ``fit_min_um``/``fit_max_um``: the lags (HHC) or wavelengths (PSD) fitted, µm;
    ``direction_deg``: the profiles' direction; ``method``: "hhc" or "psd".

    ``scale_um`` and ``value`` are the curve as data: lags r and h(r) (µm, second differences) for
    "hhc", wavelengths
    1/k and the one-sided profile PSD (µm³, i.e. µm² per 1/µm) for "psd"; ``in_fit`` marks the points
    fitted. ``prefactor`` is h(1 µm) (µm) or P at k = 1/µm (µm³) on the fitted line."""

    method: str
    hurst: float
    hurst_stderr: float
    fit_min_um: float
    fit_max_um: float
    direction_deg: float
    scale_um: np.ndarray
    value: np.ndarray
    in_fit: np.ndarray
    prefactor: float

    @property
    def not_determinable(self) -> str:
        """Why this fit does not determine H ("" when it does), with its fit range (hurst_validity)."""
        reason = hurst_validity(self.hurst, self.hurst_stderr)
        return f"{reason} (fitted over {self.fit_min_um:.3g} to {self.fit_max_um:.3g} µm)" if reason else ""


def hurst_validity(hurst: float, hurst_stderr: float) -> str:
    """ "" for an exponent a self-affine surface can have, 0 < H < 1 and not within MIN_HURST or two
    standard errors of 0, known to MAX_HURST_STDERR;
    else why it is not determinable. Outside (0, 1) the heights are not self-affine over the fit
    range (white noise reads H near 0, a form or a periodic texture left in near or above 1)."""
    if not (np.isfinite(hurst) and np.isfinite(hurst_stderr)):
        return "not determinable: the fit gave no finite H or standard error"
    if not 0.0 < hurst < 1.0:
        return (
            f"not determinable: H = {hurst:.3f} ± {hurst_stderr:.3f} is outside (0, 1), so the heights are not "
            "self-affine over the fit range (noise, or a form or periodic texture left in)"
        )
    if hurst < max(MIN_HURST, 2.0 * hurst_stderr):
        return (
            f"not determinable: H = {hurst:.3f} ± {hurst_stderr:.3f} cannot be told from 0, heights uncorrelated "
            "over the fit range (noise)"
        )
    if hurst_stderr > MAX_HURST_STDERR:
        return (
            f"not determinable: H = {hurst:.3f} ± {hurst_stderr:.3f}, a standard error above {MAX_HURST_STDERR:g} "
            "(the blocks of the field disagree)"
        )
    return ""


def trustworthy_range_um(
    shape: tuple[int, int], *, pixel_size_um: float, window_px: float, min_windows: float = TRUSTWORTHY_WINDOWS
) -> tuple[float, float]:
    """Lags [min_windows matching windows, a tenth of the shorter side] in µm, the default fit range."""
    if not pixel_size_um > 0:
        raise ValueError("pixel_size_um must be positive")
    if not window_px >= 1:
        raise ValueError("window_px must be at least 1")
    if not min_windows > 0:
        raise ValueError("min_windows must be positive")
    low, high = min_windows * window_px * pixel_size_um, min(shape) * pixel_size_um * FIELD_FRACTION
    if not high > low:
        raise ValueError(
            f"window_px: the field ({min(shape)} px) is too small for a fit range from {min_windows:g} windows "
            f"({min_windows * window_px:g} px) to a tenth of the field"
        )
    return low, high


def directional_profiles(z_um: np.ndarray, *, direction_deg: float, spacing_px: float = 1.0) -> np.ndarray:
    """Parallel profiles through the map along ``direction_deg``, one every ``spacing_px`` across it,
    sampled every pixel along it: (profiles, samples) µm, NaN off the map or in holes. Along the axes
    (0, 90, 180, 270°) they are the rows or columns themselves; otherwise bilinear samples."""
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 8:
        raise ValueError("z_um must be a (rows, cols) array of at least 8 x 8")
    if not spacing_px >= 1:
        raise ValueError("spacing_px must be at least 1")
    angle = float(direction_deg) % 180.0
    step = max(1, int(round(spacing_px)))
    if angle == 0.0:
        return z[::step, :]
    if angle == 90.0:
        return z[::-1, ::step].T.copy()  # upwards along each column
    theta = np.radians(angle)
    along = np.array([-np.sin(theta), np.cos(theta)])  # (row, col) per pixel along the profiles
    across = np.array([np.cos(theta), np.sin(theta)])
    centre = (np.array(z.shape) - 1) / 2.0
    half = np.hypot(*z.shape) / 2.0
    offsets = np.arange(-half, half + 1e-9, spacing_px)
    positions = np.arange(-half, half + 1e-9, 1.0)
    profiles = _filter_kernels.bilinear_profiles(np.ascontiguousarray(z), centre, across, along, offsets, positions)
    finite = np.isfinite(profiles)
    keep_rows = finite.sum(axis=1) >= 8
    keep_cols = finite[keep_rows].any(axis=0)
    return profiles[np.ix_(keep_rows, keep_cols)]  # one contiguous copy


def height_height_correlation(
    profiles_um: np.ndarray,
    *,
    pixel_size_um: float,
    lags_px: np.ndarray,
    order: int = 2,
    bands: int = 1,
    segments: int = 1,
) -> tuple[np.ndarray, np.ndarray]:
    """h(r) = sqrt(<(D^order z)²>) over the known samples of each profile for integer ``lags_px``,
    D z = z(x + r) - z(x) (order 1) or z(x + r) - 2 z(x) + z(x - r) (order 2). Returns (lags µm
    (L,), h µm (bands * segments, L)): one curve per block of ``bands`` groups of consecutive
    profiles times ``segments`` stretches along them (each difference counted where it starts)."""
    lags = np.asarray(lags_px, dtype=np.int64)
    length = profiles_um.shape[1]
    if order not in (1, 2):
        raise ValueError("order must be 1 or 2")
    if lags.ndim != 1 or lags.size == 0 or lags.min() < 1 or order * lags.max() >= length - segments:
        raise ValueError("lags_px must be integers from 1 to below the profiles' length / order")
    band_starts = _split_starts(profiles_um.shape[0], bands)
    profiles = np.ascontiguousarray(profiles_um, dtype=np.float64)
    sums, counts = _filter_kernels.difference_sums(profiles, lags, order, band_starts.astype(np.int64), segments)
    with np.errstate(invalid="ignore", divide="ignore"):
        return lags * pixel_size_um, np.sqrt(sums / counts).reshape(bands * segments, lags.size)


def _split_starts(length: int, parts: int) -> np.ndarray:
    """Start indices of ``parts`` near-equal consecutive pieces of range(length)."""
    return np.array([piece[0] for piece in np.array_split(np.arange(length), parts)])


def profile_psd(
    profiles_um: np.ndarray, *, pixel_size_um: float, bands: int = 1, bins_per_decade: int = LAGS_PER_DECADE
) -> tuple[np.ndarray, np.ndarray]:
    """One-sided power spectral density of the profiles, log-binned (``bins_per_decade``) and
    averaged over each of ``bands`` groups of consecutive profiles. Returns (geometric-mean wavenumber
    of each bin, cycles/µm (K,), PSD µm³ (bands, K), NaN where a band has no data); the integral of the
    PSD over k is the mean square height.

    Each profile's longest run of known samples (at least 16) is differenced (pre-whitening: the
    spectrum of a rough profile falls as steeply as k^-3, which a window's side lobes cannot hold
    off), Hann windowed and transformed at its own length, and the difference's transfer
    |2 sin(pi k dx)|² is divided out again. Percival & Walden (1993), doi:10.1017/CBO9780511622762,
    ch. 6."""
    profiles = np.ascontiguousarray(profiles_um, dtype=np.float64)
    starts, lengths = _filter_kernels.longest_known_runs(profiles)
    usable = np.flatnonzero(lengths >= 16)
    if usable.size == 0:
        raise ValueError("profiles_um: no run of 16 known samples")
    longest = int(lengths.max())
    k_min, k_max = 1.0 / (longest * pixel_size_um), 0.5 / pixel_size_um
    edges = np.geomspace(k_min, k_max * (1 + 1e-9), int(np.ceil(np.log10(k_max / k_min) * bins_per_decade)) + 1)
    band_of = np.repeat(np.arange(bands), np.diff(np.r_[_split_starts(profiles.shape[0], bands), profiles.shape[0]]))
    sums = np.zeros((bands, edges.size - 1))
    counts = np.zeros((bands, edges.size - 1))
    log_k = np.zeros(edges.size - 1)
    k_counts = np.zeros(edges.size - 1)
    # Runs of the same length share one batched transform.
    for length in np.unique(lengths[usable]):
        group = usable[lengths[usable] == length]
        runs = profiles[group[:, None], starts[group][:, None] + np.arange(length)]
        diffs = np.diff(runs, axis=1)
        window = np.hanning(length - 1)
        power = np.abs(scipy.fft.rfft((diffs - diffs.mean(axis=1, keepdims=True)) * window, axis=1)) ** 2
        k = scipy.fft.rfftfreq(length - 1, d=pixel_size_um)[1:]
        power = (
            power[:, 1:] * (2.0 * pixel_size_um / np.sum(window**2)) / (2.0 * np.sin(np.pi * k * pixel_size_um)) ** 2
        )
        _filter_kernels.bin_spectra(
            power, np.log(k), np.digitize(k, edges) - 1, band_of[group], sums, counts, log_k, k_counts
        )
    used = k_counts > 0
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.exp(log_k[used] / k_counts[used]), (sums / counts)[:, used]


def hurst_exponent(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    window_px: float,
    method: str = "hhc",
    direction_deg: float = 0.0,
    fit_range_um: tuple[float, float] | None = None,
    spacing_px: float | None = None,
) -> ScalingFit:
    """H from profiles along ``direction_deg`` by "hhc" (slope of log h against log r, second
    differences) or "psd" (slope -(1 + 2H) of log P against log k, log-binned), over lags
    ``fit_range_um`` (default ``trustworthy_range_um`` for the matcher's window ``window_px``; the
    PSD is fitted over wavelengths twice those). Profiles are ``spacing_px`` apart (default half a
    window: closer ones are nearly the same profile after the matcher's smoothing)."""
    return hurst_exponents(
        z_um,
        pixel_size_um=pixel_size_um,
        window_px=window_px,
        methods=(method,),
        direction_deg=direction_deg,
        fit_range_um=fit_range_um,
        spacing_px=spacing_px,
    )[method]


def hurst_exponents(
    z_um: np.ndarray,
    *,
    pixel_size_um: float,
    window_px: float,
    methods: tuple[str, ...] = ("hhc", "psd"),
    direction_deg: float = 0.0,
    fit_range_um: tuple[float, float] | None = None,
    spacing_px: float | None = None,
) -> dict[str, ScalingFit]:
    """``hurst_exponent`` by each of ``methods``, from one set of profiles: {method: fit}."""
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError("z_um must be a (rows, cols) array")
    for method in methods:
        if method not in ("hhc", "psd"):
            raise ValueError(f"method must be 'hhc' or 'psd', not {method!r}")
    low, high = fit_range_um or trustworthy_range_um(z.shape, pixel_size_um=pixel_size_um, window_px=window_px)
    if not 0 < low < high:
        raise ValueError("fit_range_um must be (low, high) with 0 < low < high")
    spacing = max(1.0, window_px / 2.0) if spacing_px is None else spacing_px
    profiles = directional_profiles(z, direction_deg=direction_deg, spacing_px=spacing)
    return {method: _fit(profiles, method, pixel_size_um, low, high, direction_deg) for method in methods}


def _fit(
    profiles: np.ndarray, method: str, pixel_size_um: float, low: float, high: float, direction_deg: float
) -> ScalingFit:
    """One method's power-law fit of the profiles over lags [low, high] µm, with its jackknife."""
    bands = min(JACKKNIFE_BANDS, profiles.shape[0])
    if bands < 2:
        raise ValueError("spacing_px: fewer than two profiles across the field")
    if method == "hhc":
        lags_px = _log_spaced_lags(low / pixel_size_um, high / pixel_size_um, profiles.shape[1] // 3)
        scale_um, per_block = height_height_correlation(
            profiles, pixel_size_um=pixel_size_um, lags_px=lags_px, bands=bands, segments=JACKKNIFE_SEGMENTS
        )
    else:
        k, per_block = profile_psd(profiles, pixel_size_um=pixel_size_um, bands=2 * bands)
        scale_um = 1.0 / k
        low, high = 2.0 * low, 2.0 * high
    curve = _combined(method, per_block)
    in_fit = (scale_um >= low * (1 - 1e-9)) & (scale_um <= high * (1 + 1e-9)) & np.isfinite(curve) & (curve > 0)
    if in_fit.sum() < 3:
        raise ValueError("fit_range_um spans fewer than three points of the curve")
    # Delete-one-block jackknife (Efron & Stein 1981): the curves without each block in turn give
    # each point's variance and, through the spread of H over them, its standard error.
    x = np.log(scale_um[in_fit])
    leave_out_curves = np.log(
        np.array([_combined(method, np.delete(per_block, b, axis=0))[in_fit] for b in range(per_block.shape[0])])
    )
    blocks = leave_out_curves.shape[0]
    variance = (blocks - 1) / blocks * np.sum((leave_out_curves - leave_out_curves.mean(axis=0)) ** 2, axis=0)
    # Spectral bins are nearly independent, so inverse-variance weights suit them; the h(r) of
    # neighbouring lags share most of their pairs, and weighting them would only lean the fit onto the
    # shortest lags, where the matcher's smoothing biases h(r) most.
    if method == "psd":
        weights = 1.0 / np.maximum(variance, 1e-6 * variance.max() + 1e-30)
    else:
        weights = np.ones_like(variance)
    hurst, prefactor = _power_law(method, x, np.log(curve[in_fit]), weights)
    leave_one_out = np.array([_power_law(method, x, y, weights)[0] for y in leave_out_curves])
    stderr = float(np.sqrt((blocks - 1) / blocks * np.sum((leave_one_out - leave_one_out.mean()) ** 2)))
    fitted = scale_um[in_fit]
    return ScalingFit(
        method=method,
        hurst=hurst,
        hurst_stderr=stderr,
        fit_min_um=float(fitted.min()),
        fit_max_um=float(fitted.max()),
        direction_deg=float(direction_deg),
        scale_um=scale_um,
        value=curve,
        in_fit=in_fit,
        prefactor=prefactor,
    )


def _combined(method: str, per_band: np.ndarray) -> np.ndarray:
    """One curve from the bands' (near equal sized): mean squares for h(r), mean power for the PSD."""
    with warnings.catch_warnings():  # a lag or wavelength no band has data at stays NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        if method == "hhc":
            return np.sqrt(np.nanmean(per_band**2, axis=0))
        return np.nanmean(per_band, axis=0)


def _power_law(method: str, log_scale: np.ndarray, log_value: np.ndarray, weights: np.ndarray) -> tuple[float, float]:
    """(H, prefactor) of the weighted least-squares line in log-log: h = a r^H (scale r), or
    P = a k^-(1 + 2H) (scale 1/k)."""
    x = log_scale if method == "hhc" else -log_scale
    slope, intercept = np.polyfit(x, log_value, 1, w=np.sqrt(weights))
    hurst = slope if method == "hhc" else (-slope - 1.0) / 2.0
    return float(hurst), float(np.exp(intercept))


def anisotropic_hurst(
    z_um: np.ndarray, *, pixel_size_um: float, window_px: float, direction_deg: float, method: str = "hhc", **options
) -> dict[str, ScalingFit]:
    """H along ``direction_deg`` and across it (direction + 90°): {"along": fit, "across": fit}, e.g.
    along the crack front and along the propagation direction."""
    return {
        name: hurst_exponent(
            z_um, pixel_size_um=pixel_size_um, window_px=window_px, method=method, direction_deg=angle, **options
        )
        for name, angle in (("along", direction_deg), ("across", direction_deg + 90.0))
    }


def radial_psd(z_um: np.ndarray, *, pixel_size_um: float, bins_per_decade: int = 20) -> tuple[np.ndarray, np.ndarray]:
    """Radially averaged areal PSD of the heights: returns (q in cycles/µm (Q,), C(q) in µm⁴ (Q,)),
    log-binned, normalised so that the integral of C over the frequency plane is the mean square
    height. For a self-affine surface C ~ q^-(2 + 2H). As for the profile spectra, the gradient
    (differences along rows and columns, NaN as zero) is transformed with a Hann window and the
    differences' transfer 4 (sin² pi fx dx + sin² pi fy dx) divided out again, so that the window's
    leakage does not flatten a spectrum falling faster than q^-3."""
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 8:
        raise ValueError("z_um must be a (rows, cols) array of at least 8 x 8")
    if not pixel_size_um > 0:
        raise ValueError("pixel_size_um must be positive")
    shape = (z.shape[0] - 1, z.shape[1] - 1)
    hann_rows, hann_cols = np.hanning(shape[0]), np.hanning(shape[1])
    zc = np.ascontiguousarray(z)
    # Single precision for the transforms: a spectrum is needed to a part in 1e4 at most.
    spectrum_x, spectrum_y = (
        scipy.fft.rfft2(d, workers=-1) for d in _filter_kernels.windowed_differences(zc, hann_rows, hann_cols)
    )
    scale = pixel_size_um**2 / (np.sum(hann_rows**2) * np.sum(hann_cols**2) * np.isfinite(z).mean())
    q_min, q_max = 1.0 / (min(shape) * pixel_size_um), 0.5 / pixel_size_um
    edges = np.logspace(np.log10(q_min), np.log10(q_max), int(np.log10(q_max / q_min) * bins_per_decade) + 1)
    log_step = (np.log10(q_max) - np.log10(q_min)) / (edges.size - 1)
    totals, counts = _filter_kernels.radial_bins(
        spectrum_x, spectrum_y, shape[1], scale, pixel_size_um, np.log10(q_min), log_step, edges.size - 1
    )
    with np.errstate(invalid="ignore", divide="ignore"):
        c = totals / counts
    centres = np.sqrt(edges[:-1] * edges[1:])
    keep = counts > 0
    return centres[keep], c[keep]


def _log_spaced_lags(low_px: float, high_px: float, length: int) -> np.ndarray:
    """Integer lags spaced evenly in log between low_px and high_px (both kept inside the range)."""
    decades = np.log10(high_px / low_px)
    lags = np.geomspace(low_px, high_px, max(int(np.ceil(decades * LAGS_PER_DECADE)) + 1, 4))
    lowest, highest = max(int(np.ceil(low_px - 1e-9)), 1), min(int(np.floor(high_px + 1e-9)), length - 1)
    return np.unique(np.clip(np.rint(lags), lowest, highest).astype(np.int64))
