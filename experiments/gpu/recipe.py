"""The `long` recipe on a GPU: candidate recipes side by side, each the one command `bridge-train --config=long ...`
with its own overrides, run concurrently on one device, then scored on the real-image checks.

    python3 experiments/gpu/recipe.py --out $OUT [--budget-s 420] [--candidates A,B,C]

Each candidate trains in WORK/<name> (the recipe workdir, `--work`) with `data.num_workers` worker processes for the
synthetic scenes; a candidate still training after `--budget-s` seconds is stopped with SIGTERM (it saves a
checkpoint and the recipe's latest stage stands for it). Then `experiments/real_images.py` scores the shipped
`long` and every candidate at the card's settings with and without the polish (`--eval-budget-s`). What comes back
under $OUT: `summary.json` (per candidate: stages, steps, seconds per stage, step times, validation), one
`<name>.tar.gz` per candidate (the final stage's newest checkpoint, its config and model.json, metrics.jsonl,
recipe.json) so the checks can be rerun elsewhere, and the checks' markdown/JSON.

`JAX_DEFAULT_MATMUL_PRECISION=highest` keeps matrix products and convolutions in float32 as on a CPU (no TF32), so
a candidate's training follows the CPU's.
"""
from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tarfile
import time

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

# The last stage the candidates C-I were measured with (configs/long.py until 2026-12-06, recipe D): 250 steps at
# 256x512, lr 1.25e-4 constant, no moving average. Their earlier stages are set by their own overrides.
D_LAST = ["--config.stage_overrides.hires.lr=1.25e-4", "--config.stage_overrides.hires.ema_decay=0.0",
          "--config.stage_overrides.hires.loop.num_train_steps=250",
          "--config.stage_overrides.hires.loop.steps_per_epoch=250"]
# Candidates measured before configs/long.py masked the stereo pairs by the occlusion check in its last two stages
# (2026-12-06, candidate M of long_recipe.md section 3e) keep them unmasked.
NO_STEREO_OCC = ["--config.stage_overrides.main.loss.stereo_occlusion=False",
                 "--config.stage_overrides.hires.loss.stereo_occlusion=False"]

CANDIDATES = {
    # the recipe as configs/long.py declares it (candidate M of long_recipe.md section 3e since 2026-12-06)
    "A": [],
    # its `main` stage at two cycles per step
    "B": ["--config.stage_overrides.main.global_batch=2"],
    # a longer 64x128 stage (its lr halving every 750 steps from step 2000), a shorter 128x256 one
    "C": ["--config.stage_overrides.coarse.loop.num_train_steps=6000",
          "--config.stage_overrides.coarse.loop.steps_per_epoch=500",
          "--config.stage_overrides.main.loop.num_train_steps=1000"] + D_LAST + NO_STEREO_OCC,
    # C's 64x128 stage half as long again (halving every 750 steps from step 3000)
    "D": ["--config.stage_overrides.coarse.loop.num_train_steps=9000",
          "--config.stage_overrides.coarse.loop.steps_per_epoch=750",
          "--config.stage_overrides.main.loop.num_train_steps=1000"] + D_LAST + NO_STEREO_OCC,
    # C with the 256x512 stage's time spent at 128x256 instead (hires reduced to one step)
    "E": ["--config.stage_overrides.coarse.loop.num_train_steps=6000",
          "--config.stage_overrides.coarse.loop.steps_per_epoch=500",
          "--config.stage_overrides.main.loop.num_train_steps=2400",
          "--config.stage_overrides.main.loop.steps_per_epoch=400"] + D_LAST
         + NO_STEREO_OCC + ["--config.stage_overrides.hires.loop.num_train_steps=1"],
    # D's stages with a third more 64x128 steps and twice the 128x256 ones (run end to end on a 2-core CPU:
    # 1 h 59 min, long_recipe.md section 3b)
    "G": ["--config.stage_overrides.coarse.loop.num_train_steps=12000",
          "--config.stage_overrides.coarse.loop.steps_per_epoch=1000",
          "--config.stage_overrides.main.loop.num_train_steps=2000"] + D_LAST + NO_STEREO_OCC,
    # the recipe with the stereo pairs masked by the occlusion check from the first stage on (edges.md: most of
    # Motorcycle's error is occluded background given the foreground's disparity; the recipe masks them from its
    # second stage on)
    "H": ["--config.loss.stereo_occlusion=True"],
    # G with the stereo pairs masked
    "I": ["--config.stage_overrides.coarse.loop.num_train_steps=12000",
          "--config.stage_overrides.coarse.loop.steps_per_epoch=1000",
          "--config.stage_overrides.main.loop.num_train_steps=2000",
          "--config.loss.stereo_occlusion=True"] + D_LAST,
    # J (long_recipe.md section 3c): the recipe's stages with the last at half its lr and without the average
    "J": ["--config.stage_overrides.hires.lr=1.25e-4", "--config.stage_overrides.hires.ema_decay=0.0"]
         + NO_STEREO_OCC,
    # K (section 3d): the recipe without the stereo occlusion mask
    "K": NO_STEREO_OCC,
    # K with its last stage at twice its lr (section 3d: better on Motorcycle, worse on the zooms)
    "L": ["--config.stage_overrides.hires.lr=5e-4"] + NO_STEREO_OCC,
}


