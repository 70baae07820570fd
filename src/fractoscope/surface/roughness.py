"""Areal surface texture parameters (ISO 25178-2) of height maps after least-squares de-tilting."""

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


def areal_parameters(z_um: np.ndarray, *, pixel_size_um: float) -> dict[str, float]:
    """ISO 25178-2 parameters of a height map (rows, cols) µm with square pixels after plane
    de-tilting; NaN points are left out (gradients and areas use only complete cells).
    Keys: Sa, Sq, Sp, Sv, Sz (µm), Ssk, Sku, Sdq (dimensionless), Sdr (percent)."""
    z = detilted_heights_um(np.asarray(z_um, np.float64))
    heights = z[np.isfinite(z)]
    sq = float(np.sqrt(np.mean(heights**2)))
    sp, sv = float(heights.max()), float(-heights.min())
    slope_x = np.diff(z, axis=1) / pixel_size_um
    slope_y = np.diff(z, axis=0) / pixel_size_um
    return {
        "Sa": float(np.mean(np.abs(heights))),
        "Sq": sq,
        "Ssk": float(np.mean(heights**3) / sq**3) if sq > 0 else 0.0,
        "Sku": float(np.mean(heights**4) / sq**4) if sq > 0 else 0.0,
        "Sp": sp,
        "Sv": sv,
        "Sz": sp + sv,
        "Sdq": float(np.sqrt(np.nanmean(slope_x**2) + np.nanmean(slope_y**2))),
        "Sdr": _developed_area_ratio_percent(z, pixel_size_um),
    }


def _developed_area_ratio_percent(z_um: np.ndarray, pixel_size_um: float) -> float:
    """Sdr from ISO 25178-2 (2021) D.3: each cell's area is the mean of its two triangulations,
    i.e. half the summed areas of its four corner triangles; complete cells only."""
    step = pixel_size_um
    dz_x = np.diff(z_um, axis=1)
    dz_y = np.diff(z_um, axis=0)
    edges_x = ((step * dz_x[:-1, :]) ** 2, (step * dz_x[1:, :]) ** 2)  # bottom, top edge of each cell
    edges_y = ((step * dz_y[:, :-1]) ** 2, (step * dz_y[:, 1:]) ** 2)  # left, right edge
    flat = step**4
    corners = sum(np.sqrt(ex + ey + flat) for ex in edges_x for ey in edges_y)
    cell_area = 0.25 * corners
    complete = np.isfinite(cell_area)
    return float((cell_area[complete].sum() / (complete.sum() * step**2) - 1.0) * 100.0)


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
