r"""Benchmarks: train step, inference, loss alone, the input pipeline and the time a fresh process takes to a first
prediction or train step, measured the same way every time.

    bridge-bench --what train_step --config default --micro-batch 0,2 --repeats 3 --warmup 1
    bridge-bench --what inference --config default --repeats 10
    bridge-bench --what loss --config full2 --cycles 2 --train-step-s 30.1
    bridge-bench --what all --config default:local --json out.jsonl
    bridge-bench --what train_step --config default --peer      # + upstream PyTorch beside it
    bridge-bench --what conv_backward --config default --conv-batch 16   # weight-grad methods
    bridge-bench --what first_prediction --checkpoint demo --repeats 3   # a fresh predict process, cold/warm cache
    bridge-bench --what first_step --config demo --height 128 --width 256   # a fresh trainer to its first step

Every in-process measurement reports: compile time, median / min / max wall time per call over `--repeats` calls after
`--warmup` calls (results are `block_until_ready`-ed, so the times are real), peak host RSS (`ru_maxrss` of the
process, and the peak sampled during the timed calls), device memory where the backend reports it (GPU/TPU
`memory_stats`; XLA's temp-buffer size from `memory_analysis` where a single executable exists), FLOPs from XLA's
cost analysis, achieved FLOP/s and MFU against the device's peak (`PEAK_TFLOPS` for known accelerators; on CPU
the best of a few jitted square matmuls measured in this process), the load of the machine (load average and the
share of all CPUs used by *other* processes during the timed calls) and a count of the traces and XLA compiles
that happened during the timed calls. A non-zero count means the step recompiled (e.g. a shape changed): the
record says so and the CLI exits with status 3.

Output: a table, then one JSON line per measurement (device kind, jax version, shapes, dtype, UTC date, ...),
also appended to `--json OUT` (JSON lines; written to a temporary name and renamed). `--what all` runs each
measurement in a fresh subprocess so that each peak RSS is that measurement's own.

Time to a first answer (`bridge_jax.bench.first`): `first_prediction` times a fresh `python -m bridge_jax.predict`
on one 512x256 photo pair (`--checkpoint`, default demo; `--working-size`, `--symmetry`, `--polish` passed through),
`first_step` a fresh `python -m bridge_jax.train` (default --config=demo at 128x256; `--height`, `--width`,
`--cycles`, `--dtype`, `--set` passed through as `--config.` options) for 2 steps, also reading `first_step_s` from
its status.json.
Each runs with a cold persistent compilation cache (a fresh empty BRIDGE_JAX_CACHE_DIR for each of `--repeats`
runs, default 1 for these two), a warm one (the same folder again) and, for first_prediction, once with the cache
off (BRIDGE_JAX_CACHE_DIR=""); JAX_COMPILATION_CACHE_DIR is removed from the child's environment. The records have
cold_s / warm_s / off_s (median wall seconds of the whole process), the machine and the CPU's ISA, but not the
in-process fields (compile_s, FLOPs, ...). `--what all` leaves them out: they take minutes and measure processes,
not this one; ask for each by name.

Train step variants: `--micro-batch 0` is the plain step (`train_step.make_train_step`: one jit, whole batch);
`--micro-batch k` is the maps-first micro-batched step (`micro_batch.MicroBatchedStep`, k pair-forwards per call;
its record also has `phase_s`, the seconds of each of its phases in one step); `-1` is the trainer's auto choice (the
default comes from the config); a comma list measures several in one process (RSS is then the maximum over them;
use separate runs for memory).
For the micro-batched step "flops" is the model's work (the plain step's XLA count, from its lowered HLO) and
"flops_executed" adds the extra network forward it runs.

`--devices N` (train_step only) shards the batch over a ('data',) mesh of N devices, `--cycles` then counts
cycles *per device* (weak scaling); `--num-cpu-devices N` fakes N CPU devices (set before JAX starts).
`--peer` also runs the upstream PyTorch code through its harness (train or infer, same size, 2 threads, batch 2
cycles; `--peer-dir` / `--peer-python`, see `bridge_jax.bench.peer`) in the same invocation and records it and the
time / memory ratios. `--what pipeline --pipeline-source kitti_sized` reads KITTI-sized PNG files (1242x375,
written to a temporary folder) instead of the config's data source.
"""


