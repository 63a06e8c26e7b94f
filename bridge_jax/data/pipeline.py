"""grain input pipeline: cycle source → shuffle → shard → decode → augment → resize → batch → workers.

    make_train_dataset(DataConfig(...), global_batch=..., seed=..., height=256, width=512)
      MapDataset.range(N) ─ shuffle(seed) ─ [:N - N % P] ─ [p::P] ─ repeat(num_epochs)
      ─ map(load: decode the cycle, or skip a corrupt one and take the next valid one)
      ─ random_map(augment, same draw for the 4 frames) ─ map(resize to H × W)
      ─ to_iter_dataset ─ batch(global_batch / P, drop_remainder) ─ mp_prefetch(num_workers)
      ─ map(record the batch's skipped cycles in the dataset's skip log, `dataset.skips`)
    yields {"cycle": float32 (B_local, 4, H, W, 3) in [0, 1]}; the iterator's get_state()/set_state() resume on
    the exact next batch (the state is a small dict, saved by the trainer in its orbax checkpoint).

Sharding: every process applies the same shuffle (same seed) and keeps elements p, p+P, … of it, so the P shards
are disjoint and together complete (up to N mod P elements per epoch, dropped so that all processes see the
same number of batches). Each epoch is reshuffled (grain folds the epoch into the seed).

Augmentation (the paper's, each op independently with p = 0.5, one draw shared by the four frames):
  * horizontal flip that keeps the stereo geometry valid: all four frames are mirrored AND left/right are
    swapped (mirrored right becomes the new left), so disparities stay positive and left→right matches stay at
    x − d (upstream mirrored without swapping, which turns the stereo pairs into right→left pairs);
  * gamma x^g, g ~ U(0.8, 1.2), on [0, 1] values (upstream applied it to 0-255 values);
  * brightness ×U(0.5, 2.0); per-channel colour ×U(0.8, 1.2); clip to [0, 1] after each op.
  The photometric ops are per-pixel 256-entry lookup tables on the uint8 input, applied at full resolution
  and rounded to uint8 (upstream re-quantised to uint8 after every op; we round once).
  Beyond the paper, all off by default: a zoom crop (`augment_zoom`, one window for all frames), a shifted
  crop (`augment_shift`, the t+1 window offset from the t one) and a zoom between t and t+1
  (`augment_t1_zoom`, the t+1 window scaled against the t one), drawn after the paper's ops.
Resize (after augmentation, on uint8 as upstream's PIL resize): cv2 INTER_AREA when shrinking (anti-aliased,
close to PIL's bilinear), INTER_LINEAR when enlarging; then /255 → float32.

Bad data, found in two places:
  * before training (`DataConfig.prescan`, sources "folder" and "kitti_raw"): `folders.check_cycles` reads every
    image's header; left/right frames of different sizes in most stereo frames of a sequence raise one
    ValueError naming both files (the trainer builds the dataset before it creates its workdir); cycles with an
    unreadable file, a few odd left/right pairs, or spanning a change of frame size are left out of the source,
    each with its cause (`dataset.skips.prescan_report()`);
  * while decoding: a cycle whose image is missing, truncated or undecodable, or whose frames differ in size,
    is replaced by the next valid cycle of the source (index + 1, + 2, …). More than `max_skip` consecutive
    failures raise one error naming the data folder and the causes.
`dataset.skips.report()` counts each distinct skipped cycle of that dataset once (not once per epoch), pre-scan
exclusions and decode failures together, in the process that iterates the dataset: decode failures in grain worker processes travel
with their batch (each element carries the source indices it skipped) and are recorded when the batch reaches
the iterating process. Each distinct skip is logged once, with the file and the cause.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import threading
from typing import Optional

import cv2
import grain
import jax
import numpy as np
from absl import flags
from jax.sharding import NamedSharding, PartitionSpec

from bridge_jax.data import folders, kitti, synthetic

cv2.setNumThreads(1)
log = logging.getLogger(__name__)

SOURCES = ("synthetic", "kitti_raw", "folder", "tfds")
DEFAULT_SYNTHETIC_NUM = 100_000


class SkipLog:
    """Distinct skipped cycles {cycle id: (file at fault, cause)}, first cause kept; thread-safe."""

    def __init__(self):
        self._lock = threading.Lock()
        self._cycles: dict[str, tuple[str, str]] = {}

    def add(self, cycle_id: str, path: str, cause: str) -> bool:
        """Records a skipped cycle; True when it was not recorded before."""
        with self._lock:
            if cycle_id in self._cycles:
                return False
            self._cycles[cycle_id] = (path, cause)
            return True

    def __contains__(self, cycle_id: str) -> bool:
        with self._lock:
            return cycle_id in self._cycles

    def __len__(self) -> int:
        with self._lock:
            return len(self._cycles)

    def items(self) -> list:
        with self._lock:
            return list(self._cycles.items())

    def clear(self) -> None:
        with self._lock:
            self._cycles.clear()

    # grain sends the transforms holding the log to its worker processes: pickle the records, not the lock (each
    # process gets a fresh lock; a worker's own records travel back with its batches, see `_CollectSkips`).
    def __getstate__(self) -> dict:
        return {"cycles": self.items()}

    def __setstate__(self, state: dict) -> None:
        self._lock = threading.Lock()
        self._cycles = dict(state["cycles"])


def _report(*logs: SkipLog) -> dict:
    cycles, causes = set(), {}
    for sl in logs:
        for cid, (path, cause) in sl.items():
            cycles.add(cid)
            causes.setdefault(path, cause)
    return {"cycles": len(cycles), "files": sorted(causes), "causes": {p: causes[p] for p in sorted(causes)}}


class DataSkips:
    """The skipped cycles of one training dataset (`make_train_dataset(...).skips`): those the pre-scan left out
    of its source and those whose decoding failed in the batches this process consumed (in worker processes
    too, see the module docstring). Each dataset has its own, so a second run in a process reports only its own."""

    def __init__(self):
        self.prescan = SkipLog()
        self.runtime = SkipLog()

    def record(self, source, index: int, path: str, reason: str) -> None:
        """Records a decode failure of `source[index]`; logged once per distinct cycle."""
        cycle_id = _cycle_id(source, index)
        if self.runtime.add(cycle_id, path, reason):
            log.warning("skipping unreadable cycle %s: %s: %s (%d distinct cycles skipped so far in process %d)",
                        cycle_id, path, reason, len(self.runtime), os.getpid())
        else:  # met again (a later epoch): already reported
            log.debug("skipping unreadable cycle %s again: %s", cycle_id, path)

    def report(self) -> dict:
        """Distinct cycles skipped, each counted once however often it is met:

            {"cycles": number of distinct cycle ids skipped, "files": sorted distinct files at fault,
             "causes": {file: cause}}

        Pre-scan exclusions and decode failures together; a cycle's files are named once, with the first cause.
        """
        return _report(self.prescan, self.runtime)

    def prescan_report(self) -> dict:
        """The part of `report()` found before training: cycles left out by `folders.check_cycles` when the
        dataset's source was built (same keys as `report()`)."""
        return _report(self.prescan)


