"""Evaluation data: frames with their ground truth, from KITTI 2015 / 2012, the Eigen split, the built-in synthetic
video (on disk or rendered in memory) or any KITTI-layout folder.

A `Frame` holds the images of one sample (any of left_t, right_t, left_t1, right_t1, uint8 RGB) and its ground
truth in the KITTI 2015 names (flow_occ, flow_occ_valid, flow_noc_valid, disp_occ_0, disp_noc_0, disp_occ_1,
disp_noc_1; depth + depth_mask for Eigen), plus focal length and baseline where the calibration gives them.
`list_frames` checks a folder (missing or mismatched files are one `EvaluationError` naming the path) and returns
lazy `FrameSpec`s; `load_frame` reads one.
"""

from __future__ import annotations

import dataclasses
import os
from typing import Optional

import numpy as np

from bridge_jax import metrics
from bridge_jax.data import kitti, synthetic

DATASETS = ("kitti2015", "kitti2012", "eigen", "synthetic", "folder")

KITTI_BASELINE_M = 0.54
"""KITTI stereo rig baseline in metres (the paper's protocol uses it for KITTI 2012/2015 depth)."""
KITTI_WIDTH_TO_FOCAL = {1242: 721.5377, 1241: 718.856, 1224: 707.0493, 1238: 718.3351}
"""Focal length (px) looked up by image width, as the monodepth-lineage script did for KITTI 2015."""


class EvaluationError(ValueError):
    """Bad evaluation input (missing or mismatched files, unreadable images, bad options)."""


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


def _read_rgb(path: str) -> np.ndarray:
    """uint8 RGB ``(H, W, 3)``; grayscale files (KITTI 2012 ``image_0``) are replicated to 3 channels."""
    try:
        return kitti.read_image(path)
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


def kitti_specs(data_dir: str, split: Optional[str], *, year: int, require_gt: bool) -> list[FrameSpec]:
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
        return kitti_specs(data_dir, split, year=2015, require_gt=True)
    if dataset == "folder":
        return kitti_specs(data_dir, split, year=2015, require_gt=False)
    if dataset == "kitti2012":
        return kitti_specs(data_dir, split, year=2012, require_gt=True)
    if dataset == "eigen":
        return _eigen_specs(data_dir, split)
    raise EvaluationError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")


def _focal_baseline(spec: FrameSpec, width: int, dataset: str) -> tuple[Optional[float], Optional[float]]:
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


def synthetic_frames(num: int, seed: int, height: int, width: int, scene: str = "demo") -> list[Frame]:
    """`num` frames of the built-in synthetic video rendered in memory at `height` x `width`: sample i uses
    seed `synthetic.sample_seed(seed, i)`, the same samples (images and ground truth) as the folder
    `synthetic.write_kitti_layout(dir, num, seed, height, width)` writes (without its 16-bit PNG rounding).
    `scene` names the generator's settings (`synthetic.SCENE_PRESETS`). No calibration (no depth metrics) and no
    t+1 disparity (no scene-flow metrics)."""
    frames = []
    for i in range(num):
        s = synthetic.render_sample(synthetic.sample_seed(seed, i), height=height, width=width, scene=scene)
        images = dict(zip(("left_t", "right_t", "left_t1", "right_t1"), s["cycle"]))
        gt = {"flow_occ": s["flow"], "flow_occ_valid": s["valid_flow"], "flow_noc_valid": s["noc_flow"],
              "disp_occ_0": np.where(s["valid_disp_t"], s["disp_t"], 0.0).astype(np.float32),
              "disp_noc_0": np.where(s["noc_disp_t"], s["disp_t"], 0.0).astype(np.float32)}
        frames.append(Frame(f"{i:06d}", images, gt))
    return frames
