"""Which way up the relief is, from the images themselves.

Parallel projection cannot tell a relief from its mirror image: heights z seen at tilts
(t1, t2) give the same parallax as heights -z seen at (-t1, -t2), and a stage's tilt sign, an
image order or a tilt axis given 180° off all make that swap. Nor can the secondary-electron
yield's change with the tilt: under the secant law the yield depends on the incidence angle
|slope angle - tilt| only, which the swap leaves as it is. What breaks the symmetry:

- The detector's lighting. An Everhart-Thornley detector beside the column collects more from
  facets that face it, so the image looks lit from the detector's side (the light-optical
  analogy, Goldstein et al., Scanning Electron Microscopy and X-Ray Microanalysis, 4th ed.,
  doi:10.1007/978-1-4939-6676-9, ch. 7). Facets rising towards the detector are brighter under
  the true relief and darker under its mirror image. The detector's side in the image is an
  instrument setting (by convention at the top, so that relief reads as lit from above); it is
  an input here (relative to the tilt axis), and the cue is used along the tilt axis only, where the secant law adds no
  brightness that is linear in the slope.
- Occlusion: a smooth occluder is seen compressed to nothing just before the band the other view
  cannot see (`stereo.occlusion`, geometry alone, whatever the detector; it decides only where
  many rounded occluders stand clear of one another).

The image is split into blocks, each block's brightness regressed on the heights' slopes, and a
sign test over the blocks tells whether the slopes along the detector's direction brighten the
image as the heights say (a few blocks on one surface feature cannot outvote the rest).
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum

import cv2
import numpy as np
from scipy.stats import binomtest

# The evidence decides when chance would give so lopsided a vote with less than this probability.
DECISIVE_P_VALUE = 1e-3
# Nor does a vote less lopsided than this (|agreeing - disagreeing| / all: 90 % of the blocks on
# one side). The blocks of a surface whose slopes lie in few large facets (cleavage) are not
# independent, and their sign test alone is overconfident: wrong verdicts there reached 0.77,
# right ones on self-affine and dimpled surfaces 0.85 or more (docs/matching-notes.md).
MIN_STRENGTH = 0.8
# Fewer blocks than this decide nothing, whatever their balance.
MIN_BLOCKS = 8
# Blocks per image side (fewer where a block would be under _MIN_BLOCK_PX).
_BLOCKS_PER_SIDE = 8
_MIN_BLOCK_PX = 32
# Smoothing of the image and the heights before slopes are taken, px: the matcher's noise is
# largest at the pixel scale.
_SMOOTHING_PX = 3.0
# A block votes only with heights over this share of its pixels.
_MIN_MEASURED_SHARE = 0.5
# A block votes only where its slope coefficient stands out of its noise by this many sigmas.
_MIN_T = 2.0
# The detector must lie this far off the tilt direction for its lighting to be told from the
# secant law's (|sin| of the angle between them).
_MIN_OFF_TILT_DIRECTION = 0.5
# Where the detector lies by default, degrees counter-clockwise from the tilt axis's direction as
# displayed: along the axis, on the side it points to (the top of the image for a vertical axis at
# 90°). Scan rotation turns the image of the tilt axis and of the detector, both fixed in the
# chamber, together.
DEFAULT_DETECTOR_FROM_TILT_AXIS_DEG = 0.0


class ReliefSignMode(str, Enum):
    """How the sign of the heights is chosen: from the images where they tell it (AUTO), or as
    the tilts as given say (NOMINAL), or the mirror image of that (INVERTED)."""

    AUTO = "auto"
    NOMINAL = "nominal"
    INVERTED = "inverted"


@dataclass(frozen=True)
class ReliefSign:
    """The images' verdict on the relief's sign under the tilts as given.

    inverted: the images show the mirrored relief (meaningful where `decided`).
    decided: the evidence is decisive (p_value under DECISIVE_P_VALUE from MIN_BLOCKS or more
        blocks, |strength| at least MIN_STRENGTH).
    cue: "shading" (the detector's lighting), "occlusion" (`stereo.occlusion`) or "none" where
        none could be used (`reason`).
    strength: the votes' balance, (agreeing - disagreeing) / all, -1 to 1 (1: every vote
        agrees with the tilts as given).
    blocks: the number of votes: image blocks (shading) or walls (occlusion).
    p_value: the chance of so lopsided a vote if the blocks told nothing (two-sided sign test).
    reason: why nothing was decided, in one sentence ("" when decided).
    """

    inverted: bool
    decided: bool
    cue: str
    strength: float
    blocks: int
    p_value: float
    reason: str

    @property
    def confidence(self) -> float:
        """1 - p_value: how far the vote is from chance, 0 to 1."""
        return 1.0 - self.p_value


def undetermined(reason: str) -> ReliefSign:
    """A verdict that decides nothing, for `reason`."""
    return ReliefSign(False, False, "none", 0.0, 0, 1.0, reason)


def relief_sign_from_shading(image: np.ndarray, z_px: np.ndarray, *, detector_azimuth_deg: float) -> ReliefSign:
    """Whether `z_px` (rows, cols, heights in pixels as the tilts given say, NaN where unknown)
    or its mirror image is the relief that `image` (rows, cols, the reference view, grey) shows
    lit by a detector at `detector_azimuth_deg` (counter-clockwise from the column axis as
    displayed; both arrays turned so that the tilt axis runs along the columns)."""
    towards_top = float(np.sin(np.radians(detector_azimuth_deg)))
    if not np.isfinite(towards_top):
        return undetermined("the detector's side in the image is not known")
    if abs(towards_top) < _MIN_OFF_TILT_DIRECTION:
        return undetermined("the detector lies along the tilt direction, where its lighting and the tilt's look alike")
    coefficients = _block_row_slope_coefficients(image, z_px)
    # A facet rising towards larger rows leans its normal towards the top of the image: facing
    # a detector at the top, it is the brighter the steeper it rises.
    agreeing = int(np.sum(coefficients * towards_top > 0))
    disagreeing = int(np.sum(coefficients * towards_top < 0))
    votes = agreeing + disagreeing
    return sign_test(
        agreeing,
        disagreeing,
        cue="shading",
        too_few=f"too little of the image has heights ({votes} blocks of {MIN_BLOCKS} needed)",
        ambiguous=f"the shading is ambiguous ({agreeing} of {votes} image blocks agree with the tilts)",
    )


def sign_test(agreeing: int, disagreeing: int, *, cue: str, too_few: str, ambiguous: str) -> ReliefSign:
    """The verdict of independent votes for (`agreeing`) and against the tilts as given: decided
    at p < DECISIVE_P_VALUE (two-sided sign test) with MIN_BLOCKS votes or more and |strength|
    at least MIN_STRENGTH; `too_few` and `ambiguous` are the reasons where it is not."""
    votes = agreeing + disagreeing
    if votes < MIN_BLOCKS:
        return undetermined(too_few)
    p_value = float(binomtest(agreeing, votes, 0.5).pvalue)
    strength = (agreeing - disagreeing) / votes
    decided = p_value < DECISIVE_P_VALUE and abs(strength) >= MIN_STRENGTH
    return ReliefSign(disagreeing > agreeing, decided, cue, strength, votes, p_value, "" if decided else ambiguous)


def _block_row_slope_coefficients(image: np.ndarray, z_px: np.ndarray) -> np.ndarray:
    """Per block with enough heights: the coefficient of the heights' slope along the rows in a
    least-squares fit of the image's band-passed brightness to both slopes and a constant."""
    known = np.isfinite(z_px)
    weight = cv2.GaussianBlur(known.astype(np.float32), (0, 0), _SMOOTHING_PX)
    z = cv2.GaussianBlur(np.where(known, z_px, 0).astype(np.float32), (0, 0), _SMOOTHING_PX)
    z /= np.maximum(weight, np.float32(1e-3))
    grey = cv2.GaussianBlur(image.astype(np.float32), (0, 0), _SMOOTHING_PX)
    grey -= cv2.GaussianBlur(grey, (0, 0), 8 * _SMOOTHING_PX)
    slope_rows, slope_cols = np.gradient(z)
    usable = weight > 0.9
    block = max(_MIN_BLOCK_PX, min(image.shape) // _BLOCKS_PER_SIDE)
    coefficients = []
    for top in range(0, image.shape[0] - block + 1, block):
        for left in range(0, image.shape[1] - block + 1, block):
            window = (slice(top, top + block), slice(left, left + block))
            inside = usable[window]
            if inside.mean() < _MIN_MEASURED_SHARE:
                continue
            design = np.column_stack([slope_cols[window][inside], slope_rows[window][inside], np.ones(inside.sum())])
            solution, residual, rank, _ = np.linalg.lstsq(design, grey[window][inside], rcond=None)
            if rank < 3 or not residual.size:
                continue
            # The coefficient's variance, inflated as if one sample per smoothed area were independent.
            count = inside.sum()
            correlated = count / max(count / (2 * _SMOOTHING_PX) ** 2, 1.0)
            variance = residual[0] / (count - 3) * np.linalg.inv(design.T @ design)[1, 1] * correlated
            if abs(solution[1]) > _MIN_T * np.sqrt(variance):
                coefficients.append(solution[1])
    return np.asarray(coefficients)