def _cycle_id(source, index: int) -> str:
    """A source record's cycle id (file sources), else "#<index>" (the same in every process)."""
    records = getattr(source, "records", None)
    return str(records[index]["id"]) if records is not None else f"#{index}"


# ----------------------------------------------------------------------------------------------------------
# Sources: len() + load(i) -> {"cycle": uint8 (4, H, W, 3), "id": str}; load raises kitti.CorruptImageError.
# ----------------------------------------------------------------------------------------------------------

class FileCycleSource:
    """Cycles read from image files; `records` as returned by kitti.raw_cycles / folders.folder_cycles.

    `excluded`: the cycles `folders.check_cycles` left out ([{"id", "path", "cause"}]), recorded in the skip
    report when a dataset is built on this source.
    """

    def __init__(self, records: list, root: str, excluded: Optional[list] = None):
        self.records, self.root = list(records), root
        self.excluded = list(excluded or ())

    def __len__(self) -> int:
        return len(self.records)

    def load(self, index: int) -> dict:
        rec = self.records[index]
        frames = [kitti.read_image(p) for p in rec["paths"]]
        if len({f.shape for f in frames}) != 1:
            raise kitti.CorruptImageError(*folders.frames_differ_message(rec["paths"], [f.shape for f in frames]))
        return {"cycle": np.stack(frames), "id": rec["id"]}

    def __getitem__(self, index: int) -> dict:
        return self.load(index)


