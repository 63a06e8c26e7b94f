r"""Benchmarks: train step, inference, loss alone and the input pipeline, measured the same way every time.

    python -m bridge_jax.bench --what train_step --config default --micro-batch 0,2 --repeats 3 --warmup 1
    python -m bridge_jax.bench --what inference --config default --repeats 10
    python -m bridge_jax.bench --what loss --config full2 --cycles 2 --train-step-s 30.1
    python -m bridge_jax.bench --what all --config default:local --json out.jsonl
    python -m bridge_jax.bench --what train_step --config default --peer      # + upstream PyTorch beside it

Every measurement reports: compile time, median / min / max wall time per call over `--repeats` calls after
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

Train step variants: `--micro-batch 0` is the plain step (`train_step.make_train_step`: one jit, whole batch);
`--micro-batch k` is the maps-first micro-batched step (`train_step.MicroBatchedStep`, k pair-forwards per call;
its record also has `phase_s`, the seconds of each phase of one step); `-1` is the trainer's auto choice (the
default comes from the config); a comma list measures several in one process (RSS is then the maximum over them;
use separate runs for memory).
For the micro-batched step "flops" is the model's work (the plain step's XLA count, from its lowered HLO) and
"flops_executed" adds the extra network forward it runs.

`--devices N` (train_step only) shards the batch over a ('data',) mesh of N devices, `--cycles` then counts
cycles *per device* (weak scaling); `--num-cpu-devices N` fakes N CPU devices (set before JAX starts).
`--peer` also runs the upstream PyTorch code through ../shared/peer/harness.py (train or infer, same size,
2 threads, batch 2 cycles) in the same invocation and records it and the time / memory ratios.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import datetime
import functools
import importlib
import importlib.util
import json
import os
import platform
import resource
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any, Callable, Sequence

WHATS = ("train_step", "inference", "loss", "pipeline", "conv_backward")

# Dense peak TFLOP/s per chip, (bf16, float32 as XLA runs it by default), matched by substring of the lower-cased
# `device_kind`, first match wins. float32: XLA:GPU uses TF32 tensor cores for f32 dots/convs at the default
# precision on Ampere+; XLA:TPU runs f32 matmuls as single-pass bf16 at the default precision.
PEAK_TFLOPS: tuple[tuple[str, float, float], ...] = (
    ("h200", 989.0, 494.7),
    ("h100 pcie", 756.0, 378.0),
    ("h100", 989.0, 494.7),  # SXM
    ("a100", 312.0, 156.0),
    ("tpu v6 lite", 918.0, 918.0),  # v6e
    ("tpu v6e", 918.0, 918.0),
    ("tpu v5 lite", 197.0, 197.0),  # v5e
    ("tpu v5e", 197.0, 197.0),
    ("tpu v5p", 459.0, 459.0),
    ("tpu v5", 459.0, 459.0),
    ("tpu v4", 275.0, 275.0),
)

PEER_DIR = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "..", "shared", "peer"))
PEER_PYTHON = "/tmp/peer/venv/bin/python"
PEER_WARP_TYPE = {"none": 0, "full1": 1, "full2": 2, "full3": 3}


class BenchError(Exception):
    """Bad input or a failed measurement; the CLI prints it as one line and exits 2."""


class RecompilationError(BenchError):
    """A trace or XLA compile happened during the timed calls."""


# ---------------------------------------------------------------------------------------------------------
# Trace / compile counter (jax.monitoring events; one global listener dispatching to active counters)
# ---------------------------------------------------------------------------------------------------------

_TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"
_COMPILE_EVENT = "/jax/core/compile/backend_compile_duration"
_ACTIVE: list["CompileCounter"] = []
_LISTENING = False


def _listener(event: str, duration: float, **_kw) -> None:
    for c in _ACTIVE:
        if event == _TRACE_EVENT:
            c.traces += 1
            c.trace_s += duration
        elif event == _COMPILE_EVENT:
            c.compiles += 1
            c.compile_s += duration


class CompileCounter:
    """Counts jaxpr traces and XLA backend compiles (and their seconds) while active (a context manager)."""

    def __init__(self):
        self.traces = self.compiles = 0
        self.trace_s = self.compile_s = 0.0

    def __enter__(self):
        global _LISTENING
        import jax

        if not _LISTENING:
            jax.monitoring.register_event_duration_secs_listener(_listener)
            _LISTENING = True
        _ACTIVE.append(self)
        return self

    def __exit__(self, *exc):
        _ACTIVE.remove(self)
        return False


# ---------------------------------------------------------------------------------------------------------
# Host measurements: RSS, load, other processes' CPU share
# ---------------------------------------------------------------------------------------------------------

def peak_rss_gib() -> float:
    """Peak resident set size of this process so far (ru_maxrss, KiB on Linux) in GiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def current_rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _busy_jiffies() -> int | None:
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return v[0] + v[1] + v[2] + v[5] + v[6] + (v[7] if len(v) > 7 else 0)  # user nice system irq softirq steal
    except (OSError, ValueError, IndexError):
        return None


