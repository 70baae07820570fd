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
