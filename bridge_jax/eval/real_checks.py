"""Real-image checks: a model on real photographs whose motion is known exactly.

Six checks (`CHECKS`), each a data builder (`build`) and a scorer (`score`) that returns the check's numbers
(lower is better, except the gains of `shifts` and `zooms`, where 1 is exact):

* ``motorcycle``: scikit-image's Middlebury "Motorcycle" stereo pair with its ground-truth disparity (741x500):
  disparity EPE and D1 (KITTI outliers: > 3 px and > 5 %) over the pixels with ground truth.
* ``homography``: a held-out photo (`data.photos.HELDOUT_PHOTOS`, never used in training) seen through a random
  homography, with 2-3 independently moving pasted patches and a camera-response change plus noise between the
  frames (`homography_pair`): flow EPE-all / EPE-noc and Fl-all against an exact flow and occlusion mask.
* ``heldout_synthetic``: 256x512 frames of the held-out synthetic scenes (`synthetic.SCENE_PRESETS["heldout"]`):
  flow EPE-all / EPE-noc / Fl-all and disparity EPE / D1.
* ``shifts``: each held-out photo moved by 4 and 8 px, horizontally and vertically (`shift_set`): EPE and the
  gain along the motion, per direction.
* ``zooms``: each held-out photo zoomed by +4 % and -4 % about its centre (`zoom_set`): EPE and the gain, per
  direction.
* ``kept_out``: held-out synthetic frames of another seed and homography pairs of other photos (`kept_out`): the
  check no choice is made on (`SELECTION_CHECKS` are the others), where each choice is reported.

A *method* is anything with ``predict(jobs, batch=None) -> list[np.ndarray]``, jobs ``(task, image_a,
image_b)`` of uint8 RGB ``(H, W, 3)`` images, task ``"stereo"`` -> ``(H, W)`` disparity px or ``"flow"`` ->
``(H, W, 2)`` flow px, at the input's resolution: a `bridge_jax.inference.Predictor`, or the baselines
`ZeroMotion` and `OpenCV`.

    data = real_checks.build("homography")                 # pairs with exact flow
    numbers, first = real_checks.score(predictor, "homography", data)

`compare_with_card` scores a checkpoint on the checks of a shipped model's card, at the card's test-time
settings, beside the card's numbers (`bridge-zoo compare NAME WORKDIR`). The card entries themselves come from
running every check for several models and OpenCV (`score`), outside the package.
"""
from __future__ import annotations

import dataclasses
import functools
import os
import time
from collections.abc import Callable, Sequence
from typing import Any, Optional

import cv2
import numpy as np

from bridge_jax import metrics
from bridge_jax.data import photos
from bridge_jax.eval.datasets import Frame, synthetic_frames
from bridge_jax.testtime import TestTime

HOMOGRAPHY_SEED = 20261202
HELDOUT_SYNTHETIC_SEED = 2_000_003  # disjoint from training (seed 0) and the validation seed (1,000,003)
HELDOUT_SYNTHETIC_SIZE = (256, 512)


# ----------------------------------------------------------------------------------------------------------
# Real photos under known motion
# ----------------------------------------------------------------------------------------------------------

def random_homography(rng: np.random.Generator, height: int, width: int, max_shift: float = 12.0) -> np.ndarray:
    """A 3x3 homography in pixel coordinates (x = column, y = row, centres at integers), frame t -> t+1: about
    the image centre a rotation (±3°), zoom (0.95-1.05), shear (±0.02) and perspective (±4e-5 / px), then a
    shift of up to `max_shift` px per axis."""
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    a, s = np.deg2rad(rng.uniform(-3, 3)), rng.uniform(0.95, 1.05)
    lin = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.array(
        [[1.0, rng.uniform(-0.02, 0.02)], [0.0, 1.0]])
    g = np.eye(3)
    g[:2, :2] = lin
    g[2, :2] = rng.uniform(-4e-5, 4e-5, 2)
    centre, back = np.eye(3), np.eye(3)
    centre[:2, 2] = (-cx, -cy)
    back[:2, 2] = (cx + rng.uniform(-max_shift, max_shift), cy + rng.uniform(-max_shift, max_shift))
    return back @ g @ centre


