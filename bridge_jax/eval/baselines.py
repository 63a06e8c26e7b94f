"""Baselines run on the same frames as the model, at the full image resolution: zero motion, and OpenCV's
semi-global block matching (disparity) and DIS optical flow. Both are evaluation methods (see
`bridge_jax.eval.methods`)."""

from __future__ import annotations

from typing import Optional, Sequence

import cv2
import numpy as np

from bridge_jax.eval.datasets import Frame
from bridge_jax.eval.methods import complete, frame_jobs


def _gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def fill_invalid_disparity(disp: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill holes row by row like the KITTI devkit's background interpolation: a hole between two valid pixels
    gets the smaller (farther) of their disparities, a hole at a row end the nearest valid value; rows without
    any valid pixel become 0.

    Args:
      disp: ``(H, W)`` disparity px; valid: ``(H, W)`` bool.
    Returns:
      ``(H, W)`` float32, dense.
    """
    h, w = disp.shape
    cols = np.arange(w)[None, :].repeat(h, 0)
    left_idx = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    right_idx = np.minimum.accumulate(np.where(valid, cols, w)[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(h)[:, None]
    left = np.where(left_idx >= 0, disp[rows, np.clip(left_idx, 0, w - 1)], np.inf)
    right = np.where(right_idx < w, disp[rows, np.clip(right_idx, 0, w - 1)], np.inf)
    filled = np.minimum(left, right)
    filled = np.where(np.isfinite(filled), filled, 0.0)
    return np.where(valid, disp, filled).astype(np.float32)


def sgbm_disparity(left: np.ndarray, right: np.ndarray, num_disparities: Optional[int] = None,
                   block_size: int = 5) -> np.ndarray:
    """OpenCV semi-global block matching (3-way), holes filled as the KITTI devkit does.

    Args:
      left, right: uint8 RGB ``(H, W, 3)``.
      num_disparities: search range (multiple of 16); default ``min(192, W/4)`` rounded down to 16 (192 at
        KITTI width; SGBM leaves the first ``num_disparities`` columns empty, so small images need less).
    Returns:
      ``(H, W)`` float32 disparity in pixels (≥ 0).
    """
    if num_disparities is None:
        num_disparities = int(min(192, max(16, (left.shape[1] // 4) // 16 * 16)))
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=num_disparities, blockSize=block_size,
                                 P1=8 * 3 * block_size ** 2, P2=32 * 3 * block_size ** 2, disp12MaxDiff=1,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(np.ascontiguousarray(left[..., ::-1]), np.ascontiguousarray(right[..., ::-1]))
    disp = raw.astype(np.float32) / 16.0
    return fill_invalid_disparity(disp, disp > 0)


def dis_flow(image_t: np.ndarray, image_t1: np.ndarray) -> np.ndarray:
    """OpenCV DIS optical flow (medium preset), ``(H, W, 2)`` float32 pixels t → t+1."""
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    return dis.calc(_gray(image_t), _gray(image_t1), None)


def zero_method(frames: Sequence[Frame]) -> list[dict[str, np.ndarray]]:
    """Zero motion: flow 0 and disparity 0 (depth then clamps to 80 m)."""
    out = []
    for f in frames:
        h, w = f.size
        p = {task: (np.zeros((h, w, 2), np.float32) if task == "flow" else np.zeros((h, w), np.float32))
             for task, _, _ in frame_jobs(f)}
        out.append(complete(p))
    return out


def opencv_method(frames: Sequence[Frame]) -> list[dict[str, np.ndarray]]:
    """Classical baseline: StereoSGBM for disparity, DIS for optical flow, at the full image resolution."""
    out = []
    for f in frames:
        p = {}
        for task, a, b in frame_jobs(f):
            ia, ib = f.images[a], f.images[b]
            p[task] = dis_flow(ia, ib) if task == "flow" else sgbm_disparity(ia, ib)
        out.append(complete(p))
    return out
