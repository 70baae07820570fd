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

from fractoscope.stereo.semi_global import sgbm_disparity


def sgbm_3d_sem(left: np.ndarray, right: np.ndarray, max_disparity_px: int) -> np.ndarray:
    """3D-SEM's StereoSGBM on uint8 images."""
    return sgbm_disparity(
        left,
        right,
        min_px=-max_disparity_px,
        max_px=max_disparity_px,
        block_px=1,
        mode=cv2.STEREO_SGBM_MODE_HH,
        uniqueness_percent=15,
    )


def sgbm_pollen3d(left: np.ndarray, right: np.ndarray, max_disparity_px: int) -> np.ndarray:
    """pollen3d's StereoSGBM in both directions (block 5, five paths), consistent within 1 px, averaged."""
    forward, backward = (
        sgbm_disparity(
            first, second, min_px=-max_disparity_px, max_px=max_disparity_px, block_px=5, uniqueness_percent=10
        )
        for first, second in ((left, right), (right, left))
    )
    cols = np.arange(left.shape[1], dtype=np.float32)[None, :]
    map_cols = np.nan_to_num(cols + forward, nan=-1.0).astype(np.float32)
    map_rows = np.broadcast_to(np.arange(left.shape[0], dtype=np.float32)[:, None], left.shape)
    back = cv2.remap(
        np.nan_to_num(backward, nan=1e6).astype(np.float32),
        map_cols,
        np.ascontiguousarray(map_rows),
        cv2.INTER_NEAREST,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=1e6,
    )
    consistent = np.abs(forward + back) <= 1.0
    return np.where(consistent, 0.5 * (forward - back), np.nan).astype(np.float32)
