"""Gaussian filters of ISO 16610-21 (profiles) and ISO 16610-61 (areal), and the default cut-offs
(nesting indices) of ISO 21920-3 and ISO 25178-3 for a sampling and a field.

The weighting function is s(x) = exp(-pi (x / (alpha lambda_c))²) / (alpha lambda_c) with
alpha = sqrt(ln 2 / pi), whose amplitude transmission exp(-pi (alpha lambda_c / lambda)²) is exactly
50 % at the cut-off wavelength; as a normal distribution its standard deviation is
sigma = alpha lambda_c / sqrt(2 pi) = 0.1874 lambda_c.

Unknown points (NaN) and everything outside the field are handled by normalized convolution
(Knutsson & Westin 1993, doi:10.1109/CVPR.1993.341081): the mean line is G * (w z) / G * w with
w = 1 on known points and 0 elsewhere, so holes and edges neither pull the mean line towards zero nor
need padding by invented data; near an edge the filter becomes a one-sided weighted mean (the
zero-order end-effect correction). Holes stay NaN in every output.

Small kernels are applied by direct separable convolution (compiled, the sampled Gaussian of
scipy.ndimage), large ones by FFT on a zero-padded grid (scipy.fft with ndimage.fourier_gaussian):
same transfer function; maps are filtered with the widest (sigma of 48 px and more) on blocks of
pixels (`_decimated_normalized_convolution`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft
from scipy import ndimage

from fractoscope.surface import _filter_kernels

ALPHA = float(np.sqrt(np.log(2.0) / np.pi))
_SIGMA_PER_CUTOFF = ALPHA / np.sqrt(2.0 * np.pi)
_TRUNCATE_SIGMAS = 5.0
_DIRECT_MAX_SIGMA_PX = 8.0
_DECIMATED_MIN_SIGMA_PX = 48.0  # maps filtered with a wider Gaussian are filtered on blocks of pixels
_SAMPLES_PER_SIGMA = 24.0
# A cut-off beyond this many times the field's longer side filters nothing the field can show
# (its Gaussian is flat across it) and would only cost memory.
MAX_CUTOFF_FIELDS = 10.0
# A cut-off below two sampling steps (the shortest wavelength sampled) filters nothing.
MIN_CUTOFF_STEPS = 2.0
# The default lambda_c of a profile is only taken with at least this many samples per sampling
# length: fewer leave the roughness profile a few samples per wavelength.
_DEFAULT_LAMBDA_C_MIN_STEPS = 10.0
_MIN_BAND_RATIO = 10.0  # a default lambda_s is at most this fraction of lambda_c

# ISO 21920-3:2021 Table 1, the setting classes Sc1 to Sc5: lambda_c (= sampling length, with five of
# them in the default evaluation length), lambda_s and the largest sampling distance, all µm.
ISO_21920_3_SETTINGS = (
    (80.0, 2.5, 0.5),
    (250.0, 2.5, 0.5),
    (800.0, 2.5, 0.5),
    (2500.0, 8.0, 1.5),
    (8000.0, 25.0, 5.0),
)
ISO_21920_3_SECTIONS = 5
# Below the table (SEM fields are tens of µm) the same 1-2.5-8 series continues with Sc1's ratios:
# lambda_c / lambda_s about 32 (80 / 2.5) and a largest sampling distance of lambda_s / 5.
_EXTRAPOLATED_SETTINGS = ((25.0, 0.8, 0.16), (8.0, 0.25, 0.05), (2.5, 0.08, 0.016), (0.8, 0.025, 0.005))


# ISO 25178-3's preferred nesting indices (the 1-2.5-8 series of the settings above), µm; the
# largest sampling distance for an S-filter nesting index is about a third of it, the next smaller
# value of the series (its Table 1: 2.5 µm -> 0.8 µm, 8 µm -> 2.5 µm).
PREFERRED_NESTING_INDICES_UM = tuple(
    sorted({value for setting in _EXTRAPOLATED_SETTINGS + ISO_21920_3_SETTINGS for value in setting[:2]})
)


@dataclass(frozen=True)
class NestingIndices:
    """Default cut-offs (nesting indices) for data sampled every ``spacing_um`` over ``field_um``,
    µm, 0 where that filter is not applied; ``reason`` says why, in one sentence.
    ``from_iso_table`` is False for fields below ISO 21920-3's shortest evaluation length (400 µm),
    where the series was extrapolated; ``sampling_ok`` says whether the spacing is within that
    table's largest sampling distance for its own lambda_s (False: lambda_s was raised)."""

    lambda_c_um: float
    lambda_s_um: float
    max_sampling_um: float
    evaluation_length_um: float
    from_iso_table: bool
    sampling_ok: bool
    spacing_um: float
    reason: str


