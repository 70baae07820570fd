"""OpenCV's semi-global block matching (StereoSGBM) in our disparity convention, and the default
matcher's starting disparities from it.

A window matcher fattens steps: next to a wall between cleavage facets its window is dominated by
the higher facet's edge and carries that facet's disparity 10-20 px onto the lower one, further
than the refinement's ±1 px data term can walk back, and now and then it settles a whole facet
on a wrong disparity. Semi-global matching sums pixel costs along eight (here five) image paths
with a penalty on every disparity change, so it places steps where the pixels put them and keeps
facets whole; it is noisy on weak texture, which its speckle filter masks. Its disparities are
therefore where the default matcher starts (`tgv_zncc`), at full resolution (measurements:
docs/matching-notes.md).

Convention: disparity d at left pixel (row, col) means it matches right pixel (row, col + d).

Reference: H. Hirschmüller, "Stereo processing by semiglobal matching and mutual information",
IEEE Trans. Pattern Anal. Mach. Intell. 30 (2008) 328-341, doi:10.1109/TPAMI.2007.1166.
"""

from __future__ import annotations

import cv2
import numpy as np

# The seed's matcher: 5 px blocks and five paths (StereoSGBM's single-pass mode), as pollen3d
# configures it; blocks of 3 or 7 px, eight paths or uniqueness 5 or 20 measured the same.
_BLOCK_PX = 5
_UNIQUENESS_PERCENT = 10
# Regions of fewer than 200 pixels joined by disparity steps of at most 2 px are speckles,
# dropped: without this filter the seed's noise on the weakly textured substrate of the pollen
# pair cost 25 of its 70 % measured pixels.
_SPECKLE_PIXELS = 200
_SPECKLE_RANGE_PX = 2
# Normalized images (unit local contrast) to grey levels: ±3.2 local standard deviations.
_GREY_PER_UNIT = 40.0
_GUIDE_MARGIN_PX = 4.0
# Below this size a seed is not worth its blocks.
_MIN_SIDE_PX = 32


def sgbm_disparity(
    left_u8: np.ndarray,
    right_u8: np.ndarray,
    *,
    min_px: float,
    max_px: float,
    block_px: int,
    mode: int = cv2.STEREO_SGBM_MODE_SGBM,
    uniqueness_percent: int = 10,
    speckle_pixels: int = 0,
    speckle_range_px: int = 0,
) -> np.ndarray:
    """StereoSGBM's disparities of a rectified uint8 pair (rows, cols each) searched over at least
    [min_px, max_px] (less the shifts that leave no block inside the image), with P1 = 8 w² and
    P2 = 32 w² for blocks of w = `block_px` and its left-right check within 1 px; (rows, cols)
    float32 px, NaN where it gives none."""
    lowest = int(np.floor(-max_px))  # OpenCV's disparity is x_left - x_right, our -d
    count = 16 * int(np.ceil((int(np.ceil(-min_px)) - lowest + 1) / 16))
    # OpenCV needs width - (lowest + count) > block_px // 2.
    count = min(count, 16 * ((left_u8.shape[1] - block_px // 2 - 1 - lowest) // 16))
    if count < 16:
        return np.full(left_u8.shape, np.nan, np.float32)
    matcher = cv2.StereoSGBM_create(
        minDisparity=lowest,
        numDisparities=count,
        blockSize=block_px,
        P1=8 * block_px**2,
        P2=32 * block_px**2,
        uniquenessRatio=uniqueness_percent,
        disp12MaxDiff=1,
        speckleWindowSize=speckle_pixels,
        speckleRange=speckle_range_px,
        mode=mode,
    )
    raw = matcher.compute(np.ascontiguousarray(left_u8), np.ascontiguousarray(right_u8)).astype(
        np.float32
    ) / np.float32(16.0)
    return np.where(raw >= lowest, -raw, np.float32(np.nan))


def seed_disparity(left: np.ndarray, right: np.ndarray, guide_px: np.ndarray) -> np.ndarray:
    """Starting disparities for the refinement of `left` against `right` ((rows, cols) float32,
    normalized to unit local contrast): semi-global matching over the range of `guide_px` (a
    window matcher's disparities, (rows, cols) px) widened by 4 px; (rows, cols) float32 px, NaN
    where it gives none (speckles, occlusions, failed left-right checks) or where the images are
    too small for it."""
    sample = guide_px[::4, ::4]  # every 16th pixel tells the range well enough
    known = sample[np.isfinite(sample)]
    if min(left.shape) < _MIN_SIDE_PX or known.size == 0:
        return np.full(left.shape, np.nan, np.float32)
    low_px, high_px = np.percentile(known, [0.1, 99.9])
    return sgbm_disparity(
        grey_levels(left),
        grey_levels(right),
        min_px=low_px - _GUIDE_MARGIN_PX,
        max_px=high_px + _GUIDE_MARGIN_PX,
        block_px=_BLOCK_PX,
        uniqueness_percent=_UNIQUENESS_PERCENT,
        speckle_pixels=_SPECKLE_PIXELS,
        speckle_range_px=_SPECKLE_RANGE_PX,
    )


def grey_levels(image: np.ndarray) -> np.ndarray:
    """A normalized image ((rows, cols) float32, zero mean and unit variance, as
    `correlation.normalized` gives it) as the uint8 grey levels OpenCV's matchers take: ±3.2
    standard deviations about 128, clipped. One mapping for both images of a pair, so that
    their grey levels stay comparable."""
    return np.clip(image * _GREY_PER_UNIT + 128.0, 0.0, 255.0).astype(np.uint8)
