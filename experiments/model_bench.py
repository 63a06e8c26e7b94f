"""Inference benchmark: bridge_jax `Predictor.predict_pair` (fp32) vs upstream PyTorch, side by side.

    .venv/bin/python experiments/model_bench.py --out experiments/results/model_bench.md

Runs, alternately and each in a fresh process, the upstream harness (`../shared/peer/harness.py infer`,
PyTorch, 2 threads) and this project's predictor at 512x256 for batch 1 and 4, and records medians, compile
time, peak RSS and the CPU share other processes used during the timed runs (the machine is shared).
`--mode jax` runs only the JAX side and prints one JSON line.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

PEER_PY = os.environ.get("PEER_PYTHON", "/tmp/peer/venv/bin/python")
HARNESS = os.environ.get("PEER_HARNESS", str(Path(__file__).resolve().parents[2] / "shared/peer/harness.py"))


def _busy_s():
    with open("/proc/stat") as f:
        v = [float(x) for x in f.readline().split()[1:]]
    busy = (sum(v) - v[3] - v[4]) / os.sysconf("SC_CLK_TCK")
    ru = resource.getrusage(resource.RUSAGE_SELF)
    return busy, ru.ru_utime + ru.ru_stime


def _other_frac(fn):
    b0, o0 = _busy_s()
    t0 = time.perf_counter()
    out = fn()
    wall = time.perf_counter() - t0
    b1, o1 = _busy_s()
    return out, wall, max(0.0, (b1 - b0) - (o1 - o0)) / (wall * (os.cpu_count() or 1))


def wait_quiet(max_wait_s: float, thresh: float = 0.10) -> None:
    """Wait (up to max_wait_s) until other processes use < thresh of the CPUs over a 1 s window."""
    t0 = time.perf_counter()
    while time.perf_counter() - t0 < max_wait_s:
        _, _, other = _other_frac(lambda: time.sleep(1.0))
        if other < thresh:
            return


def run_jax(batch: int, runs: int, warmup: int, dtype: str, quiet: float = 0.0) -> dict:
    import jax
    import numpy as np

    from bridge_jax import inference, models

    t = time.perf_counter()
    graphdef, params = models.init(jax.random.key(0), "resnet_md")
    init_s = time.perf_counter() - t
    pred = inference.Predictor(graphdef, params, size=inference.WorkingSize(256, 512), dtype=dtype,
                               model_cfg=models.model_config("resnet_md"))
    rng = np.random.default_rng(1)
    a = rng.integers(0, 256, size=(batch, 256, 512, 3), dtype=np.uint8)
    b = rng.integers(0, 256, size=(batch, 256, 512, 3), dtype=np.uint8)
    t = time.perf_counter()
    pred.predict_pairs(a, b)
    first_s = time.perf_counter() - t
    times, other = [], []
    for i in range(warmup + runs):
        if quiet and i >= warmup:
            wait_quiet(quiet)
        _, dt, o = _other_frac(lambda: pred.predict_pairs(a, b))
        if i >= warmup:
            times.append(dt)
            other.append(o)
    # KITTI-sized input (375x1242): includes resizing both ways
    k = rng.integers(0, 256, size=(375, 1242, 3), dtype=np.uint8)
    pred.predict_pair(k, k)
    kt = []
    for _ in range(3):
        t = time.perf_counter()
        pred.predict_pair(k, k)
        kt.append(time.perf_counter() - t)
    return dict(side="jax", batch=batch, dtype=dtype, init_s=round(init_s, 2), compile_plus_first_s=round(first_s, 2),
                median_s=round(statistics.median(times), 4), min_s=round(min(times), 4),
                times_s=[round(x, 4) for x in times], other_procs_cpu_frac=[round(x, 3) for x in other],
                kitti_size_pair_median_s=round(statistics.median(kt), 4), traces=pred.trace_count,
                peak_rss_gib=round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2 ** 20, 3),
                jax=jax.__version__)


def run_upstream(batch: int, runs: int, warmup: int, quiet: float = 0.0) -> dict:
    cmd = [PEER_PY, HARNESS, "infer", "--height", "256", "--width", "512", "--threads", "2", "--batch", str(batch),
           "--runs", str(runs), "--warmup", str(warmup), "--wait-quiet", str(quiet)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
    return dict(side="upstream", **json.loads(out))


def run_jax_subprocess(batch: int, runs: int, warmup: int, dtype: str, quiet: float = 0.0) -> dict:
    cmd = [sys.executable, __file__, "--mode", "jax", "--batch", str(batch), "--runs", str(runs),
           "--warmup", str(warmup), "--dtype", dtype, "--wait-quiet", str(quiet)]
    out = subprocess.run(cmd, capture_output=True, text=True, check=True).stdout.strip().splitlines()[-1]
    return json.loads(out)


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--mode", choices=["compare", "jax"], default="compare")
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--dtype", default="float32")
    ap.add_argument("--reps", type=int, default=2, help="compare: alternations of upstream / jax")
    ap.add_argument("--out", default=None, help="compare: markdown file to write")
    ap.add_argument("--wait-quiet", type=float, default=0.0,
                    help="before each timed run wait up to this many s for other processes to use < 10%% CPU")
    a = ap.parse_args()
    if a.mode == "jax":
        print(json.dumps(run_jax(a.batch, a.runs, a.warmup, a.dtype, a.wait_quiet)))
        return 0
    rows = []
    load = [open("/proc/loadavg").read().split()[:3]]
    for rep in range(a.reps):
        for batch in (1, 4):
            runs = a.runs if batch == 1 else max(3, a.runs // 2)
            for fn in (lambda: run_upstream(batch, runs, a.warmup, a.wait_quiet),
                       lambda: run_jax_subprocess(batch, runs, a.warmup, "float32", a.wait_quiet)):
                r = fn()
                r["rep"] = rep
                r["loadavg"] = open("/proc/loadavg").read().split()[:3]
                rows.append(r)
                print(json.dumps(r), flush=True)
    load.append(open("/proc/loadavg").read().split()[:3])
    if a.out:
        write_markdown(Path(a.out), rows, load)
    return 0


def write_markdown(path: Path, rows: list[dict], load) -> None:
    import platform

    model = next((ln.split(":", 1)[1].strip() for ln in open("/proc/cpuinfo") if ln.startswith("model name")), "?")
    lines = [
        "# Model inference benchmark: bridge_jax `predict_pair` vs upstream PyTorch",
        "",
        f"- date: {datetime.datetime.now(datetime.timezone.utc).isoformat(timespec='seconds')}",
        f"- machine: {model}, {os.cpu_count()} CPUs, {platform.machine()}; shared with other jobs "
        f"(load average at start {' '.join(load[0])}, at end {' '.join(load[-1])})",
        "- upstream: `../shared/peer/harness.py infer` (unmodified MonodepthNet, torch 2 threads, no grad);",
        "  bridge_jax: `Predictor.predict_pairs` end to end (uint8 in, numpy pixels out, fp32), 512x256 input",
        "  (= working size, so no resizing); random-init full ResNet-50 (58,461,416 params). Fresh process each.",
        "- `other` = mean CPU share used by other processes during the timed runs (0 = quiet machine).",
        "",
        "| rep | side | batch | median s | min s | per pair s | compile+1st s | peak RSS GiB | other | loadavg |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        other = r.get("other_procs_cpu_frac") or [0]
        lines.append(f"| {r['rep']} | {r['side']} | {r['batch']} | {r['median_s']:.3f} | {r['min_s']:.3f} | "
                     f"{r['median_s'] / r['batch']:.3f} | {r.get('compile_plus_first_s', '-')} | "
                     f"{r['peak_rss_gib']:.2f} | {statistics.mean(other):.2f} | {' '.join(r['loadavg'])} |")
    lines += ["", "Ratios (jax / upstream, same rep and batch, medians):", ""]
    for rep in sorted({r["rep"] for r in rows}):
        for batch in (1, 4):
            u = [r for r in rows if r["rep"] == rep and r["batch"] == batch and r["side"] == "upstream"]
            j = [r for r in rows if r["rep"] == rep and r["batch"] == batch and r["side"] == "jax"]
            if u and j:
                lines.append(f"- rep {rep}, batch {batch}: {j[0]['median_s'] / u[0]['median_s']:.2f} "
                             f"(min/min {j[0]['min_s'] / u[0]['min_s']:.2f})")
    kit = [r["kitti_size_pair_median_s"] for r in rows if r["side"] == "jax" and r["batch"] == 1]
    if kit:
        lines += ["", f"- bridge_jax one 375x1242 (KITTI-size) pair incl. resizing both ways: median "
                      f"{statistics.median(kit):.3f} s."]
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)


if __name__ == "__main__":
    sys.exit(main())