def default_nesting_indices(*, pixel_size_um: float, field_um: float) -> NestingIndices:
    """The S- and L-filter defaults for data sampled every ``pixel_size_um`` over a field of
    ``field_um`` (a profile's evaluation length, a map's shorter side), µm. lambda_c: the largest of
    the setting classes (ISO 21920-3 Table 1, extended below it by the same series) of which the
    field holds five; lambda_s: the one ISO 21920-3 pairs with it, raised where the sampling is
    too coarse for it to the smallest preferred nesting index that the sampling resolves (ISO
    25178-3 Table 1). 0 (no such filter) for a lambda_c under ten samples, or a lambda_s under two
    samples or over a tenth of lambda_c (without one, a fifth of the field)."""
    if not field_um > 0:
        raise ValueError("field_um must be positive")
    if not pixel_size_um > 0:
        raise ValueError("pixel_size_um must be positive")
    settings = sorted(_EXTRAPOLATED_SETTINGS + ISO_21920_3_SETTINGS)
    fitting = [s for s in settings if ISO_21920_3_SECTIONS * s[0] <= field_um]
    lambda_c, paired_s, max_sampling = fitting[-1] if fitting else settings[0]
    series = PREFERRED_NESTING_INDICES_UM
    resolved = next((v for finer, v in zip(series, series[1:]) if finer >= pixel_size_um * (1 - 1e-9)), series[-1])
    if lambda_c < _DEFAULT_LAMBDA_C_MIN_STEPS * pixel_size_um:
        lambda_c = 0.0
    lambda_s = _sampled(max(paired_s, resolved), pixel_size_um)
    # A raised lambda_s must leave a band: a tenth of lambda_c (the table's ratios are 32 to 320),
    # or without one a fifth of the field.
    if lambda_s > (lambda_c / _MIN_BAND_RATIO if lambda_c else field_um / ISO_21920_3_SECTIONS):
        lambda_s = 0.0
    return NestingIndices(
        lambda_c_um=lambda_c,
        lambda_s_um=lambda_s,
        max_sampling_um=max_sampling,
        evaluation_length_um=float(field_um),
        from_iso_table=fitting[-1][0] >= ISO_21920_3_SETTINGS[0][0] if fitting else False,
        sampling_ok=pixel_size_um <= max_sampling * (1 + 1e-9),
        spacing_um=float(pixel_size_um),
        reason=_nesting_reason(lambda_s, lambda_c, paired_s, pixel_size_um, field_um),
    )


def _nesting_reason(lambda_s: float, lambda_c: float, paired_s: float, spacing_um: float, field_um: float) -> str:
    """One sentence on how default_nesting_indices chose its cut-offs."""
    if lambda_c:
        why_c = (
            f"λc = {lambda_c:g} µm, the largest preferred nesting index of which the {field_um:.4g} µm field holds five"
        )
    else:
        why_c = f"no L-filter, as the {field_um:.4g} µm field holds five of no nesting index of ten samples"
    if not lambda_s:
        why_s = (
            f"no S-filter, as the λs that samples {spacing_um:.4g} µm apart resolve would leave too narrow a band "
            "(the data's own resolution limits the short wavelengths)"
        )
    elif lambda_s > paired_s:
        why_s = (
            f"λs = {lambda_s:g} µm, ISO 21920-3's {paired_s:g} µm raised to the smallest preferred nesting index that "
            f"samples {spacing_um:.4g} µm apart resolve (ISO 25178-3, about three samples per nesting index)"
        )
    else:
        why_s = (
            f"λs = {lambda_s:g} µm, the one ISO 21920-3 pairs with it, resolved by samples {spacing_um:.4g} µm apart"
        )
    return f"{why_c}; {why_s}"


