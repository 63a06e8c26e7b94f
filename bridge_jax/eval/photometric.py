"""Validation on your own held-out stereo video, without ground truth: photometric reconstruction error.

    cycles = val_cycles(run.data, run.height, run.width, max_cycles=32)     # (N, 4, H, W, 3) float32
    metrics, panel = photometric_validation(predictor, cycles, batch=8)

Per cycle (left_t, right_t, left_t1, right_t1) the predictor gives, at its working size, the stereo map
left_t → right_t (u = −disparity), the stereo map right_t → left_t (for the left-right check) and the flow
left_t → left_t1. The second image of each pair is warped into the first (`geometry.warp`, the training loss's
warp) and compared with it:

  {task}_photo_l1          mean |W(second, D) − first| over pixels and channels (images in [0, 1])
  {task}_photo_ssim_l1     alpha (1 − SSIM)/2 + (1 − alpha) L1 (`losses.photometric_loss`, alpha = 0.85: the
                           training loss's reconstruction term, without occlusion masks)
  zero_{task}_photo_*      the same for zero motion (D = 0: the second image as it is)
  {task}_photo_*_vs_zero   model / zero motion (1 = no better than not moving; lower is better)
  stereo_lr_consistency_px mean |D_lr + W(D_rl, D_lr)| in working pixels (0 for consistent disparities)
  disp_mean_px, flow_mean_px  mean disparity (−u of left → right) and mean flow length, working pixels
  *_input_px               the three above in pixels of the frames as read (the input resolution, each cycle's
                           own: `HeldOutCycles.input_sizes`): horizontal components scaled by input width /
                           working width, vertical ones by input height / working height
  num_cycles
with task = "stereo" (left_t → right_t) or "flow" (left_t → left_t1). Means run over the pixels inside the
training loss's border band (ceil(0.1 H) px on every side are left out: warps read clamped border pixels there,
and pixels that leave the view cannot be reconstructed by any map), per cycle, then over cycles; ratios are
ratios of those means. Nothing here needs ground truth, so any held-out frames of the user's own video work.
`describe(metrics)` words them for the training's validation line.
"""
from __future__ import annotations

import functools
import logging
import math
import os
from typing import Any, Optional

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import geometry, losses, visualize
from bridge_jax.data import folders, kitti, pipeline

log = logging.getLogger(__name__)

ALPHA = 0.85
BORDER_RATIO = 0.1
SCORED_PAIRS = ("stereo", "flow")
OPTION = "config.data.val_dir"


# ----------------------------------------------------------------------------------------------------------
# Held-out cycles from a folder
# ----------------------------------------------------------------------------------------------------------

class HeldOutCycles(np.ndarray):
    """`val_cycles`' (N, 4, H, W, 3) cycles at the working size that remember `input_sizes`: (N, 2) int, each
    cycle's (height, width) as read from its files, before the resize. Indexing the first axis (`cycles[:1]`,
    `cycles[[0, 2]]`) keeps the matching sizes; anything else gives a result without them (None)."""

    input_sizes: Optional[np.ndarray]

    def __new__(cls, cycles: np.ndarray, input_sizes) -> "HeldOutCycles":
        out = np.asarray(cycles).view(cls)
        out.input_sizes = np.asarray(input_sizes, np.int64).reshape(len(out), 2)
        return out

    def __array_finalize__(self, obj) -> None:
        self.input_sizes = None  # set by __new__ / __getitem__ only: other views need not match cycle for cycle

    def __getitem__(self, key):
        out = super().__getitem__(key)
        if isinstance(out, HeldOutCycles) and self.input_sizes is not None and out.ndim == self.ndim:
            first = key[0] if isinstance(key, tuple) and key else key
            rest_whole = not isinstance(key, tuple) or all(isinstance(k, slice) and k == slice(None)
                                                            for k in key[1:])
            if rest_whole and first is not Ellipsis:
                sizes = self.input_sizes[first]
                out.input_sizes = sizes if sizes.shape == (len(out), 2) else None
        return out


def input_sizes_of(cycles: Any) -> np.ndarray:
    """(N, 2) int (height, width) of each cycle of `cycles` as read from its files (`HeldOutCycles`); for a
    plain array, its own size (the cycles are taken to be the input frames)."""
    n, _, h, w, _ = np.shape(cycles)
    sizes = getattr(cycles, "input_sizes", None)
    if sizes is None or np.shape(sizes) != (n, 2):
        return np.tile(np.array([[h, w]], np.int64), (n, 1))
    return np.asarray(sizes, np.int64)


