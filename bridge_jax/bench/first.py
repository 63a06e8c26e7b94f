"""Time to a first answer: the wall time of a fresh process, as a new user starts it.

  first_prediction  `python -m bridge_jax.predict --checkpoint NAME --task flow a.png b.png --out OUT` on a
                    512x256 photo pair (scikit-image's stereo_motorcycle, resized: the same pixels every time)
  first_step        `python -m bridge_jax.train --config=NAME --config.height=H --config.width=W --workdir WD`
                    for a few steps (no validation, no pictures, no checkpoint before the one at the end); also
                    `first_step_s` of the run's status.json (process start to the end of the first train step;
                    null when the trainer does not write it)

Each command runs with BRIDGE_JAX_CACHE_DIR (the commands' persistent compilation cache; "" = off) set and
JAX_COMPILATION_CACHE_DIR removed from its environment:

  cold  a fresh empty cache folder for every run (`repeats` runs)
  warm  the folder the last cold run filled, again (`repeats` runs, each with a new output folder / workdir)
  off   BRIDGE_JAX_CACHE_DIR="" (one run; first_prediction only, where a run is cheap)

`time_cold_warm` takes a function building the command line, so a test can time a tiny stand-in command.
"""

from __future__ import annotations

import json
import os
import resource
import statistics
import subprocess
import sys
import tempfile
import time
from typing import Callable

from bridge_jax import files
from bridge_jax.bench.timing import BenchError, _busy_jiffies

CACHE_ENV = "BRIDGE_JAX_CACHE_DIR"
PAIR_SIZE = (256, 512)
"""(height, width) of the first_prediction image pair."""
FIRST_STEP_SIZE = (128, 256)
"""(height, width) first_step trains at unless --height / --width say otherwise."""
FIRST_STEP_STEPS = 2
"""Train steps of a first_step run: the first one, and one more so that the run ends as a real run does."""


def child_env(cache_dir: str) -> dict:
    """This process's environment with BRIDGE_JAX_CACHE_DIR=`cache_dir` and no JAX_COMPILATION_CACHE_DIR (which
    would win over the commands' own cache)."""
    env = dict(os.environ)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    env[CACHE_ENV] = cache_dir
    return env


def _children_cpu_s() -> float:
    ru = resource.getrusage(resource.RUSAGE_CHILDREN)
    return ru.ru_utime + ru.ru_stime


def run_timed(cmd: list[str], env: dict, label: str) -> dict:
    """Runs `cmd` to its end; {"wall_s", "cpu_s" (its user + system seconds), "other_procs_cpu_frac" (the share of
    all CPUs that other processes used meanwhile)}. A non-zero exit raises BenchError with its stderr's tail."""
    j0, c0, t0 = _busy_jiffies(), _children_cpu_s(), time.perf_counter()
    proc = subprocess.run(cmd, env=env, capture_output=True, text=True)
    wall, cpu, j1 = time.perf_counter() - t0, _children_cpu_s() - c0, _busy_jiffies()
    if proc.returncode != 0:
        lines = (proc.stderr or proc.stdout).strip().splitlines()
        tail = " | ".join(line.strip() for line in lines[-3:] if line.strip()) or "no output"
        raise BenchError(f"{label}: {' '.join(cmd[1:4])} ... failed (exit {proc.returncode}): {tail}")
    other = None
    if j0 is not None and j1 is not None and wall > 0:
        busy = (j1 - j0) / os.sysconf("SC_CLK_TCK")
        other = round(max(0.0, (busy - cpu) / (wall * (os.cpu_count() or 1))), 3)
    return {"wall_s": wall, "cpu_s": cpu, "other_procs_cpu_frac": other}


def read_first_step_s(workdir: str) -> float | None:
    """`first_step_s` of `workdir`/status.json, or None (no file, unreadable, or no such key)."""
    try:
        with open(os.path.join(workdir, "status.json")) as f:
            value = json.load(f).get("first_step_s")
    except (OSError, ValueError, AttributeError):
        return None
    return round(float(value), 3) if isinstance(value, (int, float)) else None