def paired_lambda_s_um(lambda_c_um: float, *, spacing_um: float) -> float:
    """The lambda_s that ISO 21920-3 pairs with ``lambda_c_um``, µm: the setting class of the
    nearest lambda_c (on a log scale) gives the ratio; 0 (no S-filter) under two samples."""
    settings = _EXTRAPOLATED_SETTINGS + ISO_21920_3_SETTINGS
    lambda_c, lambda_s, _ = min(settings, key=lambda setting: abs(np.log(setting[0] / lambda_c_um)))
    return _sampled(lambda_c_um * lambda_s / lambda_c, spacing_um)


def _sampled(lambda_s_um: float, spacing_um: float) -> float:
    """A default lambda_s, or 0 (no S-filter) under MIN_CUTOFF_STEPS samples, where it would do nothing."""
    return lambda_s_um if lambda_s_um >= MIN_CUTOFF_STEPS * spacing_um else 0.0


def gaussian_sigma_px(cutoff_um: float, pixel_size_um: float) -> float:
    """Standard deviation (pixels) of the ISO Gaussian weighting function with this cut-off."""
    return _SIGMA_PER_CUTOFF * cutoff_um / pixel_size_um


def transmission(wavelength_um: np.ndarray | float, *, cutoff_um: float) -> np.ndarray | float:
    """Amplitude transmission of the Gaussian mean-line (low-pass) filter, exp(-pi (alpha lc / l)²)."""
    return np.exp(-np.pi * (ALPHA * cutoff_um / np.asarray(wavelength_um, dtype=np.float64)) ** 2)


def gaussian_mean_surface(z_um: np.ndarray, *, pixel_size_um: float, cutoff_um: float) -> np.ndarray:
    """ISO 16610-61 Gaussian mean surface (the low-pass part: wavelengths well above ``cutoff_um``) of
    a (rows, cols) µm height map; NaN holes by normalized convolution, NaN in the output there."""
    z = _validated_map(z_um, pixel_size_um, cutoff_um, "cutoff_um")
    sigma = gaussian_sigma_px(cutoff_um, pixel_size_um)
    return _normalized_convolution(z, (sigma, sigma))


def gaussian_mean_line(z_um: np.ndarray, *, spacing_um: float, cutoff_um: float) -> np.ndarray:
    """ISO 16610-21 Gaussian mean line of an open profile (n,) µm sampled every ``spacing_um``."""
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 1 or z.size < 3:
        raise ValueError("z_um must be a profile (n,) with at least 3 samples")
    _check_positive(spacing_um, "spacing_um")
    _check_positive(cutoff_um, "cutoff_um")
    return _normalized_convolution(z, (gaussian_sigma_px(cutoff_um, spacing_um),))


def s_filter(z_um: np.ndarray, *, pixel_size_um: float, lambda_s_um: float) -> np.ndarray:
    """S-filter (ISO 25178-3): removes the small-scale components below ``lambda_s_um``, µm."""
    return gaussian_mean_surface(z_um, pixel_size_um=pixel_size_um, cutoff_um=lambda_s_um)


def l_filter(z_um: np.ndarray, *, pixel_size_um: float, lambda_c_um: float) -> np.ndarray:
    """L-filter (ISO 25178-3): removes the large-scale components above ``lambda_c_um``; returns the
    surface minus its Gaussian mean surface, µm."""
    return np.asarray(z_um, dtype=np.float64) - gaussian_mean_surface(
        z_um, pixel_size_um=pixel_size_um, cutoff_um=lambda_c_um
    )