from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile

import jax

from bridge_jax import cli, configs, inference, recipe, testtime
from bridge_jax.bench import first, measure
from bridge_jax.bench.device import device_peak
from bridge_jax.bench.peer import PEER_DIR_ENV, PEER_PYTHON_ENV, run_peer
from bridge_jax.bench.records import append_jsonl, environment, finish, finish_process, table
from bridge_jax.bench.timing import BenchError

WHATS = ("train_step", "inference", "loss", "pipeline", "conv_backward")
"""What `--what all` measures: in this process, or each in a subprocess of its own."""
PROCESS_WHATS = ("first_prediction", "first_step")
"""Fresh-process measurements (`bench.first`), each asked for by name."""


def load_config(spec: str, overrides=()):
    """A training config by name or path (`configs.load`; of a recipe, its first stage's) with `--set KEY=VALUE`
    overrides."""
    try:
        config = recipe.single_run(configs.load(spec))
    except ValueError as e:
        raise BenchError(str(e)) from e
    try:
        return configs.override(config, overrides)
    except ValueError as e:
        raise BenchError(f"--set {e}") from e


def apply_size_options(config, args) -> None:
    """--height / --width / --cycles / --dtype into the config (before it is parsed)."""
    if args.height:
        config.height = args.height
    if args.width:
        config.width = args.width
    if args.cycles:
        config.global_batch = args.cycles
    if args.dtype:
        config.dtype = args.dtype


def build_parser() -> argparse.ArgumentParser:
    p = cli.make_parser("bridge_jax.bench", __doc__)
    p.add_argument("--what", default="train_step", choices=WHATS + PROCESS_WHATS + ("all",),
                   help=f"what to measure (all: each of {', '.join(WHATS)} in its own subprocess)")
    p.add_argument("--config", default=None,
                   help="config name (default, full2, demo, ...[:arg]) or .py path "
                        "(default: default; first_step: demo)")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override, e.g. loss.two_warp=full2")
    p.add_argument("--height", type=int, default=None, help="working height (default: the config's)")
    p.add_argument("--width", type=int, default=None, help="working width (default: the config's)")
    p.add_argument("--cycles", type=int, default=None, help="cycles per step (per device with --devices)")
    p.add_argument("--dtype", default=None, choices=("float32", "bfloat16"),
                   help="compute dtype (default: the config's; params stay float32)")
    p.add_argument("--micro-batch", default=None,
                   help="train_step: 0 = plain step, k = maps-first micro-batches of k pair-forwards, -1 = the "
                        "trainer's auto; comma list (default: the config's micro_batch)")
    p.add_argument("--pairs", type=int, default=1, help="inference: pairs per call")
    p.add_argument("--conv-batch", type=int, default=2,
                   help="conv_backward: pair-forwards per convolution (2 = the CPU micro-batch, 16 = a plain step "
                        "of 2 cycles)")
    p.add_argument("--repeats", type=int, default=None,
                   help="timed calls per measurement (default 3); first_prediction / first_step: runs of each "
                        "cache state (default 1)")
    p.add_argument("--warmup", type=int, default=1, help="untimed calls after compiling, before the timed ones")
    p.add_argument("--devices", type=int, default=None, help="train_step: shard over this many devices")
    p.add_argument("--num-cpu-devices", type=int, default=None, help="fake this many CPU devices (before JAX starts)")
    p.add_argument("--check-single-device", action="store_true",
                   help="with --devices N>1: also compare one step against a 1-device step (max abs diff)")
    p.add_argument("--train-step-s", type=float, default=None, help="loss: train step time to report the share of")
    p.add_argument("--peak-tflops", type=float, default=None, help="override the device peak used for MFU")
    p.add_argument("--no-peak", action="store_true", help="skip the CPU matmul peak measurement (MFU = null)")
    p.add_argument("--peer", action="store_true", help="also run upstream PyTorch (train_step / inference)")
    p.add_argument("--peer-python", default=os.environ.get(PEER_PYTHON_ENV),
                   help=f"--peer: Python with PyTorch for the harness (default: ${PEER_PYTHON_ENV})")
    p.add_argument("--peer-dir", default=os.environ.get(PEER_DIR_ENV),
                   help=f"--peer: folder holding harness.py (default: ${PEER_DIR_ENV})")
    p.add_argument("--peer-runs", type=int, default=None, help="--peer: timed runs of upstream (default: --repeats)")
    p.add_argument("--peer-threads", type=int, default=2, help="--peer: torch threads of the upstream run")
    p.add_argument("--json", default=None, metavar="OUT", help="append one JSON line per measurement here")
    p.add_argument("--in-process", action="store_true", help="--what all: measure in this process (no subprocesses)")
    p.add_argument("--pipeline-source", default="config", choices=("config", "kitti_sized"),
                   help="--what pipeline: the config's data, or KITTI-sized PNG files in a temporary folder")
    p.add_argument("--checkpoint", default="demo", help="first_prediction: the model (a shipped name or a folder)")
    p.add_argument("--working-size", default=None, metavar="HxW|native|trained",
                   help="first_prediction: bridge_jax.predict's --working-size (default: the model's own choice)")
    p.add_argument("--symmetry", default=None, choices=testtime.SYMMETRY_MODES,
                   help="first_prediction: bridge_jax.predict's --symmetry (default: the model's own choice)")
    p.add_argument("--polish", default=None, choices=testtime.POLISH_MODES,
                   help="first_prediction: bridge_jax.predict's --polish (default: the model's own choice)")
    p.add_argument("--confidence", action="store_true",
                   help="first_prediction: bridge_jax.predict with --confidence (the maps' confidence and occlusion)")
    return p