class HostMonitor:
    """During a block: peak sampled RSS and the share of all CPUs used by other processes (0 = quiet host)."""

    def __init__(self, interval: float = 0.05):
        self.interval, self.peak_rss = interval, 0
        self.other_cpu_frac: float | None = None
        self._stop = threading.Event()

    def _run(self):
        while not self._stop.wait(self.interval):
            self.peak_rss = max(self.peak_rss, current_rss_bytes())

    def __enter__(self):
        self.peak_rss = current_rss_bytes()
        self._j0, self._t0 = _busy_jiffies(), time.perf_counter()
        ru = resource.getrusage(resource.RUSAGE_SELF)
        self._c0 = ru.ru_utime + ru.ru_stime
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_rss = max(self.peak_rss, current_rss_bytes())
        j1, wall = _busy_jiffies(), time.perf_counter() - self._t0
        ru = resource.getrusage(resource.RUSAGE_SELF)
        own = ru.ru_utime + ru.ru_stime - self._c0
        if j1 is not None and self._j0 is not None and wall > 0:
            busy = (j1 - self._j0) / os.sysconf("SC_CLK_TCK")
            self.other_cpu_frac = max(0.0, (busy - own) / (wall * (os.cpu_count() or 1)))
        return False


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


# ---------------------------------------------------------------------------------------------------------
# Device: kind, peak FLOP/s, memory
# ---------------------------------------------------------------------------------------------------------

def known_peak_tflops(device_kind: str, dtype: str) -> float | None:
    """Dense peak TFLOP/s of a known accelerator (`PEAK_TFLOPS`), or None."""
    kind = device_kind.lower()
    for key, bf16, f32 in PEAK_TFLOPS:
        if key in kind:
            return bf16 if dtype == "bfloat16" else f32
    return None


def measured_matmul_tflops(dtype: str = "float32", n: int = 2048, repeats: int = 4) -> float:
    """Best-of-`repeats` TFLOP/s of one jitted (n, n) @ (n, n) matmul on the default device (the CPU 'peak')."""
    import jax
    import jax.numpy as jnp

    dt = jnp.bfloat16 if dtype == "bfloat16" else jnp.float32
    k1, k2 = jax.random.split(jax.random.key(0))
    a = jax.random.normal(k1, (n, n), dt)
    b = jax.random.normal(k2, (n, n), dt)
    f = jax.jit(lambda a, b: jnp.dot(a, b, preferred_element_type=dt))
    f(a, b).block_until_ready()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        f(a, b).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best / 1e12


def device_peak(dtype: str, override_tflops: float | None = None) -> tuple[float, str]:
    """(peak TFLOP/s, where it came from) for the default device."""
    import jax

    if override_tflops:
        return float(override_tflops), "--peak-tflops"
    dev = jax.devices()[0]
    peak = known_peak_tflops(dev.device_kind, dtype)
    if peak is not None:
        return peak, f"table:{dev.device_kind}"
    return measured_matmul_tflops(dtype), "measured 2048^2 matmul (best of 4)"


def device_memory_peak_bytes() -> int | None:
    import jax

    stats = jax.devices()[0].memory_stats()
    if not stats:
        return None
    return int(stats.get("peak_bytes_in_use", stats.get("bytes_in_use", 0))) or None


def _cost_flops(cost) -> float | None:
    if cost is None:
        return None
    if isinstance(cost, (list, tuple)):
        cost = cost[0] if cost else None
        if cost is None:
            return None
    f = cost.get("flops")
    return float(f) if f is not None and f >= 0 else None


# ---------------------------------------------------------------------------------------------------------
# Config
# ---------------------------------------------------------------------------------------------------------