def val_cycles(data_cfg_or_dir: Any, height: int, width: int, max_cycles: int) -> HeldOutCycles:
    """Held-out cycles of `config.data.val_dir`, at the working size: float32 (N, 4, height, width, 3) in [0, 1],
    with each cycle's size as read (`HeldOutCycles.input_sizes`).

    Args:
      data_cfg_or_dir: a `pipeline.DataConfig` (its `val_dir` is read) or the folder itself, in any layout of
        `folders.LAYOUT_HELP` (the training layouts).
      height, width: working size; frames are resized like the training pipeline (`pipeline.resize_frames`:
        cv2 INTER_AREA when shrinking, INTER_LINEAR when enlarging) from uint8, then divided by 255.
      max_cycles: at most this many cycles, spread evenly over the folder's cycles in order (neighbouring
        cycles of a video are nearly the same pictures).
    Returns:
      (N, 4, height, width, 3) float32 `HeldOutCycles`, N = min(max_cycles, usable cycles); frames in cycle order
      (left_t, right_t, left_t1, right_t1); `.input_sizes` (N, 2): each cycle's (height, width) in its files.
    Raises:
      ValueError naming `config.data.val_dir` when it is empty, missing, holds no cycle, or its images are all
      unreadable / of mismatched sizes (`folders.check_cycles`). Unreadable cycles among good ones are left out
      with a warning.
    """
    train_dir = ""
    if isinstance(data_cfg_or_dir, pipeline.DataConfig):
        val_dir = data_cfg_or_dir.val_dir
        if data_cfg_or_dir.source in ("folder", "kitti_raw"):
            train_dir = data_cfg_or_dir.data_dir
    else:
        val_dir = os.fspath(data_cfg_or_dir)
    if not val_dir:
        raise ValueError(f"{OPTION} is empty: set it to a folder of held-out stereo frames ({folders.EXPECTED_LAYOUT})"
                         f", or leave it empty for the synthetic validation")
    if int(max_cycles) < 1:
        raise ValueError(f"{OPTION}: need at least 1 validation cycle, got max_cycles={max_cycles}")
    val_dir = os.path.abspath(os.path.expanduser(val_dir))
    if not os.path.isdir(val_dir):
        raise ValueError(f"{OPTION}={val_dir!r} {folders.not_a_folder(val_dir)} (held-out stereo video for "
                         f"validation; {folders.EXPECTED_LAYOUT})")
    if train_dir and os.path.realpath(train_dir) == os.path.realpath(val_dir):
        log.warning("%s=%s is also the training data folder: validation frames are training frames", OPTION, val_dir)
    where = f"{OPTION}={val_dir!r}"
    try:
        records = folders.folder_cycles(val_dir)
        records, _ = folders.check_cycles(records, where=where)
    except ValueError as e:
        msg = str(e)
        raise ValueError(msg if OPTION in msg else f"{where}: {msg}") from None
    if len(records) > max_cycles:
        pick = np.unique(np.round(np.linspace(0, len(records) - 1, int(max_cycles))).astype(int))
        records = [records[i] for i in pick]
    out, sizes, bad = [], [], []
    for rec in records:
        try:
            frames = np.stack([kitti.read_image(p) for p in rec["paths"]])
        except (kitti.CorruptImageError, ValueError) as e:  # stack: sizes differ (changed since the check)
            bad.append(f"{getattr(e, 'path', rec['id'])}: {getattr(e, 'reason', e)}")
            continue
        sizes.append(frames.shape[1:3])
        out.append(pipeline.resize_frames(frames, int(height), int(width)).astype(np.float32) / np.float32(255.0))
    if bad:
        log.warning("%s: %d validation cycle(s) left out, unreadable (first: %s)", where, len(bad), bad[0])
    if not out:
        raise ValueError(f"{where}: none of its {len(records)} selected cycles could be read (first: {bad[0]})")
    return HeldOutCycles(np.stack(out), sizes)


# ----------------------------------------------------------------------------------------------------------
# The metric
# ----------------------------------------------------------------------------------------------------------