def parse_args(argv=None):
    args = build_parser().parse_args(argv)
    fresh = args.what in PROCESS_WHATS
    if args.config is None:
        args.config = "demo" if args.what == "first_step" else "default"
    if args.repeats is None:
        args.repeats = 1 if fresh else 3
    return args


def _micro_list(args, config) -> list[int]:
    text = args.micro_batch if args.micro_batch is not None else str(int(config.get("micro_batch", 0)))
    try:
        vals = [int(v) for v in str(text).split(",") if v.strip() != ""]
    except ValueError as e:
        raise BenchError(f"--micro-batch {text!r}: expected integers like 0 or 0,2 (-1 = the trainer's auto)") from e
    if not vals or any(v < -1 for v in vals):
        raise BenchError(f"--micro-batch {text!r}: expected integers >= -1 like 0 or 0,2 (-1 = the trainer's auto)")
    if -1 in vals:  # the trainer's "auto", for the devices this run uses
        auto = measure.bench_run(config, num_devices=int(args.devices or 1), micro_batch=-1).micro_batch
        vals = [auto if v == -1 else v for v in vals]
    return vals


def run(args) -> list[dict]:
    """Runs the measurements of `args` in this process; returns the finished records."""
    if args.what == "first_prediction":
        return [finish_process(first.measure_first_prediction(args))]
    if args.what == "first_step":
        return [finish_process(first.measure_first_step(args))]
    if args.num_cpu_devices:
        jax.config.update("jax_num_cpu_devices", int(args.num_cpu_devices))
    config = load_config(args.config, args.set or [])
    apply_size_options(config, args)
    one_device = measure.bench_run(config)
    env = environment(one_device, args)
    peak = None if args.no_peak else device_peak(one_device.model.dtype, args.peak_tflops)
    whats = WHATS if args.what == "all" else (args.what,)
    records = []
    # The upstream runs go first, while this process is still small: Linux carries a parent's RSS high-water mark
    # into a forked/exec'd child's ru_maxrss, so a peer spawned after our measurement would report our peak.
    peers = {w: finish(run_peer(w, one_device, args), env, None) for w in whats
             if args.peer and w in ("train_step", "inference")}
    for what in whats:
        if what == "train_step":
            plain_flops = None
            for mb in _micro_list(args, config):
                rec = measure.measure_train_step(config, args, mb)
                if mb == 0:
                    plain_flops = rec["flops"]
                elif plain_flops:  # same model work, counted the same way as the plain step's
                    rec["flops_hlo_lowered"], rec["flops"] = rec["flops"], plain_flops
                    rec["flops_source"] = "compiled plain step cost_analysis (same run)"
                records.append(finish(rec, env, peak))
            if "train_step" in peers:
                records.append(peers["train_step"])
        elif what == "inference":
            records.append(finish(measure.measure_inference(config, args), env, peak))
            if "inference" in peers:
                records.append(peers["inference"])
        elif what == "loss":
            if args.train_step_s is None:
                for r in records:
                    if r["what"] == "train_step":
                        args.train_step_s = r["median_s"]
                        break
            records.extend(finish(r, env, peak) for r in measure.measure_loss(config, args))
        elif what == "pipeline":
            records.append(finish(measure.measure_pipeline(config, args), env, None))
        elif what == "conv_backward":
            records.extend(finish(r, env, peak) for r in measure.measure_conv_backward(config, args))
    _add_ratios(records)
    return records


