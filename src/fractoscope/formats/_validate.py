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
    positive(pixel_size_um, "pixel_size_um")
    return z_um


def positive(value: float, name: str) -> None:
    """Raise ValueError naming `name` unless `value` is a positive finite number."""
    try:
        ok = math.isfinite(value) and value > 0
    except TypeError:
        ok = False
    if not ok:
        raise ValueError(f"{name}: must be positive and finite, got {value!r}")
