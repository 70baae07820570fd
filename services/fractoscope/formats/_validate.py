"""Argument checks that every writer of a height map makes, with errors that name the argument."""

from __future__ import annotations

import math

import numpy as np


def height_grid(z_um, pixel_size_um: float) -> np.ndarray:
    """`z_um` as a non-empty (rows, cols) real array (not copied) after checking it and the grid
    step `pixel_size_um` (µm, positive and finite)."""
    z_um = np.asarray(z_um)
    if z_um.ndim != 2 or min(z_um.shape) < 1:
        raise ValueError(f"z_um: need a non-empty (rows, cols) array, got shape {z_um.shape}")
    if not (np.issubdtype(z_um.dtype, np.floating) or np.issubdtype(z_um.dtype, np.integer)):
        raise ValueError(f"z_um: need real numbers, got dtype {z_um.dtype}")
    require_positive(pixel_size_um, "pixel_size_um")
    return z_um


def require_positive(value: float, name: str) -> None:
    """Raise ValueError naming `name` unless `value` is a positive finite number."""
    try:
        ok = math.isfinite(value) and value > 0
    except TypeError:
        ok = False
    if not ok:
        raise ValueError(f"{name}: must be positive and finite, got {value!r}")


def origin(origin_um) -> tuple[float, float]:
    """`origin_um` as (x0, y0) floats, µm, after checking it is two finite numbers."""
    try:
        x0, y0 = (float(v) for v in origin_um)
    except (TypeError, ValueError):
        raise ValueError(f"origin_um: need (x0, y0) in µm, got {origin_um!r}") from None
    if not (math.isfinite(x0) and math.isfinite(y0)):
        raise ValueError(f"origin_um: must be finite, got {origin_um!r}")
    return x0, y0