def _parse_value(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def load_config(spec: str, overrides: Sequence[str] = ()):
    """A training config: `default`, `full2:local`, or a path `bridge_jax/configs/x.py[:arg]`; plus KEY=VALUE."""
    name, _, arg = spec.partition(":")
    arg = arg or None
    if name.endswith(".py") or os.sep in name:
        if not os.path.isfile(name):
            raise BenchError(f"--config {spec}: no such config file {name!r}")
        mod_spec = importlib.util.spec_from_file_location("bench_config", name)
        module = importlib.util.module_from_spec(mod_spec)
        mod_spec.loader.exec_module(module)
    else:
        try:
            module = importlib.import_module(f"bridge_jax.configs.{name}")
        except ModuleNotFoundError as e:
            configs = os.path.join(os.path.dirname(os.path.abspath(__file__)), "configs")
            known = sorted(f[:-3] for f in os.listdir(configs) if f.endswith(".py") and not f.startswith("_"))
            raise BenchError(f"--config {spec}: unknown config {name!r}; expected one of {known} or a .py path") from e
    try:
        config = module.get_config(arg)
    except (ValueError, TypeError) as e:
        raise BenchError(f"--config {spec}: {e}") from e
    for item in overrides:
        key, eq, value = item.partition("=")
        if not eq:
            raise BenchError(f"--set {item!r}: expected KEY=VALUE (e.g. loss.two_warp=full2)")
        path = key.split(".")
        node = config
        for p in path[:-1]:
            if p not in node:
                raise BenchError(f"--set {item!r}: config has no field {key!r}")
            node = node[p]
        if path[-1] not in node:
            raise BenchError(f"--set {item!r}: config has no field {key!r}")
        old = node[path[-1]]
        new = _parse_value(value)
        if isinstance(old, str) and not isinstance(new, str):
            new = value
        try:
            node[path[-1]] = new
        except (TypeError, ValueError) as e:
            raise BenchError(f"--set {item!r}: {e}") from e
    return config


def apply_size_options(config, args) -> None:
    if args.height:
        config.height = args.height
    if args.width:
        config.width = args.width
    if args.cycles:
        config.global_batch = args.cycles
    if args.dtype:
        config.dtype = args.dtype


# ---------------------------------------------------------------------------------------------------------
# Timing core
# ---------------------------------------------------------------------------------------------------------

def _block(tree):
    import jax

    return jax.block_until_ready(tree)


def time_calls(call: Callable[[int], Any], *, repeats: int, warmup: int, strict: bool = False) -> dict:
    """Times `call(i)` (its result is blocked on): `warmup` untimed calls, then `repeats` timed ones.

    Returns {"first_call_s", "times_s", "median_s", "min_s", "max_s", "traces_timed", "compiles_timed",
    "recompiled", "rss_timed_peak_gib", "other_procs_cpu_frac", "compile_s_first", "trace_s_first"}.
    A trace or compile during the timed calls sets "recompiled" (and raises RecompilationError if `strict`).
    """
    if repeats < 1 or warmup < 0:
        raise BenchError(f"--repeats must be >= 1 and --warmup >= 0, got {repeats} and {warmup}")
    first = None
    with CompileCounter() as warm:
        for i in range(warmup):
            t0 = time.perf_counter()
            _block(call(i))
            if first is None:
                first = time.perf_counter() - t0
    times = []
    with CompileCounter() as timed, HostMonitor() as mon:
        for i in range(repeats):
            t0 = time.perf_counter()
            _block(call(warmup + i))
            times.append(time.perf_counter() - t0)
    out = {
        "first_call_s": round(first if first is not None else times[0], 4),
        "times_s": [round(t, 4) for t in times],
        "median_s": round(statistics.median(times), 4),
        "min_s": round(min(times), 4),
        "max_s": round(max(times), 4),
        "traces_timed": timed.traces,
        "compiles_timed": timed.compiles,
        "recompiled": bool(timed.traces or timed.compiles),
        "rss_timed_peak_gib": round(mon.peak_rss / 2**30, 3),
        "other_procs_cpu_frac": None if mon.other_cpu_frac is None else round(mon.other_cpu_frac, 3),
        "warmup_traces": warm.traces,
        "warmup_compile_s": round(warm.compile_s, 3),
        "warmup_trace_s": round(warm.trace_s, 3),
    }
    if strict and out["recompiled"]:
        raise RecompilationError(f"{timed.traces} trace(s) / {timed.compiles} compile(s) during the timed calls")
    return out


# ---------------------------------------------------------------------------------------------------------
# Builders (call the project's own training code; nothing re-implemented here)
# ---------------------------------------------------------------------------------------------------------

def _model_setup(config):
    import jax

    from bridge_jax import losses, models, train, train_step

    try:
        mcfg = train.model_config_of(config)
        lcfg = train.loss_config_of(config)
    except ValueError as e:
        raise BenchError(str(e)) from e
    if config.dtype not in train.DTYPES:
        raise BenchError(f"--dtype must be one of {sorted(train.DTYPES)}, got {config.dtype!r}")
    mult = models.INPUT_MULTIPLE.get(mcfg["name"], 64)
    if config.height % mult or config.width % mult or config.height <= 0 or config.width <= 0:
        raise BenchError(f"--height/--width must be positive multiples of {mult} for {mcfg['name']}, "
                         f"got {config.height}x{config.width}")
    key = jax.random.key(int(config.seed))
    graphdef, params = models.init(key, mcfg)
    if config.separate_networks:
        params = {"stereo": params, "flow": models.init(jax.random.fold_in(key, 1), mcfg)[1]}
    dtype = train.DTYPES[config.dtype]
    net = train_step.Network(models.apply, graphdef, separate=bool(config.separate_networks),
                             dtype=None if config.dtype == "float32" else dtype)
    return mcfg, lcfg, graphdef, params, net, losses, train_step


def build_train_step(config, micro_batch: int, num_devices: int = 1):
    """(state, step, cycles, info) for the config's train step on `num_devices` devices.

    `cycles` is a random batch of `config.global_batch * num_devices` cycles (weak scaling: global_batch is per
    device here), sharded over a ('data',) mesh when num_devices > 1.
    """
    import jax
    import numpy as np
    from jax.sharding import NamedSharding, PartitionSpec as P

    mcfg, lcfg, graphdef, params, net, losses, train_step = _model_setup(config)
    steps_per_epoch = int(config.steps_per_epoch) if int(config.steps_per_epoch) > 0 else 1000
    tx, schedule = train_step.make_optimizer(config, steps_per_epoch)
    state = train_step.create_train_state(params, tx, jax.random.key_data(jax.random.key(1)))
    batch = int(config.global_batch) * num_devices
    rows = batch * len(lcfg.pairs) * 2
    if micro_batch and (rows // num_devices) % micro_batch:
        raise BenchError(f"--micro-batch {micro_batch} must divide the {rows // num_devices} pair-forwards per device")
    cycles = np.random.default_rng(0).random((batch, 4, config.height, config.width, 3), dtype=np.float32)
    kw = {}
    if num_devices > 1:
        devices = jax.devices()
        if num_devices > len(devices):
            raise BenchError(f"--devices {num_devices}: only {len(devices)} devices (use --num-cpu-devices on CPU)")
        mesh = jax.make_mesh((num_devices,), ("data",), axis_types=(jax.sharding.AxisType.Auto,),
                             devices=devices[:num_devices])
        rep = NamedSharding(mesh, P())
        kw = dict(state_sharding=jax.tree.map(lambda _: rep, state), batch_sharding=NamedSharding(mesh, P("data")))
        state = jax.device_put(state, kw["state_sharding"])
        cycles = jax.device_put(cycles, kw["batch_sharding"])
    else:
        state = jax.device_put(state, jax.devices()[0])
        cycles = jax.device_put(cycles, jax.devices()[0])
    step = train_step.build_step(net, losses, lcfg, lcfg.pairs, tx, schedule, micro_batch=micro_batch,
                                 num_devices=num_devices, **kw)
    info = dict(model=mcfg["name"], pairs_per_step=rows, two_warp=lcfg.two_warp, tasks=lcfg.tasks,
                params=int(sum(x.size for x in jax.tree.leaves(params))),
                param_bytes=int(sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(params))))
    return state, step, cycles, info, (net, losses, lcfg, train_step, kw)


def _jit_of_step(step):
    """The jitted function behind a plain step (it has .lower), else None."""
    return step if hasattr(step, "lower") else None


def measure_train_step(config, args, micro_batch: int) -> dict:
    """One train-step variant (plain jit or maps-first micro-batched), built by train_step.build_step."""
    import jax

    num_devices = int(args.devices or 1)
    state, step, cycles, info, (net, losses, lcfg, train_step, kw) = build_train_step(config, micro_batch,
                                                                                       num_devices)
    rec = dict(what="train_step", variant="plain" if not micro_batch else f"micro_batch={micro_batch}",
               micro_batch=micro_batch, devices=num_devices, **info)
    flops = flops_exec = temp = None
    compile_s = None
    plain = _jit_of_step(step)
    trace_before = dict(train_step.TRACE_COUNTS)
    if plain is not None:
        with CompileCounter() as cc:
            t0 = time.perf_counter()
            lowered = plain.lower(state, cycles)
            compiled = lowered.compile()
            compile_s = time.perf_counter() - t0
        flops = flops_exec = _cost_flops(compiled.cost_analysis())
        mem = compiled.memory_analysis()
        temp = getattr(mem, "temp_size_in_bytes", None) if mem is not None else None
        rec["flops_source"] = "compiled step cost_analysis"
        del compiled, lowered
    else:
        # Model FLOPs = the plain step's (lowered HLO, no compile); executed adds the extra network forward.
        plain_fn = train_step.make_train_step(net, losses, lcfg, lcfg.pairs,
                                              *train_step.make_optimizer(config, 1000), **kw)
        flops = _cost_flops(plain_fn.lower(state, cycles).cost_analysis())
        from bridge_jax import cycle as cyc

        x = jax.eval_shape(lambda c: cyc.batch_pair_inputs(c, lcfg.pairs), cycles)
        stereo = train_step.row_is_stereo(lcfg.pairs, x.shape[0])
        fwd = _cost_flops(jax.jit(lambda p, x: net(p, x, stereo)).lower(state["params"], x).cost_analysis())
        flops_exec = flops + fwd if flops is not None and fwd is not None else None
        rec["flops_source"] = "plain step lowered-HLO cost_analysis (+ one forward for flops_executed)"
        # The first call of the micro-batched step compiles its pieces (counted by the listener).
    holder = {"state": state}

    def call(i):
        holder["state"], holder["metrics"] = step(holder["state"], cycles)
        return holder["metrics"], holder["state"]["step"]

    timing = time_calls(call, repeats=args.repeats, warmup=args.warmup)
    if compile_s is None:  # the micro-batched pieces compile during the first (warm-up) call
        compile_s = timing["warmup_compile_s"] + timing["warmup_trace_s"]
    loss = float(jax.device_get(holder["metrics"]["loss"]))
    if plain is None and hasattr(step, "_split"):
        rec["phase_s"] = micro_phases(step, holder["state"], cycles)
    rec.update(timing)
    if num_devices > 1 and plain is not None:  # a compiled SPMD executable's cost analysis is one device's program
        rec["flops_per_device"] = flops
        flops = flops * num_devices if flops is not None else None
        flops_exec = flops_exec * num_devices if flops_exec is not None else None
    rec.update(compile_s=round(compile_s, 3), flops=flops, flops_executed=flops_exec, xla_temp_bytes=temp,
               final_loss=loss, step_traces={k: v - trace_before.get(k, 0) for k, v in train_step.TRACE_COUNTS.items()
                                             if v - trace_before.get(k, 0)})
    rec["pairs_per_s"] = round(info["pairs_per_step"] / rec["median_s"], 3)
    rec["cycles_per_s"] = round(info["pairs_per_step"] / len(lcfg.pairs) / 2 / rec["median_s"], 4)
    if args.check_single_device and num_devices > 1:
        rec["max_abs_diff_vs_1dev"] = _check_vs_one_device(config, micro_batch, num_devices)
    return rec


def micro_phases(step, state, cycles) -> dict:
    """Seconds of each phase of one maps-first micro-batched step (blocking between phases; compiled already).

    Uses MicroBatchedStep's own jitted pieces in its own order: network forward of every micro-batch, loss and
    its gradient w.r.t. the maps, the VJP passes (forward again + backward, gradient accumulation), Adam.
    """
    import jax

    t = {}
    t0 = time.perf_counter()
    xs = jax.block_until_ready(step._split(cycles))
    params = state["params"]
    t1 = time.perf_counter()
    if step.net.separate:
        maps = [step._forward(params, x, i) for i, x in enumerate(xs)]
    else:
        maps = [step._forward(params, x) for x in xs]
    jax.block_until_ready(maps)
    t2 = time.perf_counter()
    loss, terms, dmaps = jax.block_until_ready(step._loss(tuple(maps), cycles))
    del maps
    t3 = time.perf_counter()
    state_copy = jax.block_until_ready(jax.tree.map(lambda a: a.copy(), state))  # _update donates its state
    t3b = time.perf_counter()
    acc = step._zeros(params)
    for i, (x, dm) in enumerate(zip(xs, dmaps)):
        acc = step._accumulate(acc, params, x, dm, i) if step.net.separate else step._accumulate(acc, params, x, dm)
    jax.block_until_ready(acc)
    t4 = time.perf_counter()
    new_state, metrics = jax.block_until_ready(step._update(state_copy, acc, loss, terms))
    t5 = time.perf_counter()
    del new_state, metrics
    t.update(split=t1 - t0, forward_all=t2 - t1, loss_and_map_grads=t3 - t2, vjp_accumulate_all=t4 - t3b,
             adam_update=t5 - t4, total=t5 - t0 - (t3b - t3))
    return {k: round(v, 3) for k, v in t.items()}


def _check_vs_one_device(config, micro_batch: int, num_devices: int) -> float:
    """One step of the sharded and of an unsharded (1 device) step on the same batch: max |loss diff|, params."""
    import jax
    import numpy as np

    st_n, step_n, c_n, _, _ = build_train_step(config, micro_batch, num_devices)
    cfg1 = config.copy_and_resolve_references()
    cfg1.global_batch = int(config.global_batch) * num_devices
    st_1, step_1, c_1, _, _ = build_train_step(cfg1, micro_batch, 1)
    s_n, m_n = step_n(st_n, c_n)
    s_1, m_1 = step_1(st_1, c_1)
    d = abs(float(m_n["loss"]) - float(m_1["loss"]))
    pd = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
             for a, b in zip(jax.tree.leaves(s_n["params"]), jax.tree.leaves(s_1["params"])))
    return max(d, pd)


