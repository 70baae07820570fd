"""Flat textured specimens seen displaced, with the displacement known exactly: what matching and
alignment must get right whatever the relief (a pure translation tilts nothing; a sinusoid of
shrinking period tells resolution against noise, as the DIC Challenge's star pattern does).

Images are (rows, cols) uint8 grey images of a periodic texture; disparities follow the matchers'
convention: d at first-image pixel (row, col) means it matches second-image pixel (row, col + d).
"""

from __future__ import annotations

from collections.abc import Callable

import cv2
import numpy as np

from fractoscope.synthetic.physics import DEFAULT_PHYSICS, material_contrast, secondary_electron_yield
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


def speckle_texture(shape: tuple[int, int], *, speckle_px: float, seed: int) -> np.ndarray:
    """A DIC speckle pattern of `shape` (rows, cols), float32 in [0, 1]: blobs about `speckle_px`
    across covering half the area (blurred white noise thresholded at its median), their edges
    softened over a tenth of that, as a lens does."""
    rng = np.random.default_rng(seed)
    blobs = cv2.GaussianBlur(rng.standard_normal(shape).astype(np.float32), (0, 0), speckle_px / 4.0)
    binary = (blobs > np.median(blobs)).astype(np.float32)
    return cv2.GaussianBlur(binary, (0, 0), speckle_px / 10.0)


def sem_texture(shape: tuple[int, int], *, pixel_size_um: float, seed: int) -> np.ndarray:
    """What an SEM shows of a rough surface seen flat on (stage tilt 0, the default physics): the
    secondary-electron shading of self-affine relief (wavelengths of 2 to 32 px, RMS slope 0.5)
    and its material contrast, `shape` (rows, cols) float32 from 0.1 to 0.9 (0.5th to 99.5th
    percentile), as `render_sem_view` scales it. For a camera's fine grid, `pixel_size_um` is the
    fine one, and the wavelengths scale with it."""
    surface = self_affine_surface(
        shape,
        hurst=0.8,
        rms_um=1.0,
        seed=seed,
        min_wavelength_px=_SEM_WAVELENGTHS_UM[0] / pixel_size_um,
        max_wavelength_px=_SEM_WAVELENGTHS_UM[1] / pixel_size_um,
    )
    slope_rows, slope_cols = np.gradient(surface, pixel_size_um)
    surface *= _SEM_RMS_SLOPE / np.sqrt(np.mean(slope_rows**2 + slope_cols**2))
    material = material_contrast(shape, DEFAULT_PHYSICS, seed=seed + 1)
    shading = secondary_electron_yield(surface, pixel_size_um, 0.0, material, DEFAULT_PHYSICS)
    low, high = np.percentile(shading, [0.5, 99.5])
    return np.clip(0.1 + 0.8 * (shading - low) / (high - low), 0.0, 1.0).astype(np.float32)


# The SEM-like texture's relief: wavelengths in µm (2 to 32 px at 0.1 µm/px, band-limited so that
# its detail does not depend on the image's size) and its RMS slope.
_SEM_WAVELENGTHS_UM = (0.2, 3.2)
_SEM_RMS_SLOPE = 0.5


def displaced_pair(
    fine_texture: np.ndarray,
    displacement_px: Callable[[np.ndarray, np.ndarray], np.ndarray],
    *,
    factor: int,
    noise_fraction: float = 0.02,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A texture and the texture displaced along rows, as a camera integrates them: both images
    are `fine_texture` ((rows·factor, cols·factor), values in [0, 1]) averaged over factor ×
    factor blocks, the second after moving it by `displacement_px(rows, cols)` (a function of
    output pixel coordinates, broadcast arrays, returning px along the row) with bicubic
    interpolation on the fine grid; each with its own Gaussian noise of `noise_fraction` of the
    grey range, uint8. Returns (first, second, disparity_px), the last the exact disparity of
    each first-image pixel ((rows, cols) float64, the matchers' convention): the second image at
    (row, col) shows the texture at (row, col − u(row, col)), so d = u(row, col + d), solved by
    fixed-point iteration (|∂u/∂col| < 1)."""
    fine_rows, fine_cols = fine_texture.shape
    rows, cols = fine_rows // factor, fine_cols // factor
    fine_r = (np.arange(fine_rows, dtype=np.float32)[:, None] + 0.5) / factor - 0.5
    fine_c = (np.arange(fine_cols, dtype=np.float32)[None, :] + 0.5) / factor - 0.5
    moved = np.float32(factor) * displacement_px(fine_r, fine_c).astype(np.float32)
    map_cols = np.arange(fine_cols, dtype=np.float32)[None, :] - moved
    map_rows = np.broadcast_to(np.arange(fine_rows, dtype=np.float32)[:, None], map_cols.shape)
    texture = fine_texture.astype(np.float32)
    second_fine = cv2.remap(
        texture, map_cols, np.ascontiguousarray(map_rows), cv2.INTER_CUBIC, borderMode=cv2.BORDER_REFLECT
    )
    rng = np.random.default_rng(seed)

    def camera(values: np.ndarray) -> np.ndarray:
        averaged = cv2.resize(values, (cols, rows), interpolation=cv2.INTER_AREA)
        noisy = averaged + noise_fraction * rng.standard_normal(averaged.shape).astype(np.float32)
        return np.clip(np.round(noisy * 255.0), 0, 255).astype(np.uint8)

    row_px = np.arange(rows, dtype=np.float64)[:, None]
    col_px = np.broadcast_to(np.arange(cols, dtype=np.float64)[None, :], (rows, cols))
    disparity = np.asarray(displacement_px(row_px, col_px), np.float64)
    for _ in range(_FIXED_POINT_STEPS):
        disparity = np.asarray(displacement_px(row_px, col_px + disparity), np.float64)
    return camera(texture), camera(second_fine), disparity


# Fixed-point steps for the displaced pair's disparity: each shrinks its error by |∂u/∂col|
# (0.31 for 0.5 px at a 10 px period), so 30 leave less than 1e-12 px.
_FIXED_POINT_STEPS = 30