def _median(values):
    values = [v for v in values if v is not None]
    return round(statistics.median(values), 3) if values else None


def time_cold_warm(make_cmd: Callable[[str], list[str]], *, repeats: int, label: str, off: bool = False,
                   status_json: bool = False) -> dict:
    """Times fresh processes `make_cmd(run_dir)` (`run_dir`: a new path that does not exist yet, for the command's
    output folder or workdir): `repeats` cold runs, `repeats` warm runs, and one off run if `off`.

    Returns {"cold_s", "warm_s", "off_s"} (medians of wall seconds; off_s None unless `off`), the single times
    ("cold_times_s", ...), "cpu_s" (median child CPU seconds, cold and warm), the other processes' CPU share,
    and with `status_json` "first_step_cold_s" / "first_step_warm_s" / "first_step_times_s" from each run's
    status.json (None where missing)."""
    if repeats < 1:
        raise BenchError(f"--repeats must be >= 1, got {repeats}")
    runs = {"cold": [], "warm": [], "off": []}
    with tempfile.TemporaryDirectory(prefix="bridge_bench_first_") as root:
        def one(kind: str, cache_dir: str) -> None:
            run_dir = os.path.join(root, f"run{sum(len(v) for v in runs.values())}")
            r = run_timed(make_cmd(run_dir), child_env(cache_dir), f"{label} ({kind} cache)")
            r["first_step_s"] = read_first_step_s(run_dir) if status_json else None
            runs[kind].append(r)

        cache_dir = ""
        for i in range(repeats):
            cache_dir = os.path.join(root, f"cache{i}")
            os.makedirs(cache_dir)
            one("cold", cache_dir)
        for _ in range(repeats):
            one("warm", cache_dir)
        if off:
            one("off", "")
    rec = {f"{k}_s": _median([r["wall_s"] for r in v]) for k, v in runs.items()}
    rec.update({f"{k}_times_s": [round(r["wall_s"], 3) for r in v] for k, v in runs.items() if v})
    rec["cpu_s"] = {k: _median([r["cpu_s"] for r in v]) for k, v in runs.items() if v}
    everything = [r for v in runs.values() for r in v]
    rec["other_procs_cpu_frac"] = _median([r["other_procs_cpu_frac"] for r in everything])
    if status_json:
        rec["first_step_cold_s"] = _median([r["first_step_s"] for r in runs["cold"]])
        rec["first_step_warm_s"] = _median([r["first_step_s"] for r in runs["warm"]])
        rec["first_step_times_s"] = {k: [r["first_step_s"] for r in v] for k, v in runs.items() if v}
    rec["children_peak_rss_gib"] = round(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss / 2**20, 3)
    return rec


# ---------------------------------------------------------------------------------------------------------
# The two commands
# ---------------------------------------------------------------------------------------------------------

def write_photo_pair(folder: str, height: int = PAIR_SIZE[0], width: int = PAIR_SIZE[1]) -> tuple[str, str]:
    """scikit-image's stereo_motorcycle left and right photos resized to `width` x `height`, as a.png and b.png."""
    import cv2
    from skimage import data as skdata

    paths = []
    for name, img in zip(("a.png", "b.png"), skdata.stereo_motorcycle()[:2]):
        small = cv2.resize(img, (width, height), interpolation=cv2.INTER_AREA)
        path = os.path.join(folder, name)
        try:
            files.imwrite(path, cv2.cvtColor(small, cv2.COLOR_RGB2BGR))
        except (ValueError, OSError) as e:
            raise BenchError(f"first_prediction: could not write {path} ({e})") from None
        paths.append(path)
    return paths[0], paths[1]