def apply_homography(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maps pixel coordinates `(x, y)` (any same-shape arrays) through the 3x3 `h`."""
    d = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / d, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / d


def _patch_ids(patches: list[dict], x: np.ndarray, y: np.ndarray, time: int) -> np.ndarray:
    """Topmost patch (1..K; 0 = background) covering each position `(x, y)` at `time` (0 = t, 1 = t+1)."""
    ids = np.zeros(x.shape, np.int32)
    for k, p in enumerate(patches, start=1):
        lx, ly = _patch_local(p, x, y, time)
        if p["ellipse"]:
            inside = (lx / p["half"][0]) ** 2 + (ly / p["half"][1]) ** 2 <= 1.0
        else:
            inside = (np.abs(lx) <= p["half"][0]) & (np.abs(ly) <= p["half"][1])
        ids[inside] = k
    return ids


def _patch_local(p: dict, x: np.ndarray, y: np.ndarray, time: int) -> tuple[np.ndarray, np.ndarray]:
    """Patch-local coordinates of positions `(x, y)`: r = p - c at t, r = M^-1 (q - c - v) at t+1."""
    dx, dy = x - p["centre"][0], y - p["centre"][1]
    if time == 0:
        return dx, dy
    dx, dy = dx - p["shift"][0], dy - p["shift"][1]
    inv = np.linalg.inv(p["affine"])
    return inv[0, 0] * dx + inv[0, 1] * dy, inv[1, 0] * dx + inv[1, 1] * dy


def camera_change(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """uint8 RGB (H, W, 3) -> uint8 RGB (H, W, 3) through another camera response: per-channel gain 0.9-1.1,
    offset ±3 %, gamma 0.9-1.1 and noise of 1 % std."""
    x = img.astype(np.float32) / 255.0
    x = np.clip(x * rng.uniform(0.9, 1.1, 3) + rng.uniform(-0.03, 0.03, 3), 0, 1) ** rng.uniform(0.9, 1.1)
    x = x + rng.normal(0.0, 0.01, x.shape)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


MARGIN = 0.1
"""The share of a photo's height and width `homography_pair` crops from each side by default."""


def crop_margins(shape: tuple, margin: float = MARGIN) -> tuple[int, int]:
    """(rows, columns) `homography_pair` crops from each side of a photo of `shape` (h, w, ...)."""
    return int(round(margin * shape[0])), int(round(margin * shape[1]))


def homography_pair(photo: np.ndarray, patch_photo: np.ndarray, rng: np.random.Generator, *,
                    homography: np.ndarray | None = None, patches: list[dict] | None = None,
                    margin: float = MARGIN, photometric: bool = True) -> dict:
    """Two frames of a real photo under known motion, with exact flow and occlusion.

    Frame t is the photo (uint8 (h, w, 3)) cropped by `margin` on each side; frame t+1 sees the same plane
    through the homography `homography` (frame-t pixel -> frame-t+1 pixel; default `random_homography`).
    Patches of `patch_photo` (default 2-3 random rectangles and ellipses, 25-55 px half sizes) lie on top, each
    moving by its own affine map q = c + v + M (p - c). Frame t+1 gets `camera_change` when `photometric`.

    Returns {"frame_t", "frame_t1": uint8 (H, W, 3), "flow": float32 (H, W, 2) px t -> t+1, "valid": all True,
    "noc": bool (H, W) — the match lies inside frame t+1 and shows the same surface there}.
    """
    ph, pw = photo.shape[:2]
    my, mx = crop_margins(photo.shape, margin)
    height, width = ph - 2 * my, pw - 2 * mx
    g = random_homography(rng, height, width) if homography is None else np.asarray(homography, np.float64)
    if patches is None:
        patches = []
        for _ in range(int(rng.integers(2, 4))):
            a, s = np.deg2rad(rng.uniform(-5, 5)), rng.uniform(0.95, 1.05)
            patches.append({"centre": (rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * height),
                            "half": (rng.uniform(25, 55), rng.uniform(25, 55)), "ellipse": bool(rng.uniform() < 0.5),
                            "shift": tuple(rng.uniform(-15, 15, 2)),
                            "affine": s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]),
                            "offset": (rng.uniform(60, patch_photo.shape[1] - 60),
                                       rng.uniform(60, patch_photo.shape[0] - 60))})
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))

    def render(time: int) -> tuple[np.ndarray, np.ndarray]:
        if time == 0:
            sx, sy = xs, ys
        else:
            sx, sy = apply_homography(np.linalg.inv(g), xs, ys)
        img = cv2.remap(photo, (sx + mx).astype(np.float32), (sy + my).astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT_101)
        ids = _patch_ids(patches, xs, ys, time)
        for k, p in enumerate(patches, start=1):
            lx, ly = _patch_local(p, xs, ys, time)
            tex = cv2.remap(patch_photo, (lx + p["offset"][0]).astype(np.float32),
                            (ly + p["offset"][1]).astype(np.float32), cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REFLECT_101)
            img[ids == k] = tex[ids == k]
        return img, ids

    frame_t, ids_t = render(0)
    frame_t1, _ = render(1)
    tx, ty = apply_homography(g, xs, ys)
    for k, p in enumerate(patches, start=1):
        sel = ids_t == k
        dx, dy = xs[sel] - p["centre"][0], ys[sel] - p["centre"][1]
        m = p["affine"]
        tx[sel] = p["centre"][0] + p["shift"][0] + m[0, 0] * dx + m[0, 1] * dy
        ty[sel] = p["centre"][1] + p["shift"][1] + m[1, 0] * dx + m[1, 1] * dy
    inside = (tx >= 0) & (tx <= width - 1) & (ty >= 0) & (ty <= height - 1)
    noc = inside & (_patch_ids(patches, tx, ty, 1) == ids_t)
    if photometric:
        frame_t1 = camera_change(frame_t1, rng)
    flow = np.stack([tx - xs, ty - ys], -1).astype(np.float32)
    return {"frame_t": frame_t, "frame_t1": frame_t1, "flow": flow, "valid": np.ones((height, width), bool),
            "noc": noc}


