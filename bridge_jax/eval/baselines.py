"""Baselines run on the same frames as the model, at the full image resolution: zero motion, OpenCV's
semi-global block matching (disparity) in its standard form, and three OpenCV optical flows: DIS (medium
preset), DIS down to the finest scale, and DeepFlow. The first two flows and SGBM come with
`opencv-python-headless`; DeepFlow lives in OpenCV's contrib modules (`cv2.optflow`,
`opencv-contrib-python-headless`, the project's `experiments` extra), never a runtime dependency.
`opencv_method` (SGBM + DIS medium) is an evaluation method (see `bridge_jax.eval.methods`)."""

from __future__ import annotations

import math
from typing import Optional, Sequence

import cv2
import numpy as np

from bridge_jax.confidence import background_fill
from bridge_jax.eval.datasets import Frame
from bridge_jax.eval.methods import complete, frame_jobs

CONTRIB_HINT = ("OpenCV's contrib modules (cv2.optflow) are missing: install opencv-contrib-python-headless of the "
                "same version as opencv-python-headless (pip install '.[experiments]')")
"""The one line a baseline that needs OpenCV's contrib modules raises when they are not installed."""


def _gray(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY)


def _rgb_pair(a: np.ndarray, b: np.ndarray, what: str) -> None:
    for name, img in (("first", a), ("second", b)):
        if not (isinstance(img, np.ndarray) and img.dtype == np.uint8 and img.ndim == 3 and img.shape[2] == 3):
            raise ValueError(f"{what}: the {name} image must be a uint8 RGB (H, W, 3) array, got "
                             f"{getattr(img, 'dtype', type(img).__name__)} {getattr(img, 'shape', '')}")
    if a.shape != b.shape:
        raise ValueError(f"{what}: the two images differ in size, {a.shape[:2]} and {b.shape[:2]}")


fill_invalid_disparity = background_fill
"""The KITTI devkit's background interpolation (`confidence.background_fill`): the SGBM baseline's hole fill and
the test-time left-right fill share it."""


SGBM_SEARCH_DEFAULT = 192
"""`sgbm_disparity`'s search range when no maximum disparity is stated: at most 192 levels (KITTI's
customary range at its 1242 px width), at most a quarter of the image width."""


def sgbm_levels(width: int, max_disparity: Optional[float] = None) -> int:
    """The `numDisparities` (a multiple of 16) SGBM searches for an image `width` px wide: enough for
    disparities 0..`max_disparity` px (a stated maximum of the pair), else ``min(192, W/4)`` rounded down to 16
    (SGBM leaves its first `numDisparities` columns empty, so a small image needs less)."""
    if max_disparity is None:
        return int(min(SGBM_SEARCH_DEFAULT, max(16, (width // 4) // 16 * 16)))
    if not (isinstance(max_disparity, (int, float)) and math.isfinite(max_disparity) and max_disparity >= 0):
        raise ValueError(f"max_disparity: expected a disparity in pixels >= 0, got {max_disparity!r}")
    return int(16 * math.ceil((math.floor(max_disparity) + 1) / 16))


def sgbm_disparity(left: np.ndarray, right: np.ndarray, max_disparity: Optional[float] = None,
                   block_size: int = 5) -> np.ndarray:
    """OpenCV semi-global block matching in its standard form: 3-way mode, block 5, P1 = 8·3·b², P2 = 32·3·b²,
    uniquenessRatio 10, speckle window 100 and range 2, disp12MaxDiff 1; its invalid pixels (and zeros, which
    KITTI's format reads as invalid) filled by `fill_invalid_disparity`.

    Args:
      left, right: uint8 RGB ``(H, W, 3)``.
      max_disparity: the largest disparity px the pair may have, as its user knows it (a dataset's stated
        range, a rig's nearest depth): SGBM then searches 0..`max_disparity` (`sgbm_levels`); None searches
        ``min(192, W/4)`` levels.
    Returns:
      ``(H, W)`` float32 disparity in pixels (≥ 0).
    """
    _rgb_pair(left, right, "sgbm_disparity")
    levels = sgbm_levels(left.shape[1], max_disparity)
    sgbm = cv2.StereoSGBM_create(minDisparity=0, numDisparities=levels, blockSize=block_size,
                                 P1=8 * 3 * block_size ** 2, P2=32 * 3 * block_size ** 2, disp12MaxDiff=1,
                                 uniquenessRatio=10, speckleWindowSize=100, speckleRange=2,
                                 mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY)
    raw = sgbm.compute(np.ascontiguousarray(left[..., ::-1]), np.ascontiguousarray(right[..., ::-1]))
    disp = raw.astype(np.float32) / 16.0
    return fill_invalid_disparity(disp, disp > 0)


def dis_flow(image_t: np.ndarray, image_t1: np.ndarray, finest_scale: Optional[int] = None) -> np.ndarray:
    """OpenCV DIS optical flow (medium preset), ``(H, W, 2)`` float32 pixels t → t+1. `finest_scale`: the
    pyramid level its patch search stops at (the medium preset's is 1, half resolution; 0 = full resolution,
    `dis_fine_flow`)."""
    _rgb_pair(image_t, image_t1, "dis_flow")
    dis = cv2.DISOpticalFlow_create(cv2.DISOPTICAL_FLOW_PRESET_MEDIUM)
    if finest_scale is not None:
        dis.setFinestScale(int(finest_scale))
    return dis.calc(_gray(image_t), _gray(image_t1), None)


def dis_fine_flow(image_t: np.ndarray, image_t1: np.ndarray) -> np.ndarray:
    """DIS (medium preset) searching down to the full resolution (``setFinestScale(0)``): ``(H, W, 2)`` px."""
    return dis_flow(image_t, image_t1, finest_scale=0)


def has_contrib() -> bool:
    """Whether OpenCV's contrib modules (`cv2.optflow`, for `deepflow`) are installed."""
    return hasattr(cv2, "optflow") and hasattr(cv2.optflow, "createOptFlow_DeepFlow")


def deepflow(image_t: np.ndarray, image_t1: np.ndarray) -> np.ndarray:
    """OpenCV's DeepFlow (Weinzaepfel et al. 2013, `cv2.optflow.createOptFlow_DeepFlow`, default settings) on
    the grey images: ``(H, W, 2)`` float32 pixels t → t+1. Needs OpenCV's contrib modules; without them raises
    RuntimeError(`CONTRIB_HINT`)."""
    _rgb_pair(image_t, image_t1, "deepflow")
    if not has_contrib():
        raise RuntimeError(f"DeepFlow: {CONTRIB_HINT}")
    return cv2.optflow.createOptFlow_DeepFlow().calc(_gray(image_t), _gray(image_t1), None)


FLOWS = {"DIS medium": dis_flow, "DIS fine": dis_fine_flow, "DeepFlow": deepflow}
"""The OpenCV optical flows by name, each ``(image_t, image_t1) -> (H, W, 2)`` px."""


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
