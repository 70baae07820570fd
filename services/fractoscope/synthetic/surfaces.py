"""Synthetic surfaces with known truth: self-affine roughness, ductile dimples and brittle cleavage
(fracture surfaces), and particles, steps and pits whose walls are steeper than a stereo pair's
views (`wall_surface`), as (rows, cols) float64 height fields in micrometres on a square pixel grid."""

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
    isotropic: bool = False,
) -> np.ndarray:
    """Gaussian self-affine roughness by spectral synthesis: PSD ~ q^-(2 + 2 hurst), rolled off
    below `min_wavelength_px` as a finite SEM probe would and, if given, above `max_wavelength_px`
    (detail to add to a coarser surface). Returns heights with the given RMS, µm.

    `isotropic`: statistically isotropic down to the longest wavelengths, for scaling tests.
    irfft2 keeps only the Hermitian half of a half-plane spectrum's zero (and Nyquist) column, so
    there the modes that vary along columns alone lose half their power, and column profiles miss
    up to a tenth of their longest waves and read H about 0.04 low; `isotropic` gives those two
    columns sqrt(2) more amplitude."""
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
    if isotropic:
        amplitude[:, 0] *= np.sqrt(2.0)
        if cols % 2 == 0:
            amplitude[:, -1] *= np.sqrt(2.0)
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
# Relief with walls steeper than a stereo pair's views (`wall_surface`).
WALL_MORPHOLOGIES = ("particles", "sharp_steps", "rounded_steps", "pits")


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


def surface(kind: str, size_px: int, *, seed: int = 1) -> np.ndarray:
    """A surface of any kind known here, (size_px, size_px) µm at REFERENCE_PIXEL_SIZE_UM: one of
    REFERENCE_SURFACES (`reference_surface`) or WALL_MORPHOLOGIES (`wall_surface`)."""
    if kind in WALL_MORPHOLOGIES:
        return wall_surface(kind, size_px, pixel_size_um=REFERENCE_PIXEL_SIZE_UM, seed=seed)
    if kind in REFERENCE_SURFACES:
        return reference_surface(kind, size_px, seed=seed)
    raise ValueError(f"unknown surface kind {kind!r}; known: {REFERENCE_SURFACES + WALL_MORPHOLOGIES}")


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


def wall_surface(
    kind: str,
    size_px: int,
    *,
    pixel_size_um: float = REFERENCE_PIXEL_SIZE_UM,
    wall_um: float = 12.0,
    seed: int = 1,
) -> np.ndarray:
    """Relief with walls steeper than any view of a stereo pair sees, (size_px, size_px) µm on a
    substrate of fine self-affine roughness (0.1 µm RMS):

    - "particles": rounded particles of radius 50-100 px on the substrate, each a vertical wall
      whose top edge is rounded with a radius of 0.8-1 times the particle's (1: a ball's cap on a
      stem), `wall_um` high in all (0.8-1.2 times);
    - "sharp_steps": terraces between straight steps `wall_um` high (0.8-1.2 times), at up to 30°
      from the columns, rising and falling in turn, with sharp edges;
    - "rounded_steps": the same steps with their top edges rounded (radius 3-5 µm);
    - "pits": circular pits of radius 35-70 px, `wall_um` deep (0.8-1.2 times), whose rims are
      rounded (radius 3-5 µm).

    The rounded edges of particles, rounded steps and pits give a view an occluding contour;
    sharp edges do not (`stereo.occlusion`)."""
    if kind not in WALL_MORPHOLOGIES:
        raise ValueError(f"unknown wall morphology {kind!r}; known: {WALL_MORPHOLOGIES}")
    rng = np.random.default_rng(seed)
    shape = (size_px, size_px)
    substrate = self_affine_surface(shape, hurst=0.8, rms_um=0.1, seed=seed + 1)
    grid_px = np.mgrid[0:size_px, 0:size_px].astype(np.float64)
    if kind.endswith("steps"):
        relief = _steps(grid_px, rng, pixel_size_um, wall_um, rounded=kind == "rounded_steps")
    else:
        relief = _discs(grid_px, rng, pixel_size_um, wall_um, pits=kind == "pits")
    return substrate + relief


def _discs(grid_px: np.ndarray, rng: np.random.Generator, pixel_size_um: float, wall_um: float, *, pits: bool):
    """Particles (raised discs whose top edge is rounded) or pits (sunk discs whose rim is
    rounded) that do not overlap, on the (2, rows, cols) pixel grid `grid_px`; heights in µm."""
    size_px = grid_px.shape[1]
    radius_range_px = (35.0, 70.0) if pits else (50.0, 100.0)
    heights = np.zeros(grid_px.shape[1:])
    placed: list[tuple[float, float, float]] = []
    for _ in range(200):
        radius_px = rng.uniform(*radius_range_px)
        centre = rng.uniform(0.6 * radius_px, size_px - 0.6 * radius_px, size=2)
        if any(np.hypot(*(centre - other)) < radius_px + other_radius + 8 for *other, other_radius in placed):
            continue
        placed.append((*centre, radius_px))
        height_um = wall_um * rng.uniform(0.8, 1.2)
        inside_px = radius_px - np.hypot(grid_px[0] - centre[0], grid_px[1] - centre[1])
        if pits:
            rim_um = rng.uniform(3.0, 5.0)
            heights = np.minimum(heights, _rounded_edge(-inside_px * pixel_size_um, height_um, rim_um) - height_um)
        else:
            edge_um = radius_px * pixel_size_um * rng.uniform(0.8, 1.0)
            heights = np.maximum(heights, _rounded_edge(inside_px * pixel_size_um, height_um, edge_um))
    return heights


def _steps(grid_px: np.ndarray, rng: np.random.Generator, pixel_size_um: float, wall_um: float, *, rounded: bool):
    """Straight steps across the (2, rows, cols) pixel grid `grid_px`, one per ~100 columns, all
    at one angle up to 30° from the columns (±2° each, so that they do not cross), rising and
    falling in turn along the rows (the first one either way); heights in µm."""
    size_px = grid_px.shape[1]
    heights = np.zeros(grid_px.shape[1:])
    side, angle_deg = rng.choice((-1.0, 1.0)), rng.uniform(-30.0, 30.0)
    for position_px in np.linspace(0.0, size_px, max(size_px // 100, 1) + 2)[1:-1]:
        angle = np.radians(angle_deg + rng.uniform(-2.0, 2.0))
        offset_px = position_px + rng.uniform(-15.0, 15.0)
        across_px = (grid_px[1] - offset_px) * np.cos(angle) - (grid_px[0] - size_px / 2) * np.sin(angle)
        across_px *= side
        side = -side
        edge_um = rng.uniform(3.0, 5.0) if rounded else 0.0
        heights += _rounded_edge(across_px * pixel_size_um, wall_um * rng.uniform(0.8, 1.2), edge_um)
    return heights


def _rounded_edge(distance_um: np.ndarray, height_um: float, edge_radius_um: float) -> np.ndarray:
    """A wall `height_um` high along distance 0, raised where `distance_um` > 0: vertical from the
    ground up to `edge_radius_um` below its top, then rounding off with that radius onto the flat
    top (0: a sharp edge). Heights in µm, 0 on the ground."""
    radius_um = min(edge_radius_um, height_um)
    into_um = np.clip(distance_um, 0.0, radius_um)
    rounding = np.sqrt(np.maximum(radius_um**2 - (radius_um - into_um) ** 2, 0.0))
    return np.where(distance_um > 0.0, height_um - radius_um + rounding, 0.0)