class SyntheticSource:
    """The procedural synthetic data, rendered on the fly (never corrupt)."""

    def __init__(self, num: int, seed: int, height: int, width: int, **render_kw):
        self.inner = synthetic.SyntheticCycles(num, seed, height, width, **render_kw)
        self.root = f"<synthetic seed={seed}>"

    def __len__(self) -> int:
        return len(self.inner)

    def load(self, index: int) -> dict:
        return self.inner[index]

    def __getitem__(self, index: int) -> dict:
        return self.load(index)


class TfdsCycleSource:
    """Cycles from the `kitti_cycles` TFDS builder (ArrayRecord), read with tfds.data_source (no TensorFlow)."""

    def __init__(self, data_dir: str, config: str = "all", split: str = "train"):
        # imported here: tensorflow_datasets takes seconds to import and only this source needs it
        from bridge_jax.data.tfds_kitti_cycles import open_data_source
        self.data_dir, self.config, self.split = data_dir, config, split
        self.source = open_data_source(data_dir, config, split)
        self.root = data_dir

    def __len__(self) -> int:
        return len(self.source)

    def load(self, index: int) -> dict:
        from bridge_jax.data.tfds_kitti_cycles import decode_example
        return decode_example(self.source[index])

    def __getitem__(self, index: int) -> dict:
        return self.load(index)


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """The training data (the `data` section of a training config).

    source: "synthetic" (the built-in procedural stereo video, rendered on the fly at the working size),
      "kitti_raw" (a KITTI raw root, see `kitti.RAW_LAYOUT`), "folder" (your own stereo video, see
      `folders.EXPECTED_LAYOUT`) or "tfds" (the `kitti_cycles` TFDS builder's ArrayRecord files).
    data_dir: the folder of kitti_raw | folder | tfds.
    split: kitti_raw: "all" | "kitti" | "eigen" | a list file; tfds: the builder config ("all").
    augment: the paper's augmentation (see the module docstring).
    augment_zoom: geometric augmentation beyond the paper: with `augment`, each cycle is cropped to a random
      window of s x its size, s ~ U(augment_zoom, 1), the same window in all four frames (rows stay rectified),
      before the resize to the working size: motions and disparities grow by 1/s, as with a longer lens.
      1.0 = off (the paper).
    augment_shift: geometric augmentation beyond the paper: with `augment`, frames t and t+1 are cut from
      windows up to this fraction of the height apart, vertically and horizontally (`shift_crop`); each stereo
      pair keeps one window, so it stays rectified, and the flow gains the windows' offset. It gives a model
      vertical motion, which driving-like video (and the synthetic scenes before `real_motion`) hardly has.
      0.0 = off (the paper).
    augment_t1_zoom: geometric augmentation beyond the paper: with `augment`, frames t+1 are seen through a
      window z x smaller than frame t's, z ~ U(1 - a, 1 + a) (`t1_zoom_crop`): the flow gains an expansion or a
      contraction (as when the camera or the scene moves along the optical axis), which the synthetic scenes
      hardly show and real video often does. Each stereo pair keeps one window (rows stay rectified). 0.0 = off
      (the paper); at most 0.2.
    num_workers: grain worker processes (0 = decode in the training process).
    prefetch, read_threads, worker_buffer_size: grain read options.
    max_skip: consecutive unreadable cycles tolerated before the data folder is reported as broken.
    prescan: read every image's header when the dataset is built (folder | kitti_raw): sizes and readability
      are checked before training (see the module docstring); False skips it (very large folders on slow
      storage: bad cycles are then only found while decoding).
    val_dir: held-out frames of your own for training's validation, in the layouts of `folders.LAYOUT_HELP`
      (`bridge_jax.eval.photometric`: photometric error without ground truth); "" = the synthetic validation.
    synthetic_num: cycles of the synthetic source per epoch (it is endless; this fixes the shuffle period).
    synthetic_scene: the synthetic source's scene settings, a name of `synthetic.SCENE_PRESETS`: "demo" (the
      demo's procedural look), "real" (photo textures, uniform regions, slanted and rotating objects, varied
      rigs, larger motions, per-camera photometric differences: a domain that carries over to real images),
      "real_motion" (`real` plus vertical motion: rig pitch, roll and vertical translation, objects moving up
      and down) or "heldout" (settings kept for checking generalisation; do not train on it).
    num_epochs: passes over the source (None = forever, the trainer's choice).
    """

    source: str = "synthetic"  # synthetic | kitti_raw | folder | tfds
    data_dir: str = ""  # the folder of kitti_raw | folder | tfds
    split: str = ""  # kitti_raw: all | kitti | eigen | a list file; tfds: the builder config
    augment: bool = True  # the paper's augmentation (flip, gamma, brightness, colour)
    augment_zoom: float = 1.0  # with augment, a random zoom crop of s in [augment_zoom, 1] (1 = off)
    augment_shift: float = 0.0  # with augment, frames t+1 cut up to this fraction of the height away from t (0 = off)
    augment_t1_zoom: float = 0.0  # with augment, frames t+1 zoomed by z in [1 - a, 1 + a] against t (0 = off)
    num_workers: int = 0  # grain worker processes (0 = decode in the training process)
    prefetch: int = 2  # grain read-ahead buffer (elements)
    read_threads: int = 1  # grain read threads
    worker_buffer_size: int = 2  # batches buffered per worker process
    max_skip: int = 100  # consecutive unreadable cycles tolerated before the folder is reported broken
    synthetic_num: int = DEFAULT_SYNTHETIC_NUM  # synthetic cycles per epoch (fixes the shuffle period)
    synthetic_scene: str = "demo"  # synthetic scene settings: demo | real | real_motion | heldout (synthetic.SCENE_PRESETS)
    num_epochs: Optional[int] = None  # passes over the source (None = forever, the trainer's choice)
    prescan: bool = True  # read every image header before training (folder | kitti_raw)
    val_dir: str = ""  # held-out frames of your own for validation ("" = synthetic validation)

    def __post_init__(self):
        if self.source not in SOURCES:
            raise ValueError(f"data.source must be one of {SOURCES}, got {self.source!r}")
        if self.source != "synthetic" and not self.data_dir:
            raise ValueError(f"data.source={self.source!r} needs data.data_dir")
        if not 0.1 <= float(self.augment_zoom) <= 1.0:
            raise ValueError(f"data.augment_zoom must be in [0.1, 1] (1 = off), got {self.augment_zoom!r}")
        if not 0.0 <= float(self.augment_shift) <= 0.25:
            raise ValueError(f"data.augment_shift must be in [0, 0.25] (a fraction of the height; 0 = off), got "
                             f"{self.augment_shift!r}")
        if not 0.0 <= float(self.augment_t1_zoom) <= 0.2:
            raise ValueError(f"data.augment_t1_zoom must be in [0, 0.2] (the largest relative zoom between t and "
                             f"t+1; 0 = off), got {self.augment_t1_zoom!r}")
        if self.synthetic_scene not in synthetic.SCENE_PRESETS:
            raise ValueError(f"data.synthetic_scene must be one of {tuple(synthetic.SCENE_PRESETS)}, got "
                             f"{self.synthetic_scene!r}")
        if not isinstance(self.val_dir, str):
            raise ValueError(f"data.val_dir must be a folder or '' (synthetic validation), got {self.val_dir!r}")


