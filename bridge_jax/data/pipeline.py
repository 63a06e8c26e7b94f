"""grain input pipeline: cycle source → shuffle → shard → decode → augment → resize → batch → workers.

    make_train_dataset(data_cfg, global_batch=..., seed=..., height=256, width=512)
      MapDataset.range(N) ─ shuffle(seed) ─ [:N - N % P] ─ [p::P] ─ repeat(num_epochs)
      ─ map(load: decode the cycle, or skip a corrupt one and take the next valid one)
      ─ random_map(augment, same draw for the 4 frames) ─ map(resize to H × W)
      ─ to_iter_dataset ─ batch(global_batch / P, drop_remainder) ─ mp_prefetch(num_workers)
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
Resize (after augmentation, on uint8 as upstream's PIL resize): cv2 INTER_AREA when shrinking (anti-aliased,
close to PIL's bilinear), INTER_LINEAR when enlarging; then /255 → float32.

Corrupt data: a cycle whose image is missing, truncated or undecodable, or whose frames differ in size, is
replaced by the next valid cycle of the source (index + 1, + 2, …); each skip is logged with the file path and
counted (`skip_counts()` in this process; workers log their own). More than `max_skip` consecutive failures
raise one error naming the data folder.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import tempfile
import threading
import time
from typing import Any, Mapping

import cv2
import grain
import numpy as np

from bridge_jax.data import kitti

cv2.setNumThreads(1)
log = logging.getLogger(__name__)

SOURCES = ("synthetic", "kitti_raw", "folder", "tfds")
DEFAULT_SYNTHETIC_NUM = 100_000

_SKIPS = {"count": 0, "paths": []}
_SKIPS_LOCK = threading.Lock()


def skip_counts() -> dict:
    """{"count": corrupt cycles skipped in this process, "paths": their file paths (first 1000)}."""
    with _SKIPS_LOCK:
        return {"count": _SKIPS["count"], "paths": list(_SKIPS["paths"])}


def reset_skip_counts() -> None:
    with _SKIPS_LOCK:
        _SKIPS["count"] = 0
        _SKIPS["paths"].clear()


def _record_skip(path: str, reason: str, cycle_id: str) -> None:
    with _SKIPS_LOCK:
        _SKIPS["count"] += 1
        if len(_SKIPS["paths"]) < 1000:
            _SKIPS["paths"].append(path)
        n = _SKIPS["count"]
    log.warning("skipping corrupt cycle %s: %s: %s (%d skipped so far in process %d)", cycle_id, path, reason, n,
                os.getpid())


# ----------------------------------------------------------------------------------------------------------
# Sources: len() + load(i) -> {"cycle": uint8 (4, H, W, 3), "id": str}; load raises kitti.CorruptImageError.
# ----------------------------------------------------------------------------------------------------------

class FileCycleSource:
    """Cycles read from image files; `records` as returned by kitti.raw_cycles / folders.folder_cycles."""

    def __init__(self, records: list, root: str):
        self.records, self.root = list(records), root

    def __len__(self) -> int:
        return len(self.records)

    def load(self, index: int) -> dict:
        rec = self.records[index]
        frames = [kitti.read_image(p) for p in rec["paths"]]
        shapes = {f.shape for f in frames}
        if len(shapes) != 1:
            raise kitti.CorruptImageError(rec["paths"][0], f"the 4 frames of the cycle differ in size {shapes}")
        return {"cycle": np.stack(frames), "id": rec["id"]}

    def __getitem__(self, index: int) -> dict:
        return self.load(index)


class SyntheticSource:
    """The procedural synthetic data, rendered on the fly (never corrupt)."""

    def __init__(self, num: int, seed: int, height: int, width: int, **render_kw):
        from bridge_jax.data import synthetic
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


def _cfg(data_cfg: Any, key: str, default: Any = None) -> Any:
    if data_cfg is None:
        return default
    if isinstance(data_cfg, Mapping):
        return data_cfg.get(key, default)
    getter = getattr(data_cfg, "get", None)
    if getter is not None:
        return getter(key, default)
    return getattr(data_cfg, key, default)


def make_source(data_cfg: Any, *, height: int = 256, width: int = 512, seed: int = 0):
    """The cycle source named by `data_cfg.source` ("synthetic" | "kitti_raw" | "folder" | "tfds").

    Keys: data_dir, split ("all" | "kitti" | "eigen" | list file for kitti_raw; TFDS config for tfds),
    synthetic_num (100000), synthetic_seed (= seed), synthetic_height/width (= working size).
    """
    kind = _cfg(data_cfg, "source", "synthetic")
    data_dir = _cfg(data_cfg, "data_dir", None)
    split = _cfg(data_cfg, "split", None)
    if kind == "synthetic":
        return SyntheticSource(int(_cfg(data_cfg, "synthetic_num", DEFAULT_SYNTHETIC_NUM)),
                               int(_cfg(data_cfg, "synthetic_seed", seed)),
                               int(_cfg(data_cfg, "synthetic_height", None) or height),
                               int(_cfg(data_cfg, "synthetic_width", None) or width))
    if kind in ("kitti_raw", "folder", "tfds") and not data_dir:
        raise ValueError(f"data.source={kind!r} needs data.data_dir")
    if kind == "kitti_raw":
        return FileCycleSource(kitti.raw_cycles(data_dir, split or "all"), data_dir)
    if kind == "folder":
        from bridge_jax.data import folders
        return FileCycleSource(folders.folder_cycles(data_dir), data_dir)
    if kind == "tfds":
        return TfdsCycleSource(data_dir, split or "all")
    raise ValueError(f"data.source must be one of {SOURCES}, got {kind!r}")


class LoadCycle:
    """index → {"cycle": uint8 (4, H, W, 3), "id"}: loads cycle `index`, or the next valid one after it."""

    def __init__(self, source, max_skip: int = 100):
        self.source, self.max_skip = source, max_skip

    def __call__(self, index) -> dict:
        n = len(self.source)
        first = int(index) % n
        for attempt in range(min(self.max_skip, n)):
            j = (first + attempt) % n
            try:
                rec = self.source.load(j)
            except kitti.CorruptImageError as e:
                _record_skip(e.path, e.reason, str(j))
                continue
            return {"cycle": rec["cycle"], "id": rec["id"]}
        raise RuntimeError(f"{min(self.max_skip, n)} consecutive cycles starting at #{first} of "
                           f"{getattr(self.source, 'root', '?')!r} are unreadable (corrupt, truncated or missing "
                           f"images); check the data folder")


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


def to_float(cycle: np.ndarray) -> np.ndarray:
    """uint8 (4, H, W, 3) → float32 [0, 1] (no augmentation)."""
    return apply_augment(cycle, AugmentParams())


def resize_frames(frames: np.ndarray, height: int, width: int) -> np.ndarray:
    """(N, H, W, C) float32 or uint8 → (N, height, width, C), same dtype; INTER_AREA when shrinking,
    INTER_LINEAR otherwise."""
    n, h, w, c = frames.shape
    if (h, w) == (height, width):
        return frames
    interp = cv2.INTER_AREA if (height <= h and width <= w) else cv2.INTER_LINEAR
    return np.stack([cv2.resize(f, (width, height), interpolation=interp).reshape(height, width, c)
                     for f in frames])


class _Augment(grain.transforms.RandomMap):
    def __init__(self, enabled: bool):
        self.enabled = enabled

    def random_map(self, element: dict, rng: np.random.Generator) -> dict:
        if not self.enabled:
            return element
        return {"cycle": apply_augment_uint8(element["cycle"], draw_augment(rng)), "id": element["id"]}


class _Resize(grain.transforms.Map):
    def __init__(self, height: int, width: int):
        self.height, self.width = height, width

    def map(self, element: dict) -> dict:
        small = resize_frames(element["cycle"], self.height, self.width)
        return {"cycle": small.astype(np.float32) * np.float32(1.0 / 255.0)}


# ----------------------------------------------------------------------------------------------------------
# The training dataset
# ----------------------------------------------------------------------------------------------------------

def make_train_dataset(data_cfg: Any, *, global_batch: int, seed: int, height: int = 256, width: int = 512,
                       process_index: int | None = None, process_count: int | None = None,
                       source=None) -> grain.IterDataset:
    """The training input pipeline (see the module docstring).

    Args:
      data_cfg: mapping / ConfigDict: source, data_dir, split, augment (True), num_workers (0),
        num_epochs (None = forever), max_skip (100), worker_buffer_size (2), synthetic_num, ...
      global_batch: cycles per step over all processes (divisible by process_count).
      seed: shuffle and augmentation seed.
      height, width: working size of the yielded cycles.
      process_index, process_count: this host's shard (default jax.process_index() / jax.process_count()).
      source: optional ready source object (len + load) instead of building one from data_cfg.
    Returns:
      grain IterDataset; iter(ds) yields {"cycle": float32 (global_batch // P, 4, height, width, 3)} and has
      get_state() / set_state().
    """
    if process_index is None or process_count is None:
        import jax
        process_index = jax.process_index() if process_index is None else process_index
        process_count = jax.process_count() if process_count is None else process_count
    if global_batch <= 0 or global_batch % process_count:
        raise ValueError(f"global batch {global_batch} must be a positive multiple of the process count "
                         f"{process_count}")
    if not 0 <= process_index < process_count:
        raise ValueError(f"process_index {process_index} not in [0, {process_count})")
    local_batch = global_batch // process_count
    src = source if source is not None else make_source(data_cfg, height=height, width=width, seed=seed)
    n = len(src)
    usable = n - n % process_count
    if usable // process_count < 1:
        raise ValueError(f"data source {getattr(src, 'root', src)!r} has {n} cycles: fewer than the "
                         f"{process_count} processes")
    num_epochs = _cfg(data_cfg, "num_epochs", None)
    ds = grain.MapDataset.range(n).shuffle(seed=seed)
    if usable != n:
        ds = ds[:usable]
    ds = ds[process_index::process_count]
    ds = ds.repeat(None if num_epochs is None else int(num_epochs))
    ds = ds.map(LoadCycle(src, int(_cfg(data_cfg, "max_skip", 100))))
    ds = ds.random_map(_Augment(bool(_cfg(data_cfg, "augment", True))),
                       seed=(seed * 1_000_003 + 7919 * (process_index + 1)) % 2**32)
    ds = ds.map(_Resize(height, width))
    ds = ds.to_iter_dataset(grain.ReadOptions(num_threads=int(_cfg(data_cfg, "read_threads", 0)) or 1,
                                              prefetch_buffer_size=int(_cfg(data_cfg, "prefetch", 2))))
    ds = ds.batch(local_batch, drop_remainder=True)
    workers = int(_cfg(data_cfg, "num_workers", 0))
    if workers > 0:
        # grain's worker processes read absl flags; outside absl.app.run (tests, notebooks, library use) they
        # are unparsed, so mark them parsed with their defaults (argv is left alone).
        from absl import flags
        if not flags.FLAGS.is_parsed():
            flags.FLAGS.mark_as_parsed()
        ds = ds.mp_prefetch(grain.MultiprocessingOptions(
            num_workers=workers, per_worker_buffer_size=int(_cfg(data_cfg, "worker_buffer_size", 2))))
    return ds


def shard_batch(batch: dict, mesh, axis_names=None):
    """Places this process's batch (leading dim = local batch) onto `mesh`, sharded over `axis_names` (default:
    all mesh axes) along the batch dimension; returns global jax.Arrays (leading dim = global batch)."""
    import jax
    from jax.sharding import NamedSharding, PartitionSpec
    axes = tuple(mesh.axis_names) if axis_names is None else axis_names
    sharding = NamedSharding(mesh, PartitionSpec(axes))
    return jax.tree.map(lambda x: jax.make_array_from_process_local_data(sharding, np.asarray(x)), batch)


def bench_pipeline(data_cfg: Any, *, num_workers: int = 0, batch: int = 2, height: int = 256, width: int = 512,
                   num_batches: int = 20, warmup: int = 2, seed: int = 0) -> dict:
    """Cycles per second delivered by make_train_dataset (decode + augment + resize + batch) in this process.

    Returns {"cycles_per_s", "seconds", "cycles", "num_workers", "startup_s", "main_cpu_ms_per_cycle"};
    startup (warm-up batches, worker spawn) is excluded from the rate. With num_workers=0 the main process does
    all the work, so main_cpu_ms_per_cycle is the pipeline's CPU cost per cycle (independent of machine load).
    """
    cfg = dict(data_cfg) if isinstance(data_cfg, Mapping) else dict(data_cfg.items())
    cfg["num_workers"] = num_workers
    ds = make_train_dataset(cfg, global_batch=batch, seed=seed, height=height, width=width, process_index=0,
                            process_count=1)
    it = iter(ds)
    t0 = time.perf_counter()
    for _ in range(warmup):
        next(it)
    t1, c1 = time.perf_counter(), time.process_time()
    for _ in range(num_batches):
        next(it)
    t2, c2 = time.perf_counter(), time.process_time()
    close = getattr(it, "close", None)
    if close:
        close()
    return {"cycles_per_s": num_batches * batch / (t2 - t1), "seconds": t2 - t1, "cycles": num_batches * batch,
            "num_workers": num_workers, "startup_s": t1 - t0,
            "main_cpu_ms_per_cycle": 1000.0 * (c2 - c1) / (num_batches * batch)}


# ----------------------------------------------------------------------------------------------------------
# Benchmark: python -m bridge_jax.data.pipeline --out experiments/results/data_bench.md
# ----------------------------------------------------------------------------------------------------------

def make_kitti_sized_raw(root: str, num_frames: int = 9, height: int = 375, width: int = 1242, seed: int = 0) -> str:
    """Writes a KITTI-raw-layout drive of synthetic PNG frames (default 1242×375, KITTI's size) for benchmarks."""
    from bridge_jax.data import synthetic
    drive = os.path.join(root, "2011_09_26", "2011_09_26_drive_0001_sync")
    for k in range(num_frames):
        s = synthetic.render_sample(synthetic.sample_seed(seed, k), height, width)
        for cam, frame in (("image_02", 0), ("image_03", 1)):
            kitti.write_image(os.path.join(drive, cam, "data", f"{k:010d}.png"), s["cycle"][frame])
    return root


def _bench_main(argv=None) -> int:
    import argparse
    import datetime
    import platform
    import subprocess

    ap = argparse.ArgumentParser(prog="python -m bridge_jax.data.pipeline",
                                 description="Benchmark the input pipeline (cycles/s at the working size).")
    ap.add_argument("--out", default=None, help="markdown file to write (default: print only)")
    ap.add_argument("--workers", default="0,1,2")
    ap.add_argument("--batches", type=int, default=10)
    ap.add_argument("--batch", type=int, default=2)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--tmp", default=None, help="folder for the KITTI-sized PNGs (default: a temp dir)")
    args = ap.parse_args(argv)

    def sh(cmd):
        try:
            return subprocess.run(cmd, capture_output=True, text=True, timeout=30).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            return "n/a"

    uptime_before = sh(["uptime"])
    workers = [int(w) for w in args.workers.split(",")]
    tmp = args.tmp or tempfile.mkdtemp(prefix="bridge_data_bench-")
    if not kitti.find_raw_drives(tmp):
        make_kitti_sized_raw(tmp)
    png_bytes = os.path.getsize(os.path.join(tmp, "2011_09_26", "2011_09_26_drive_0001_sync", "image_02", "data",
                                             "0000000000.png"))
    rows = []
    for name, cfg in (("KITTI-sized PNG files (1242×375), kitti_raw source", {"source": "kitti_raw",
                                                                              "data_dir": tmp}),
                      ("synthetic, rendered on the fly at the working size", {"source": "synthetic"})):
        for w in workers:
            r = bench_pipeline(cfg, num_workers=w, batch=args.batch, height=args.height, width=args.width,
                               num_batches=args.batches)
            rows.append((name, w, r))
            print(f"{name}: workers={w}: {r['cycles_per_s']:.1f} cycles/s, main-process CPU "
                  f"{r['main_cpu_ms_per_cycle']:.0f} ms/cycle (startup {r['startup_s']:.1f} s)", flush=True)
    if args.out:
        lscpu = "\n".join(l for l in sh(["lscpu"]).splitlines()
                          if l.split(":")[0].strip() in ("Architecture", "CPU(s)", "Model name", "Thread(s) per core",
                                                         "Core(s) per socket"))
        lines = ["# Input pipeline throughput", "",
                 f"Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M UTC}; "
                 f"python {platform.python_version()}, numpy {np.__version__}, opencv {cv2.__version__}, "
                 f"grain 0.2.x.", "",
                 "Machine (lscpu):", "```", lscpu, "```",
                 f"Load before/after (uptime): `{uptime_before}` / `{sh(['uptime'])}` — the 2 cores were shared "
                 "with other jobs, so these are lower bounds.", "",
                 f"Command: `python -m bridge_jax.data.pipeline --out {args.out}` (batch {args.batch}, "
                 f"{args.batches} timed batches after 2 warm-up batches; worker start-up excluded).",
                 f"Working size {args.width}×{args.height}; pipeline = decode → augment (paper, p=0.5 each) → "
                 f"resize → batch. KITTI-sized frames: synthetic 1242×375 PNGs (≈{png_bytes / 1e3:.0f} kB "
                 "each).", "",
                 "| source | workers | cycles/s (wall) | main-process CPU ms / cycle | start-up s |",
                 "|---|---|---|---|---|"]
        lines += [f"| {n} | {w} | {r['cycles_per_s']:.1f} | {r['main_cpu_ms_per_cycle']:.0f} | "
                  f"{r['startup_s']:.1f} |" for n, w, r in rows]
        lines += ["", "With 0 workers the CPU ms / cycle is the whole pipeline's cost on one core; 1000 / it is the "
                  "load-free single-core rate, about twice that the 2-worker rate on 2 idle cores."]
        os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
        with open(args.out + ".tmp", "w") as fh:
            fh.write("\n".join(lines) + "\n")
        os.replace(args.out + ".tmp", args.out)
    return 0


if __name__ == "__main__":
    # Run through the importable module so that grain worker processes unpickle its classes by reference.
    import sys
    from bridge_jax.data import pipeline as _pipeline
    sys.exit(_pipeline._bench_main())