def homography_set(per_photo: int = 3, seed: int = HOMOGRAPHY_SEED,
                   names: Sequence[str] = photos.HELDOUT_PHOTOS, limit: Optional[int] = None) -> list[dict]:
    """`per_photo` pairs (`homography_pair`, plus "id") of each photo of `names` (default the held-out photos);
    the patches come from the next photo. One generator draws every pair in turn, so the first pairs of a set do
    not depend on how many follow; `limit` stops after that many (the same first pairs, without drawing the
    rest)."""
    rng = np.random.default_rng(seed)
    load = functools.lru_cache(maxsize=None)(photos.load_photo)
    out = []
    for i, name in enumerate(names):
        for j in range(per_photo):
            if limit is not None and len(out) >= limit:
                return out
            pair = homography_pair(load(name), load(names[(i + 1) % len(names)]), rng)
            pair["id"] = f"{name}-{j}"
            out.append(pair)
    return out


SHIFTS = ((4.0, 0.0), (-8.0, 0.0), (0.0, 4.0), (0.0, -8.0))
"""The translations (dx, dy) px of `shift_set`: two horizontal, then the same two turned vertical."""


def shift_set(seed: int = HOMOGRAPHY_SEED + 1) -> list[dict]:
    """Each held-out photo moved by each of `SHIFTS` (no patches, a camera-response change between the frames;
    `homography_pair` plus "id" and "shift" (dx, dy)): the simplest motion there is, asked once horizontally and
    once vertically. A model that learned flow from scenes that hardly move vertically answers the vertical ones
    short (`shift_metrics`)."""
    rng = np.random.default_rng(seed)
    out = []
    for name in photos.HELDOUT_PHOTOS:
        image = photos.load_photo(name)
        for dx, dy in SHIFTS:
            g = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
            pair = homography_pair(image, image, rng, homography=g, patches=[])
            pair.update(id=f"{name}-{dx:+.0f},{dy:+.0f}", shift=(dx, dy))
            out.append(pair)
    return out


ZOOMS = (1.04, 0.96)
"""The zooms of `zoom_set`: the scene expands by 4 % (the camera moves towards it), then contracts by 4 %."""


def zoom_set(seed: int = HOMOGRAPHY_SEED + 2) -> list[dict]:
    """Each held-out photo zoomed by each of `ZOOMS` about its centre (no patches, a camera-response change
    between the frames; `homography_pair` plus "id" and "zoom"): flow s (p - c) - (p - c), from 0 at the centre
    to about 8 px at the corners. A model whose training scenes expand only one way (a rig driving forward), or
    only far from the horizon, reads the zoom short (`zoom_metrics`)."""
    rng = np.random.default_rng(seed)
    out = []
    for name in photos.HELDOUT_PHOTOS:
        image = photos.load_photo(name)
        my, mx = crop_margins(image.shape)
        cx, cy = (image.shape[1] - 2 * mx - 1) / 2.0, (image.shape[0] - 2 * my - 1) / 2.0  # centre of frame t
        for s in ZOOMS:
            g = np.array([[s, 0.0, (1 - s) * cx], [0.0, s, (1 - s) * cy], [0.0, 0.0, 1.0]])
            pair = homography_pair(image, image, rng, homography=g, patches=[])
            pair.update(id=f"{name}-x{s:.2f}", zoom=s)
            out.append(pair)
    return out


def zoom_metrics(flows: Sequence[np.ndarray], pairs: Sequence[dict]) -> dict:
    """EPE (noc pixels) of the expanding and of the contracting zooms of `zoom_set` (`flows`: (H, W, 2) px per
    pair), and the gain: the least-squares scale of the predicted flow against the true one over the noc pixels
    (sum f.g / sum g.g; 1 = exact, < 1 = the zoom read short)."""
    out: dict[str, list] = {"epe_expand": [], "epe_contract": [], "gain_expand": [], "gain_contract": []}
    for f, pair in zip(flows, pairs):
        kind = "expand" if pair["zoom"] > 1 else "contract"
        m, g = pair["noc"], pair["flow"].astype(np.float64)
        out[f"epe_{kind}"].append(float(np.linalg.norm(f - g, axis=-1)[m].mean()))
        out[f"gain_{kind}"].append(float((f[m] * g[m]).sum() / (g[m] ** 2).sum()))
    return {k: float(np.mean(v)) for k, v in out.items()}


