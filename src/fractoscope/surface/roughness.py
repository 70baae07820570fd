"""Least-squares de-tilting of height maps, Sa and Sq after it, and the fracture metrics (Hurst
exponent by the height-height correlation); the full ISO 25178-2 set is areal_parameters'."""

from __future__ import annotations

import numpy as np


def detilted_heights_um(z_um: np.ndarray) -> np.ndarray:
    """Heights (rows, cols) minus their least-squares plane; NaN stays NaN and is ignored in the fit."""
    valid = np.isfinite(z_um)
    if valid.sum() < 3:
        raise ValueError("at least three finite heights are needed to fit a plane")
    rows, cols = np.nonzero(valid)
    design = np.column_stack([rows, cols, np.ones_like(rows)]).astype(np.float64)
    coefficients, *_ = np.linalg.lstsq(design, z_um[valid].astype(np.float64), rcond=None)
    all_rows, all_cols = np.indices(z_um.shape)
    return z_um - (coefficients[0] * all_rows + coefficients[1] * all_cols + coefficients[2])


def sa_um(z_um: np.ndarray) -> float:
    """Arithmetic mean height Sa = mean |z| after plane de-tilting, µm (NaN ignored)."""
    return float(np.nanmean(np.abs(detilted_heights_um(z_um))))


def sq_um(z_um: np.ndarray) -> float:
    """Root mean square height Sq after plane de-tilting, µm (NaN ignored)."""
    return float(np.sqrt(np.nanmean(detilted_heights_um(z_um) ** 2)))


def height_height_correlation(z_um: np.ndarray, *, pixel_size_um: float, lag_count: int = 24) -> tuple[np.ndarray, np.ndarray]:
    """Height-height correlation h(r) = sqrt(<(z(x + r) - z(x))²>) along rows and columns together,
    for about `lag_count` lags spaced logarithmically from 1 pixel to a quarter of the shorter side.
    Returns (lags µm, h µm); NaN pairs are skipped."""
    z = np.asarray(z_um, np.float64)
    lags_px = np.unique(np.geomspace(1, max(min(z.shape) // 4, 2), lag_count).astype(int))
    rms = []
    for lag in lags_px:
        along_rows = (z[:, lag:] - z[:, :-lag]) ** 2
        along_cols = (z[lag:, :] - z[:-lag, :]) ** 2
        total = np.nansum(along_rows) + np.nansum(along_cols)
        count = np.isfinite(along_rows).sum() + np.isfinite(along_cols).sum()
        rms.append(np.sqrt(total / count) if count else np.nan)
    return lags_px * pixel_size_um, np.array(rms)


def fracture_metrics(z_um: np.ndarray, *, pixel_size_um: float, fit_px: tuple[float, float] | None = None) -> dict:
    """Hurst exponent H as the slope of log h(r) against log r over the fit range (default 4 pixels
    to a tenth of the shorter side, where SEM surfaces are self-affine between the probe's blur and
    the correlation length), and the fractal dimension 3 - H of the surface. Returns the fit range
    (µm) and the curve it was fitted to."""
    lags_um, rms_um = height_height_correlation(detilted_heights_um(np.asarray(z_um, np.float64)), pixel_size_um=pixel_size_um)
    low_px, high_px = fit_px or (4.0, max(min(z_um.shape) / 10.0, 8.0))
    fit = (lags_um >= low_px * pixel_size_um) & (lags_um <= high_px * pixel_size_um) & (rms_um > 0)
    if fit.sum() < 3:
        raise ValueError("the area is too small to fit a Hurst exponent (needs lags over at least 3 steps)")
    hurst = float(np.polyfit(np.log(lags_um[fit]), np.log(rms_um[fit]), 1)[0])
    return {
        "hurst_exponent": hurst,
        "hurst_fit_min_um": float(lags_um[fit].min()),
        "hurst_fit_max_um": float(lags_um[fit].max()),
        "fractal_dimension": 3.0 - hurst,
        "hhc_lag_um": lags_um.tolist(),
        "hhc_rms_um": rms_um.tolist(),
    }
