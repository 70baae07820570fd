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
