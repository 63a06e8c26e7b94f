"""Scoring predictions against ground truth: per-frame metric sums by task, accumulated per method.

Tasks: "flow" (EPE / Fl), "disparity" (EPE / D1), "scene_flow" (D2 / SF, KITTI 2015) and "depth" (from the
disparity at t with the frame's focal length and baseline). Reductions and units: see `bridge_jax.metrics`.
"""

from __future__ import annotations

from typing import Iterable

import numpy as np

from bridge_jax import metrics
from bridge_jax.eval.datasets import Frame

TASKS = ("flow", "disparity", "scene_flow", "depth")


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
        self.accumulators = {m: {t: metrics.MetricAccumulator() for t in TASKS} for m in methods}

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
