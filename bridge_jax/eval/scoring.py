"""Scoring predictions against ground truth: per-frame metric sums by task, accumulated per method.

Tasks: "flow" (EPE / Fl), "disparity" (EPE / D1), "scene_flow" (D2 / SF, KITTI 2015) and "depth" (from the
disparity at t with the frame's focal length and baseline). Reductions and units: see `bridge_jax.metrics`.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Optional

import numpy as np

from bridge_jax import metrics
from bridge_jax.eval.datasets import Frame
from bridge_jax.eval.report import frame_panel

SCORED_TASKS = ("flow", "disparity", "scene_flow", "depth")
"""What a frame is scored on (one metric accumulator each; `report.METRIC_GROUPS` has a table per task)."""


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


class Scores:
    """Metric accumulators per method and task (`metrics.MetricAccumulator`)."""

    def __init__(self, methods: Iterable[str]):
        self.accumulators = {m: {t: metrics.MetricAccumulator() for t in SCORED_TASKS} for m in methods}

    def add(self, method: str, frame: Frame, pred: dict[str, np.ndarray]) -> None:
        for task, sums in frame_sums(pred, frame).items():
            self.accumulators[method][task].add(sums)

    def summary(self) -> dict:
        """{method: {task: {"per_image_mean", "pooled", "num_images"}}} for the tasks that were scored."""
        return {m: {t: acc.summary() for t, acc in tasks.items() if acc.names}
                for m, tasks in self.accumulators.items()}

    def per_image_means(self, method: str, prefixes: dict[str, str]) -> dict[str, float]:
        """Per-image means of one method as one flat dict, each task's names prefixed (e.g. {"flow": "flow_"})."""
        out = {}
        for task, prefix in prefixes.items():
            out.update({prefix + k: v for k, v in self.accumulators[method][task].per_image_mean().items()})
        return out


@dataclasses.dataclass
class Scored:
    """What `score_methods` measured: the scores, seconds per method and for loading, the picture panels."""

    scores: Scores
    method_s: dict[str, float]
    load_s: float
    pictures: list[tuple[str, np.ndarray]]
    num_frames: int


def score_methods(batches: Iterable[Sequence[Frame]], methods: dict[str, Callable], *, num_pictures: int = 0,
                  picture_method: Optional[str] = None, bar=None) -> Scored:
    """Runs every method on every batch of frames and scores its predictions.

    Args:
      batches: lists of frames (a generator may load them lazily: its time is counted as loading).
      methods: name -> method (frames -> predictions, see `bridge_jax.eval.methods`).
      num_pictures: keep `frame_panel`s of the first frames, drawn from `picture_method`'s predictions.
      bar: optional progress bar (tqdm), advanced by the frames of each batch.
    """
    scores = Scores(methods)
    method_s = {m: 0.0 for m in methods}
    pictures: list[tuple[str, np.ndarray]] = []
    load_s, n = 0.0, 0
    batches = iter(batches)
    while True:
        t0 = time.perf_counter()
        frames = next(batches, None)
        load_s += time.perf_counter() - t0
        if frames is None:
            break
        for name, method in methods.items():
            t0 = time.perf_counter()
            for frame, pred in zip(frames, method(frames)):
                scores.add(name, frame, pred)
                if name == picture_method and len(pictures) < num_pictures:
                    pictures.append((frame.frame_id, frame_panel(frame, pred)))
            method_s[name] += time.perf_counter() - t0
        n += len(frames)
        if bar is not None:
            bar.update(len(frames))
    return Scored(scores, method_s, load_s, pictures, n)
