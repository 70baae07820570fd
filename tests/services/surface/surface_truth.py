"""Known-truth surfaces for the surface-analysis tests: the synthetic self-affine generator of
fractoscope.synthetic, and a stereo matcher's view of it (small white noise, then an average over the
matching window)."""

from __future__ import annotations

import numpy as np
from scipy import ndimage

from fractoscope import synthetic

MATCHING_WINDOW_PX = 15
MATCHING_NOISE_FRACTION = 0.02


def self_affine(shape: tuple[int, int], *, hurst: float, seed: int, rms_um: float = 1.0, **options) -> np.ndarray:
    """Gaussian self-affine heights (µm) by spectral synthesis, 2-D PSD ~ q^-(2 + 2H)
    (fractoscope.synthetic.self_affine_surface, whose options it takes)."""
    return synthetic.self_affine_surface(shape, hurst=hurst, rms_um=rms_um, seed=seed, **options)


def isotropic_self_affine(
    shape: tuple[int, int], *, hurst: float, seed: int, min_wavelength_px: float = 2.0
) -> np.ndarray:
    """Like self_affine, but statistically isotropic down to the longest wavelengths, for scaling
    tests. irfft2 keeps only the Hermitian half of a half-plane spectrum's zero (and Nyquist) column,
    so there the modes that vary along columns alone lose half their power, and column profiles of
    self_affine miss up to a tenth of their longest waves and read H about 0.04 low; here those two
    columns are given sqrt(2) more amplitude."""
    rng = np.random.default_rng(seed)
    q = np.hypot(np.fft.fftfreq(shape[0])[:, None], np.fft.rfftfreq(shape[1])[None, :])
    q[0, 0] = 1.0
    amplitude = q ** -(1.0 + hurst) * np.exp(-((q * min_wavelength_px) ** 2))
    amplitude[0, 0] = 0.0
    amplitude[:, 0] *= np.sqrt(2.0)
    if shape[1] % 2 == 0:
        amplitude[:, -1] *= np.sqrt(2.0)
    heights = np.fft.irfft2(amplitude * (rng.standard_normal(q.shape) + 1j * rng.standard_normal(q.shape)), s=shape)
    return heights / heights.std()


def fractional_brownian_sheet(shape: tuple[int, int], *, hurst_x: float, hurst_y: float, seed: int) -> np.ndarray:
    """An anisotropic Gaussian field whose rows are self-affine with hurst_x and whose columns with
    hurst_y: separable spectrum |kx|^-(1 + 2 Hx) |ky|^-(1 + 2 Hy) (a fractional Brownian sheet)."""
    rng = np.random.default_rng(seed)
    kx = np.abs(np.fft.fftfreq(shape[1]))
    ky = np.abs(np.fft.fftfreq(shape[0]))
    kx[0], ky[0] = np.inf, np.inf  # no zero-frequency row or column
    amplitude = np.outer(ky ** -(0.5 + hurst_y), kx ** -(0.5 + hurst_x))
    heights = np.fft.ifft2(amplitude * (rng.standard_normal(shape) + 1j * rng.standard_normal(shape))).real
    return heights / heights.std()


def as_matched(z_um: np.ndarray, *, seed: int, window_px: int = MATCHING_WINDOW_PX) -> np.ndarray:
    """What a window matcher returns: white noise of 2 % of the RMS added, then averaged over a
    window_px box."""
    rng = np.random.default_rng(seed)
    noisy = z_um + MATCHING_NOISE_FRACTION * z_um.std() * rng.standard_normal(z_um.shape)
    return ndimage.uniform_filter(noisy, size=window_px)


def centred_sa(z_um: np.ndarray) -> float:
    heights = z_um[np.isfinite(z_um)]
    return float(np.mean(np.abs(heights - heights.mean())))