def measure_inference(config, args) -> dict:
    import jax
    import numpy as np

    from bridge_jax import models

    mcfg, lcfg, graphdef, params, net, *_ = _model_setup(config)
    params = params["stereo"] if config.separate_networks else params
    pairs = int(args.pairs)
    dtype = None if config.dtype == "float32" else jax.numpy.dtype(config.dtype)
    fwd = jax.jit(lambda p, x: models.apply(graphdef, p, x, dtype=dtype))
    x = jax.device_put(np.random.default_rng(0).random((pairs, config.height, config.width, 6), dtype=np.float32))
    params = jax.device_put(params)
    t0 = time.perf_counter()
    compiled = fwd.lower(params, x).compile()
    compile_s = time.perf_counter() - t0
    flops = _cost_flops(compiled.cost_analysis())
    mem = compiled.memory_analysis()
    del compiled
    timing = time_calls(lambda i: fwd(params, x), repeats=args.repeats, warmup=args.warmup)
    rec = dict(what="inference", variant=f"batch={pairs}", model=mcfg["name"], pairs_per_call=pairs,
               compile_s=round(compile_s, 3), flops=flops, flops_executed=flops,
               flops_source="compiled forward cost_analysis",
               xla_temp_bytes=getattr(mem, "temp_size_in_bytes", None) if mem is not None else None, **timing)
    rec["s_per_pair"] = round(rec["median_s"] / pairs, 4)
    rec["pairs_per_s"] = round(pairs / rec["median_s"], 3)
    return rec


