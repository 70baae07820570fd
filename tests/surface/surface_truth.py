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
    """Gaussian self-affine heights (µm) by spectral synthesis, 2-D PSD ~ q^-(2 + 2H)."""
    return synthetic.self_affine_surface(shape, hurst=hurst, rms_um=rms_um, seed=seed, **options)


def as_matched(z_um: np.ndarray, *, seed: int, window_px: int = MATCHING_WINDOW_PX) -> np.ndarray:
    """What a window matcher returns: white noise of 2 % of the RMS added, then averaged over a
    window_px box."""
    rng = np.random.default_rng(seed)
    noisy = z_um + MATCHING_NOISE_FRACTION * z_um.std() * rng.standard_normal(z_um.shape)
    return ndimage.uniform_filter(noisy, size=window_px)


def centred_sa(z_um: np.ndarray) -> float:
    heights = z_um[np.isfinite(z_um)]
    return float(np.mean(np.abs(heights - heights.mean())))
