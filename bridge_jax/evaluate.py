"""Evaluation on KITTI 2015 / 2012, the Eigen split, the built-in synthetic set or any KITTI-layout folder.

    python -m bridge_jax.evaluate --checkpoint CKPT --dataset kitti2015 --data-dir ~/data/data_scene_flow
    python -m bridge_jax.evaluate --checkpoint work/demo --dataset synthetic --data-dir work/demo/val --out eval/

The model runs on each frame at the working size (256×512 = H×W, like the paper), one compiled function per
working size and batch, and its maps are brought to the ground-truth resolution exactly as the paper's scripts
did (REFERENCE.md §1d):

* flow: the full-resolution pixel map is resized to the GT size with bilinear ``align_corners=True``, then
  ``u·W/w`` and ``v·H/h`` (:func:`flow_to_gt_resolution`);
* disparity: ``-channel 0`` of the fraction map (pixel map / w), resized with OpenCV ``INTER_LINEAR`` and
  multiplied by the GT width (:func:`disparity_to_gt_resolution`); depth = f·B/d clamped to [1e-3, 80] m;
* the t+1 disparity is brought into frame t along the predicted flow (KITTI ``disp_1``) for D2 and SF.

Metrics (see :mod:`bridge_jax.metrics`) are reported as per-image means (paper) and pooled over pixels (KITTI
devkit), next to two baselines run on the same frames at full resolution: zero motion and OpenCV (StereoSGBM for
disparity, DIS for optical flow). Results are printed and written as JSON + Markdown (+ a few picture panels).
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import os
import shutil
import sys
import tempfile
import time
from collections.abc import Callable, Sequence
from typing import Any, Optional

import cv2
import numpy as np

from bridge_jax import metrics, visualize

DATASETS = ("kitti2015", "kitti2012", "eigen", "synthetic", "folder")

KITTI_BASELINE_M = 0.54
"""KITTI stereo rig baseline in metres (the paper's protocol uses it for KITTI 2012/2015 depth)."""
KITTI_WIDTH_TO_FOCAL = {1242: 721.5377, 1241: 718.856, 1224: 707.0493, 1238: 718.3351}
"""Focal length (px) looked up by image width, as the monodepth-lineage script did for KITTI 2015."""

METHOD_LABELS = {"model": "bridge_jax", "zero": "zero motion", "opencv": "OpenCV SGBM (disp) / DIS (flow)"}

METRIC_GROUPS = (
    ("Optical flow (t → t+1), EPE px / Fl %", ("epe_all", "epe_noc", "epe_occ", "fl_all", "fl_noc", "fl_occ")),
    ("Disparity at t, EPE px / D1 %", ("epe_all", "epe_noc", "d1_all", "d1_noc", "d1_occ", "d1_all_paper",
                                        "d1_noc_paper")),
    ("Disparity at t+1 in frame t (D2 %) and scene flow (SF %)",
     ("d2_epe_all", "d2_epe_noc", "d2_all", "d2_noc", "sf_all", "sf_noc")),
    ("Depth from disparity at t (m; δ fractions)", ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2", "a3")),
)
# metric name -> group key (the flow EPE and disparity EPE share names, so results are grouped by task)
TASKS = ("flow", "disparity", "scene_flow", "depth")


class EvaluationError(ValueError):
    """Bad evaluation input (missing or mismatched files, unreadable images, bad options)."""


# --------------------------------------------------------------------------------------------------------------
# Resolution handling (REFERENCE.md §1d)


def flow_to_gt_resolution(flow_px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Flow predicted at the working size → flow at the GT size, as upstream ``test_flow.py``.

    Args:
      flow_px: ``(h, w, 2)`` flow in pixels of the working size (e.g. 256×512).
      height, width: GT size.
    Returns:
      ``(height, width, 2)`` float32 flow in GT pixels: bilinear (align_corners=True), u·width/w, v·height/h.
    """
    from bridge_jax import inference  # lazy, like load_predictor: the baselines need no JAX

    # the same rescaling the Predictor applies to its own outputs: one implementation of §1d
    return inference.maps_to_input_resolution(np.asarray(flow_px, np.float32), height, width)


def disparity_to_gt_resolution(disp_px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Disparity predicted at the working size → disparity at the GT size, as upstream ``evaluate_kitti.py``.

    Args:
      disp_px: ``(h, w)`` disparity (= −channel 0 of the map) in pixels of the working size.
    Returns:
      ``(height, width)`` float32: the fraction ``disp_px / w`` resized with OpenCV INTER_LINEAR, × width.
    """
    w = disp_px.shape[1]
    frac = np.asarray(disp_px, np.float32) / np.float32(w)
    return cv2.resize(frac, (width, height), interpolation=cv2.INTER_LINEAR) * np.float32(width)


def bring_to_frame_t(disp_t1: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """The t+1 disparity seen from frame t: ``disp_1(x, y) = disp_t1(x + u, y + v)`` (bilinear, border clamp).

    This is what KITTI 2015 calls ``disp_1`` (disparity of frame t+1 at the pixels of the reference frame t).

    Args:
      disp_t1: ``(H, W)`` disparity of the left image at t+1, pixels.
      flow: ``(H, W, 2)`` optical flow t → t+1 of the left camera, pixels.
    Returns:
      ``(H, W)`` float32.
    """
    h, w = disp_t1.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(np.asarray(disp_t1, np.float32), gx + flow[..., 0].astype(np.float32),
                     gy + flow[..., 1].astype(np.float32), cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


# --------------------------------------------------------------------------------------------------------------
# Frames and datasets


@dataclasses.dataclass
class Frame:
    """One evaluation sample.

    images: subset of ``left_t, right_t, left_t1, right_t1`` → uint8 RGB ``(H, W, 3)`` (all the same size).
    gt: any of ``flow_occ`` ``(H, W, 2)`` px + ``flow_occ_valid`` / ``flow_noc_valid`` ``(H, W)`` bool;
      ``disp_occ_0``, ``disp_noc_0``, ``disp_occ_1``, ``disp_noc_1`` ``(H, W)`` px (0 = no GT);
      ``depth`` ``(H, W)`` m (0 = no GT, Eigen).
    focal: px at the image resolution; baseline: m (for depth).
    """

    frame_id: str
    images: dict[str, np.ndarray]
    gt: dict[str, np.ndarray]
    focal: Optional[float] = None
    baseline: Optional[float] = None

    @property
    def size(self) -> tuple[int, int]:
        return self.images["left_t"].shape[:2]


@dataclasses.dataclass
class FrameSpec:
    """Where to find one frame: image paths and GT paths; loaded lazily by :func:`load_frame`."""

    frame_id: str
    images: dict[str, str]
    gt: dict[str, str]
    grayscale: bool = False
    calib: Optional[str] = None
    extra: dict = dataclasses.field(default_factory=dict)


def _kitti():
    from bridge_jax.data import kitti  # imported lazily: the data module is optional for baselines on arrays
    return kitti


def _read_rgb(path: str) -> np.ndarray:
    """uint8 RGB ``(H, W, 3)``; grayscale files (KITTI 2012 ``image_0``) are replicated to 3 channels."""
    try:
        return _kitti().read_image(path)
    except ValueError as e:  # CorruptImageError: missing, truncated or undecodable; names the path
        raise EvaluationError(str(e)) from None


def _find_root(data_dir: str, split: Optional[str], marker: str) -> str:
    """``data_dir/<split>`` if it holds ``marker``, else ``data_dir`` itself."""
    split = split or "training"
    for cand in (os.path.join(data_dir, split), data_dir):
        if os.path.isdir(os.path.join(cand, marker)):
            return cand
    raise EvaluationError(f"no {marker}/ folder under {data_dir} (nor {os.path.join(data_dir, split)}); expected a "
                          f"KITTI layout folder")


def _frame_ids(folder: str, suffix: str = "_10.png") -> list[str]:
    return sorted(f[: -len(suffix)] for f in os.listdir(folder) if f.endswith(suffix))


def _kitti_specs(data_dir: str, split: Optional[str], *, year: int, require_gt: bool) -> list[FrameSpec]:
    """Frame specs of a KITTI 2015 (``image_2/3``, ``*_0/1`` GT) or 2012 (``image_0/1``, GT without suffix) folder."""
    left, right = ("image_2", "image_3") if year == 2015 else ("image_0", "image_1")
    root = _find_root(data_dir, split, left)
    ids = _frame_ids(os.path.join(root, left))
    if not ids:
        raise EvaluationError(f"no *_10.png frames in {os.path.join(root, left)}")
    gt_dirs = (("flow_occ", "flow_occ"), ("flow_noc", "flow_noc"))
    if year == 2015:
        gt_dirs += (("disp_occ_0", "disp_occ_0"), ("disp_noc_0", "disp_noc_0"), ("disp_occ_1", "disp_occ_1"),
                    ("disp_noc_1", "disp_noc_1"))
    else:
        gt_dirs += (("disp_occ_0", "disp_occ"), ("disp_noc_0", "disp_noc"))
    present = {key: os.path.join(root, d) for key, d in gt_dirs if os.path.isdir(os.path.join(root, d))}
    if require_gt and not present:
        raise EvaluationError(f"no ground-truth folder ({', '.join(d for _, d in gt_dirs)}) in {root}")
    for key, d in present.items():
        n = len(_frame_ids(d))
        if n != len(ids):
            raise EvaluationError(f"mismatched counts: {d} has {n} *_10.png files but {os.path.join(root, left)} "
                                  f"has {len(ids)} frames")
    specs = []
    for fid in ids:
        images = {"left_t": os.path.join(root, left, f"{fid}_10.png"),
                  "right_t": os.path.join(root, right, f"{fid}_10.png"),
                  "left_t1": os.path.join(root, left, f"{fid}_11.png"),
                  "right_t1": os.path.join(root, right, f"{fid}_11.png")}
        for name, path in images.items():
            if not os.path.isfile(path):
                raise EvaluationError(f"missing image {path} (frame {fid}, {name})")
        gt = {}
        for key, d in present.items():
            path = os.path.join(d, f"{fid}_10.png")
            if not os.path.isfile(path):
                raise EvaluationError(f"missing ground truth {path}")
            gt[key] = path
        calib = os.path.join(root, "calib_cam_to_cam" if year == 2015 else "calib", f"{fid}.txt")
        specs.append(FrameSpec(fid, images, gt, grayscale=(year == 2012),
                               calib=calib if os.path.isfile(calib) else None))
    return specs


def _eigen_specs(data_dir: str, split: Optional[str]) -> list[FrameSpec]:
    """Eigen test frames of a KITTI raw root (default list: the bundled 697; ``split`` = another list file)."""
    kitti = _kitti()
    try:
        if split is None:
            samples = kitti.eigen_test_samples(data_dir)
        else:
            if not os.path.isfile(split):
                raise EvaluationError(f"--split {split}: Eigen list file not found")
            drives = {kitti.drive_name(d): d for d in kitti.find_raw_drives(data_dir)}
            samples = []
            for name, k in kitti.read_split_ids(split):
                d = drives.get(name)
                frames = kitti.raw_drive_frames(d) if d else {}
                velo = os.path.join(d, "velodyne_points", "data", f"{k:010d}.bin") if d else ""
                if k not in frames or not os.path.isfile(velo):
                    raise EvaluationError(f"Eigen frame {name}/{k:010d} of {split} missing under {data_dir}")
                samples.append({"id": f"{name}/{k:010d}", "left": frames[k][0], "right": frames[k][1],
                                "velo": velo, "calib_dir": os.path.dirname(d)})
    except EvaluationError:
        raise
    except ValueError as e:
        raise EvaluationError(str(e)) from None
    return [FrameSpec(smp["id"].replace("/", "_"), {"left_t": smp["left"], "right_t": smp["right"]},
                      {"velodyne": smp["velo"]}, calib=smp["calib_dir"]) for smp in samples]


def list_frames(dataset: str, data_dir: str, split: Optional[str] = None) -> list[FrameSpec]:
    """The frames of a dataset, checked for missing / mismatched files (errors name the path).

    Args:
      dataset: one of :data:`DATASETS`. ``synthetic`` and ``folder`` read the KITTI 2015 layout (``image_2``,
        ``image_3``, optional ``flow_occ``/``flow_noc``/``disp_{occ,noc}_{0,1}``) from ``data_dir`` or
        ``data_dir/<split>``; ``folder`` accepts frames without ground truth (baselines/pictures only).
      split: KITTI: sub-folder (default ``training``); Eigen: a list file (default: the bundled 697 frames).
    """
    if not os.path.isdir(data_dir):
        raise EvaluationError(f"--data-dir {data_dir} is not a directory")
    if dataset in ("kitti2015", "synthetic"):
        return _kitti_specs(data_dir, split, year=2015, require_gt=True)
    if dataset == "folder":
        return _kitti_specs(data_dir, split, year=2015, require_gt=False)
    if dataset == "kitti2012":
        return _kitti_specs(data_dir, split, year=2012, require_gt=True)
    if dataset == "eigen":
        return _eigen_specs(data_dir, split)
    raise EvaluationError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")


def _focal_baseline(spec: FrameSpec, width: int, dataset: str) -> tuple[Optional[float], Optional[float]]:
    kitti = _kitti()
    try:
        if dataset == "eigen":
            return kitti.raw_focal_baseline(spec.calib)
        if dataset in ("kitti2015", "kitti2012") and width in KITTI_WIDTH_TO_FOCAL:
            return KITTI_WIDTH_TO_FOCAL[width], KITTI_BASELINE_M   # the paper's lookup (upstream evaluate_kitti.py)
        if spec.calib is not None:
            cams = (0, 1) if spec.grayscale else (2, 3)
            return kitti.focal_baseline(kitti.read_calib_file(spec.calib), cams, spec.calib)
    except (ValueError, KeyError) as e:
        raise EvaluationError(f"bad calibration for frame {spec.frame_id}: {e}") from None
    return None, None


def load_frame(spec: FrameSpec, dataset: str, *, garg_crop: bool = True) -> Frame:
    """Read the images and ground truth of one frame (see :class:`Frame`)."""
    kitti = _kitti()
    images = {name: _read_rgb(path) for name, path in spec.images.items()}
    size = images["left_t"].shape[:2]
    for name, img in images.items():
        if img.shape[:2] != size:
            raise EvaluationError(f"image {spec.images[name]} is {img.shape[:2]}, expected {size} like left_t")
    try:
        gt = _load_gt(spec, size)
    except EvaluationError:
        raise
    except (ValueError, KeyError) as e:
        raise EvaluationError(f"frame {spec.frame_id}: {e}") from None
    focal, baseline = _focal_baseline(spec, size[1], dataset)
    if dataset == "eigen":
        mask = (gt["depth"] > metrics.MIN_DEPTH) & (gt["depth"] < metrics.MAX_DEPTH)
        if garg_crop:
            mask &= metrics.garg_crop_mask(*size)
        gt["depth_mask"] = mask
    return Frame(spec.frame_id, images, gt, focal, baseline)


def _load_gt(spec: FrameSpec, size: tuple[int, int]) -> dict[str, np.ndarray]:
    kitti = _kitti()
    gt: dict[str, np.ndarray] = {}
    for key, path in spec.gt.items():
        if key.startswith("flow"):
            flow, valid = kitti.read_flow_png(path)
            if flow.shape[:2] != size:
                raise EvaluationError(f"ground truth {path} is {flow.shape[:2]}, images are {size}")
            if key == "flow_occ":
                gt["flow_occ"], gt["flow_occ_valid"] = flow.astype(np.float32), valid.astype(bool)
            else:
                gt["flow_noc_valid"] = valid.astype(bool)
                gt.setdefault("flow_noc", flow.astype(np.float32))
        elif key.startswith("disp"):
            disp = _disp_only(kitti.read_disp_png(path))
            if disp.shape != size:
                raise EvaluationError(f"ground truth {path} is {disp.shape}, images are {size}")
            gt[key] = disp.astype(np.float32)
        elif key == "velodyne":
            gt["depth"] = kitti.velodyne_depth_map(spec.calib, path, size).astype(np.float32)
    if "flow_noc_valid" in gt and "flow_occ" not in gt:   # noc only: score it as the only region
        gt["flow_occ"], gt["flow_occ_valid"] = gt["flow_noc"], gt["flow_noc_valid"]
        del gt["flow_noc_valid"]
    gt.pop("flow_noc", None)
    return gt


def _disp_only(x):
    """Data readers may return ``disp`` or ``(disp, valid)``; keep the disparity (0 where invalid)."""
    if isinstance(x, tuple):
        disp, valid = x
        return np.where(valid, disp, 0.0)
    return x


# --------------------------------------------------------------------------------------------------------------
# Predictions: model and baselines (all at the GT resolution)


def _pairs_of(frame: Frame) -> list[tuple[str, str, str]]:
    """(task, image a, image b) that this frame needs."""
    pairs = [("disp_t", "left_t", "right_t")]
    if "left_t1" in frame.images:
        pairs.append(("flow", "left_t", "left_t1"))
        if "right_t1" in frame.images and any(k.endswith("_1") for k in frame.gt):
            pairs.append(("disp_t1", "left_t1", "right_t1"))
    return pairs


def _finish(frame: Frame, pred: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    if "disp_t1" in pred and "flow" in pred:
        pred["disp_1"] = bring_to_frame_t(pred["disp_t1"], pred["flow"])
    return pred


class ModelMethod:
    """Runs a predictor on frames in fixed-size batches (one compiled function) and rescales to GT size.

    See :func:`_working_maps` for how the predictor is called; ``inference_s`` accumulates the time spent there
    (resize to the working size + network).
    """

    name = "model"

    def __init__(self, predictor, batch_frames: int = 1):
        self.predictor = predictor
        self.batch_frames = max(1, int(batch_frames))
        self.inference_s = 0.0

    def __call__(self, frames: Sequence[Frame]) -> list[dict[str, np.ndarray]]:
        jobs = [(i, task, frame.images[a], frame.images[b])
                for i, frame in enumerate(frames) for task, a, b in _pairs_of(frame)]
        t0 = time.perf_counter()
        maps = _working_maps(self.predictor, [j[2] for j in jobs], [j[3] for j in jobs],
                             pad_to=3 * self.batch_frames, tasks=[_task_of(j[1]) for j in jobs])
        self.inference_s += time.perf_counter() - t0
        preds: list[dict[str, np.ndarray]] = [{} for _ in frames]
        for (i, task, _, _), m in zip(jobs, maps):
            h, w = frames[i].size
            if task == "flow":
                preds[i]["flow"] = flow_to_gt_resolution(m, h, w)
            else:
                preds[i][task] = disparity_to_gt_resolution(-m[..., 0], h, w)
        return [_finish(f, p) for f, p in zip(frames, preds)]


def _task_of(job_task: str) -> str:
    return "flow" if job_task == "flow" else "stereo"


def _working_maps(predictor, images_a: list[np.ndarray], images_b: list[np.ndarray], pad_to: int,
                  tasks: Optional[Sequence[str]] = None) -> list[np.ndarray]:
    """Working-size pixel maps ``(h, w, 2)`` for each pair (a → b).

    The predictor is called in chunks of exactly ``pad_to`` pairs (the last chunk padded by repetition), so one
    compiled network function serves the whole run. Uses :class:`bridge_jax.inference.Predictor`'s
    ``prepare`` (antialiased resize to the working size, per pair, so frames of different sizes can share a
    chunk) and ``run_network``; pairs are grouped by task (``"stereo"`` / ``"flow"``) only for two-network models.
    A predictor offering ``predict_pairs_working(a, b)`` (tests) is used directly.
    """
    tasks = list(tasks) if tasks is not None else ["flow"] * len(images_a)
    if not getattr(predictor, "separate", False):
        tasks = ["flow"] * len(images_a)   # one shared network: no need to split (and pad) by task
    out: list[Optional[np.ndarray]] = [None] * len(images_a)
    direct = hasattr(predictor, "predict_pairs_working")
    for task in dict.fromkeys(tasks):
        idx = [i for i, t in enumerate(tasks) if t == task]
        for start in range(0, len(idx), pad_to):
            chunk = idx[start:start + pad_to]
            padded = chunk + [chunk[-1]] * (pad_to - len(chunk))
            if direct:
                res = np.asarray(predictor.predict_pairs_working([images_a[i] for i in padded],
                                                                 [images_b[i] for i in padded]))
            else:
                pairs = np.concatenate([predictor.prepare([images_a[i]], [images_b[i]])[0] for i in chunk])
                if len(chunk) < pad_to:
                    pairs = np.concatenate([pairs, np.repeat(pairs[-1:], pad_to - len(chunk), 0)])
                res = predictor.run_network(pairs, task)
            for i, m in zip(chunk, res):
                out[i] = np.asarray(m)
    return out  # type: ignore[return-value]


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
             for task, _, _ in _pairs_of(f)}
        out.append(_finish(f, p))
    return out


def opencv_method(frames: Sequence[Frame]) -> list[dict[str, np.ndarray]]:
    """Classical baseline: StereoSGBM for disparity, DIS for optical flow, at the full image resolution."""
    out = []
    for f in frames:
        p = {}
        for task, a, b in _pairs_of(f):
            ia, ib = f.images[a], f.images[b]
            p[task] = dis_flow(ia, ib) if task == "flow" else sgbm_disparity(ia, ib)
        out.append(_finish(f, p))
    return out


# --------------------------------------------------------------------------------------------------------------
# Scoring


def frame_sums(pred: dict[str, np.ndarray], frame: Frame) -> dict[str, metrics.Sums]:
    """Metric sums of one frame, per task (``flow``, ``disparity``, ``scene_flow``, ``depth``)."""
    gt = frame.gt
    out: dict[str, metrics.Sums] = {}
    if "flow_occ" in gt and "flow" in pred:
        out["flow"] = metrics.flow_sums(pred["flow"], gt["flow_occ"], gt["flow_occ_valid"], gt.get("flow_noc_valid"))
    if "disp_occ_0" in gt or "disp_noc_0" in gt:
        ref = gt.get("disp_occ_0", gt.get("disp_noc_0"))
        noc = gt["disp_noc_0"] > 0 if "disp_occ_0" in gt and "disp_noc_0" in gt else None
        out["disparity"] = metrics.disparity_sums(pred["disp_t"], ref, ref > 0, noc)
        if frame.focal:
            # paper protocol: depth from the disp_occ_0 GT (upstream reads disp_occ_0), mask gt > 0, GT uncapped
            mask = ref > 0
            gt_depth = frame.focal * frame.baseline / np.where(mask, ref, 1.0)
            pred_depth = metrics.disparity_to_depth(pred["disp_t"], frame.focal, frame.baseline)
            out["depth"] = metrics.depth_sums(pred_depth, gt_depth, mask)
    if "depth" in gt and frame.focal:
        # Eigen protocol (upstream evaluate_kitti.py --split eigen): infinite depth (d = 0) → 0 → clamped to 1e-3
        pred_depth = metrics.disparity_to_depth(pred["disp_t"], frame.focal, frame.baseline, zero_disparity_depth=0.0)
        out["depth"] = metrics.depth_sums(pred_depth, gt["depth"], gt["depth_mask"])
    if "disp_1" in pred and ("disp_occ_1" in gt or "disp_noc_1" in gt):
        ref1 = gt.get("disp_occ_1", gt.get("disp_noc_1"))
        noc1 = gt["disp_noc_1"] > 0 if "disp_occ_1" in gt and "disp_noc_1" in gt else None
        sf = metrics.disparity_sums(pred["disp_1"], ref1, ref1 > 0, noc1, prefix="d2")
        sf = {k: v for k, v in sf.items() if not k.endswith("_paper")}
        if "flow" in out and "disp_occ_0" in gt:
            d0 = gt["disp_occ_0"]
            sf.update(metrics.scene_flow_sums((pred["disp_t"], d0, d0 > 0), (pred["disp_1"], ref1, ref1 > 0),
                                              (pred["flow"], gt["flow_occ"], gt["flow_occ_valid"]), suffix="all"))
            if all(k in gt for k in ("disp_noc_0", "disp_noc_1", "flow_noc_valid")):
                n0, n1 = gt["disp_noc_0"], gt["disp_noc_1"]
                sf.update(metrics.scene_flow_sums((pred["disp_t"], n0, n0 > 0), (pred["disp_1"], n1, n1 > 0),
                                                  (pred["flow"], gt["flow_occ"], gt["flow_noc_valid"]),
                                                  suffix="noc"))
        out["scene_flow"] = sf
    return out


def frame_panel(frame: Frame, pred: dict[str, np.ndarray]) -> np.ndarray:
    """Side-by-side picture of one frame: input, predicted flow / disparity, GT and error maps (RGB uint8)."""
    tiles, labels = [frame.images["left_t"]], ["left t"]
    gt = frame.gt
    if "flow" in pred:
        valid = gt.get("flow_occ_valid")
        max_flow = (visualize.flow_magnitude_max(gt["flow_occ"], valid) if valid is not None
                    else visualize.flow_magnitude_max(pred["flow"]))
        tiles.append(visualize.flow_to_color(pred["flow"], max_flow=max_flow)); labels.append("flow")
        if valid is not None:
            tiles.append(visualize.flow_to_color(gt["flow_occ"], max_flow=max_flow, valid=valid))
            labels.append("flow GT")
            tiles.append(visualize.error_to_color(metrics.endpoint_error(pred["flow"], gt["flow_occ"]), valid))
            labels.append("flow error")
    ref = gt.get("disp_occ_0")
    vmax = float(np.percentile(ref[ref > 0], 99)) if ref is not None and (ref > 0).any() else None
    tiles.append(visualize.disparity_to_color(pred["disp_t"], vmax=vmax)); labels.append("disparity t")
    if ref is not None:
        tiles.append(visualize.disparity_to_color(ref, vmax=vmax, valid=ref > 0)); labels.append("disparity GT")
        tiles.append(visualize.error_to_color(metrics.endpoint_error(pred["disp_t"], ref), ref > 0))
        labels.append("disparity error")
    return visualize.panel(tiles, labels, ncols=4 if len(tiles) > 4 else len(tiles))


def evaluate(predictor, dataset: str, data_dir: str, *, split: Optional[str] = None, baselines: bool = True,
             garg_crop: bool = True, batch: int = 1, max_frames: Optional[int] = None,
             out_dir: Optional[str] = None, num_pictures: int = 4, overwrite: bool = False,
             progress: bool = True, extra_info: Optional[dict] = None) -> dict:
    """Evaluate a predictor (and the baselines) on a dataset.

    Args:
      predictor: an :class:`bridge_jax.inference.Predictor` (or None to run the baselines only).
      dataset: one of :data:`DATASETS`; data_dir / split: see :func:`list_frames`.
      baselines: also run zero motion and OpenCV SGBM / DIS on the same frames.
      garg_crop: Eigen only: apply the Garg crop (the papers' protocol).
      batch: frames per inference call (pairs per call = 3 × batch, a fixed shape).
      max_frames: evaluate only the first frames (smoke runs).
      out_dir: if given, write ``results.json``, ``results.md`` and ``pictures/*.png`` there (refused if it
        exists and is not empty, unless ``overwrite``; written to a temporary folder, then renamed).
    Returns:
      ``{"dataset", "data_dir", "split", "num_frames", "methods": {method: {task: {"per_image_mean": {...},
      "pooled": {...}, "num_images": {...}}}}, "timing": {...}, "markdown": str}``.
    """
    if dataset not in DATASETS:
        raise EvaluationError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")
    if out_dir is not None:
        check_output_dir(out_dir, overwrite)
    specs = list_frames(dataset, data_dir, split)
    if max_frames is not None:
        specs = specs[:max_frames]
    methods: dict[str, Callable] = {}
    model = None
    if predictor is not None:
        model = ModelMethod(predictor, batch)
        methods["model"] = model
    if baselines:
        methods["zero"] = zero_method
        methods["opencv"] = opencv_method
    if not methods:
        raise EvaluationError("nothing to evaluate: no predictor and --no-baselines")
    accs = {m: {t: metrics.MetricAccumulator() for t in TASKS} for m in methods}
    method_s = {m: 0.0 for m in methods}
    pictures: list[tuple[str, np.ndarray]] = []
    t_start = time.perf_counter()
    load_s = 0.0
    step = max(1, int(batch))
    bar = _progress(len(specs), progress, f"evaluate {dataset}")
    for start in range(0, len(specs), step):
        t0 = time.perf_counter()
        frames = [load_frame(s, dataset, garg_crop=garg_crop) for s in specs[start:start + step]]
        load_s += time.perf_counter() - t0
        for name, method in methods.items():
            t0 = time.perf_counter()
            preds = method(frames)
            for frame, pred in zip(frames, preds):
                for task, sums in frame_sums(pred, frame).items():
                    accs[name][task].add(sums)
                if name == ("model" if model is not None else "opencv") and len(pictures) < num_pictures \
                        and out_dir is not None:
                    pictures.append((frame.frame_id, frame_panel(frame, pred)))
            method_s[name] += time.perf_counter() - t0
        bar.update(len(frames))
    bar.close()
    total_s = time.perf_counter() - t_start
    results: dict[str, Any] = {
        "dataset": dataset, "data_dir": os.path.abspath(data_dir), "split": split, "num_frames": len(specs),
        "garg_crop": garg_crop if dataset == "eigen" else None,
        "methods": {m: {t: accs[m][t].summary() for t in TASKS if accs[m][t].names} for m in methods},
        "units": "EPE in GT pixels; Fl/D1/D2/SF in %; depth errors in m; a1..a3 fractions",
    }
    timing = {"total_s": total_s, "load_s": load_s, "frames_per_s": len(specs) / total_s if total_s else None}
    for m, s in method_s.items():
        timing[f"{m}_s"] = s
    if model is not None:
        timing["model_inference_s"] = model.inference_s
        timing["model_frames_per_s"] = len(specs) / method_s["model"] if method_s["model"] else None
        timing["model_inference_share"] = model.inference_s / method_s["model"] if method_s["model"] else None
    results["timing"] = timing
    if extra_info:
        results.update(extra_info)
    results["markdown"] = markdown_table(results)
    if out_dir is not None:
        write_outputs(out_dir, results, pictures, overwrite)
    return results


def evaluate_synthetic(predictor, data_dir: str, **kwargs) -> dict:
    """:func:`evaluate` on a folder written by :func:`bridge_jax.data.synthetic.write_kitti_layout`."""
    return evaluate(predictor, "synthetic", data_dir, **kwargs)


class _NoBar:
    def update(self, n):
        pass

    def close(self):
        pass


def _progress(total: int, enabled: bool, desc: str):
    if not enabled:
        return _NoBar()
    from tqdm import tqdm
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr)


# --------------------------------------------------------------------------------------------------------------
# Reports


def _fmt(v: Optional[float]) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    return f"{v:.4g}" if abs(v) < 1000 else f"{v:.1f}"


def markdown_table(results: dict) -> str:
    """Markdown tables of all metrics, one per task; a row per method × reduction."""
    lines = [f"## {results['dataset']} — {results['num_frames']} frames", "",
             "Per-image mean = the paper's reduction; pooled = over all pixels (KITTI devkit). "
             "EPE in GT pixels, Fl/D1/D2/SF in %, depth errors in m, a1..a3 = δ < 1.25^k fractions. "
             "`*_paper` = `>=` outliers (monodepth-lineage script): `d1_all_paper` on disp_occ (as upstream), "
             "`d1_noc_paper` on disp_noc.", ""]
    for (title, names), task in zip(METRIC_GROUPS, TASKS):
        present = [n for n in names if any(n in results["methods"][m].get(task, {}).get("pooled", {})
                                           for m in results["methods"])]
        if not present:
            continue
        lines += [f"### {title}", "", "| method | reduction | " + " | ".join(present) + " |",
                  "|---|---|" + "---|" * len(present)]
        for m, per_task in results["methods"].items():
            if task not in per_task:
                continue
            for red, red_label in (("per_image_mean", "per-image mean"), ("pooled", "pooled")):
                vals = [_fmt(per_task[task][red].get(n)) for n in present]
                lines.append(f"| {METHOD_LABELS.get(m, m)} | {red_label} | " + " | ".join(vals) + " |")
        lines.append("")
    t = results.get("timing", {})
    if t:
        lines.append(f"Time: {_fmt(t.get('total_s'))} s total, {_fmt(t.get('frames_per_s'))} frames/s overall"
                     + (f"; model {_fmt(t.get('model_frames_per_s'))} frames/s, inference share "
                        f"{_fmt(100 * t['model_inference_share'])} %" if t.get("model_inference_share") else ""))
    return "\n".join(lines) + "\n"


def check_output_dir(out_dir: str, overwrite: bool) -> None:
    """Refuse an existing non-empty output folder unless ``overwrite`` (error names the path)."""
    if os.path.exists(out_dir):
        if not os.path.isdir(out_dir):
            raise EvaluationError(f"output path {out_dir} exists and is not a folder")
        if os.listdir(out_dir) and not overwrite:
            raise EvaluationError(f"output folder {out_dir} exists and is not empty (use --overwrite)")


def publish_dir(tmp_dir: str, out_dir: str) -> None:
    """Move a completely written temporary folder to ``out_dir`` (replacing it), so that ``out_dir`` is never
    half-written."""
    out_dir = os.path.abspath(out_dir)
    if os.path.isdir(out_dir):
        old = tempfile.mkdtemp(prefix=".old-", dir=os.path.dirname(out_dir))
        os.rename(out_dir, os.path.join(old, "x"))
        os.rename(tmp_dir, out_dir)
        shutil.rmtree(old, ignore_errors=True)
    else:
        os.rename(tmp_dir, out_dir)


def make_temp_dir(out_dir: str) -> str:
    parent = os.path.dirname(os.path.abspath(out_dir))
    os.makedirs(parent, exist_ok=True)
    return tempfile.mkdtemp(prefix=f".{os.path.basename(os.path.abspath(out_dir))}.tmp-", dir=parent)


def _json_safe(x):
    """NaN / inf (a metric without valid pixels) → null, numpy scalars → Python numbers (strict JSON)."""
    if isinstance(x, dict):
        return {k: _json_safe(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_json_safe(v) for v in x]
    if isinstance(x, (float, np.floating)):
        return float(x) if math.isfinite(x) else None
    if isinstance(x, np.integer):
        return int(x)
    return x


def write_outputs(out_dir: str, results: dict, pictures: Sequence[tuple[str, np.ndarray]],
                  overwrite: bool) -> None:
    """Write ``results.json``, ``results.md`` and ``pictures/<id>.png`` into ``out_dir`` (atomically)."""
    check_output_dir(out_dir, overwrite)
    tmp = make_temp_dir(out_dir)
    try:
        with open(os.path.join(tmp, "results.json"), "w") as f:
            json.dump(_json_safe({k: v for k, v in results.items() if k != "markdown"}), f, indent=1)
        with open(os.path.join(tmp, "results.md"), "w") as f:
            f.write(results["markdown"])
        if pictures:
            os.makedirs(os.path.join(tmp, "pictures"))
            for fid, img in pictures:
                visualize.write_image(os.path.join(tmp, "pictures", f"{fid}.png"), img)
        publish_dir(tmp, out_dir)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


# --------------------------------------------------------------------------------------------------------------
# Command line


def parse_size(text: str) -> tuple[int, int]:
    """``"256x512"`` → ``(256, 512)`` = (H, W)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW like 256x512, got {text!r}") from None
    if h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"expected positive HxW, got {text!r}")
    return h, w


def load_predictor(checkpoint: str, working_size: Optional[tuple[int, int]]):
    """Load a checkpoint as a predictor; any failure becomes an :class:`EvaluationError` naming the path."""
    from bridge_jax import inference
    if not os.path.exists(checkpoint):
        raise EvaluationError(f"checkpoint {checkpoint} does not exist")
    try:
        if working_size is None:
            return inference.load_predictor(checkpoint)
        return inference.load_predictor(checkpoint, height=working_size[0], width=working_size[1])
    except Exception as e:  # noqa: BLE001 - any loader failure is reported as one line naming the path
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise EvaluationError(f"cannot load checkpoint {checkpoint}: {msg}") from e


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m bridge_jax.evaluate", description=__doc__.split("\n\n")[0])
    p.add_argument("--checkpoint", help="params-only dir, training workdir or step dir (omit: baselines only)")
    p.add_argument("--dataset", required=True, choices=DATASETS)
    p.add_argument("--data-dir", required=True, help="dataset root (KITTI layout folder, or KITTI raw for eigen)")
    p.add_argument("--split", default=None, help="KITTI: sub-folder (default training); eigen: list file")
    p.add_argument("--out", default=None, help="write results.json / results.md / pictures here")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out folder")
    p.add_argument("--working-size", type=parse_size, default=None, help="HxW of the network input (default: the size a training workdir was trained at, else 256x512)")
    p.add_argument("--batch", type=int, default=1, help="frames per inference call")
    p.add_argument("--max-frames", type=int, default=None)
    p.add_argument("--pictures", type=int, default=4, help="number of picture panels written to --out")
    p.add_argument("--no-garg-crop", dest="garg_crop", action="store_false", help="eigen: no Garg crop")
    p.add_argument("--baselines", dest="baselines", action="store_true", default=True)
    p.add_argument("--no-baselines", dest="baselines", action="store_false")
    p.add_argument("--no-progress", dest="progress", action="store_false")
    return p


def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.batch < 1:
            raise EvaluationError(f"--batch must be >= 1, got {args.batch}")
        if args.out is not None:
            check_output_dir(args.out, args.overwrite)
        predictor = load_predictor(args.checkpoint, args.working_size) if args.checkpoint else None
        results = evaluate(predictor, args.dataset, args.data_dir, split=args.split, baselines=args.baselines,
                           garg_crop=args.garg_crop, batch=args.batch, max_frames=args.max_frames, out_dir=args.out,
                           num_pictures=args.pictures, overwrite=args.overwrite, progress=args.progress,
                           extra_info={"checkpoint": args.checkpoint})
    except (ValueError, OSError) as e:  # EvaluationError, CorruptImageError...: one line naming the path
        print(f"error: {e}", file=sys.stderr)
        return 2
    print(results["markdown"])
    if args.out:
        print(f"wrote {os.path.join(args.out, 'results.json')} and results.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