def _add_ratios(records: list[dict]) -> None:
    """Upstream / ours ratios on every record measured beside a peer record of the same kind."""
    for kind in ("train_step", "inference"):
        peer = [r for r in records if r["what"] == f"peer_{kind}"]
        if not peer or not peer[0].get("median_s"):
            continue
        for r in records:
            if r["what"] == kind and r.get("median_s"):
                key = "s_per_pair" if kind == "inference" else "median_s"
                r["time_vs_upstream"] = round(r[key] / (peer[0].get(key) or peer[0]["median_s"]), 3)
                if peer[0].get("peak_rss_gib"):
                    r["rss_vs_upstream"] = round(r["peak_rss_gib"] / peer[0]["peak_rss_gib"], 3)


def run_all_subprocesses(args, argv) -> list[dict]:
    """--what all: each measurement in its own process (honest per-measurement peak RSS)."""
    records = []
    # drop "--what X" / "--json OUT" (and their --opt=value forms); each child gets its own --what and --json
    cleaned, skip = [], False
    for a in argv:
        if skip:
            skip = False
            continue
        if a in ("--what", "--json"):
            skip = True
            continue
        if a.startswith("--what=") or a.startswith("--json="):
            continue
        cleaned.append(a)
    train_s = None
    for what in WHATS:
        with tempfile.TemporaryDirectory() as tmp:
            out = os.path.join(tmp, "r.jsonl")
            extra = ["--train-step-s", str(train_s)] if what == "loss" and train_s and not args.train_step_s else []
            cmd = [sys.executable, "-m", "bridge_jax.bench", "--what", what, *cleaned, *extra, "--json", out]
            proc = subprocess.run(cmd, capture_output=True, text=True)
            if proc.returncode not in (0, 3) or not os.path.exists(out):
                tail = (proc.stderr or proc.stdout).strip().splitlines()[-1:] or ["no output"]
                raise BenchError(f"--what all: {what} failed (exit {proc.returncode}): {tail[0]}")
            with open(out) as f:
                recs = [json.loads(line) for line in f if line.strip()]
        for r in recs:
            if r["what"] == "train_step" and train_s is None:
                train_s = r["median_s"]
        records.extend(recs)
    return records


@cli.entry_point
def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = parse_args(argv)
        if args.what == "all" and not args.in_process:
            records = run_all_subprocesses(args, argv)
        else:
            records = run(args)
        print(table(records), flush=True)
        for r in records:
            print(json.dumps(r, sort_keys=True), flush=True)
        if args.json:
            append_jsonl(args.json, records)
    except BenchError as e:
        print(f"bench: error: {e}", file=sys.stderr)
        return 2
    bad = [r for r in records if r.get("recompiled")]
    if bad:
        print(f"bench: error: {len(bad)} measurement(s) traced/compiled during the timed calls "
              f"({', '.join(r['what'] + ' ' + r['variant'] for r in bad)})", file=sys.stderr)
        return 3
    return 0
