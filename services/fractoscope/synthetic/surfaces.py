"""Synthetic fracture surfaces with known truth: self-affine roughness, ductile dimples and brittle
cleavage, as (rows, cols) float64 height fields in micrometres on a square pixel grid."""

from __future__ import annotations

import cv2
import numpy as np
from scipy.spatial import cKDTree


def self_affine_surface(
    shape: tuple[int, int],
    *,
    hurst: float,
    rms_um: float,
    seed: int,
    min_wavelength_px: float = 4.0,
    max_wavelength_px: float | None = None,
) -> np.ndarray:
    """Gaussian self-affine roughness by spectral synthesis: PSD ~ q^-(2 + 2 hurst), rolled off
    below `min_wavelength_px` as a finite SEM probe would and, if given, above `max_wavelength_px`
    (detail to add to a coarser surface). Returns heights with the given RMS, µm."""
    rng = np.random.default_rng(seed)
    rows, cols = shape
    q_rows = np.fft.fftfreq(rows)[:, None]
    q_cols = np.fft.rfftfreq(cols)[None, :]
    q = np.hypot(q_rows, q_cols)
    q[0, 0] = 1.0
    amplitude = q ** -(1.0 + hurst) * np.exp(-((q * min_wavelength_px) ** 2))
    if max_wavelength_px is not None:
        amplitude *= 1.0 - np.exp(-((q * max_wavelength_px) ** 2))
    amplitude[0, 0] = 0.0
    phases = rng.standard_normal(q.shape) + 1j * rng.standard_normal(q.shape)
    heights = np.fft.irfft2(amplitude * phases, s=shape)
    return heights * (rms_um / heights.std())


def dimple_surface(shape: tuple[int, int], *, dimple_radius_px: float, depth_um: float, seed: int) -> np.ndarray:
    """Ductile fracture: paraboloid dimples (pits of radius ~`dimple_radius_px`, depth ~`depth_um`)
    around random centres; where dimples overlap the deeper one wins, so neighbours meet in sharp
    rims. Fine self-affine roughness on top. Heights in µm."""
    rng = np.random.default_rng(seed)
    rows, cols = shape
    count = max(int(1.5 * rows * cols / (np.pi * dimple_radius_px**2)), 8)
    centres = rng.uniform((0, 0), (rows, cols), size=(count, 2))
    radii = dimple_radius_px * rng.uniform(0.7, 1.3, size=count)
    depths = depth_um * rng.uniform(0.7, 1.3, size=count)
    grid = np.stack(np.mgrid[0:rows, 0:cols], axis=-1).reshape(-1, 2)
    distance, nearest = cKDTree(centres).query(grid, k=min(6, count))
    pits = -depths[nearest] * np.maximum(1.0 - (distance / radii[nearest]) ** 2, 0.0)
    heights = pits.min(axis=1).reshape(shape)
    roughness = self_affine_surface(shape, hurst=0.8, rms_um=0.04 * depth_um, seed=seed + 1)
    return heights + roughness


def cleavage_surface(
    shape: tuple[int, int], *, facet_size_px: float, step_um: float, slope_um_per_px: float, seed: int
) -> np.ndarray:
    """Brittle cleavage: flat facets (Voronoi grains) at random slopes up to `slope_um_per_px`, each crossed by
    parallel river steps of height `step_um`, with fine roughness. Heights in µm."""
    rng = np.random.default_rng(seed)
    rows, cols = shape
    count = max(int(rows * cols / facet_size_px**2), 2)
    centres = rng.uniform((0, 0), (rows, cols), size=(count, 2))
    grid = np.mgrid[0:rows, 0:cols].astype(np.float64)
    _, facet = cKDTree(centres).query(grid.reshape(2, -1).T)
    facet = facet.reshape(shape)
    slopes = rng.uniform(-slope_um_per_px, slope_um_per_px, size=(count, 2))
    offsets = rng.uniform(-3 * step_um, 3 * step_um, size=count)
    step_angle = rng.uniform(0, np.pi, size=count)
    step_spacing_px = facet_size_px * rng.uniform(0.25, 0.5, size=count)
    row_px, col_px = grid
    along = row_px * np.cos(step_angle[facet]) + col_px * np.sin(step_angle[facet])
    steps = step_um * np.floor(along / step_spacing_px[facet])
    heights = offsets[facet] + (slopes[facet, 0] * row_px + slopes[facet, 1] * col_px) + steps
    heights -= heights.mean()
    return heights + self_affine_surface(shape, hurst=0.8, rms_um=0.1 * step_um, seed=seed + 1)


REFERENCE_PIXEL_SIZE_UM = 0.1
REFERENCE_SURFACES = ("self_affine", "dimples", "cleavage")


def reference_surface(kind: str, size_px: int, *, seed: int = 1) -> np.ndarray:
    """The fracture surface types that accuracy is measured on, (size_px, size_px) µm at
    REFERENCE_PIXEL_SIZE_UM: "self_affine" (H = 0.8, 2.5 µm RMS), "dimples" (ductile: pits of
    radius ~4 µm, ~3 µm deep, sharp rims) or "cleavage" (brittle: ~16 µm facets at slopes up
    to 0.2 with 0.5 µm river steps)."""
    shape = (size_px, size_px)
    if kind == "self_affine":
        return self_affine_surface(shape, hurst=0.8, rms_um=2.5, seed=seed)
    if kind == "dimples":
        return dimple_surface(shape, dimple_radius_px=40, depth_um=3.0, seed=seed)
    if kind == "cleavage":
        return cleavage_surface(shape, facet_size_px=160, step_um=0.5, slope_um_per_px=0.02, seed=seed)
    raise ValueError(f"unknown surface kind {kind!r}; known: {REFERENCE_SURFACES}")


OVERVIEW_PIXEL_SIZE_UM = 0.4
_OVERVIEW_AVERAGING = 4


def overview_dimple_surface(size_px: int, *, seed: int = 1) -> np.ndarray:
    """Ductile dimples seen at low magnification, (size_px, size_px) µm at OVERVIEW_PIXEL_SIZE_UM:
    pits of radius ~10 µm (25 px), ~3 µm deep, with sharp rims and fine roughness, made on a grid
    4× finer (REFERENCE_PIXEL_SIZE_UM) and area-averaged, as the finite probe of an overview does.
    Structure finer than a matching window is a larger share of it than of the reference dimples."""
    fine_px = _OVERVIEW_AVERAGING * size_px
    fine = dimple_surface((fine_px, fine_px), dimple_radius_px=100, depth_um=3.0, seed=seed)
    return cv2.resize(fine, (size_px, size_px), interpolation=cv2.INTER_AREA)