def random_maps(num_rows: int, height: int, width: int, num_scales: int = 4, seed: int = 0) -> dict:
    """Plausible network output for the loss benchmark: small smooth-ish fractions (|frac| < 0.05), px = frac·size."""
    import numpy as np

    rng = np.random.default_rng(seed)
    px, frac = [], []
    for s in range(num_scales):
        h, w = height >> s, width >> s
        f = (0.05 * np.tanh(rng.standard_normal((num_rows, h, w, 2)))).astype(np.float32)
        frac.append(f)
        px.append(f * np.array([w, h], np.float32))
    return {"px": tuple(px), "frac": tuple(frac)}


def measure_loss(config, args) -> list[dict]:
    """losses.batch_cycle_loss alone (maps given): forward, and forward + gradient w.r.t. the maps."""
    import jax
    import numpy as np

    from bridge_jax import cycle as cyc
    from bridge_jax import losses

    try:
        from bridge_jax import train

        lcfg = train.loss_config_of(config)
    except ValueError as e:
        raise BenchError(str(e)) from e
    batch = int(config.global_batch)
    rows = batch * cyc.rows_per_cycle(lcfg.pairs)
    maps = jax.device_put(random_maps(rows, config.height, config.width, lcfg.num_scales))
    cycles = jax.device_put(np.random.default_rng(1).random((batch, 4, config.height, config.width, 3),
                                                            dtype=np.float32))
    fwd = jax.jit(lambda m, c: losses.batch_cycle_loss(m, c, lcfg)[0])
    grad = jax.jit(jax.value_and_grad(lambda m, c: losses.batch_cycle_loss(m, c, lcfg)[0]))
    recs = []
    for kind, fn in (("forward", fwd), ("forward+grad", grad)):
        t0 = time.perf_counter()
        compiled = fn.lower(maps, cycles).compile()
        compile_s = time.perf_counter() - t0
        flops = _cost_flops(compiled.cost_analysis())
        del compiled
        timing = time_calls(lambda i, fn=fn: fn(maps, cycles), repeats=args.repeats, warmup=args.warmup)
        rec = dict(what="loss", variant=kind, two_warp=lcfg.two_warp, tasks=lcfg.tasks, maps_rows=rows,
                   compile_s=round(compile_s, 3), flops=flops, flops_executed=flops,
                   flops_source="compiled cost_analysis", xla_temp_bytes=None, **timing)
        if args.train_step_s:
            rec["train_step_s"] = float(args.train_step_s)
            rec["share_of_train_step"] = round(rec["median_s"] / float(args.train_step_s), 4)
        recs.append(rec)
    return recs


