"""Evaluation reports: Markdown tables, picture panels, and the results folder (results.json, results.md,
pictures/<frame id>.png) written atomically."""

from __future__ import annotations

import json
import math
import os
from typing import Optional, Sequence

import numpy as np

from bridge_jax import files, metrics, visualize
from bridge_jax.eval.datasets import Frame

METHOD_LABELS = {"model": "bridge_jax", "zero": "zero motion", "opencv": "OpenCV SGBM (disp) / DIS (flow)"}

# One table per scored task (`scoring.SCORED_TASKS`): (task, title, metric names).
METRIC_GROUPS = (
    ("flow", "Optical flow (t → t+1), EPE px / Fl %", ("epe_all", "epe_noc", "epe_occ", "fl_all", "fl_noc",
                                                        "fl_occ")),
    ("disparity", "Disparity at t, EPE px / D1 %", ("epe_all", "epe_noc", "d1_all", "d1_noc", "d1_occ",
                                                     "d1_all_paper", "d1_noc_paper")),
    ("scene_flow", "Disparity at t+1 in frame t (D2 %) and scene flow (SF %)",
     ("d2_epe_all", "d2_epe_noc", "d2_all", "d2_noc", "sf_all", "sf_noc")),
    ("depth", "Depth from disparity at t (m; δ fractions)", ("abs_rel", "sq_rel", "rmse", "rmse_log", "a1", "a2",
                                                              "a3")),
)


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
    for task, title, names in METRIC_GROUPS:
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


ERROR_BAR_MIN_HEIGHT = 96
"""The error colour bar is as tall as the panel, but at least this (shorter bars have no room for ticks)."""


def frame_panel(frame: Frame, pred: dict[str, np.ndarray]) -> np.ndarray:
    """Side-by-side picture of one frame: input, predicted flow / disparity, GT and error maps, and the flow's
    occlusion estimate when the prediction has one (RGB uint8).

    When there are error maps (the frame has GT), the error colour bar (`visualize.error_colorbar`, end-point
    error in px on the log scale of `visualize.error_to_color`) is attached to the right of the whole grid, so
    that the error of any pixel can be read from its colour.
    """
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
    if "occlusion" in pred:
        tiles.append(visualize.to_uint8(pred["occlusion"]))
        labels.append("occluded (flow)")
    grid = visualize.panel(tiles, labels, ncols=4 if len(tiles) > 4 else len(tiles))
    if not any(label.endswith(" error") for label in labels):
        return grid
    bar = visualize.error_colorbar(max(grid.shape[0], ERROR_BAR_MIN_HEIGHT), label="error")
    return visualize.attach_colorbar(grid, bar)


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
    """Write ``results.json``, ``results.md`` and ``pictures/<id>.png`` into ``out_dir`` (atomically: the folder
    appears complete or not at all)."""
    with files.staged_dir(out_dir, overwrite=overwrite) as tmp:
        with open(os.path.join(tmp, "results.json"), "w") as f:
            json.dump(_json_safe({k: v for k, v in results.items() if k != "markdown"}), f, indent=1)
        with open(os.path.join(tmp, "results.md"), "w") as f:
            f.write(results["markdown"])
        if pictures:
            os.makedirs(os.path.join(tmp, "pictures"))
            for fid, img in pictures:
                visualize.write_image(os.path.join(tmp, "pictures", f"{fid}.png"), img)
