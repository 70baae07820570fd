"""The physics of a rendered SEM view, configurable: the secondary-electron yield law, the
edge contrast, the detector's position and the material contrast. `DEFAULT_PHYSICS` is the
renderer the matching methods were tuned on; `PHYSICS_VARIANTS` are renderers they were not,
to test that nothing learned from the pair assumes the default's shading.

Geometry: surface normals are (column, row, up) unit vectors of a (rows, cols) height field; the
beam comes down the stage tilt about the column axis. Yield laws of the incidence angle θ between
beam and normal, with a share `se2_fraction` that does not depend on it:

- "secant": se2 + (1 - se2) sec^k θ, the SE1 law (brighter on steep facets);
- "lambert": se2 + (1 - se2) cos^k θ, darker on steep facets, as a backscatter-like signal;
- "tanh": se2 + (1 - se2) (1 + tanh(k (sec θ - 1))), steep facets saturating;
- "none": no dependence on θ at all, so the image shows only material contrast (and edges and
  the detector's view, if those are set).

The edge contrast brightens convex relief, (1 + edge_contrast tanh(κ ℓ)), κ the convex curvature
(minus the Laplacian, clipped at 0) of the relief averaged over the SE2 range ℓ = `edge_length_um`. The
detector (an Everhart-Thornley detector to one side) weights each facet by
(1 - strength) + strength max(detector · normal, 0); it stays put either on the specimen (the
tuning renderer) or in the chamber, as in a microscope, where the stage's tilt turns it about the
tilt axis in the specimen's frame, so that the two views see each facet's lighting differently.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np

from fractoscope.synthetic.surfaces import self_affine_surface

YIELD_LAWS = ("secant", "lambert", "tanh", "none")


@dataclass(frozen=True)
class SemPhysics:
    """How a surface's shape and material make an SEM image (see the module docstring).

    yield_law: one of YIELD_LAWS; yield_exponent: its k; se2_fraction: share of the yield that
    does not depend on the incidence, 0 to 1.
    edge_contrast: relative brightening of convex edges (0: none); edge_length_um: SE2 range, µm.
    detector_azimuth_deg: where the detector lies as seen in the image, counter-clockwise from
    the column axis as displayed (90: towards the top of the image); detector_elevation_deg: its
    elevation above the stage; detector_strength: how much of the signal depends on the facet
    facing it, 0 to 1; detector_in_chamber: whether those angles are the chamber's (the stage
    tilts under the detector) rather than the specimen's.
    material_rms: RMS of the relative yield change of the material contrast; material_hurst and
    material_min_wavelength_px (on the 2x supersampled rendering grid): its spectrum.
    """

    yield_law: str = "secant"
    yield_exponent: float = 1.0
    se2_fraction: float = 0.5
    edge_contrast: float = 0.0
    edge_length_um: float = 0.2
    detector_azimuth_deg: float = 90.0
    detector_elevation_deg: float = field(default=float(np.degrees(np.arctan2(0.8, 0.6))))
    detector_strength: float = 0.45
    detector_in_chamber: bool = False
    material_rms: float = 0.15
    material_hurst: float = 0.3
    material_min_wavelength_px: float = 4.0

    def __post_init__(self):
        if self.yield_law not in YIELD_LAWS:
            raise ValueError(f"unknown yield_law {self.yield_law!r}; known: {YIELD_LAWS}")
        if not 0.0 <= self.se2_fraction <= 1.0 or not 0.0 <= self.detector_strength <= 1.0:
            raise ValueError("se2_fraction and detector_strength must lie in [0, 1]")

    @property
    def detector_from_tilt_axis_deg(self) -> float:
        """Where the detector lies as MatchingOptions.detector_from_tilt_axis_deg takes it (from the
        vertical tilt axis of these renderings), as a user who knows the microscope would give it."""
        return self.detector_azimuth_deg - 90.0


DEFAULT_PHYSICS = SemPhysics()

# Renderers other than the tuning one: other yield laws, exponents, detector placements and textures.
PHYSICS_VARIANTS = {
    "secant_k1.6_side_detector": SemPhysics(
        yield_exponent=1.6, se2_fraction=0.3, detector_azimuth_deg=180.0, detector_elevation_deg=40.0,
        detector_strength=0.6, detector_in_chamber=True,
    ),
    "lambert": SemPhysics(
        yield_law="lambert", se2_fraction=0.4, detector_azimuth_deg=45.0, detector_strength=0.3, material_rms=0.1,
        detector_in_chamber=True,
    ),
    "tanh_edges": SemPhysics(
        yield_law="tanh", yield_exponent=2.0, edge_contrast=0.8, detector_azimuth_deg=270.0, detector_in_chamber=True
    ),
    "secant_k0.6_coarse_texture": SemPhysics(
        yield_exponent=0.6, se2_fraction=0.6, material_rms=0.3, material_hurst=0.6, material_min_wavelength_px=8.0
    ),
    "texture_only": SemPhysics(yield_law="none", detector_strength=0.0, material_rms=0.3),
}  # fmt: skip


def material_contrast(shape: tuple[int, int], physics: SemPhysics, *, seed: int) -> np.ndarray:
    """A material contrast (relative yield change) of `shape` (rows, cols) on the rendering grid."""
    return self_affine_surface(
        shape,
        hurst=physics.material_hurst,
        rms_um=physics.material_rms,
        seed=seed,
        min_wavelength_px=physics.material_min_wavelength_px,
    )


def secondary_electron_yield(
    z_um: np.ndarray, pixel_size_um: float, tilt_rad: float, material: np.ndarray, physics: SemPhysics
) -> np.ndarray:
    """The signal (rows, cols) of surface `z_um` (rows, cols, µm) under a beam tilted by `tilt_rad`
    about the column axis: the yield law of the incidence, times the edge contrast, the
    detector's view of the facet and (1 + `material`)."""
    slope_rows, slope_cols = np.gradient(z_um, pixel_size_um)
    normal = np.stack([-slope_cols, -slope_rows, np.ones_like(z_um)])
    normal /= np.linalg.norm(normal, axis=0)
    beam = np.array([-np.sin(tilt_rad), 0.0, np.cos(tilt_rad)])
    cos_incidence = np.clip(np.tensordot(beam, normal, axes=1), 0.15, 1.0)
    facing = np.clip(np.tensordot(_detector_direction(physics, tilt_rad), normal, axes=1), 0.0, 1.0)
    signal = _incidence_yield(cos_incidence, physics) * (
        (1.0 - physics.detector_strength) + physics.detector_strength * facing
    )
    if physics.edge_contrast:
        signal *= 1.0 + physics.edge_contrast * _convexity(z_um, pixel_size_um, physics.edge_length_um)
    return signal * (1.0 + material)


