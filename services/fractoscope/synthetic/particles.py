"""Particles on a substrate, the scene of a pollen grain or a powder particle: rounded grains
(spherical caps with fine roughness) standing on a flat substrate whose surface the matcher can
barely measure (its material contrast a small share of the grains', or none), as (rows, cols)
float64 heights in µm and the material contrast to render them with (rendering's `material`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from fractoscope.synthetic.physics import DEFAULT_PHYSICS, material_contrast
from fractoscope.synthetic.surfaces import self_affine_surface


@dataclass(frozen=True)
class ParticleScene:
    """z_um: heights (rows, cols) µm, the substrate at zero where `substrate_slope` is (0, 0);
    material: relative yield change on the same grid (rendering's `material`); on_particle: where
    a grain stands; substrate_slope: the substrate's slope (along columns, along rows), µm per µm."""

    z_um: np.ndarray
    material: np.ndarray
    on_particle: np.ndarray
    substrate_slope: tuple[float, float]


def particle_scene(
    size_px: int,
    *,
    pixel_size_um: float,
    radii_um: tuple[float, ...],
    centres_px: tuple[tuple[float, float], ...],
    seed: int,
    height_ratio: float = 0.8,
    substrate_contrast: float = 0.0,
    substrate_slope: tuple[float, float] = (0.0, 0.0),
) -> ParticleScene:
    """Grains of the given radii (µm) at (col, row) centres (px), each a spherical cap standing
    `height_ratio` of its diameter high on the substrate, with 1 % of its radius of self-affine
    roughness; the substrate carries `substrate_contrast` of the grains' material contrast (0: a
    featureless background, which no matcher measures) and the given slope."""
    rows, cols = np.mgrid[0:size_px, 0:size_px].astype(np.float64)
    substrate = substrate_slope[0] * cols * pixel_size_um + substrate_slope[1] * rows * pixel_size_um
    caps = np.zeros((size_px, size_px))
    on_particle = np.zeros((size_px, size_px), bool)
    for radius_um, (col, row) in zip(radii_um, centres_px):
        # A sphere of radius R whose centre stands (2 h - 1) R above the substrate, h = height_ratio.
        centre_height_um = (2 * height_ratio - 1) * radius_um
        distance_um = np.hypot(cols - col, rows - row) * pixel_size_um
        cap = centre_height_um + np.sqrt(np.clip(radius_um**2 - distance_um**2, 0, None))
        grain = (distance_um < radius_um) & (cap > 0)
        caps = np.where(grain, np.maximum(caps, cap), caps)
        on_particle |= grain
    roughness = self_affine_surface((size_px, size_px), hurst=0.7, rms_um=0.01 * max(radii_um), seed=seed)
    z = substrate + np.where(on_particle, caps + roughness, 0.0)
    texture = material_contrast((size_px, size_px), DEFAULT_PHYSICS, seed=seed + 1)
    material = np.where(on_particle, texture, substrate_contrast * texture)
    return ParticleScene(z, material, on_particle, substrate_slope)