# 3x3 conv layers of resnet_md at input H x W as (H divisor, Cin, Cout, stride): encoder bottleneck 3x3s (the
# stride-2 ones first in their stage), decoder iconvs (concatenated skip + upsampled map widths).
CONV3X3_LAYERS = ((4, 64, 64, 1), (4, 128, 128, 2), (8, 128, 128, 1), (8, 256, 256, 2), (16, 256, 256, 1),
                  (16, 512, 512, 2), (32, 512, 512, 1), (16, 514, 128, 1), (8, 258, 64, 1), (4, 130, 32, 1),
                  (2, 98, 32, 1), (1, 18, 16, 1), (2, 64, 32, 1), (4, 128, 64, 1))


def measure_conv_backward(config, args) -> list[dict]:
    """Gradient of one 3x3 conv w.r.t. input and weights: XLA's own conv backward vs the weight gradient as 9
    shifted dots (models.layers._conv_dots_wgrad), for the resnet_md layer shapes at the config's size, batch =
    2 pair-forwards (the CPU micro-batch). Each pair is timed interleaved in the same process."""
    import jax
    import jax.numpy as jnp
    import numpy as np
    from jax import lax

    from bridge_jax.models import layers

    n = 2
    recs = []
    for div, ci, co, stride in CONV3X3_LAYERS:
        h, w = max(1, int(config.height) // div), max(1, int(config.width) // div)
        rng = np.random.default_rng(0)
        x = jnp.asarray(rng.standard_normal((n, h, w, ci), np.float32))
        k = jnp.asarray(rng.standard_normal((3, 3, ci, co), np.float32) * 0.05)
        g = jnp.asarray(rng.standard_normal((n, (h - 1) // stride + 1, (w - 1) // stride + 1, co), np.float32))

        def loss(a, b, c, kind, s=stride):
            if kind == "xla":
                y = lax.conv_general_dilated(a, b, (s, s), [(1, 1)] * 2, dimension_numbers=layers._DN)
            else:
                y = layers._conv_dots_wgrad(a, b, s, 1)
            return jnp.sum(y * c)

        fns = {kind: jax.jit(jax.grad(functools.partial(loss, kind=kind), argnums=(0, 1))) for kind in ("xla", "dots")}
        timings = {kind: [] for kind in fns}
        for _ in range(2):  # interleaved halves: both variants see the same machine state
            for kind, fn in fns.items():
                timings[kind].append(time_calls(lambda i, fn=fn: fn(x, k, g), repeats=max(1, args.repeats // 2),
                                                warmup=max(1, args.warmup)))
        ref, alt = fns["xla"](x, k, g), fns["dots"](x, k, g)
        rel = float(jnp.abs(ref[1] - alt[1]).max() / jnp.abs(ref[1]).max())
        base = None
        for kind in ("xla", "dots"):
            t = timings[kind]
            times = t[0]["times_s"] + t[1]["times_s"]
            flops = _cost_flops(fns[kind].lower(x, k, g).compile().cost_analysis())
            rec = dict(what="conv_backward", variant=f"{kind} {n}x{h}x{w} {ci}->{co} s{stride}", compile_s=None,
                       median_s=round(statistics.median(times), 5), min_s=round(min(times), 5),
                       max_s=round(max(times), 5), times_s=times, first_call_s=t[0]["first_call_s"],
                       traces_timed=t[0]["traces_timed"] + t[1]["traces_timed"],
                       compiles_timed=t[0]["compiles_timed"] + t[1]["compiles_timed"],
                       recompiled=t[0]["recompiled"] or t[1]["recompiled"], flops=flops, flops_executed=flops,
                       flops_source="compiled cost_analysis", xla_temp_bytes=None,
                       rss_timed_peak_gib=t[1]["rss_timed_peak_gib"],
                       other_procs_cpu_frac=t[1]["other_procs_cpu_frac"], layer=[n, h, w, ci, co, stride],
                       weight_grad=kind, dw_rel_diff_vs_xla=rel if kind == "dots" else 0.0)
            if kind == "xla":
                base = rec["min_s"]
            else:
                rec["min_time_vs_xla"] = round(rec["min_s"] / base, 3) if base else None
            recs.append(rec)
    return recs


def measure_pipeline(config, args) -> dict:
    from bridge_jax.data import pipeline

    data_cfg = config.data.to_dict() if hasattr(config.data, "to_dict") else dict(config.data)
    r = pipeline.bench_pipeline(data_cfg, num_workers=int(data_cfg.get("num_workers", 0)),
                                batch=int(config.global_batch), height=int(config.height), width=int(config.width),
                                num_batches=int(args.repeats), warmup=int(args.warmup))
    per_batch = r["seconds"] / max(1, int(args.repeats))
    return dict(what="pipeline", variant=f"{data_cfg.get('source')} workers={r['num_workers']}", compile_s=0.0,
                median_s=round(per_batch, 4), min_s=None, max_s=None, times_s=None, first_call_s=round(r["startup_s"], 4),
                traces_timed=0, compiles_timed=0, recompiled=False, flops=None, flops_executed=None,
                flops_source=None, xla_temp_bytes=None, rss_timed_peak_gib=None, other_procs_cpu_frac=None,
                cycles_per_s=round(r["cycles_per_s"], 3), main_cpu_ms_per_cycle=round(r["main_cpu_ms_per_cycle"], 2))


# ---------------------------------------------------------------------------------------------------------
# Upstream PyTorch beside it (../shared/peer/harness.py)
# ---------------------------------------------------------------------------------------------------------

def run_peer(what: str, config, args) -> dict:
    """Runs the unmodified upstream code through the peer harness; returns its JSON as a record."""
    harness = os.path.join(args.peer_dir, "harness.py")
    if not (os.path.isfile(harness) and os.path.isfile(args.peer_python)):
        raise BenchError(f"--peer: need {harness} and {args.peer_python} (see ../shared/peer/README.md, setup.sh)")
    if what == "train_step":
        two_warp = str(config.loss.two_warp)
        cmd = ["train", "--warp-type", str(PEER_WARP_TYPE.get(two_warp, 0)), "--warmup", "1",
               "--runs", str(args.peer_runs or args.repeats)]
    else:
        cmd = ["infer", "--batch", str(args.pairs), "--warmup", "2", "--runs", str(args.peer_runs or args.repeats)]
    parent_rss = current_rss_bytes() / 2**30
    with tempfile.TemporaryDirectory() as tmp:
        out = os.path.join(tmp, "peer.json")
        full = [args.peer_python, harness, *cmd, "--height", str(config.height), "--width", str(config.width),
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


# ---------------------------------------------------------------------------------------------------------
# Records, table, CLI
# ---------------------------------------------------------------------------------------------------------

REQUIRED_FIELDS = ("what", "variant", "config", "height", "width", "cycles", "dtype", "repeats", "warmup",
                   "compile_s", "median_s", "min_s", "max_s", "peak_rss_gib", "device_memory_peak_bytes", "flops",
                   "achieved_tflops", "peak_tflops", "peak_source", "mfu", "traces_timed", "compiles_timed",
                   "recompiled", "device_kind", "platform", "num_devices", "jax_version", "jaxlib_version",
                   "date", "cpu_model", "loadavg", "other_procs_cpu_frac")


def environment(config, args) -> dict:
    import jax
    import jaxlib

    dev = jax.devices()[0]
    return dict(config=args.config, overrides=list(args.set or []), height=int(config.height), width=int(config.width),
                cycles=int(config.global_batch), dtype=str(config.dtype), repeats=args.repeats, warmup=args.warmup,
                device_kind=dev.device_kind, platform=dev.platform, num_devices=jax.device_count(),
                jax_version=jax.__version__, jaxlib_version=jaxlib.__version__, python=platform.python_version(),
                cpu_model=cpu_model(), cpu_count=os.cpu_count(),
                date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))


def finish(rec: dict, env: dict, peak: tuple[float, str] | None) -> dict:
    out = dict(env)
    out.update(rec)
    out["peak_rss_gib"] = rec.get("peak_rss_gib") or round(peak_rss_gib(), 3)
    if "device_memory_peak_bytes" not in rec:
        out["device_memory_peak_bytes"] = device_memory_peak_bytes() if not rec["what"].startswith("peer") else None
    flops, med = out.get("flops"), out.get("median_s")
    out["achieved_tflops"] = round(flops / med / 1e12, 5) if flops and med else None
    if peak is not None and out["achieved_tflops"] is not None:
        out["peak_tflops"], out["peak_source"] = round(peak[0], 4), peak[1]
        out["mfu"] = round(out["achieved_tflops"] / peak[0], 4)
    else:
        out["peak_tflops"] = round(peak[0], 4) if peak else None
        out["peak_source"] = peak[1] if peak else None
        out["mfu"] = None
    out["loadavg"] = loadavg()
    return out


def _fmt(v, spec=".3g"):
    return "-" if v is None else format(v, spec) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def table(records: Sequence[dict]) -> str:
    head = ("what", "variant", "shape", "dtype", "compile s", "median s", "min s", "max s", "peak RSS GiB",
            "GFLOP", "TFLOP/s", "MFU", "retraced", "others' CPU")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        shape = f"{r.get('cycles')}x{r.get('height')}x{r.get('width')}"
        row = (r["what"], r["variant"], shape, r.get("dtype"), _fmt(r.get("compile_s")), _fmt(r.get("median_s"), ".4g"),
               _fmt(r.get("min_s"), ".4g"), _fmt(r.get("max_s"), ".4g"), _fmt(r.get("peak_rss_gib")),
               _fmt(r["flops"] / 1e9 if r.get("flops") else None, ".5g"), _fmt(r.get("achieved_tflops"), ".4g"),
               _fmt(r.get("mfu"), ".1%") if r.get("mfu") is not None else "-", _fmt(r.get("recompiled")),
               _fmt(r.get("other_procs_cpu_frac")))
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def append_jsonl(path: str, records: Sequence[dict]) -> None:
    """Appends records to a JSON-lines file atomically (temp file + rename)."""
    old = ""
    if os.path.exists(path):
        with open(path) as f:
            old = f.read()
        if old and not old.endswith("\n"):
            old += "\n"
    d = os.path.dirname(os.path.abspath(path))
    os.makedirs(d, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".bench-", suffix=".jsonl")
    try:
        with os.fdopen(fd, "w") as f:
            f.write(old + "".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def parse_args(argv=None):
    p = argparse.ArgumentParser(prog="python -m bridge_jax.bench", description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--what", default="train_step", choices=WHATS + ("all",))
    p.add_argument("--config", default="default", help="config name (default, full2, demo, ...[:arg]) or .py path")
    p.add_argument("--set", action="append", metavar="KEY=VALUE", help="config override, e.g. loss.two_warp=full2")
    p.add_argument("--height", type=int, default=None)
    p.add_argument("--width", type=int, default=None)
    p.add_argument("--cycles", type=int, default=None, help="cycles per step (per device with --devices)")
    p.add_argument("--dtype", default=None, choices=("float32", "bfloat16"))
    p.add_argument("--micro-batch", default=None,
                   help="train_step: 0 = plain step, k = maps-first micro-batches of k pair-forwards, -1 = the "
                        "trainer's auto; comma list (default: the config's micro_batch)")
    p.add_argument("--pairs", type=int, default=1, help="inference: pairs per call")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--warmup", type=int, default=1)
    p.add_argument("--devices", type=int, default=None, help="train_step: shard over this many devices")
    p.add_argument("--num-cpu-devices", type=int, default=None, help="fake this many CPU devices (before JAX starts)")
    p.add_argument("--check-single-device", action="store_true",
                   help="with --devices N>1: also compare one step against a 1-device step (max abs diff)")
    p.add_argument("--train-step-s", type=float, default=None, help="loss: train step time to report the share of")
    p.add_argument("--peak-tflops", type=float, default=None, help="override the device peak used for MFU")
    p.add_argument("--no-peak", action="store_true", help="skip the CPU matmul peak measurement (MFU = null)")
    p.add_argument("--peer", action="store_true", help="also run upstream PyTorch (train_step / inference)")
    p.add_argument("--peer-python", default=os.environ.get("BRIDGE_JAX_PEER_PYTHON", PEER_PYTHON))
    p.add_argument("--peer-dir", default=os.environ.get("BRIDGE_JAX_PEER_DIR", PEER_DIR))
    p.add_argument("--peer-runs", type=int, default=None)
    p.add_argument("--peer-threads", type=int, default=2)
    p.add_argument("--json", default=None, metavar="OUT", help="append one JSON line per measurement here")
    p.add_argument("--in-process", action="store_true", help="--what all: measure in this process (no subprocesses)")
    return p.parse_args(argv)


def _micro_list(args, config) -> list[int]:
    text = args.micro_batch if args.micro_batch is not None else str(int(config.get("micro_batch", 0)))
    try:
        vals = [int(v) for v in str(text).split(",") if v.strip() != ""]
    except ValueError as e:
        raise BenchError(f"--micro-batch {text!r}: expected integers like 0 or 0,2 (-1 = the trainer's auto)") from e
    if not vals or any(v < -1 for v in vals):
        raise BenchError(f"--micro-batch {text!r}: expected integers >= -1 like 0 or 0,2 (-1 = the trainer's auto)")
    if -1 in vals:  # the trainer's "auto" (train.resolve_micro_batch), for the devices this run uses
        from bridge_jax import train

        cfg = config.copy_and_resolve_references()
        cfg.micro_batch = -1
        cfg.global_batch = int(config.global_batch) * int(args.devices or 1)
        auto = train.resolve_micro_batch(cfg, int(args.devices or 1))
        vals = [auto if v == -1 else v for v in vals]
    return vals


def run(args) -> list[dict]:
    """Runs the measurements of `args` in this process; returns the finished records."""
    if args.num_cpu_devices:
        import jax

        jax.config.update("jax_num_cpu_devices", int(args.num_cpu_devices))
    config = load_config(args.config, args.set or [])
    apply_size_options(config, args)
    env = environment(config, args)
    peak = None if args.no_peak else device_peak(str(config.dtype), args.peak_tflops)
    whats = WHATS if args.what == "all" else (args.what,)
    records = []
    # The upstream runs go first, while this process is still small: Linux carries a parent's RSS high-water mark
    # into a forked/exec'd child's ru_maxrss, so a peer spawned after our measurement would report our peak.
    peers = {w: finish(run_peer(w, config, args), env, None) for w in whats
             if args.peer and w in ("train_step", "inference")}
    for what in whats:
        if what == "train_step":
            plain_flops = None
            for mb in _micro_list(args, config):
                rec = measure_train_step(config, args, mb)
                if mb == 0:
                    plain_flops = rec["flops"]
                elif plain_flops:  # same model work, counted the same way as the plain step's
                    rec["flops_hlo_lowered"], rec["flops"] = rec["flops"], plain_flops
                    rec["flops_source"] = "compiled plain step cost_analysis (same run)"
                records.append(finish(rec, env, peak))
            if "train_step" in peers:
                records.append(peers["train_step"])
        elif what == "inference":
            records.append(finish(measure_inference(config, args), env, peak))
            if "inference" in peers:
                records.append(peers["inference"])
        elif what == "loss":
            if args.train_step_s is None:
                for r in records:
                    if r["what"] == "train_step":
                        args.train_step_s = r["median_s"]
                        break
            records.extend(finish(r, env, peak) for r in measure_loss(config, args))
        elif what == "pipeline":
            records.append(finish(measure_pipeline(config, args), env, None))
        elif what == "conv_backward":
            records.extend(finish(r, env, peak) for r in measure_conv_backward(config, args))
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


if __name__ == "__main__":
    sys.exit(main())
