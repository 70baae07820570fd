"""Flat textured specimens seen displaced, with the displacement known exactly: what matching and
alignment must get right whatever the relief (a pure translation tilts nothing).

Images are (rows, cols) uint8 grey images of a periodic texture; disparities follow the matchers'
convention: d at first-image pixel (row, col) means it matches second-image pixel (row, col + d).
"""

from __future__ import annotations

import numpy as np

from fractoscope.synthetic.rendering import StereoPair
from fractoscope.synthetic.surfaces import self_affine_surface

# The texture's roughness exponent and its band of wavelengths: fine, isotropic detail, its
# contrast the same whatever the image's size (without the longest limit, large images' range
# went to the coarse undulation and their detail drowned in the noise).
_TEXTURE_HURST = 0.5
_TEXTURE_MIN_WAVELENGTH_PX = 3.0
_TEXTURE_MAX_WAVELENGTH_PX = 32.0


def shifted_texture_pair(
    shape: tuple[int, int], *, shift_px: tuple[float, float], noise_fraction: float = 0.02, seed: int = 0
) -> StereoPair:
    """A periodic self-affine texture of `shape` (rows, cols) and the same texture shifted by
    `shift_px` (columns, rows), exactly (the Fourier shift theorem), each with its own Gaussian
    noise of `noise_fraction` of the grey range, as uint8; `z_seen_um` is zero (no relief). The
    second image's pixel (row + shift_rows, col + shift_cols) shows what the first's (row, col)
    does: a pure translation."""
    rows, cols = shape
    texture = self_affine_surface(
        shape,
        hurst=_TEXTURE_HURST,
        rms_um=1.0,
        seed=seed,
        min_wavelength_px=_TEXTURE_MIN_WAVELENGTH_PX,
        max_wavelength_px=_TEXTURE_MAX_WAVELENGTH_PX,
    )
    q_rows, q_cols = np.fft.fftfreq(rows)[:, None], np.fft.rfftfreq(cols)[None, :]
    phase = np.exp(-2j * np.pi * (q_cols * shift_px[0] + q_rows * shift_px[1]))
    shifted = np.fft.irfft2(np.fft.rfft2(texture) * phase, s=shape)
    rng = np.random.default_rng(seed + 1)
    low, high = np.percentile(texture, [0.5, 99.5])

    def grey(values: np.ndarray) -> np.ndarray:
        scaled = (values - low) / (high - low) + noise_fraction * rng.standard_normal(shape)
        return np.clip(np.round(scaled * 255.0), 0, 255).astype(np.uint8)

    return StereoPair(grey(texture), grey(shifted), np.zeros(shape))