def _train(name: str, extra: list[str], work: str, workers: int) -> subprocess.Popen:
    workdir = os.path.join(work, name)
    os.makedirs(workdir, exist_ok=True)
    cmd = [sys.executable, "-m", "bridge_jax.train", "--config=long", f"--workdir={workdir}",
           f"--config.data.num_workers={workers}", "--config.loop.progress_bar=False",
           f"--config.compilation_cache_dir={os.path.join(work, 'xla_cache')}", *extra]
    log = open(os.path.join(workdir, "train.log"), "w")
    print(f"[{name}] {' '.join(cmd)}", flush=True)
    return subprocess.Popen(cmd, cwd=REPO, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)


def _summary(workdir: str) -> dict:
    out: dict = {"stages": {}}
    try:
        with open(os.path.join(workdir, "recipe.json")) as f:
            names = json.load(f)["stages"]
    except (OSError, ValueError, KeyError):
        return out
    times: dict = {}
    try:
        with open(os.path.join(workdir, "metrics.jsonl")) as f:
            for line in f:
                rec = json.loads(line)
                if rec.get("kind") == "train" and "step_time_s" in rec:
                    times.setdefault(rec["stage"], []).append(rec["step_time_s"])
                if rec.get("kind") == "val":
                    out["stages"].setdefault(rec["stage"], {})["last_val"] = {
                        k: rec[k] for k in ("flow_epe_all", "flow_epe_vs_zero", "disp_epe_all", "disp_d1_all")
                        if k in rec}
    except (OSError, ValueError):
        pass
    for name in names:
        st = out["stages"].setdefault(name, {})
        try:
            with open(os.path.join(workdir, "stages", name, "finished.json")) as f:
                done = json.load(f)
            st.update(steps=done["steps"], seconds=done["seconds"])
        except (OSError, ValueError, KeyError):
            st["finished"] = False
        if times.get(name):
            ts = sorted(times[name])
            st["median_step_time_s"] = ts[len(ts) // 2]
    return out


def _pack(name: str, workdir: str, out: str) -> None:
    sys.path.insert(0, REPO)
    from bridge_jax import checkpointing
    try:
        stage = checkpointing.model_dir(workdir)
    except ValueError:
        return
    step = checkpointing.find_train_step_dir(stage)
    with tarfile.open(os.path.join(out, f"{name}.tar.gz"), "w:gz") as tar:
        for rel in ("recipe.json", "metrics.jsonl", "train.log"):
            if os.path.exists(os.path.join(workdir, rel)):
                tar.add(os.path.join(workdir, rel), arcname=f"{name}/{rel}")
        for rel in ("config.json", "model.json", "finished.json"):
            if os.path.exists(os.path.join(stage, rel)):
                tar.add(os.path.join(stage, rel), arcname=f"{name}/stages/{os.path.basename(stage)}/{rel}")
        if step:
            tar.add(step, arcname=f"{name}/stages/{os.path.basename(stage)}/checkpoints/{os.path.basename(step)}")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", required=True, help="results: summary.json, <name>.tar.gz, real_images.md/.json")
    p.add_argument("--work", default="/tmp/bridge_recipe_work", help="the candidates' workdirs and XLA cache")
    p.add_argument("--candidates", default=",".join(CANDIDATES))
    p.add_argument("--budget-s", type=float, default=420.0, help="training wall time for all candidates together")
    p.add_argument("--eval-budget-s", type=float, default=120.0, help="wall time for the real-image checks")
    p.add_argument("--workers", type=int, default=4, help="data workers per candidate")
    p.add_argument("--polish", default="none,photometric", help="the checks' --polish list")
    p.add_argument("--with-long", action=argparse.BooleanOptionalAction, default=True,
                   help="score the shipped `long` beside the candidates")
    p.add_argument("--checks", default=os.path.join(REPO, "experiments", "real_images.py"),
                   help="the real-image checks script")
    args = p.parse_args(argv)
    os.makedirs(args.out, exist_ok=True)
    os.environ.setdefault("JAX_DEFAULT_MATMUL_PRECISION", "highest")
    names = [n for n in args.candidates.split(",") if n]
    t0 = time.time()
    procs = {n: _train(n, CANDIDATES[n], args.work, args.workers) for n in names}
    stopped = set()
    while any(proc.poll() is None for proc in procs.values()):
        time.sleep(5)
        if time.time() - t0 > args.budget_s:
            for n, proc in procs.items():
                if proc.poll() is None and n not in stopped:
                    print(f"[{n}] over the budget: SIGTERM", flush=True)
                    os.killpg(proc.pid, signal.SIGTERM)
                    stopped.add(n)
            if time.time() - t0 > args.budget_s + 60:
                for proc in procs.values():
                    if proc.poll() is None:
                        os.killpg(proc.pid, signal.SIGKILL)
    train_s = time.time() - t0
    summary = {"train_wall_s": round(train_s, 1), "candidates": {}}
    for n in names:
        workdir = os.path.join(args.work, n)
        summary["candidates"][n] = {"overrides": CANDIDATES[n], "rc": procs[n].returncode,
                                    "stopped": n in stopped, **_summary(workdir)}
        _pack(n, workdir, args.out)
    with open(os.path.join(args.out, "summary.json"), "w") as f:
        json.dump(summary, f, indent=1)
    print(json.dumps(summary, indent=1), flush=True)
    models = ",".join((["long"] if args.with_long else []) + [os.path.join(args.work, n) for n in names])
    cmd = [sys.executable, args.checks, "--models", models,
           "--sizes", "native", "--refine", "1", "--symmetry", "flips", "--polish", args.polish,
           "--out", os.path.join(args.out, "real_images.md")]
    print(" ".join(cmd), flush=True)
    try:
        subprocess.run(cmd, cwd=REPO, timeout=args.eval_budget_s)
    except subprocess.TimeoutExpired:
        print("real-image checks: over their budget, stopped", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