@dataclass(frozen=True)
class ScaleLimitedSurface:
    """The S-F surface (after the S-filter; the form is removed beforehand) and, when an L-filter is
    given, the S-L surface. ``z_um`` is the one to evaluate (S-L if lambda_c_um is set, else S-F);
    cut-offs in µm (None: that filter was not applied)."""

    z_um: np.ndarray
    sf_um: np.ndarray
    lambda_s_um: float | None
    lambda_c_um: float | None


def scale_limited_surface(
    z_um: np.ndarray, *, pixel_size_um: float, lambda_s_um: float | None = None, lambda_c_um: float | None = None
) -> ScaleLimitedSurface:
    """Apply the S-filter then the L-filter (either may be None) to a form-removed height map."""
    if lambda_s_um is not None and lambda_c_um is not None and not lambda_s_um < lambda_c_um:
        raise ValueError(f"lambda_s_um ({lambda_s_um}) must be below lambda_c_um ({lambda_c_um})")
    z = np.asarray(z_um, dtype=np.float64)
    check_cutoffs_fit(
        max(z.shape) * pixel_size_um, step_um=pixel_size_um, lambda_s_um=lambda_s_um, lambda_c_um=lambda_c_um
    )
    sf = z if lambda_s_um is None else s_filter(z, pixel_size_um=pixel_size_um, lambda_s_um=lambda_s_um)
    sl = sf if lambda_c_um is None else l_filter(sf, pixel_size_um=pixel_size_um, lambda_c_um=lambda_c_um)
    return ScaleLimitedSurface(z_um=sl, sf_um=sf, lambda_s_um=lambda_s_um, lambda_c_um=lambda_c_um)


def check_cutoffs_fit(field_um: float, *, step_um: float, lambda_s_um: float | None, lambda_c_um: float | None) -> None:
    """ValueError naming lambda_s_um or lambda_c_um when one exceeds MAX_CUTOFF_FIELDS times the
    field (its longer side, or the profile's length, µm) or is below MIN_CUTOFF_STEPS sampling
    steps (``step_um``, the pixel size or spacing: shorter wavelengths are not sampled, and a
    filter there acts on nothing); None or 0: no such filter."""
    for name, cutoff in (("lambda_c_um", lambda_c_um), ("lambda_s_um", lambda_s_um)):  # lambda_s may follow lambda_c
        if cutoff and not cutoff <= MAX_CUTOFF_FIELDS * field_um:
            raise ValueError(
                f"{name} ({cutoff:g} µm) must be at most {MAX_CUTOFF_FIELDS:g} times the field's {field_um:.4g} µm"
            )
        if cutoff and not cutoff >= MIN_CUTOFF_STEPS * step_um:
            raise ValueError(
                f"{name} ({cutoff:g} µm) must be at least {MIN_CUTOFF_STEPS:g} sampling steps "
                f"({MIN_CUTOFF_STEPS * step_um:.4g} µm)"
            )


def _check_positive(value: float, name: str) -> None:
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be positive and finite, not {value}")


def _validated_map(z_um: np.ndarray, pixel_size_um: float, cutoff_um: float, cutoff_name: str) -> np.ndarray:
    z = np.asarray(z_um, dtype=np.float64)
    if z.ndim != 2 or min(z.shape) < 3:
        raise ValueError("z_um must be a (rows, cols) array with at least 3 rows and columns")
    _check_positive(pixel_size_um, "pixel_size_um")
    _check_positive(cutoff_um, cutoff_name)
    return z


def _normalized_convolution(z: np.ndarray, sigma_px: tuple[float, ...]) -> np.ndarray:
    """G * (w z) / G * w over 1 or 2 axes, w the finite points, zero weight outside the array."""
    if z.ndim == 2 and max(sigma_px) <= _DIRECT_MAX_SIGMA_PX:
        kernels = [_gaussian_kernel(sigma) for sigma in sigma_px]
        return _filter_kernels.normalized_separable_filter(np.ascontiguousarray(z), kernels[0], kernels[1])
    if z.ndim == 2 and min(sigma_px) >= _DECIMATED_MIN_SIGMA_PX:
        return _decimated_normalized_convolution(z, sigma_px)
    known = np.isfinite(z)
    filled = np.where(known, z, 0.0)
    numerator = _gaussian(filled, sigma_px)
    if known.all():
        # The weight is then a box: its blur is separable, one 1-D blur per axis.
        denominator = np.ones((), dtype=np.float64)
        for axis, (length, sigma) in enumerate(zip(z.shape, sigma_px)):
            profile = _gaussian(np.ones(length), (sigma,))
            shape = [1] * z.ndim
            shape[axis] = length
            denominator = denominator * profile.reshape(shape)
    else:
        denominator = _gaussian(known.astype(np.float64), sigma_px)
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = numerator / denominator
    mean[~known] = np.nan
    return mean