def predict_command(a: str, b: str, out: str, checkpoint: str, working_size: str | None = None,
                    symmetry: str | None = None, polish: str | None = None, confidence: bool = False) -> list[str]:
    cmd = [sys.executable, "-m", "bridge_jax.predict", "--checkpoint", checkpoint, "--task", "flow", a, b,
           "--out", out]
    return (cmd + (["--working-size", working_size] if working_size else [])
            + (["--symmetry", symmetry] if symmetry else []) + (["--polish", polish] if polish else [])
            + (["--confidence"] if confidence else []))


def measure_first_prediction(args) -> dict:
    """A fresh `bridge_jax.predict` process on one 512x256 flow pair: cold, warm and off (see the module doc)."""
    checkpoint = args.checkpoint
    with tempfile.TemporaryDirectory(prefix="bridge_bench_pair_") as tmp:
        a, b = write_photo_pair(tmp)
        rec = time_cold_warm(lambda out: predict_command(a, b, out, checkpoint, args.working_size, args.symmetry,
                                                         args.polish, confidence=args.confidence),
                             repeats=int(args.repeats), label="first_prediction", off=True)
    size, symmetry, polish = args.working_size or "default", args.symmetry or "default", args.polish or "default"
    variant = (f"{checkpoint} working size {size}" + (f" symmetry {symmetry}" if args.symmetry else "")
               + (f" polish {polish}" if args.polish else "") + (" confidence" if args.confidence else ""))
    return dict(what="first_prediction", variant=variant, checkpoint=checkpoint, working_size=size,
                symmetry=symmetry, polish=polish, confidence=bool(args.confidence), height=PAIR_SIZE[0],
                width=PAIR_SIZE[1], task="flow", repeats=int(args.repeats), **rec)


def _first_stage(config: str) -> str | None:
    """The first stage's name when `config` names a recipe, else None (and None when it does not load: the
    training command then says what is wrong with it)."""
    from bridge_jax import configs, recipe
    try:
        cfg = configs.load(config)
        return recipe.stage_names(cfg)[0] if recipe.is_recipe(cfg) else None
    except Exception:  # noqa: BLE001
        return None


def train_command(workdir: str, config: str, height: int, width: int, *, steps: int = FIRST_STEP_STEPS,
                  extra: tuple[str, ...] = ()) -> list[str]:
    """A short training run: `steps` steps, a metrics line every step, no validation, no pictures, no periodic
    checkpoint (the trainer still writes one at the end), no progress bar. A recipe config (the demo's) runs its
    first stage only (`--config.stages=NAME`): the first step of what the command trains first."""
    first_stage = _first_stage(config)
    if first_stage:
        extra = (f"--config.stages={first_stage}", *extra)
    return [sys.executable, "-m", "bridge_jax.train", f"--config={config}", f"--config.height={height}",
            f"--config.width={width}", "--workdir", workdir, f"--config.loop.num_train_steps={steps}",
            f"--config.loop.checkpoint_every={steps + 1}", "--config.loop.eval_every=-1",
            "--config.loop.image_every=-1", "--config.loop.log_every=1", "--config.loop.progress_bar=False", *extra]


def measure_first_step(args) -> dict:
    """Fresh `bridge_jax.train` processes of FIRST_STEP_STEPS steps: cold and warm (see the module doc)."""
    height = args.height or FIRST_STEP_SIZE[0]
    width = args.width or FIRST_STEP_SIZE[1]
    extra = [f"--config.{kv}" for kv in (args.set or [])]
    if args.cycles:
        extra.append(f"--config.global_batch={args.cycles}")
    if args.dtype:
        extra.append(f"--config.dtype={args.dtype}")
    rec = time_cold_warm(lambda wd: train_command(wd, args.config, height, width, extra=tuple(extra)),
                         repeats=int(args.repeats), label="first_step", status_json=True)
    return dict(what="first_step", variant=f"{args.config} {FIRST_STEP_STEPS} steps", config=args.config,
                overrides=list(args.set or []), height=height, width=width, cycles=args.cycles, dtype=args.dtype,
                train_steps=FIRST_STEP_STEPS, repeats=int(args.repeats), **rec)