def make_source(data: DataConfig, *, height: int = 256, width: int = 512, seed: int = 0):
    """The cycle source named by `data.source` (len + load(i) -> {"cycle": uint8 (4, H, W, 3), "id"})."""
    if data.source == "synthetic":
        return SyntheticSource(int(data.synthetic_num), int(seed), int(height), int(width),
                               scene=data.synthetic_scene)
    if data.source in ("kitti_raw", "folder"):
        if data.source == "kitti_raw":
            records = kitti.raw_cycles(data.data_dir, data.split or "all")
        else:
            records = folders.folder_cycles(data.data_dir)
        excluded: list = []
        if data.prescan:  # raises ValueError for systematic size mismatches: before any workdir exists
            records, excluded = folders.check_cycles(records, where=data.data_dir)
        return FileCycleSource(records, data.data_dir, excluded)
    return TfdsCycleSource(data.data_dir, data.split or "all")


class LoadCycle:
    """index → {"cycle": uint8 (4, H, W, 3), "id", "skipped": int64 (2,)}: loads cycle `index`, or the next
    valid one after it; "skipped" = (first, count): source indices first … first + count − 1 (mod len) failed."""

    def __init__(self, source, max_skip: int = 100, skips: Optional[DataSkips] = None):
        self.source, self.max_skip = source, max_skip
        self.skips = DataSkips() if skips is None else skips

    def __call__(self, index) -> dict:
        n = len(self.source)
        first = int(index) % n
        limit = min(self.max_skip, n)
        causes: dict[str, str] = {}
        for attempt in range(limit):
            j = (first + attempt) % n
            try:
                rec = self.source.load(j)
            except kitti.CorruptImageError as e:
                self.skips.record(self.source, j, e.path, e.reason)
                causes.setdefault(e.path, e.reason)
                continue
            return {"cycle": rec["cycle"], "id": rec["id"], "skipped": np.array([first, attempt], np.int64)}
        shown = "; ".join(f"{p}: {r}" for p, r in list(causes.items())[:3])
        more = f" and {len(causes) - 3} more files" if len(causes) > 3 else ""
        raise RuntimeError(f"{limit} consecutive cycles starting at #{first} of {getattr(self.source, 'root', '?')!r} "
                           f"are unreadable ({shown}{more}); check the data folder")


