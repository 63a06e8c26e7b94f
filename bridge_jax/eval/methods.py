"""Evaluation methods: frames -> predictions at the ground-truth resolution.

A *method* maps a list of `datasets.Frame`s to one prediction dict per frame:

    "disp_t"  (H, W)     disparity of left_t, pixels (>= 0)
    "flow"    (H, W, 2)  optical flow left_t -> left_t1, pixels
    "disp_t1" (H, W)     disparity of left_t1 (when the frame has t+1 disparity ground truth)
    "disp_1"  (H, W)     disp_t1 brought into frame t along the flow (KITTI's disp_1), from the two above
    "occlusion" (H, W)   optional, the model's forward-backward occlusion estimate of the flow (1 = occluded)

`ModelMethod` runs a `bridge_jax.inference.Predictor`; `bridge_jax.eval.baselines` has zero motion and OpenCV.
"""

from __future__ import annotations

import time
from typing import Sequence

import cv2
import jax
import numpy as np

from bridge_jax import geometry
from bridge_jax.confidence import reverse_job
from bridge_jax.eval.datasets import Frame
from bridge_jax.inference import map_to_input_resolution


def frame_jobs(frame: Frame) -> list[tuple[str, str, str]]:
    """(prediction key, image a, image b) of the pairs this frame needs."""
    jobs = [("disp_t", "left_t", "right_t")]
    if "left_t1" in frame.images:
        jobs.append(("flow", "left_t", "left_t1"))
        if "right_t1" in frame.images and any(k.endswith("_1") for k in frame.gt):
            jobs.append(("disp_t1", "left_t1", "right_t1"))
    return jobs


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


def complete(pred: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Adds "disp_1" to a prediction that has "disp_t1" and "flow"."""
    if "disp_t1" in pred and "flow" in pred:
        pred["disp_1"] = bring_to_frame_t(pred["disp_t1"], pred["flow"])
    return pred


class ModelMethod:
    """A predictor as an evaluation method: each frame's pairs in fixed-size batches (one compiled function for
    the whole run), maps brought to the ground-truth resolution as the paper's evaluation did (see
    `bridge_jax.inference`).

    Args:
      predictor: a `bridge_jax.inference.Predictor`.
      batch_frames: frames per predictor call; the call's size in pairs is fixed by the first frame (frames of
        one dataset need the same pairs), so later calls never recompile.
      occlusion: also predict the backward flow and add the forward-backward occlusion estimate (paper eq. 6 at
        the working size, nearest-resized) as "occlusion" (training's validation pictures).
    Attributes:
      inference_s: seconds spent in the predictor (input resize + network + output resize).
    """

    name = "model"

    def __init__(self, predictor, batch_frames: int = 1, *, occlusion: bool = False):
        self.predictor = predictor
        self.batch_frames = max(1, int(batch_frames))
        self.occlusion = occlusion
        self.batch_pairs = None  # set by the first call
        self.inference_s = 0.0

    def _jobs(self, frame: Frame) -> list[tuple[str, str, str, str]]:
        """(prediction key, predictor task, image a, image b) of one frame."""
        jobs = []
        for key, a, b in frame_jobs(frame):
            jobs.append((key, "flow" if key == "flow" else "stereo", a, b))
            if key == "flow" and self.occlusion:
                jobs.append(("flow_bwd", "flow", b, a))
        return jobs

    def __call__(self, frames: Sequence[Frame]) -> list[dict[str, np.ndarray]]:
        jobs, owners = [], []
        for i, frame in enumerate(frames):
            for key, task, a, b in self._jobs(frame):
                jobs.append((task, frame.images[a], frame.images[b]))
                owners.append((i, key))
        if self.batch_pairs is None:
            self.batch_pairs = len(self._jobs(frames[0])) * self.batch_frames
        t0 = time.perf_counter()
        maps = self.predictor.stage_maps(jobs, self.batch_pairs)
        # the polish's fill step: the reverse pairs' maps (the stereo pairs' right views, the flow pairs' backward
        # flows), then `Predictor.fill_maps`; a backward flow kept for the occlusion estimate is not filled
        fill = [j for j in self.predictor.fill_jobs(jobs) if owners[j][1] != "flow_bwd"]
        reverse = self.predictor.stage_maps([reverse_job(*jobs[j]) for j in fill], self.batch_pairs) if fill else []
        at_input = self.predictor.fill_maps(
            jobs, [None if key == "flow_bwd" else map_to_input_resolution(task, m, *image_a.shape[:2])
                   for (_, key), (task, image_a, _), m in zip(owners, jobs, maps)], reverse, fill)
        preds: list[dict[str, np.ndarray]] = [{} for _ in frames]
        working = {}
        for (i, key), m, value in zip(owners, maps, at_input):
            working[i, key] = m
            if key != "flow_bwd":
                preds[i][key] = value
        self.inference_s += time.perf_counter() - t0
        for i, frame in enumerate(frames):
            if (i, "flow_bwd") in working:
                preds[i]["occlusion"] = occlusion_estimate(working[i, "flow"], working[i, "flow_bwd"], frame.size)
        return [complete(p) for p in preds]


# jitted: eager op-by-op dispatch of the warps would cost more than the network per frame
_forward_occlusion = jax.jit(lambda fwd, bwd: geometry.forward_backward_occlusion(fwd, bwd)[0])


def occlusion_estimate(flow_fwd: np.ndarray, flow_bwd: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(H, W) float32 {0, 1} occlusion map of a forward / backward working-size flow pair (1 = occluded, paper
    eq. 6), nearest-resized to `size`."""
    occ = np.asarray(_forward_occlusion(flow_fwd[None], flow_bwd[None])[0, ..., 0], np.float32)
    if occ.shape != tuple(size):
        occ = cv2.resize(occ, (size[1], size[0]), interpolation=cv2.INTER_NEAREST)
    return occ