def shift_metrics(flows: Sequence[np.ndarray], pairs: Sequence[dict]) -> dict:
    """EPE (noc pixels) of the horizontal and of the vertical shifts of `shift_set` (`flows`: (H, W, 2) px per
    pair), and the gain along the motion: median predicted component / true component, over the noc pixels
    (1 = exact, < 1 = short)."""
    out: dict[str, list] = {"epe_horizontal": [], "epe_vertical": [], "gain_horizontal": [], "gain_vertical": []}
    for f, pair in zip(flows, pairs):
        dx, dy = pair["shift"]
        axis = "horizontal" if dy == 0 else "vertical"
        m = pair["noc"]
        out[f"epe_{axis}"].append(float(np.linalg.norm(f - pair["flow"], axis=-1)[m].mean()))
        c, true = (0, dx) if dy == 0 else (1, dy)
        out[f"gain_{axis}"].append(float(np.median(f[..., c][m]) / true))
    return {k: float(np.mean(v)) for k, v in out.items()}


def motorcycle() -> dict:
    """scikit-image's Middlebury Motorcycle pair: {"left", "right": uint8 (500, 741, 3), "disp": float32
    (500, 741) px (0 where there is no ground truth), "valid": bool (500, 741)}."""
    from skimage import data as skdata
    left, right, disp = skdata.stereo_motorcycle()
    valid = np.isfinite(disp) & (disp > 0)
    return {"left": left, "right": right, "disp": np.where(valid, disp, 0).astype(np.float32), "valid": valid}


def heldout_synthetic(num: int = 16) -> list[Frame]:
    """`num` held-out synthetic frames at `HELDOUT_SYNTHETIC_SIZE` (`datasets.synthetic_frames`: images
    "left_t", "right_t", "left_t1" uint8 (256, 512, 3); ground truth "flow_occ" (256, 512, 2), "disp_occ_0"
    (256, 512) and their masks); frame i is the same whatever `num`."""
    return synthetic_frames(num, HELDOUT_SYNTHETIC_SEED, *HELDOUT_SYNTHETIC_SIZE, scene="heldout")


KEPT_OUT_SYNTHETIC_SEED = 3_000_003  # disjoint from training (0), validation (1,000,003) and the held-out check
KEPT_OUT_PHOTOS = ("rocket", "hubble_deep_field", "immunohistochemistry", "retina", "brick", "grass")
"""The photos of the kept-out check's flow pairs: training photos (their textures were seen in training, their
motions under these homographies were not), so that no photo of a selection's checks is reused."""
KEPT_OUT_PHOTO_SEED = 7


def kept_out(synthetic_num: int = 16, per_photo: int = 2, limit: Optional[int] = None) -> dict:
    """The data of the ``kept_out`` check, which no choice of this project may look at (the test-time settings a
    card recommends, the polish's parameters, the working size: each is chosen on the other checks and reported
    here): {"frames": `synthetic_num` frames of the held-out synthetic scenes drawn with another seed than the
    ``heldout_synthetic`` check's (`KEPT_OUT_SYNTHETIC_SEED`, 256x512), "pairs": `per_photo` homography pairs
    (`homography_set`, moving patches and camera change included) of each of `KEPT_OUT_PHOTOS`}; `limit`: only
    the first `limit` frames and pairs (a quick look)."""
    num = synthetic_num if limit is None else min(limit, synthetic_num)
    return {"frames": synthetic_frames(num, KEPT_OUT_SYNTHETIC_SEED, *HELDOUT_SYNTHETIC_SIZE, scene="heldout"),
            "pairs": homography_set(per_photo, KEPT_OUT_PHOTO_SEED, KEPT_OUT_PHOTOS, limit=limit)}


# ----------------------------------------------------------------------------------------------------------
# Methods and scoring
# ----------------------------------------------------------------------------------------------------------