class _CollectSkips(grain.transforms.Map):
    """Runs in the iterating process (after the worker processes): records the skips a batch carries, so that
    the dataset's `skips` there also knows the decode failures of the workers; yields {"cycle"} only."""

    def __init__(self, source, skips: DataSkips):
        self.source, self.skips = source, skips

    def map(self, batch: dict) -> dict:
        n = len(self.source)
        for first, count in np.asarray(batch["skipped"]).reshape(-1, 2):
            for a in range(int(count)):
                j = (int(first) + a) % n
                if _cycle_id(self.source, j) in self.skips.runtime:
                    continue
                # The worker knew the file and the cause; a second read here names them (rare: once per
                # distinct bad cycle).
                try:
                    self.source.load(j)
                except kitti.CorruptImageError as e:
                    self.skips.record(self.source, j, e.path, e.reason)
                else:
                    self.skips.record(self.source, j, f"{getattr(self.source, 'root', '?')}#{j}",
                                 "unreadable in a worker process (readable when read again)")
        return {"cycle": batch["cycle"]}


# ----------------------------------------------------------------------------------------------------------
# Augmentation and resizing (pure functions of the cycle and the drawn parameters)
# ----------------------------------------------------------------------------------------------------------

@dataclasses.dataclass(frozen=True)
class AugmentParams:
    """One draw of the paper's augmentation; identity values when an op is not applied."""
    flip: bool = False
    gamma: float = 1.0
    brightness: float = 1.0
    colour: tuple = (1.0, 1.0, 1.0)


def draw_augment(rng: np.random.Generator, prob: float = 0.5) -> AugmentParams:
    """Draws AugmentParams: each op independently with probability `prob` (fixed draw order)."""
    u = rng.uniform(size=4)
    gamma = rng.uniform(0.8, 1.2)
    brightness = rng.uniform(0.5, 2.0)
    colour = tuple(float(c) for c in rng.uniform(0.8, 1.2, 3))
    return AugmentParams(flip=bool(u[0] < prob), gamma=float(gamma) if u[1] < prob else 1.0,
                         brightness=float(brightness) if u[2] < prob else 1.0,
                         colour=colour if u[3] < prob else (1.0, 1.0, 1.0))


def flip_cycle(cycle: np.ndarray) -> np.ndarray:
    """Mirrors a cycle (4, H, W, C) horizontally and swaps left/right so that stereo stays valid.

    New frames: (mirror(right_t), mirror(left_t), mirror(right_t1), mirror(left_t1)). A left pixel x with
    disparity d (match at x − d on the right) becomes right pixel W−1−x whose new-left match is W−1−x+d, i.e.
    the new pair again has positive disparity (the mirrored *right* disparity map). Flow stays flow (mirrored).
    """
    return np.stack([cv2.flip(np.ascontiguousarray(cycle[k]), 1).reshape(cycle.shape[1:]) for k in (1, 0, 3, 2)])


def photometric_lut(params: AugmentParams) -> np.ndarray:
    """float32 (256, 1, 3) table: uint8 value → augmented [0, 1] value per channel (gamma → brightness →
    colour, clipped to [0, 1] after each op)."""
    x = np.arange(256, dtype=np.float64) / 255.0
    x = np.clip(x ** params.gamma, 0.0, 1.0)
    x = np.clip(x * params.brightness, 0.0, 1.0)
    lut = np.clip(x[:, None] * np.asarray(params.colour, np.float64)[None, :], 0.0, 1.0)
    return lut.astype(np.float32).reshape(256, 1, 3)


