"""OpenCV's StereoSGBM configured as the open SEM tools configure it, for the side-by-side tables
of `make bench`. Both take a rectified pair (parallax along rows, disparity d at left (row, col)
matching right (row, col + d), as our matchers) and return disparities in pixels, NaN where SGBM
gives none.

- 3D-SEM: 8 paths (MODE_HH), block 1, P1 = 8 w², P2 = 32 w², uniqueness 15.
- pollen3d: SGBM in both directions; the WLS filter it applies after is in opencv-contrib only,
  which cannot be installed beside our opencv-python-headless, so here the two directions are
  checked against each other (within 1 px) and averaged instead.
"""

from __future__ import annotations

import cv2
import numpy as np


def _sgbm(left, right, max_disparity_px: int, *, block_px: int, mode: int, uniqueness: int) -> np.ndarray:
    half = 16 * int(np.ceil((max_disparity_px + 1) / 16))
    matcher = cv2.StereoSGBM_create(
        minDisparity=-half, numDisparities=2 * half, blockSize=block_px, P1=8 * block_px**2, P2=32 * block_px**2,
        uniquenessRatio=uniqueness, disp12MaxDiff=1, mode=mode,
    )
    raw = matcher.compute(np.ascontiguousarray(left), np.ascontiguousarray(right)).astype(np.float32) / 16.0
    return np.where(raw > -half, -raw, np.nan)  # OpenCV's disparity is x_left - x_right


def sgbm_3d_sem(left: np.ndarray, right: np.ndarray, max_disparity_px: int) -> np.ndarray:
    """3D-SEM's StereoSGBM on uint8 images."""
    return _sgbm(left, right, max_disparity_px, block_px=1, mode=cv2.STEREO_SGBM_MODE_HH, uniqueness=15)


def sgbm_pollen3d(left: np.ndarray, right: np.ndarray, max_disparity_px: int) -> np.ndarray:
    """pollen3d's StereoSGBM in both directions (block 5, five paths), consistent within 1 px, averaged."""
    forward = _sgbm(left, right, max_disparity_px, block_px=5, mode=cv2.STEREO_SGBM_MODE_SGBM, uniqueness=10)
    backward = _sgbm(right, left, max_disparity_px, block_px=5, mode=cv2.STEREO_SGBM_MODE_SGBM, uniqueness=10)
    cols = np.arange(left.shape[1], dtype=np.float32)[None, :]
    map_cols = np.nan_to_num(cols + forward, nan=-1.0).astype(np.float32)
    map_rows = np.broadcast_to(np.arange(left.shape[0], dtype=np.float32)[:, None], left.shape)
    back = cv2.remap(np.nan_to_num(backward, nan=1e6).astype(np.float32), map_cols, np.ascontiguousarray(map_rows),
                     cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=1e6)
    consistent = np.abs(forward + back) <= 1.0
    return np.where(consistent, 0.5 * (forward - back), np.nan).astype(np.float32)