class ZeroMotion:
    """The method that sees no motion: disparity 0 and flow 0 at each input's resolution, the scale every
    check's numbers are read against."""

    def predict(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        del batch  # nothing is batched
        return [np.zeros(a.shape[:2] + ((2,) if task == "flow" else ()), np.float32) for task, a, _ in jobs]


MIDDLEBURY_MOTORCYCLE_NDISP = (270, 2964)
"""Middlebury 2014's stated disparity range of the Motorcycle pair: ``ndisp`` = 270 levels (a conservative bound
a stereo method may use: it searches d = 0..269) at the full 2964 px width (its calib.txt; scikit-image's copy
is the pair downsampled 4×)."""

HELDOUT_SYNTHETIC_MAX_DISPARITY = 46.4
"""The largest disparity px the held-out synthetic scenes have at 256x512 (`synthetic.SCENE_PRESETS["heldout"]`):
the maximum over 64 frames of that generator drawn with seeds other than the check's (`sample_seed(7_000_001,
i)`, i < 64), 46.4 px; the check's own 16 frames reach 30.2."""


def stated_max_disparity(check: str, width: int) -> Optional[float]:
    """The largest disparity px a user of `check`'s stereo pairs would know they have, at an image `width` px
    wide, from the data's own statement, never from a score: Motorcycle's ``ndisp`` (`MIDDLEBURY_MOTORCYCLE_NDISP`,
    269 px at 2964 px, scaled to `width`: 67.3 px at scikit-image's 741), the held-out synthetic generator's
    maximum (`HELDOUT_SYNTHETIC_MAX_DISPARITY` at 512 px, scaled to `width`); None for the checks without stereo
    pairs."""
    if check == "motorcycle":
        ndisp, full_width = MIDDLEBURY_MOTORCYCLE_NDISP
        return (ndisp - 1) * width / full_width
    if check == "heldout_synthetic":
        return HELDOUT_SYNTHETIC_MAX_DISPARITY * width / HELDOUT_SYNTHETIC_SIZE[1]
    if check not in CHECKS:
        raise ValueError(f"unknown real-image check {check!r}; checks: {', '.join(CHECKS)}")
    return None


class OpenCV:
    """OpenCV at the full input resolution (`eval.baselines`): StereoSGBM in its standard form with its holes
    filled for "stereo", and the optical flow `flow` (a name of `baselines.FLOWS`: "DIS medium", "DIS fine",
    "DeepFlow") for "flow". SGBM searches 0..`max_disparity` px when given; else, with `check`, the range
    that check's pairs state (`stated_max_disparity` at each pair's width); else ``min(192, W/4)`` levels.
    `score` runs it with `check` set (`for_check`)."""

    def __init__(self, flow: str = "DIS medium", max_disparity: Optional[float] = None,
                 check: Optional[str] = None):
        from bridge_jax.eval import baselines  # see predict
        if flow not in baselines.FLOWS:
            raise ValueError(f"OpenCV flow {flow!r}: expected one of {', '.join(baselines.FLOWS)}")
        if check is not None and check not in CHECKS:
            raise ValueError(f"unknown real-image check {check!r}; checks: {', '.join(CHECKS)}")
        self.flow, self.max_disparity, self.check = flow, max_disparity, check

    def for_check(self, check: str) -> "OpenCV":
        """The same method with the stereo range `check`'s pairs state (unless `max_disparity` is set)."""
        return OpenCV(self.flow, self.max_disparity, check)

    def _max_disparity(self, width: int) -> Optional[float]:
        if self.max_disparity is not None or self.check is None:
            return self.max_disparity
        return stated_max_disparity(self.check, width)

    def predict(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        del batch  # one pair at a time
        # imported here: eval.baselines brings jax (through eval.methods), which `bridge-zoo` would otherwise load
        # for every command, since its parser takes POLISH_CHOICES from this module
        from bridge_jax.eval import baselines
        flow = baselines.FLOWS[self.flow]
        return [flow(a, b) if task == "flow" else baselines.sgbm_disparity(a, b, self._max_disparity(a.shape[1]))
                for task, a, b in jobs]


def _pick(d: dict, keys: Sequence[str]) -> dict:
    return {k: d[k] for k in keys}


def _mean(rows: list[dict]) -> dict:
    return {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}


def pair_flows(method, pairs: Sequence[dict]) -> list[np.ndarray]:
    """The flow (H, W, 2) px of each of `pairs` (frame_t -> frame_t1) by `method`, one pair per batch (the pairs
    differ in size)."""
    return method.predict([("flow", p["frame_t"], p["frame_t1"]) for p in pairs], batch=1)


def score_motorcycle(method, moto: dict) -> tuple[dict, np.ndarray]:
    """{"epe_all", "d1_all"} of `method`'s disparity of `motorcycle()` over its ground-truth pixels, the same
    within a few pixels of the depth edges ("epe_edge", "d1_edge", and "fat_edge", the share of those pixels
    given a nearer surface's disparity: `metrics.disparity_edge_metrics`) and on the strip along the left edge
    that the right image does not see ("epe_outview", "d1_outview": `metrics.disparity_out_of_view_metrics`),
    and that disparity (500, 741) px."""
    d = method.predict([("stereo", moto["left"], moto["right"])])[0]
    return {**_pick(metrics.disparity_metrics(d, moto["disp"], moto["valid"]), ("epe_all", "d1_all")),
            **metrics.disparity_edge_metrics(d, moto["disp"], moto["valid"]),
            **metrics.disparity_out_of_view_metrics(d, moto["disp"], moto["valid"])}, d


def score_homography(method, pairs: Sequence[dict]) -> tuple[dict, np.ndarray]:
    """{"epe_all", "epe_noc", "fl_all"} of `method`'s flow, each the mean over `pairs` (`homography_set`), and
    the first pair's flow (H, W, 2) px."""
    flows = pair_flows(method, pairs)
    rows = [_pick(metrics.flow_metrics(f, p["flow"], p["valid"], p["noc"]), ("epe_all", "epe_noc", "fl_all"))
            for p, f in zip(pairs, flows)]
    return _mean(rows), flows[0]


def score_heldout_synthetic(method, frames: Sequence[Frame]) -> tuple[dict, np.ndarray]:
    """{"flow_epe_all", "flow_epe_noc", "fl_all", "disp_epe_all", "d1_all", "disp_epe_edge", "d1_edge",
    "fat_edge"} of `method` (the last three within a few pixels of the depth edges,
    `metrics.disparity_edge_metrics`), each the mean over `frames` (`heldout_synthetic`; the edge numbers over
    the frames with a depth edge), and the first frame's flow (256, 512, 2) px."""
    rows, first = [], None
    for fr in frames:
        im = fr.images
        # one call for both pairs of a frame: a predictor runs them as one batch of two
        d, f = method.predict([("stereo", im["left_t"], im["right_t"]), ("flow", im["left_t"], im["left_t1"])])
        fm = metrics.flow_metrics(f, fr.gt["flow_occ"], fr.gt["flow_occ_valid"], fr.gt["flow_noc_valid"])
        dm = metrics.disparity_metrics(d, fr.gt["disp_occ_0"])
        em = metrics.disparity_edge_metrics(d, fr.gt["disp_occ_0"])
        rows.append({"flow_epe_all": fm["epe_all"], "flow_epe_noc": fm["epe_noc"], "fl_all": fm["fl_all"],
                     "disp_epe_all": dm["epe_all"], "d1_all": dm["d1_all"], "disp_epe_edge": em["epe_edge"],
                     "d1_edge": em["d1_edge"], "fat_edge": em["fat_edge"]})
        first = f if first is None else first
    return _mean(rows), first


def score_kept_out(method, data: dict) -> tuple[dict, np.ndarray]:
    """The ``kept_out`` check (`kept_out`): the held-out synthetic numbers of its frames
    (`score_heldout_synthetic`: flow, disparity, near depth edges) and "photo_epe_all" / "photo_epe_noc", the
    mean flow EPE over its photo pairs; and the first frame's flow (256, 512, 2) px."""
    numbers, first = score_heldout_synthetic(method, data["frames"])
    photo, _ = score_homography(method, data["pairs"])
    return {**numbers, "photo_epe_all": photo["epe_all"], "photo_epe_noc": photo["epe_noc"]}, first


def score_shifts(method, pairs: Sequence[dict]) -> tuple[dict, np.ndarray]:
    """`shift_metrics` of `method`'s flows of `pairs` (`shift_set`), and the first pair's flow (H, W, 2) px."""
    flows = pair_flows(method, pairs)
    return shift_metrics(flows, pairs), flows[0]


def score_zooms(method, pairs: Sequence[dict]) -> tuple[dict, np.ndarray]:
    """`zoom_metrics` of `method`'s flows of `pairs` (`zoom_set`), and the first pair's flow (H, W, 2) px."""
    flows = pair_flows(method, pairs)
    return zoom_metrics(flows, pairs), flows[0]


CHECKS: dict[str, Callable] = {"motorcycle": score_motorcycle, "homography": score_homography,
                               "heldout_synthetic": score_heldout_synthetic, "shifts": score_shifts,
                               "zooms": score_zooms, "kept_out": score_kept_out}
"""The checks by name, in the order they run, with their scorers."""
SELECTION_CHECKS = tuple(c for c in CHECKS if c != "kept_out")
"""The checks a choice (a card's test-time settings, the polish's parameters, a recipe) may be made on; the
``kept_out`` check only reports how each choice fares on data it did not see."""


def build(check: str, *, per_photo: int = 3, synthetic_num: int = 16, limit: Optional[int] = None) -> Any:
    """The inputs and ground truth of `check` (one of `CHECKS`): `motorcycle()` (a dict), else a list of pairs
    or frames: `homography_set(per_photo)`, `heldout_synthetic(synthetic_num)`, `shift_set()`, `zoom_set()`;
    `kept_out(synthetic_num)` (a dict of frames and pairs).
    `limit`: keep only the first `limit` pairs or frames (a quick look: the first ones are the same as in the
    full set, so the numbers are those of a subset, not the card's)."""
    if check == "motorcycle":
        return motorcycle()
    if check == "heldout_synthetic":
        return heldout_synthetic(synthetic_num if limit is None else min(limit, synthetic_num))
    if check == "kept_out":
        return kept_out(synthetic_num, limit=limit)
    sets = {"homography": lambda: homography_set(per_photo, limit=limit), "shifts": shift_set, "zooms": zoom_set}
    if check not in sets:
        raise ValueError(f"unknown real-image check {check!r}; checks: {', '.join(CHECKS)}")
    return sets[check]()[:limit]


def score(method, check: str, data: Any) -> tuple[dict, np.ndarray]:
    """(numbers, first map) of `method` on `check` given its `build` data: numbers {metric: value}, the map
    the check's first input got (a disparity (H, W) px for "motorcycle", else a flow (H, W, 2) px). A method
    with a `for_check(check)` (`OpenCV`: the check's stated disparity range) runs as that returns."""
    if check not in CHECKS:
        raise ValueError(f"unknown real-image check {check!r}; checks: {', '.join(CHECKS)}")
    if hasattr(method, "for_check"):
        method = method.for_check(check)
    return CHECKS[check](method, data)


# ----------------------------------------------------------------------------------------------------------
# Comparing a checkpoint with a shipped model's card
# ----------------------------------------------------------------------------------------------------------

CARD_KEY = "real_images"
"""The card entry with the real-image numbers at the card's test-time settings: {check: {size: {metric: value}}}
("size" as the card names it, e.g. "native" or "192x384", plus "opencv")."""
CARD_KEY_POLISH_NONE = "real_images_polish_none"
"""The card entry, when a card has one, with the same numbers measured without the test-time polish."""
POLISH_CHOICES = ("card", "none", "both")
MISSING = "–"
"""What a table cell shows where there is no number."""


def card_settings(card: dict) -> dict:
    """The test-time settings a shipped model's card (`zoo.info`) recommends and measured its real-image
    numbers at: {"working_size": "native" | "trained" | "HxW" (as the card names it), "refine": int,
    "symmetry": str, "polish": str} (`TestTime.from_card`)."""
    return {"working_size": str(card.get("default_working_size") or "trained"),
            **TestTime.from_card(card).to_dict()}


def card_numbers(card: dict, polish: str) -> Optional[dict]:
    """The card's real-image numbers at its working size with test-time polish `polish`: {check: {metric:
    value}}; None when the card holds none for that polish (only the card's own polish, and "none" when the card
    has `CARD_KEY_POLISH_NONE`, are measured)."""
    settings = card_settings(card)
    if polish == settings["polish"]:
        key = CARD_KEY
    elif polish == "none":
        key = CARD_KEY_POLISH_NONE
    else:
        return None
    by_check = card.get(key)
    if not isinstance(by_check, dict):
        return None
    size = settings["working_size"]
    return {check: dict(by_check[check][size]) for check in CHECKS  # in the order the checks run
            if isinstance(by_check.get(check), dict) and isinstance(by_check[check].get(size), dict)}


TIE = 1e-3
"""Relative differences below this count as a tie in `at_least_as_good`: the same weights score differently on
another kind of CPU (`long` against its own card, measured on an Intel Xeon, on an AMD EPYC: up to 1e-4)."""


def at_least_as_good(metric: str, value: float, reference: float, decimals: int = 3) -> bool:
    """Whether `value` of `metric` is at least as good as `reference`: lower is better, except for a gain, where
    closer to 1 is; a difference within `TIE` or that the table (`decimals`) prints as 0 counts as a tie."""
    def error(v: float) -> float:
        return abs(v - 1.0) if metric.startswith("gain") else v
    a, b = error(value), error(reference)
    return a <= b * (1.0 + TIE) or round(a, decimals) <= round(b, decimals)


def comparison_rows(card: Optional[dict], measured: dict, card_none: Optional[dict] = None,
                    measured_none: Optional[dict] = None) -> list[dict]:
    """One row per check and metric of `measured` ({check: {metric: value}}, the checkpoint's numbers): {"check",
    "metric", "card", "workdir", "difference" (workdir - card), "as_good" (`at_least_as_good`)}, plus
    "card_polish_none" and "workdir_polish_none" when `measured_none` is given. A number the card lacks
    (`card` / `card_none` None, or without that check or metric) is None, and so are its difference and
    as_good."""
    rows = []
    for check, values in measured.items():
        for metric, value in values.items():
            ref = ((card or {}).get(check) or {}).get(metric)
            row = {"check": check, "metric": metric, "card": ref, "workdir": value,
                   "difference": None if ref is None else value - ref,
                   "as_good": None if ref is None else at_least_as_good(metric, value, ref)}
            if measured_none is not None:
                row["card_polish_none"] = ((card_none or {}).get(check) or {}).get(metric)
                row["workdir_polish_none"] = measured_none[check][metric]
            rows.append(row)
    return rows


def _cell(value: Any, signed: bool = False) -> str:
    if value is None:
        return MISSING
    if isinstance(value, bool):
        return "yes" if value else "no"
    value = round(value, 3) + 0.0  # + 0.0: a difference that rounds to zero prints as +0.000, not -0.000
    return f"{value:+.3f}" if signed else f"{value:.3f}"


def comparison_table(rows: Sequence[dict], polish: str) -> list[str]:
    """`comparison_rows` as an aligned Markdown table (one line per row, after a header and a rule); `polish`:
    the test-time polish of the "card" and "workdir" columns."""
    head = ["check", "metric", f"card (polish {polish})", f"workdir (polish {polish})", "difference",
            "at least as good"]
    extra = bool(rows) and "workdir_polish_none" in rows[0]
    if extra:
        head += ["card (polish none)", "workdir (polish none)"]
    body = []
    for r in rows:
        cells = [r["check"], r["metric"], _cell(r["card"]), _cell(r["workdir"]), _cell(r["difference"], True),
                 _cell(r["as_good"])]
        if extra:
            cells += [_cell(r["card_polish_none"]), _cell(r["workdir_polish_none"])]
        body.append(cells)
    widths = [max(len(c[i]) for c in [head] + body) for i in range(len(head))]

    def line(cells: Sequence[str]) -> str:
        # text columns to the left, numbers to the right (their decimal points line up)
        return "| " + " | ".join(c.ljust(w) if i < 2 else c.rjust(w)
                                 for i, (c, w) in enumerate(zip(cells, widths))) + " |"
    rule = "|" + "|".join("-" * (w + 2) if i < 2 else "-" * (w + 1) + ":" for i, w in enumerate(widths)) + "|"
    return [line(head), rule] + [line(c) for c in body]


def compare_with_card(name: str, checkpoint: str | os.PathLike, *, polish: str = "both",
                      limit: Optional[int] = None, log: Optional[Callable[[str], None]] = None) -> dict:
    """Scores `checkpoint` (a shipped name or any checkpoint `inference.load_predictor` takes: training
    workdir, step dir, params dir) on the real-image checks of the shipped model `name`'s card, at the card's
    test-time settings (`card_settings`; a card's "trained" size is `name`'s trained size, so both see the same
    pixels), beside the card's numbers.

    `polish`: "card" scores it with the card's test-time polish, "none" without a polish, "both" with both
    (once when the card's polish is "none"). `limit`: only the first `limit` inputs of each check (`build`; a
    quick look). `log`: called with a line of progress per check.

    Returns {"name", "checkpoint", "settings" (`card_settings`), "card_measured", "limit", "polish" (the
    polish of the main columns), "runs": {polish: {"numbers": {check: {metric: value}}, "seconds"}}, "rows"
    (`comparison_rows`)}. Raises ValueError naming NAME when it is not a shipped model or its card holds no
    real-image numbers, and naming the checkpoint when it cannot be read.
    """
    from bridge_jax import cli, inference, zoo  # a predictor's imports (jax) only when one is wanted

    shipped = [n for n in zoo.names() if zoo.entry(n).kind == "shipped"]
    if name not in shipped:
        raise ValueError(f"NAME {name!r}: not a shipped model (shipped: {', '.join(shipped)})")
    if polish not in POLISH_CHOICES:
        raise ValueError(f"--polish {polish!r}: expected one of {', '.join(POLISH_CHOICES)}")
    if limit is not None and limit < 1:
        raise ValueError(f"--limit {limit}: expected a positive number of inputs per check")
    card = zoo.info(name)
    settings = card_settings(card)
    reference = card_numbers(card, settings["polish"])
    if not reference:
        raise ValueError(f"NAME {name!r}: its card holds no real-image numbers at its working size "
                         f"{settings['working_size']} to compare with")
    polishes = list(dict.fromkeys({"card": [settings["polish"]], "none": ["none"],
                                   "both": [settings["polish"], "none"]}[polish]))
    size = settings["working_size"]
    working_size = (int(card["height"]), int(card["width"])) if size == "trained" else cli.parse_working_size(size)
    # every predictor loads (and so every path is checked) before the minutes of scoring start
    test_time = TestTime(settings["refine"], settings["symmetry"])
    # the polish's parameters the card was measured with (a retrained workdir has no card of its own to read them
    # from, and its numbers are only comparable at the same ones)
    polish_config = zoo.card_polish_config(name)
    predictors = {q: inference.load_predictor(checkpoint, size=working_size,
                                              size_option=f"{name}'s working size {size}",
                                              test_time=dataclasses.replace(test_time, polish=q),
                                              polish_config=polish_config)
                  for q in polishes}
    data = {check: build(check, limit=limit) for check in reference}
    runs = {}
    for q, predictor in predictors.items():
        numbers, t_run = {}, time.perf_counter()
        for check in reference:
            t0 = time.perf_counter()
            values, _ = score(predictor, check, data[check])
            numbers[check] = {k: v for k, v in values.items() if k in reference[check]}
            if log:
                log(f"polish {q}: {check} {time.perf_counter() - t0:.1f} s")
        runs[q] = {"numbers": numbers, "seconds": round(time.perf_counter() - t_run, 1)}
    main, other = polishes[0], polishes[1:]
    rows = comparison_rows(card_numbers(card, main), runs[main]["numbers"],
                           *((card_numbers(card, "none"), runs["none"]["numbers"]) if other else ()))
    return {"name": name, "checkpoint": os.fspath(checkpoint), "settings": settings,
            "card_measured": card.get("real_images_measured"), "limit": limit, "polish": main, "runs": runs,
            "rows": rows}


def comparison_lines(result: dict) -> list[str]:
    """What `bridge-zoo compare` prints of a `compare_with_card` result: a line naming the model, the
    checkpoint and the settings, the table (`comparison_table`) and the seconds each run took."""
    s = result["settings"]
    lines = [f"{result['checkpoint']} on the real-image checks of {result['name']}'s card (measured "
             f"{result['card_measured'] or '?'})",
             f"at the card's test-time settings: working size {s['working_size']}, refine {s['refine']}, symmetry "
             f"{s['symmetry']}, polish {s['polish']}"]
    if result["limit"] is not None:
        lines.append(f"only the first {result['limit']} input(s) of each check (--limit): the card's numbers are "
                     "over all of them")
    lines += [""] + comparison_table(result["rows"], result["polish"]) + [""]
    gains = any(r["metric"].startswith("gain") for r in result["rows"])
    seconds = ", ".join(f"polish {q} {r['seconds']:.1f}" for q, r in result["runs"].items())
    lines.append(f"lower is better{', for a gain closer to 1' if gains else ''}; seconds: {seconds}")
    return lines
