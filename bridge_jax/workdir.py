"""A training workdir: its layout, the metrics log, the status file and what a finished run left there.

    <workdir>/
      config.json, model.json         the run's config and the model description (params-only loaders)
      checkpoints/<step>/{state,data} orbax: train state + grain iterator state (`checkpointing`)
      metrics.jsonl                   one JSON object per log/eval event (one run's history, also after resumes)
      tensorboard/                    tensorboardX event files (scalars, images)
      images/                         the same pictures as PNG files
      status.json                     {"status": "running" | "finished" | "interrupted" | "failed", "step": ...}

The trainer writes it (`MetricsLogger`, `write_status`); `zoo.build_shipped` and a re-run of a finished run read
it back (`last_validation`). Nothing here knows how training works.
"""

from __future__ import annotations

import json
import math
import os
import time
from typing import Optional

import numpy as np
from tensorboardX import SummaryWriter

from bridge_jax import files, visualize

METRICS_JSONL = "metrics.jsonl"
STATUS_JSON = "status.json"
TENSORBOARD_DIR = "tensorboard"
IMAGES_DIR = "images"


def scalar(v) -> float:
    """A 0-d array (numpy or jax) or number as a Python float."""
    return float(np.asarray(v))


class MetricsLogger:
    """metrics.jsonl + TensorBoard (tensorboardX) on process 0; no-ops elsewhere.

    `resume_step`: the step a resumed run restarts from. Records of later steps (written by the previous run
    after its last checkpoint, and redone now) are dropped from metrics.jsonl and TensorBoard's events are
    purged past it, so both read as one run."""

    def __init__(self, workdir: str, enabled: bool, resume_step: Optional[int] = None):
        self.enabled = enabled
        self.image_dir = os.path.join(workdir, IMAGES_DIR)
        self.tb = None
        self.jsonl = None
        if enabled:
            path = os.path.join(workdir, METRICS_JSONL)
            if resume_step is not None:
                truncate_metrics(path, resume_step)
            self.tb = SummaryWriter(os.path.join(workdir, TENSORBOARD_DIR),
                                    purge_step=None if resume_step is None else int(resume_step) + 1)
            self.jsonl = open(path, "a")

    def scalars(self, step: int, values: dict, kind: str = "train") -> None:
        if not self.enabled:
            return
        clean = {k: scalar(v) for k, v in values.items()}
        rec = {"step": int(step), "kind": kind, "time": time.time(), **clean}
        self.jsonl.write(json.dumps(rec, allow_nan=True) + "\n")
        self.jsonl.flush()
        for k, v in clean.items():
            if math.isfinite(v):
                self.tb.add_scalar(k if "/" in k and kind == "train" else f"{kind}/{k}", v, int(step))

    def record(self, step: int, kind: str, payload: dict) -> None:
        """A non-scalar event (e.g. the data-skip report) in metrics.jsonl only."""
        if self.enabled:
            self.jsonl.write(json.dumps({"step": int(step), "kind": kind, "time": time.time(), **payload}) + "\n")
            self.jsonl.flush()

    def image(self, step: int, tag: str, rgb: np.ndarray) -> None:
        """An RGB uint8 (H, W, 3) picture: TensorBoard (tensorboardX's add_image) and images/<tag>_<step>.png."""
        if not self.enabled:
            return
        rgb = np.ascontiguousarray(np.asarray(rgb, np.uint8))
        self.tb.add_image(tag, rgb, int(step), dataformats="HWC")
        os.makedirs(self.image_dir, exist_ok=True)
        visualize.write_image(os.path.join(self.image_dir, f"{tag.replace('/', '_')}_{int(step):07d}.png"), rgb)

    def close(self) -> None:
        if self.enabled:
            self.tb.close()
            self.jsonl.close()


def truncate_metrics(path: str, resume_step: int) -> int:
    """Drops the records of steps after `resume_step` from the metrics.jsonl at `path` (rewritten atomically);
    returns how many were dropped. A torn last line (a crash mid-write) is dropped too."""
    if not os.path.exists(path):
        return 0
    kept, dropped = [], 0
    with open(path) as f:
        for line in f:
            try:
                rec = json.loads(line)
                keep = int(rec.get("step", 0)) <= resume_step
            except (json.JSONDecodeError, TypeError, ValueError, AttributeError):
                keep = False
            if keep and line.endswith("\n"):
                kept.append(line)
            else:
                dropped += 1
    if dropped:
        files.write_text(path, "".join(kept))
    return dropped


def last_validation(workdir: str) -> dict:
    """The last "val" record of a workdir's metrics.jsonl (a finished run re-run does not validate again)."""
    last: dict = {}
    path = os.path.join(workdir, METRICS_JSONL)
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if rec.get("kind") == "val":
                    last = {k: v for k, v in rec.items() if k not in ("kind", "time", "step")}
    return last


def write_status(workdir: str, status: str, step: int, **extra) -> None:
    """status.json: {"status": "running" | "finished" | "interrupted" | "failed", "step", "time", **extra}."""
    files.write_json(os.path.join(workdir, STATUS_JSON), {"status": status, "step": int(step), "time": time.time(),
                                                         **extra})

