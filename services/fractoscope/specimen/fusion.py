"""One continuous surface from ROIs at several magnifications ("optical" and "digital" zoom).

Specimen frame: micrometres in the plane of the overview, x along its columns, y down its rows.
An ROI's pixel (row i, column j) lies at (origin_x + j·p, origin_y + i·p) for its pixel size p.
Wherever a finer ROI has data it wins; elsewhere coarser data is resampled. At an ROI's border its
weight ramps smoothly from 0 to 1 over `FEATHER_PX` of its pixels (from its border and, for the
heights, from any hole in its data), so neither heights nor texture step where magnifications
meet. The texture is the SEM image, known where heights are not: it blends by the image's
footprint alone, so that a hole in the heights does not blacken the picture of what is there.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from fractoscope.mesh.grid import cell_sums

FEATHER_PX = 32


@dataclass(frozen=True)
class PlacedRoi:
    """An ROI's height map and texture placed in the specimen frame.

    z_um: (rows, cols) float32 heights, µm, already aligned to its parent; NaN unknown.
    texture: (rows, cols) uint8 grey SEM image on the same grid.
    origin_um: (x, y) of pixel (0, 0) in the specimen frame, µm.
    sigma_um: (rows, cols) float32 one-sigma matching noise of the heights (the tilt error, which
        scales all heights together, left out), µm, NaN unknown; None when not known at all (a
        specimen stored before it was kept).
    max_slope: the steepest slope its pair could measure (mesh.walls; None: unknown, no walls).
    noise_um: the typical local uncertainty of its heights, µm (median of sigma_um).
    filled: (rows, cols) bool, True where a height was interpolated rather than matched (None:
        not known, a specimen stored before it was kept).
    """

    id: str
    magnification: float
    pixel_size_um: float
    origin_um: tuple[float, float]
    z_um: np.ndarray
    texture: np.ndarray
    sigma_um: np.ndarray | None = None
    max_slope: float | None = None
    noise_um: float = 0.0
    filled: np.ndarray | None = None

    @property
    def extent_um(self) -> tuple[float, float, float, float]:
        return footprint_um(self.origin_um, self.z_um.shape, self.pixel_size_um)


def footprint_um(
    origin_um: tuple[float, float], shape: tuple[int, int], pixel_size_um: float
) -> tuple[float, float, float, float]:
    """(x_min, y_min, x_max, y_max) of the pixel centres of a (rows, cols) grid whose pixel (0, 0)
    lies at `origin_um` (x, y), µm."""
    rows, cols = shape
    x0, y0 = origin_um
    return x0, y0, x0 + (cols - 1) * pixel_size_um, y0 + (rows - 1) * pixel_size_um


@dataclass(frozen=True)
class FusedSamples:
    """Fused values at sample points (any shape): heights µm (NaN unknown), texture 0-255 float32,
    the index (into FusedSurface.rois) of the ROI that contributes most (-1 where none), the
    heights' one-sigma matching noise µm, blended as the heights are (NaN unknown), and whether a
    height is mostly interpolated rather than matched (`filled`, bool: its share of filled points,
    blended as the heights are, is at least a half). A finer ROI's sigma is averaged over the
    sampling cell, not reduced by it: an upper bound for errors that correlate over a matching
    window."""

    z_um: np.ndarray
    texture: np.ndarray
    source: np.ndarray
    sigma_um: np.ndarray
    filled: np.ndarray


@dataclass(frozen=True)
class _PyramidLevel:
    z_um: np.ndarray
    texture: np.ndarray
    weight: np.ndarray
    texture_weight: np.ndarray
    sigma_um: np.ndarray
    filled_share: np.ndarray  # of the known points, NaN where none is


class FusedSurface:
    """Samples the fused surface of ROIs at any point and resolution."""

    def __init__(self, rois: Sequence[PlacedRoi]):
        if not rois:
            raise ValueError("a surface needs at least one ROI")
        # Coarse to fine, so finer data is blended over coarser.
        self.rois = sorted(rois, key=lambda roi: -roi.pixel_size_um)
        self._pyramids = [_pyramid(roi) for roi in self.rois]

    @property
    def finest_pixel_size_um(self) -> float:
        return self.rois[-1].pixel_size_um

    def rois_intersecting(self, region_um: tuple[float, float, float, float]) -> list[PlacedRoi]:
        """ROIs whose extent meets (x_min, y_min, x_max, y_max)."""
        x0, y0, x1, y1 = region_um
        return [roi for roi in self.rois if overlaps(roi.extent_um, (x0, y0, x1, y1))]

    def sample(self, x_um: np.ndarray, y_um: np.ndarray, *, cell_um: float) -> FusedSamples:
        """The surface at points (x_um, y_um) (equal shapes, specimen frame) as seen with a sampling
        cell of `cell_um`: finer ROIs are area-averaged to about that cell, coarser ones upsampled."""
        x_um = np.asarray(x_um, np.float64)
        y_um = np.asarray(y_um, np.float64)
        # OpenCV remaps at most 32767 x 32767 points: lay them out in rows of 1024.
        padding = -x_um.size % 1024
        flat_x = np.pad(x_um.ravel(), (0, padding), mode="edge").reshape(-1, 1024)
        flat_y = np.pad(y_um.ravel(), (0, padding), mode="edge").reshape(-1, 1024)
        z = np.full(flat_x.shape, np.nan, np.float32)
        texture = np.zeros(flat_x.shape, np.float32)
        pictured = np.zeros(flat_x.shape, bool)
        source = np.full(flat_x.shape, -1, np.int32)
        sigma = np.full(flat_x.shape, np.nan, np.float32)
        filled = np.zeros(flat_x.shape, np.float32)
        for index, (roi, pyramid) in enumerate(zip(self.rois, self._pyramids)):
            if not overlaps(roi.extent_um, (flat_x.min(), flat_y.min(), flat_x.max(), flat_y.max())):
                continue
            level = _pyramid_level(cell_um, roi.pixel_size_um, len(pyramid))
            scale = 2**level
            # Level pixel k averages level-0 pixels k·s .. k·s + s - 1, centred at k·s + (s - 1) / 2.
            col = ((flat_x - roi.origin_um[0]) / roi.pixel_size_um - (scale - 1) / 2) / scale
            row = ((flat_y - roi.origin_um[1]) / roi.pixel_size_um - (scale - 1) / 2) / scale
            maps = (col.astype(np.float32), row.astype(np.float32))
            arrays = pyramid[level]
            inside = _inside(maps, arrays.z_um.shape)  # every array of a level shares its grid
            roi_z = _remap(arrays.z_um, maps, inside, np.nan)
            roi_weight = _remap(arrays.weight, maps, inside, 0.0)
            roi_weight[~np.isfinite(roi_z)] = 0.0
            roi_texture = _remap(arrays.texture, maps, inside, 0.0)
            roi_texture_weight = _remap(arrays.texture_weight, maps, inside, 0.0)
            roi_sigma = _remap(arrays.sigma_um, maps, inside, np.nan)
            roi_filled = np.nan_to_num(_remap(arrays.filled_share, maps, inside, np.nan))
            unknown = ~np.isfinite(z)
            # Where nothing coarser is known, an ROI's height counts in full, up to its very edge.
            blend = np.where(unknown & np.isfinite(roi_z), 1.0, roi_weight).astype(np.float32)
            z = np.where(blend > 0, np.where(unknown, roi_z, z * (1 - blend) + np.nan_to_num(roi_z) * blend), z)
            sigma = np.where(blend > 0, np.where(unknown, roi_sigma, sigma * (1 - blend) + roi_sigma * blend), sigma)
            filled = np.where(
                blend > 0, np.where(unknown, roi_filled, filled * (1 - blend) + roi_filled * blend), filled
            )
            texture_blend = np.where(~pictured & inside, 1.0, roi_texture_weight).astype(np.float32)
            texture = texture * (1 - texture_blend) + roi_texture * texture_blend
            pictured |= inside
            source = np.where(blend >= 0.5, index, source)
        filled = (filled >= 0.5) & np.isfinite(z)
        return FusedSamples(
            *(values.ravel()[: x_um.size].reshape(x_um.shape) for values in (z, texture, source, sigma, filled))
        )


def overlaps(a, b) -> bool:
    """Whether rectangles (x_min, y_min, x_max, y_max) meet."""
    return a[0] <= b[2] and b[0] <= a[2] and a[1] <= b[3] and b[1] <= a[3]


def contains(a, b) -> bool:
    """Whether rectangle a (x_min, y_min, x_max, y_max) holds all of rectangle b."""
    return a[0] <= b[0] and a[1] <= b[1] and a[2] >= b[2] and a[3] >= b[3]


def _pyramid_level(cell_um: float, pixel_size_um: float, levels: int) -> int:
    """The coarsest pyramid level whose pixels are no larger than the sampling cell."""
    ratio = cell_um / pixel_size_um
    return int(min(max(math.floor(math.log2(ratio) + 1e-9), 0), levels - 1)) if ratio > 1 else 0


def _remap(values: np.ndarray, maps, inside: np.ndarray, fill: float) -> np.ndarray:
    """`values` bilinearly at (col, row) `maps`, `fill` where they are not `inside` the pixel
    centres' span (`_inside`): points on the outermost row or column get its values (a constant
    border would blend them with the fill, and a NaN fill made the whole border unknown)."""
    sampled = cv2.remap(values, maps[0], maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    sampled[~inside] = fill
    return sampled


def _inside(maps, shape: tuple[int, int]) -> np.ndarray:
    """Where the (col, row) `maps` lie within the span of an array's pixel centres."""
    rows, cols = shape
    return (maps[0] >= -1e-3) & (maps[0] <= cols - 1 + 1e-3) & (maps[1] >= -1e-3) & (maps[1] <= rows - 1 + 1e-3)