def apply_augment(cycle: np.ndarray, params: AugmentParams) -> np.ndarray:
    """uint8 (4, H, W, 3) → float32 (4, H, W, 3) in [0, 1], the same ops on all four frames."""
    if params.flip:
        cycle = flip_cycle(cycle)
    n, h, w, c = cycle.shape
    out = cv2.LUT(np.ascontiguousarray(cycle).reshape(n * h, w, c), photometric_lut(params))
    return out.reshape(n, h, w, c)


def apply_augment_uint8(cycle: np.ndarray, params: AugmentParams) -> np.ndarray:
    """uint8 (4, H, W, 3) → uint8 (4, H, W, 3): `apply_augment` rounded to 8 bits (what the training pipeline
    uses: the photometric table is applied at full resolution, then the cheaper uint8 resize follows)."""
    if params.flip:
        cycle = flip_cycle(cycle)
    n, h, w, c = cycle.shape
    lut = np.clip(np.rint(photometric_lut(params) * 255.0), 0, 255).astype(np.uint8)
    return cv2.LUT(np.ascontiguousarray(cycle).reshape(n * h, w, c), lut).reshape(n, h, w, c)


def resize_frames(frames: np.ndarray, height: int, width: int) -> np.ndarray:
    """(N, H, W, C) float32 or uint8 → (N, height, width, C), same dtype; INTER_AREA when shrinking,
    INTER_LINEAR otherwise."""
    n, h, w, c = frames.shape
    if (h, w) == (height, width):
        return frames
    interp = cv2.INTER_AREA if (height <= h and width <= w) else cv2.INTER_LINEAR
    return np.stack([cv2.resize(f, (width, height), interpolation=interp).reshape(height, width, c)
                     for f in frames])


def zoom_crop(cycle: np.ndarray, rng: np.random.Generator, min_scale: float) -> np.ndarray:
    """The same random window of s x the size, s ~ U(min_scale, 1), cut from all frames of `cycle`
    `(4, H, W, C)` (at least 8 x 8 pixels); drawn after the paper's ops, so those draws are unchanged."""
    if min_scale >= 1.0:
        return cycle
    _, h, w, _ = cycle.shape
    s = rng.uniform(min_scale, 1.0)
    ch, cw = max(8, int(round(s * h))), max(8, int(round(s * w)))
    y0, x0 = int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1))
    return cycle[:, y0:y0 + ch, x0:x0 + cw]


def draw_shift(rng: np.random.Generator, height: int, width: int, max_shift: float) -> tuple[int, int, int, int]:
    """One draw of `shift_crop`'s windows for a cycle of `height x width`: (y0, x0, dy, dx) = the top-left corner
    of the t window and the offset of the t+1 window, |dy| <= m = round(max_shift * height) and |dx| <=
    round(m * width / height), both windows inside the frame. (0, 0, 0, 0) when m < 1."""
    m = int(round(max_shift * height))
    if m < 1:
        return 0, 0, 0, 0
    mx = int(round(m * width / height))
    dy, dx = int(rng.integers(-m, m + 1)), int(rng.integers(-mx, mx + 1))
    y0 = int(rng.integers(max(0, -dy), m - max(0, dy) + 1))
    x0 = int(rng.integers(max(0, -dx), mx - max(0, dx) + 1))
    return y0, x0, dy, dx


def shift_crop(cycle: np.ndarray, rng: np.random.Generator, max_shift: float) -> np.ndarray:
    """Frames t and t+1 cut from windows `(dy, dx)` pixels apart (`draw_shift`): a window of (H - m) x
    (W - mx) at (y0, x0) from left_t and right_t, the same size at (y0 + dy, x0 + dx) from left_t1 and
    right_t1. Each stereo pair keeps one window, so it stays rectified with the same disparities; the flow
    t -> t+1 gains (-dx, -dy) everywhere, the camera shake a rig without it never shows: the synthetic scenes'
    flow is nearly all horizontal, so vertical motion of every size comes from here. `(4, H, W, C)` in,
    `(4, H - m, W - mx, C)` out (the same cycle when m < 1)."""
    _, h, w, _ = cycle.shape
    y0, x0, dy, dx = draw_shift(rng, h, w, max_shift)
    m = int(round(max_shift * h))
    if m < 1:
        return cycle
    ch, cw = h - m, w - int(round(m * w / h))
    t = cycle[:2, y0:y0 + ch, x0:x0 + cw]
    t1 = cycle[2:, y0 + dy:y0 + dy + ch, x0 + dx:x0 + dx + cw]
    return np.concatenate([t, t1])