@functools.partial(jax.jit, static_argnames=("alpha", "border_ratio"))
def _terms(left, right, left1, d_lr, d_rl, flow, to_input, *, alpha: float, border_ratio: float):
    """Per-cycle values (B,) of the metrics of the module docstring, and the error maps (B, H, W) of the picture.

    left, right, left1: (B, H, W, 3) in [0, 1]; d_lr, d_rl, flow: (B, H, W, 2) working pixels; to_input: (B, 2)
    input pixels per working pixel (x, y).
    """
    h, w = left.shape[1:3]
    mask = geometry.border_mask(h, w, border_ratio)  # (H, W, 1), 1 inside the band
    masked_mean = lambda x: jnp.sum(x * mask, axis=(1, 2, 3)) / jnp.sum(mask)  # (B, H, W, 1) -> (B,)

    def photometric(estimate, target):
        p = jax.vmap(lambda e, t: losses.photometric_loss(e, t, mask))(estimate, target)
        l1 = p.l1.num / p.l1.den
        return l1, alpha * (p.ssim.num / p.ssim.den) + (1 - alpha) * l1

    out, maps = {}, {}
    for task, first, second, d in (("stereo", left, right, d_lr), ("flow", left, left1, flow)):
        est = geometry.warp(second, d)
        out[f"{task}_photo_l1"], out[f"{task}_photo_ssim_l1"] = photometric(est, first)
        out[f"zero_{task}_photo_l1"], out[f"zero_{task}_photo_ssim_l1"] = photometric(second, first)
        maps[task] = jnp.mean(jnp.abs(est - first), axis=-1)
        maps[f"zero_{task}"] = jnp.mean(jnp.abs(second - first), axis=-1)
    # left-right check: the right->left map brought into the left frame must cancel the left->right map
    lr = d_lr + geometry.warp(d_rl, d_lr)
    length = lambda v: jnp.sqrt(jnp.sum(jnp.square(v), -1, keepdims=True))
    scale = to_input[:, None, None, :]  # (B, 1, 1, 2)
    for suffix, s in (("px", 1.0), ("input_px", scale)):
        out[f"stereo_lr_consistency_{suffix}"] = masked_mean(length(lr * s))
        out[f"disp_mean_{suffix}"] = masked_mean(-(d_lr * s)[..., :1])
        out[f"flow_mean_{suffix}"] = masked_mean(length(flow * s))
    return out, maps


def photometric_validation(predictor, cycles: np.ndarray, batch: int, *, params: Any = None,
                           picture: bool = True, alpha: float = ALPHA, border_ratio: float = BORDER_RATIO
                           ) -> tuple[dict[str, float], Optional[np.ndarray]]:
    """Photometric validation metrics of a predictor on held-out cycles (see the module docstring).

    Args:
      predictor: a `bridge_jax.inference.Predictor` (anything with `stage_maps(jobs, batch=)` returning
        (H, W, 2) pixel maps at the cycles' size; `height`/`width`, when present, must match the cycles).
      cycles: float32 (N, 4, H, W, 3) in [0, 1] at the predictor's working size (`val_cycles`); the `*_input_px`
        metrics are in pixels of its `input_sizes` (`HeldOutCycles`), of the cycles themselves for a plain array.
      batch: pairs per network call (one compiled shape for the whole run) and cycles per metric call.
      params: optional params to evaluate (`predictor.with_params(params)`), e.g. the training state's.
      picture: also return the first cycle's picture panel.
      alpha: weight of the SSIM term in the SSIM + L1 mix (the training loss's 0.85).
      border_ratio: the band left out on every side, as a fraction of H (the training loss's 0.1).
    Returns:
      (metrics {name: float}, panel uint8 (h, w, 3) of the first cycle | None): left_t, disparity, flow, and
      the per-pixel reconstruction errors of the model (stereo, flow) and of zero motion (flow).
    """
    if np.ndim(cycles) != 5 or np.shape(cycles)[1] != 4 or np.shape(cycles)[-1] != 3 or len(cycles) < 1:
        raise ValueError(f"cycles must be (N, 4, H, W, 3) with N >= 1, got {np.shape(cycles)}")
    input_sizes = input_sizes_of(cycles)
    cycles = np.asarray(cycles, np.float32)
    n, _, h, w, _ = cycles.shape
    to_input = (input_sizes[:, ::-1] / np.array([w, h], np.float64)).astype(np.float32)  # (N, 2): x, y
    size = (getattr(predictor, "height", h), getattr(predictor, "width", w))
    if (h, w) != tuple(size):
        raise ValueError(f"cycles are {h}x{w} but the predictor's working size is {size[0]}x{size[1]} "
                         f"(load them with val_cycles(..., height={size[0]}, width={size[1]}, ...))")
    if params is not None:
        predictor = predictor.with_params(params)
    batch = max(1, int(batch))
    jobs = []
    for c in cycles:
        jobs += [("stereo", c[0], c[1]), ("stereo", c[1], c[0]), ("flow", c[0], c[2])]
    maps = np.stack([np.asarray(m, np.float32) for m in predictor.stage_maps(jobs, batch=batch)])
    maps = maps.reshape(n, 3, h, w, 2)

    sums: dict[str, float] = {}
    first_maps = None
    for start in range(0, n, batch):
        idx = np.arange(start, min(start + batch, n))
        pad = np.concatenate([idx, np.full(batch - len(idx), idx[-1])]) if n > batch else idx  # one shape
        c, m = cycles[pad], maps[pad]
        vals, err = _terms(c[:, 0], c[:, 1], c[:, 2], m[:, 0], m[:, 1], m[:, 2], to_input[pad], alpha=float(alpha),
                           border_ratio=float(border_ratio))
        for k, v in vals.items():
            sums[k] = sums.get(k, 0.0) + float(np.sum(np.asarray(v, np.float64)[:len(idx)]))
        if first_maps is None:
            first_maps = {k: np.asarray(v[0]) for k, v in err.items()}
    metrics = {k: v / n for k, v in sums.items()}
    for task in SCORED_PAIRS:
        for kind in ("l1", "ssim_l1"):
            zero = metrics[f"zero_{task}_photo_{kind}"]
            metrics[f"{task}_photo_{kind}_vs_zero"] = metrics[f"{task}_photo_{kind}"] / max(zero, 1e-12)
    metrics["num_cycles"] = float(n)
    panel = _panel(cycles[0], maps[0], first_maps) if picture else None
    return metrics, panel