def _incidence_yield(cos_incidence: np.ndarray, physics: SemPhysics) -> np.ndarray:
    se2, k = physics.se2_fraction, physics.yield_exponent
    if physics.yield_law == "secant":
        return (1.0 - se2) / cos_incidence**k + se2
    if physics.yield_law == "lambert":
        return (1.0 - se2) * cos_incidence**k + se2
    if physics.yield_law == "tanh":
        return (1.0 - se2) * (1.0 + np.tanh(k * (1.0 / cos_incidence - 1.0))) + se2
    return np.ones_like(cos_incidence)


def _detector_direction(physics: SemPhysics, tilt_rad: float) -> np.ndarray:
    """Unit vector (column, row, up) towards the detector in the specimen's frame, rows growing
    downwards in the image; a detector in the chamber turned as the beam is by the tilt. Rounded
    to 12 decimals so that an azimuth along an axis gives exact zeros."""
    azimuth, elevation = np.radians(physics.detector_azimuth_deg), np.radians(physics.detector_elevation_deg)
    column, row, up = np.cos(elevation) * np.cos(azimuth), -np.cos(elevation) * np.sin(azimuth), np.sin(elevation)
    if physics.detector_in_chamber:  # the chamber's up is the beam, (-sin t, 0, cos t) here
        column, up = (
            column * np.cos(tilt_rad) - up * np.sin(tilt_rad),
            column * np.sin(tilt_rad) + up * np.cos(tilt_rad),
        )
    return np.array([column, row, up]).round(12)


def _convexity(z_um: np.ndarray, pixel_size_um: float, edge_length_um: float) -> np.ndarray:
    """tanh(κ ℓ), κ the convex curvature (1/µm, minus the Laplacian clipped at 0) of the relief
    averaged over ℓ = `edge_length_um`: 0 on flat or concave relief, towards 1 on sharp rims."""
    relief_um = cv2.GaussianBlur(z_um, (0, 0), edge_length_um / pixel_size_um)
    curvature = np.maximum(-cv2.Laplacian(relief_um, cv2.CV_64F) / pixel_size_um**2, 0.0)
    return np.tanh(curvature * edge_length_um)