def draw_t1_zoom(rng: np.random.Generator, height: int, width: int,
                 amount: float) -> tuple[float, int, int, int, int, float, float]:
    """One draw of `t1_zoom_crop`'s windows for a cycle of `height x width`: (z, ch, cw, y0, x0, y1, x1) =
    the zoom z ~ U(1 - amount, 1 + amount), the t window's size ch x cw = round((1 - amount) x the frame) and
    top-left corner (y0, x0), and the top-left corner (y1, x1) (float) of the t+1 window, of size
    (ch / z) x (cw / z); both windows lie inside the frame, each at a uniform position."""
    z = float(rng.uniform(1.0 - amount, 1.0 + amount))
    ch, cw = int(round((1.0 - amount) * height)), int(round((1.0 - amount) * width))
    y0, x0 = int(rng.integers(0, height - ch + 1)), int(rng.integers(0, width - cw + 1))
    y1 = float(rng.uniform(0.0, max(0.0, height - ch / z)))
    x1 = float(rng.uniform(0.0, max(0.0, width - cw / z)))
    return z, ch, cw, y0, x0, y1, x1


def t1_zoom_crop(cycle: np.ndarray, rng: np.random.Generator, amount: float) -> np.ndarray:
    """Frames t cut from a window of (1 - amount) x the frame, frames t+1 from a window z times smaller
    (`draw_t1_zoom`) resampled to the same size: pixel (x, y) of frame t+1 shows the point (x1 + (x + 0.5) / z
    - 0.5, y1 + (y + 0.5) / z - 0.5) of the rendered t+1 frame, so a point at pixel p of the new frame t with
    rendered flow f lands at q = z (p + (x0, y0) + f - (x1, y1) + 0.5) - 0.5 of the new frame t+1: the flow
    gains a zoom about a random centre (z > 1: the scene expands, as when the camera moves towards it).
    Each stereo pair keeps one window (the same resampling for left and right), so rows stay rectified and
    disparities at t+1 scale by z. `(4, H, W, C)` uint8 in, `(4, round((1 - amount) H), round((1 - amount) W),
    C)` out (the same cycle when amount is 0)."""
    if amount <= 0.0:
        return cycle
    _, h, w, _ = cycle.shape
    z, ch, cw, y0, x0, y1, x1 = draw_t1_zoom(rng, h, w, amount)
    # Output pixel (x, y) <- source (x1 + (x + 0.5) / z - 0.5, ...): pixel centres, not corners, scale by 1/z.
    m = np.array([[1.0 / z, 0.0, x1 + 0.5 / z - 0.5], [0.0, 1.0 / z, y1 + 0.5 / z - 0.5]], np.float64)
    t1 = [cv2.warpAffine(frame, m, (cw, ch), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_REPLICATE) for frame in cycle[2:]]
    t1 = [f[..., None] if f.ndim == 2 else f for f in t1]  # cv2 drops a single channel
    return np.concatenate([cycle[:2, y0:y0 + ch, x0:x0 + cw], np.stack(t1)])


class _Augment(grain.transforms.RandomMap):
    def __init__(self, enabled: bool, zoom: float = 1.0, shift: float = 0.0, t1_zoom: float = 0.0):
        self.enabled, self.zoom, self.shift, self.t1_zoom = enabled, float(zoom), float(shift), float(t1_zoom)

    def random_map(self, element: dict, rng: np.random.Generator) -> dict:
        if not self.enabled:
            return element
        cycle = apply_augment_uint8(element["cycle"], draw_augment(rng))
        cycle = zoom_crop(cycle, rng, self.zoom)
        if self.shift > 0:  # drawn last, so the draws above stay what they were without it
            cycle = shift_crop(cycle, rng, self.shift)
        if self.t1_zoom > 0:  # drawn after the shift, so runs without it keep their draws
            cycle = t1_zoom_crop(cycle, rng, self.t1_zoom)
        return {**element, "cycle": cycle}


