"""The upstream PyTorch code beside our measurement (`--peer`): a harness script runs the unmodified upstream train
step or inference at the same size and prints its timings as JSON.

Where the harness and its Python live is the user's to say: `--peer-dir DIR` (holding `harness.py`) and
`--peer-python PATH` (an interpreter with PyTorch), or the environment variables BRIDGE_JAX_PEER_DIR and
BRIDGE_JAX_PEER_PYTHON. `harness.py` prints one JSON object of timings per call (see `run_peer`).
"""

from __future__ import annotations

import json
import os
import subprocess
import tempfile
import time

from bridge_jax.bench.timing import BenchError, current_rss_bytes

PEER_DIR_ENV = "BRIDGE_JAX_PEER_DIR"
PEER_PYTHON_ENV = "BRIDGE_JAX_PEER_PYTHON"
PEER_WARP_TYPE = {"none": 0, "full1": 1, "full2": 2, "full3": 3}
"""Upstream's --type_of_2warp for each of our 2-warp variants."""


def run_peer(what: str, run, args) -> dict:
    """Runs the upstream code through the peer harness (`what` = "train_step" or "inference", at the size and
    2-warp variant of `run`); returns its JSON as a record."""
    if not args.peer_dir or not args.peer_python:
        raise BenchError(f"--peer needs --peer-dir and --peer-python (or {PEER_DIR_ENV} / {PEER_PYTHON_ENV})")
    harness = os.path.join(args.peer_dir, "harness.py")
    if not os.path.isfile(harness):
        raise BenchError(f"--peer-dir {args.peer_dir}: no harness.py there")
    if not os.path.isfile(args.peer_python):
        raise BenchError(f"--peer-python {args.peer_python}: no such interpreter")
    if what == "train_step":
        cmd = ["train", "--warp-type", str(PEER_WARP_TYPE.get(run.loss.two_warp, 0)), "--warmup", "1",
               "--runs", str(args.peer_runs or args.repeats)]
    else:
        cmd = ["infer", "--batch", str(args.pairs), "--warmup", "2", "--runs", str(args.peer_runs or args.repeats)]
    parent_rss = current_rss_bytes() / 2**30
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "peer.json")
        full = [args.peer_python, harness, *cmd, "--height", str(run.height), "--width", str(run.width),
                "--threads", str(args.peer_threads), "--wait-quiet", "0", "--max-retries", "0", "--json", out]
        t0 = time.perf_counter()
        proc = subprocess.run(full, capture_output=True, text=True)
        if proc.returncode != 0 or not os.path.exists(out):
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            raise BenchError(f"--peer: harness.py {cmd[0]} failed (exit {proc.returncode}): {tail[0]}")
        with open(out) as f:
            peer = json.load(f)
    rec = dict(what=f"peer_{what}", variant=f"upstream PyTorch {cmd[0]}" + (
        f" type {cmd[2]}" if what == "train_step" else f" batch={args.pairs}"),
        median_s=peer.get("median_s"), min_s=peer.get("min_s"), max_s=peer.get("max_s"),
        times_s=peer.get("times_s"), peak_rss_gib=peer.get("peak_rss_gib"),
        other_procs_cpu_frac=peer.get("other_procs_cpu_frac"), compile_s=None, flops=None,
        flops_executed=None, flops_source=None, xla_temp_bytes=None, traces_timed=None, compiles_timed=None,
        recompiled=False, first_call_s=None, rss_timed_peak_gib=None, wall_total_s=round(time.perf_counter() - t0, 1),
        parent_rss_at_spawn_gib=round(parent_rss, 3), peer_json=peer)
    if what == "inference":
        rec["s_per_pair"] = round(peer["median_s"] / args.pairs, 4)
    return rec