def _border_weight(valid: np.ndarray) -> np.ndarray:
    """0 at the edge of an ROI's measured data (its border and its holes) rising smoothly
    (smoothstep) to 1 at FEATHER_PX pixels inside, so coarser data takes over gradually."""
    padded = np.pad(valid, 1, constant_values=False).astype(np.uint8)
    distance = cv2.distanceTransform(padded, cv2.DIST_L2, cv2.DIST_MASK_PRECISE)[1:-1, 1:-1]
    ramp = np.clip((distance - 1) / FEATHER_PX, 0.0, 1.0)
    return (ramp * ramp * (3 - 2 * ramp)).astype(np.float32)


def _pyramid(roi: PlacedRoi) -> list[_PyramidLevel]:
    """Levels 0, 1, ... of 2x2 averages (unknown heights and sigmas ignored) down to about 64
    pixels; a level's pixel is unknown where less than a quarter of what it covers is known."""
    valid = np.isfinite(roi.z_um)
    with_sigma = valid & np.isfinite(roi.sigma_um) if roi.sigma_um is not None else np.zeros_like(valid)
    z, counts = np.where(valid, roi.z_um, 0).astype(np.float32), valid.astype(np.float32)
    sigma, sigma_counts = _zero_where_not(roi.sigma_um, with_sigma), with_sigma.astype(np.float32)
    filled = _zero_where_not(roi.filled, valid)
    texture, weight = roi.texture.astype(np.float32), _border_weight(valid)
    texture_weight = _border_weight(np.ones(valid.shape, bool))
    levels = [
        _PyramidLevel(
            np.where(valid, z, np.nan),
            texture,
            weight,
            texture_weight,
            np.where(with_sigma, sigma, np.nan),
            np.where(valid, filled, np.nan),
        )
    ]
    while min(counts.shape) >= 128:
        filled, _ = _halved(filled, counts)
        z, counts = _halved(z, counts)
        sigma, sigma_counts = _halved(sigma, sigma_counts)
        texture, weight, texture_weight = (
            cell_sums(values, factor=2) / 4 for values in (texture, weight, texture_weight)
        )
        kept = counts > 0.25
        levels.append(
            _PyramidLevel(
                np.where(kept, z, np.nan),
                texture,
                weight,
                texture_weight,
                np.where(kept & (sigma_counts > 0), sigma, np.nan),
                np.where(kept, filled, np.nan),
            )
        )
    return levels


def _zero_where_not(values: np.ndarray | None, known: np.ndarray) -> np.ndarray:
    """`values` as float32 where `known`, 0 elsewhere and everywhere when they are None."""
    if values is None:
        return np.zeros(known.shape, np.float32)
    return np.where(known, values, 0).astype(np.float32)


def _halved(values: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The count-weighted mean of every 2x2 block (0 where the block has no count) and the
    blocks' mean counts (float32; an odd last row or column is dropped)."""
    sums = cell_sums(values * counts, factor=2)
    counts = cell_sums(counts, factor=2) / 4
    return np.where(counts > 0, sums / 4 / np.maximum(counts, 1e-6), 0).astype(np.float32), counts