class _Resize(grain.transforms.Map):
    def __init__(self, height: int, width: int):
        self.height, self.width = height, width

    def map(self, element: dict) -> dict:
        small = resize_frames(element["cycle"], self.height, self.width)
        return {"cycle": small.astype(np.float32) * np.float32(1.0 / 255.0), "skipped": element["skipped"]}


# ----------------------------------------------------------------------------------------------------------
# The training dataset
# ----------------------------------------------------------------------------------------------------------

def make_train_dataset(data: DataConfig, *, global_batch: int, seed: int, height: int = 256, width: int = 512,
                       process_index: int | None = None, process_count: int | None = None,
                       source=None) -> grain.IterDataset:
    """The training input pipeline (see the module docstring).

    Args:
      data: which data and how to read it.
      global_batch: cycles per step over all processes (divisible by process_count).
      seed: shuffle and augmentation seed.
      height, width: working size of the yielded cycles.
      process_index, process_count: this host's shard (default jax.process_index() / jax.process_count()).
      source: optional ready source object (len + load) instead of building one from `data`.
    Returns:
      grain IterDataset; iter(ds) yields {"cycle": float32 (global_batch // P, 4, height, width, 3)} and has
      get_state() / set_state(). Its `skips` (`DataSkips`) holds the source's pre-scan exclusions from here on
      and grows with the decode failures of the batches consumed.
    Raises:
      ValueError for bad arguments and bad data found before training (missing folder, no cycles, left and
      right frames of different sizes; see `folders.check_cycles`).
    """
    if process_index is None or process_count is None:
        process_index = jax.process_index() if process_index is None else process_index
        process_count = jax.process_count() if process_count is None else process_count
    if global_batch <= 0 or global_batch % process_count:
        raise ValueError(f"global batch {global_batch} must be a positive multiple of the process count "
                         f"{process_count}")
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} not in [0, {process_count})")
    local_batch = global_batch // process_count
    src = source if source is not None else make_source(data, height=height, width=width, seed=seed)
    skips = DataSkips()
    for e in getattr(src, "excluded", ()):
        skips.prescan.add(e["id"], e["path"], e["cause"])
    n = len(src)
    usable = n - n % process_count
    if usable // process_count < 1:
        raise ValueError(f"data source {getattr(src, 'root', src)!r} has {n} cycles: fewer than the "
                         f"{process_count} processes")
    ds = grain.MapDataset.range(n).shuffle(seed=seed)
    if usable != n:
        ds = ds[:usable]
    ds = ds[process_index::process_count]
    ds = ds.repeat(None if data.num_epochs is None else int(data.num_epochs))
    ds = ds.map(LoadCycle(src, int(data.max_skip), skips))
    ds = ds.random_map(_Augment(bool(data.augment), float(data.augment_zoom), float(data.augment_shift),
                                float(data.augment_t1_zoom)),
                       seed=(seed * 1_000_003 + 7919 * (process_index + 1)) % 2**32)
    ds = ds.map(_Resize(height, width))
    ds = ds.to_iter_dataset(grain.ReadOptions(num_threads=int(data.read_threads) or 1,
                                              prefetch_buffer_size=int(data.prefetch)))
    ds = ds.batch(local_batch, drop_remainder=True)
    workers = int(data.num_workers)
    if workers > 0:
        # grain's worker processes read absl flags; outside absl.app.run (tests, notebooks, library use) they
        # are unparsed, so mark them parsed with their defaults (argv is left alone).
        if not flags.FLAGS.is_parsed():
            flags.FLAGS.mark_as_parsed()
        ds = ds.mp_prefetch(grain.MultiprocessingOptions(num_workers=workers,
                                                         per_worker_buffer_size=int(data.worker_buffer_size)))
    ds = ds.map(_CollectSkips(src, skips))
    ds.skips = skips  # the dataset's own skip log (grain datasets are plain Python objects)
    return ds


def shard_batch(batch: dict, mesh, axis_names=None):
    """Places this process's batch (leading dim = local batch) onto `mesh`, sharded over `axis_names` (default:
    all mesh axes) along the batch dimension; returns global jax.Arrays (leading dim = global batch)."""
    axes = tuple(mesh.axis_names) if axis_names is None else axis_names
    sharding = NamedSharding(mesh, PartitionSpec(axes))
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), batch)