def _gaussian_kernel(sigma_px: float) -> np.ndarray:
    """The sampled Gaussian of scipy.ndimage.gaussian_filter (truncated at _TRUNCATE_SIGMAS)."""
    radius = int(_TRUNCATE_SIGMAS * sigma_px + 0.5)
    x = np.arange(-radius, radius + 1)
    kernel = np.exp(-0.5 * (x / sigma_px) ** 2)
    return kernel / kernel.sum()


def _decimated_normalized_convolution(z: np.ndarray, sigma_px: tuple[float, float]) -> np.ndarray:
    """The normalized convolution of a wide Gaussian on blocks of pixels: a Gaussian of sigma px
    passes nothing shorter than a few sigma, so G * (w z) and G * w are computed from block sums
    (blocks of sigma / _SAMPLES_PER_SIGMA pixels; a block's own spread, (b² - 1) / 12 px², taken
    off the Gaussian's variance), their ratio interpolated back to every pixel by cubic
    convolution. On the benchmark's surface (2048², lambda_c = 80 µm: sigma 150 px, blocks of 6)
    the mean surface is within 1.4e-5 of the heights' range of the full-resolution filter (RMS
    1.6e-5 Sq), at a third of its time."""
    block = max(1, int(min(sigma_px) // _SAMPLES_PER_SIGMA))
    pad = 3  # blocks of zero weight around the map, so that every pixel has two samples either side
    sums, counts = _filter_kernels.block_sums_and_counts(np.ascontiguousarray(z), block, pad)
    coarse_sigma = tuple(np.sqrt(sigma**2 - (block**2 - 1) / 12.0) / block for sigma in sigma_px)
    numerator = _gaussian(sums, coarse_sigma)
    denominator = _gaussian(counts, coarse_sigma)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(denominator > 1e-9 * denominator.max(), numerator / denominator, 0.0)
    # Fine pixel i is at coarse coordinate pad + (i - (block - 1) / 2) / block.
    start = pad - (block - 1) / (2.0 * block)
    return _filter_kernels.upsample_cubic(ratio, start, 1.0 / block, z.shape[0], z.shape[1], np.isfinite(z))


def _gaussian(values: np.ndarray, sigma_px: tuple[float, ...]) -> np.ndarray:
    """Gaussian blur with zero outside the array: direct for small sigma, FFT on a padded grid else."""
    if max(sigma_px) <= _DIRECT_MAX_SIGMA_PX:
        return ndimage.gaussian_filter(values, sigma_px, mode="constant", cval=0.0, truncate=_TRUNCATE_SIGMAS)
    pad = [int(np.ceil(_TRUNCATE_SIGMAS * s)) for s in sigma_px]
    shape = [scipy.fft.next_fast_len(n + p, real=True) for n, p in zip(values.shape, pad)]
    axes = tuple(range(values.ndim))
    # Single precision: the mean surface comes out to about 1e-7 of the heights' range, far below any
    # height a stereo map resolves, at half the cost of the two padded transforms.
    spectrum = scipy.fft.rfftn(values.astype(np.float32), s=shape, axes=axes, workers=-1)
    spectrum = ndimage.fourier_gaussian(spectrum, sigma_px, n=shape[-1], axis=-1)
    blurred = scipy.fft.irfftn(spectrum, s=shape, axes=axes, workers=-1)
    return blurred[tuple(slice(0, n) for n in values.shape)].astype(np.float64)