def describe(res: dict) -> list[str]:
    """Parts of the one-line validation report for the metrics of `photometric_validation` in `res` (none when
    absent): each task's SSIM + L1 error as a ratio to zero motion and as the two absolute values, the
    left-right inconsistency in working pixels and in pixels of the input frames, and the mean disparity and
    flow in pixels of the input frames."""
    parts = []
    for task, label in (("flow", "flow photometric error"), ("stereo", "stereo photometric error")):
        ratio = res.get(f"{task}_photo_ssim_l1_vs_zero")
        if ratio is None:
            continue
        part = f"{label} {ratio:.2f}x zero motion"
        model, zero = res.get(f"{task}_photo_ssim_l1"), res.get(f"zero_{task}_photo_ssim_l1")
        if model is not None and zero is not None:
            part += f" (SSIM+L1 {model:.4f} vs {zero:.4f})"
        parts.append(part)
    if "stereo_lr_consistency_px" in res:
        part = f"left-right disparity inconsistency {res['stereo_lr_consistency_px']:.2f} px"
        if "stereo_lr_consistency_input_px" in res:
            part += f" ({res['stereo_lr_consistency_input_px']:.2f} px of the input frames)"
        parts.append(part)
    means = [f"mean {label} {res[key]:.2f} px" for key, label in (("disp_mean_input_px", "disparity"),
                                                                    ("flow_mean_input_px", "flow")) if key in res]
    if means:
        parts.append(", ".join(means) + " of the input frames")
    return parts


def _panel(cycle: np.ndarray, maps: np.ndarray, err: dict) -> np.ndarray:
    """3 x 2 tiles: left_t | disparity | flow / stereo error | flow error | zero-motion flow error."""
    vmax = max(float(np.percentile(err["zero_flow"], 99)), 1e-3)  # one scale for the three error tiles
    tiles = [cycle[0], visualize.disparity_to_color(-maps[0, ..., 0]), visualize.flow_to_color(maps[2]),
             # disparity_to_color is a plain colormap of a scalar map: used here for the errors as well
             visualize.disparity_to_color(err["stereo"], vmax=vmax),
             visualize.disparity_to_color(err["flow"], vmax=vmax),
             visualize.disparity_to_color(err["zero_flow"], vmax=vmax)]
    labels = ["left t", "disparity", "flow t->t+1", "stereo photometric error", "flow photometric error",
              "zero-motion flow error"]
    return visualize.panel(tiles, labels, ncols=3)


def border_pixels(height: int, ratio: float = BORDER_RATIO) -> int:
    """Width in pixels of the band left out on every side (ceil(ratio * height), as `geometry.border_mask`)."""
    return int(math.ceil(height * ratio))
