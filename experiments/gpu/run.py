"""The GPU run: the train step, inference and upstream PyTorch measured on one CUDA GPU in < 10 min.

    # on the GPU machine (see experiments/gpu/README.md for the set-up and the exact command):
    python experiments/gpu/run.py --out $OUT/gpu.jsonl --peer-dir .peer/harness --peer-src .peer/src
    # here, on CPU, in the test suite: the same sequence at tiny shapes, upstream skipped unless torch is there
    python experiments/gpu/run.py --dry-run --out /tmp/gpu_dry.jsonl

Measured, each by `python -m bridge_jax.bench` in this process (compile time, median step time over the timed
calls, device memory from the backend's `memory_stats` where it reports it, XLA's FLOP count, MFU against the
device's dense peak, trace/compile counts during the timed calls):
  1. the full2 train step at 512x256 (2 cycles = upstream's batch, plain step), float32 and bfloat16 compute;
  2. the same at 8 cycles in bfloat16 (throughput and MFU at a batch that fills the GPU better);
  3. inference: 1 and 8 pairs per call at 512x256;
  4. upstream PyTorch on the same device through the peer harness (`experiments/gpu/peer_cuda.py`: its CPU
     shims undone, tensors on CUDA), train step plain and with bfloat16 autocast (AMP), and inference.
Then one summary: bf16 cycles/s vs upstream AMP cycles/s, MFU, and where each number came from. Every record is
one JSON line in --out (and printed); the summary is printed as Markdown for experiments/results/gpu.md.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
REPO = os.path.dirname(os.path.dirname(HERE))
sys.path.insert(0, REPO)

FULL = {"config": "full2", "height": 256, "width": 512, "repeats": 5, "warmup": 2, "peer_runs": 5}
# the dry run: the demo's small model (compiles in seconds on CPU) at 64x128, one timed call each
DRY = {"config": "demo:short", "height": 64, "width": 128, "repeats": 1, "warmup": 0, "peer_runs": 1}


def plan(size: dict, dry: bool) -> list[tuple[str, str, list[str]]]:
    """(key, label, bench arguments) of every JAX measurement, in order: the headline (bf16 at upstream's batch)
    first, in case the device time runs out."""
    common = ["--config", size["config"], "--height", str(size["height"]), "--width", str(size["width"]),
              "--repeats", str(size["repeats"]), "--warmup", str(size["warmup"])]
    big = "2" if dry else "8"
    step = ["--what", "train_step", *common, "--micro-batch", "0"]
    infer = ["--what", "inference", *common]
    return [
        ("train_step_bf16", "train_step bfloat16, 2 cycles", [*step, "--cycles", "2", "--dtype", "bfloat16"]),
        ("train_step_f32", "train_step float32, 2 cycles", [*step, "--cycles", "2", "--dtype", "float32"]),
        ("train_step_bf16_big", f"train_step bfloat16, {big} cycles", [*step, "--cycles", big, "--dtype", "bfloat16"]),
        ("inference_f32", "inference float32, 1 pair", [*infer, "--pairs", "1", "--dtype", "float32"]),
        ("inference_bf16_big", f"inference bfloat16, {big} pairs", [*infer, "--pairs", big, "--dtype", "bfloat16"]),
    ]


def run_bench(argv: list[str], dry: bool) -> list[dict]:
    """One `python -m bridge_jax.bench` measurement in its own process, so that its device-memory peak and RSS
    are its own; returns its JSON records."""
    import tempfile
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "r.jsonl")
        cmd = [sys.executable, "-m", "bridge_jax.bench", *argv, *(["--no-peak"] if dry else []), "--json", out]
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=REPO,
                              env=dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", "")))
        if proc.returncode not in (0, 3) or not os.path.exists(out):
            tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
            return [{"what": argv[1], "skipped": f"bench failed (exit {proc.returncode}): {tail[0]}"}]
        with open(out) as f:
            return [json.loads(line) for line in f if line.strip()]


def run_peer(size: dict, peer_dir: str | None, peer_src: str | None, mode: str, amp: bool, batch: int,
             python: str = sys.executable) -> dict:
    """Upstream PyTorch through peer_cuda.py in a subprocess (its own CUDA context and memory peak)."""
    if not peer_dir:
        return {"what": f"peer_{mode}", "skipped": "no --peer-dir"}
    cmd = [python, os.path.join(HERE, "peer_cuda.py"), mode, "--harness-dir", peer_dir,
           "--height", str(size["height"]), "--width", str(size["width"]), "--runs", str(size["peer_runs"]),
           "--batch", str(batch), *(["--amp"] if amp else [])]
    env = dict(os.environ, **({"BDF_SRC": peer_src} if peer_src else {}))
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    if proc.returncode != 0:
        tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
        return {"what": f"peer_{mode}", "amp": amp, "skipped": f"failed (exit {proc.returncode}): {tail[0]}"}
    rec = json.loads(proc.stdout.strip().splitlines()[-1])
    rec["wall_total_s"] = round(time.perf_counter() - t0, 1)
    return rec


def summary(records: list[dict], dry: bool = False) -> str:
    """Markdown: one row per measurement and the headline ratios."""
    rows = ["| measurement | median s | compile s | cycles or pairs / s | device memory GiB | TFLOP per call | MFU |",
            "|---|---|---|---|---|---|---|"]
    for r in records:
        if r.get("skipped"):
            rows.append(f"| {r.get('label', r['what'])} | skipped: {r['skipped']} | | | | | |")
            continue
        n = (r.get("pairs_per_call") or r.get("batch")) if r["what"] in ("inference", "peer_infer") else (
            r.get("cycles") or r.get("batch_cycles"))
        n = n or r.get("batch") or 1
        med = r.get("median_s")
        rate = f"{n / med:.2f}" if med else ""
        mem = r.get("device_memory_peak_bytes") or r.get("cuda_max_allocated_bytes")
        mem = f"{mem / 2**30:.2f}" if isinstance(mem, (int, float)) else ""
        flops = r.get("flops")
        rows.append(f"| {r.get('label', r['what'])} | {med} | {r.get('compile_s') or ''} | {rate} | {mem} | "
                    f"{flops / 1e12:.3f} | {r.get('mfu') if r.get('mfu') is not None else ''} |"
                    if flops else f"| {r.get('label', r['what'])} | {med} | {r.get('compile_s') or ''} | {rate} | "
                                  f"{mem} | | |")
    ours = next((r for r in records if r.get("label", "").startswith("train_step bfloat16, 2")), None)
    amp = next((r for r in records if r.get("what") == "peer_train" and r.get("amp") and r.get("median_s")), None)
    if ours and amp and ours.get("median_s"):
        rows.append("")
        rows.append(f"bf16 train step throughput vs upstream AMP (2 cycles each): "
                    f"{amp['median_s'] / ours['median_s']:.2f}x (goal >= 2x)"
                    + (" -- dry run: the demo's small model vs upstream's network on CPU, not comparable" if dry
                       else ""))
    return "\n".join(rows)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--out", required=True, help="JSON lines output (one per measurement)")
    ap.add_argument("--dry-run", action="store_true", help="tiny shapes on whatever device is there (CPU)")
    ap.add_argument("--peer-dir", default=None, help="folder holding the peer harness.py (upstream skipped if unset)")
    ap.add_argument("--peer-src", default=None, help="upstream BridgeDepthFlow source folder (BDF_SRC)")
    ap.add_argument("--peer-python", default=sys.executable, help="Python with PyTorch for the upstream runs")
    ap.add_argument("--only", default="", help="comma list of measurement keys (train_step_f32, train_step_bf16, "
                    "train_step_bf16_big, inference_f32, inference_bf16_big, peer); default all")
    args = ap.parse_args(argv)
    size = DRY if args.dry_run else FULL
    t_start = time.perf_counter()
    records = []
    # upstream first, while this process holds no device memory
    only = {k for k in args.only.split(",") if k}
    for mode, amp, batch in (("train", False, 2), ("train", True, 2), ("infer", False, 1)):
        if only and "peer" not in only:
            break
        rec = run_peer(size, args.peer_dir, args.peer_src, mode, amp, batch, args.peer_python)
        rec["label"] = f"upstream {mode}{' AMP bf16' if amp else ''}, {batch} {'cycles' if mode == 'train' else 'pair'}"
        records.append(rec)
        print(json.dumps(rec, sort_keys=True), flush=True)
    for key, label, bench_argv in plan(size, args.dry_run):
        if only and key not in only:
            continue
        for rec in run_bench(bench_argv, args.dry_run):
            rec["label"] = label if rec["what"] in ("train_step", "inference") else rec["what"]
            records.append(rec)
            print(json.dumps(rec, sort_keys=True, default=str), flush=True)
    with open(args.out, "w") as f:
        for r in records:
            f.write(json.dumps(r, sort_keys=True, default=str) + "\n")
    print(summary(records, args.dry_run))
    print(f"total {time.perf_counter() - t_start:.0f} s; wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
