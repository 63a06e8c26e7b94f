"""The measurements: train step (plain or micro-batched), inference, the loss alone, one 3x3 conv's backward, and
the input pipeline. Each builds what it measures with the project's own code (`setup.parse` + `setup.build_step`,
the `inference.Predictor`, `losses.cycle_loss`, `data.pipeline`) and returns record dicts (see `records`)."""

from __future__ import annotations

import copy
import dataclasses
import functools
import os
import statistics
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from bridge_jax import cycle, inference, losses, network, setup, train_step
from bridge_jax.bench.device import cost_flops
from bridge_jax.bench.timing import BenchError, time_calls
from bridge_jax.data import kitti, pipeline, synthetic
from bridge_jax.micro_batch import MicroBatchedStep
from bridge_jax.models import layers


def bench_run(config, *, num_devices: int = 1, micro_batch: int | None = None) -> setup.Run:
    """The config's `setup.Run` on the first `num_devices` devices, with `config.global_batch` cycles per device
    (weak scaling) and optionally another `micro_batch` (-1 = the trainer's auto choice)."""
    cfg = copy.deepcopy(config)
    cfg.global_batch = int(config.global_batch) * num_devices
    if micro_batch is not None:
        cfg.micro_batch = micro_batch
    devices = jax.devices()
    if num_devices > len(devices):
        raise BenchError(f"--devices {num_devices}: only {len(devices)} devices (use --num-cpu-devices on CPU)")
    try:
        return setup.parse(cfg, devices=devices[:num_devices], num_processes=1)
    except setup.ConfigError as e:
        raise BenchError(str(e).replace("config.height/config.width", "--height/--width")) from e


def _init_params(run: setup.Run):
    return network.init_params(jax.random.key(run.seed), run.model.config, run.model.separate)


# ---------------------------------------------------------------------------------------------------------
# Train step
# ---------------------------------------------------------------------------------------------------------

def build_train_step(config, micro_batch: int, num_devices: int = 1):
    """(state, step, cycles, info, run, net) for the config's train step on `num_devices` devices.

    `cycles` is a random batch of `config.global_batch * num_devices` cycles (weak scaling: global_batch is per
    device here), sharded over a ('data',) mesh when num_devices > 1.
    """
    run = bench_run(config, num_devices=num_devices, micro_batch=micro_batch)
    graphdef, params = _init_params(run)
    net = run.model.network(graphdef)
    tx, schedule = train_step.make_optimizer(run.optimizer, run.loop.steps_per_epoch if run.loop.steps_per_epoch > 0 else 1000)
    state = train_step.create_train_state(params, tx, jax.random.key_data(jax.random.key(1)))
    cycles = np.random.default_rng(0).random((run.global_batch, 4, run.height, run.width, 3), dtype=np.float32)
    kw = {}
    if num_devices > 1:
        _, state_sharding, batch_sharding = setup.data_parallel(run, state)
        kw = dict(state_sharding=state_sharding, batch_sharding=batch_sharding)
        state = jax.device_put(state, kw["state_sharding"])
        cycles = jax.device_put(cycles, kw["batch_sharding"])
    else:
        state = jax.device_put(state, run.devices[0])
        cycles = jax.device_put(cycles, run.devices[0])
    step = setup.build_step(run, net, tx, schedule, **kw)
    rows = run.global_batch * cycle.rows_per_cycle(run.loss.pairs)
    info = dict(model=run.model.config["name"], pairs_per_step=rows, two_warp=run.loss.two_warp, tasks=run.loss.tasks,
                params=int(sum(x.size for x in jax.tree.leaves(params))),
                param_bytes=int(sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(params))))
    return state, step, cycles, info, run, net


def measure_train_step(config, args, micro_batch: int) -> dict:
    """One train-step variant (plain jit or maps-first micro-batched), built by `setup.build_step`."""
    num_devices = int(args.devices or 1)
    state, step, cycles, info, run, net = build_train_step(config, micro_batch, num_devices)
    micro = isinstance(step, MicroBatchedStep)
    rec = dict(what="train_step", variant="plain" if not micro else f"micro_batch={run.micro_batch}",
               micro_batch=run.micro_batch, devices=num_devices, **info)
    flops = flops_exec = temp = None
    compile_s = None
    trace_before = dict(train_step.TRACE_COUNTS)
    if not micro:
        t0 = time.perf_counter()
        compiled = step.lower(state, cycles).compile()
        compile_s = time.perf_counter() - t0
        flops = flops_exec = cost_flops(compiled.cost_analysis())
        mem = compiled.memory_analysis()
        temp = getattr(mem, "temp_size_in_bytes", None) if mem is not None else None
        rec["flops_source"] = "compiled step cost_analysis"
        del compiled
    else:
        # Model FLOPs = the plain step's (lowered HLO, no compile); executed adds the extra network forward.
        tx, schedule = train_step.make_optimizer(run.optimizer, 1000)
        plain = train_step.make_train_step(net, run.loss, tx, schedule, **_shardings(state, cycles, num_devices))
        flops = cost_flops(plain.lower(state, cycles).cost_analysis())
        x = jax.eval_shape(lambda c: cycle.batch_pair_inputs(c, run.loss.pairs), cycles)
        tasks = net.static_tasks(cycle.row_tasks(run.loss.pairs, x.shape[0]))
        fwd = cost_flops(jax.jit(lambda p, x: net(p, x, tasks)).lower(state["params"], x).cost_analysis())
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
    if micro:
        rec["phase_s"], holder["state"] = micro_phases(step, holder["state"], cycles)
    rec.update(timing)
    if num_devices > 1 and not micro:  # a compiled SPMD executable's cost analysis is one device's program
        rec["flops_per_device"] = flops
        flops = flops * num_devices if flops is not None else None
        flops_exec = flops_exec * num_devices if flops_exec is not None else None
    rec.update(compile_s=round(compile_s, 3), flops=flops, flops_executed=flops_exec, xla_temp_bytes=temp,
               final_loss=loss, step_traces={k: v - trace_before.get(k, 0) for k, v in train_step.TRACE_COUNTS.items()
                                             if v - trace_before.get(k, 0)})
    rec["pairs_per_s"] = round(info["pairs_per_step"] / rec["median_s"], 3)
    rec["cycles_per_s"] = round(run.global_batch / rec["median_s"], 4)
    if args.check_single_device and num_devices > 1:
        rec["max_abs_diff_vs_1dev"] = _check_vs_one_device(config, micro_batch, num_devices)
    return rec


def _shardings(state, cycles, num_devices: int) -> dict:
    """The shardings a step built by `build_train_step` uses (none on one device)."""
    if num_devices <= 1:
        return {}
    return dict(state_sharding=jax.tree.map(lambda x: x.sharding, state), batch_sharding=cycles.sharding)


def micro_phases(step: MicroBatchedStep, state, cycles) -> tuple[dict, dict]:
    """Seconds of each phase of one micro-batched step (`MicroBatchedStep.phases`, blocking after each), and the
    new state (the step donates `state`)."""
    t, out = {}, None
    start = t0 = time.perf_counter()
    for name, out in step.phases(state, cycles):
        jax.block_until_ready(out)
        t1 = time.perf_counter()
        t[name] = round(t1 - t0, 3)
        t0 = t1
    t["total"] = round(t0 - start, 3)
    return t, out[0]


def _check_vs_one_device(config, micro_batch: int, num_devices: int) -> float:
    """One step of the sharded and of an unsharded (1 device) step on the same batch: max |loss diff|, params."""
    st_n, step_n, c_n, _, _, _ = build_train_step(config, micro_batch, num_devices)
    cfg1 = copy.deepcopy(config)
    cfg1.global_batch = int(config.global_batch) * num_devices
    st_1, step_1, c_1, _, _, _ = build_train_step(cfg1, micro_batch, 1)
    s_n, m_n = step_n(st_n, c_n)
    s_1, m_1 = step_1(st_1, c_1)
    d = abs(float(m_n["loss"]) - float(m_1["loss"]))
    pd = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
             for a, b in zip(jax.tree.leaves(s_n["params"]), jax.tree.leaves(s_1["params"])))
    return max(d, pd)


# ---------------------------------------------------------------------------------------------------------
# Inference, loss, conv backward, pipeline
# ---------------------------------------------------------------------------------------------------------

def measure_inference(config, args) -> dict:
    """The predictor's compiled network on `--pairs` pairs per call (device arrays in and out)."""
    run = bench_run(config)
    graphdef, params = _init_params(run)
    if run.model.separate:
        params = params["stereo"]
    predictor = inference.Predictor(graphdef, params, size=inference.WorkingSize(run.height, run.width),
                                    dtype=run.model.dtype,
                                    model_cfg=run.model.config)
    pairs = int(args.pairs)
    x = jax.device_put(np.random.default_rng(0).random((pairs, run.height, run.width, 6), dtype=np.float32))
    t0 = time.perf_counter()
    compiled = predictor.lower(pairs).compile()
    compile_s = time.perf_counter() - t0
    flops = cost_flops(compiled.cost_analysis())
    mem = compiled.memory_analysis()
    del compiled
    tasks = ("flow",) * pairs
    timing = time_calls(lambda i: predictor.forward(x, tasks), repeats=args.repeats, warmup=args.warmup)
    rec = dict(what="inference", variant=f"batch={pairs}", model=run.model.config["name"], pairs_per_call=pairs,
               compile_s=round(compile_s, 3), flops=flops, flops_executed=flops,
               flops_source="compiled forward cost_analysis",
               xla_temp_bytes=getattr(mem, "temp_size_in_bytes", None) if mem is not None else None, **timing)
    rec["s_per_pair"] = round(rec["median_s"] / pairs, 4)
    rec["pairs_per_s"] = round(pairs / rec["median_s"], 3)
    return rec


def random_maps(num_rows: int, height: int, width: int, num_scales: int = 4, seed: int = 0) -> dict:
    """Plausible network output for the loss benchmark: small smooth-ish fractions (|frac| < 0.05), px = frac·size."""
    rng = np.random.default_rng(seed)
    px, frac = [], []
    for s in range(num_scales):
        h, w = height >> s, width >> s
        f = (0.05 * np.tanh(rng.standard_normal((num_rows, h, w, 2)))).astype(np.float32)
        frac.append(f)
        px.append(f * np.array([w, h], np.float32))
    return {"px": tuple(px), "frac": tuple(frac)}


def measure_loss(config, args) -> list[dict]:
    """`losses.cycle_loss` alone (maps given): forward, and forward + gradient w.r.t. the maps."""
    run = bench_run(config)
    lcfg = run.loss
    rows = run.global_batch * cycle.rows_per_cycle(lcfg.pairs)
    maps = jax.device_put(random_maps(rows, run.height, run.width, lcfg.num_scales))
    cycles = jax.device_put(np.random.default_rng(1).random((run.global_batch, 4, run.height, run.width, 3),
                                                            dtype=np.float32))
    fwd = jax.jit(lambda m, c: losses.cycle_loss(m, c, lcfg)[0])
    grad = jax.jit(jax.value_and_grad(lambda m, c: losses.cycle_loss(m, c, lcfg)[0]))
    recs = []
    for kind, fn in (("forward", fwd), ("forward+grad", grad)):
        t0 = time.perf_counter()
        compiled = fn.lower(maps, cycles).compile()
        compile_s = time.perf_counter() - t0
        flops = cost_flops(compiled.cost_analysis())
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


# Convolutions of resnet_md at input H x W as (H divisor, Cin, Cout, stride, kernel, padding ((top, bottom),
# (left, right))): the 7x7 stem, the encoder bottleneck 3x3s (the stride-2 ones first in their stage), the
# decoder iconvs (concatenated skip + upsampled map widths), and two of the sub-pixel upconvs' 2x2 phases.
_P1 = ((1, 1), (1, 1))
CONV_LAYERS = ((1, 6, 64, 2, 7, ((3, 3), (3, 3))),
               (4, 64, 64, 1, 3, _P1), (4, 128, 128, 2, 3, _P1), (8, 128, 128, 1, 3, _P1), (8, 256, 256, 2, 3, _P1),
               (16, 256, 256, 1, 3, _P1), (16, 512, 512, 2, 3, _P1), (32, 512, 512, 1, 3, _P1),
               (16, 768, 256, 1, 3, _P1), (8, 384, 128, 1, 3, _P1), (4, 130, 64, 1, 3, _P1), (2, 98, 32, 1, 3, _P1),
               (1, 18, 16, 1, 3, _P1), (1, 16, 2, 1, 3, _P1), (4, 64, 32, 1, 2, ((1, 0), (1, 0))),
               (8, 128, 64, 1, 2, ((0, 1), (0, 1))))
CONV_WEIGHT_GRADS = ("xla", "shift_dy", "shift_x", "xla_chunks", "xla_nchw")
"""The methods `--what conv_backward` times: the four of `layers.WEIGHT_GRAD_METHODS` (NHWC) and XLA's own
backward in the NCHW / OIHW layout (the transposes are outside the timed function)."""
CONV_COPIES_MAX_BYTES = 4 << 30
"""A shifted-copy method whose kh*kw copies would take more than this is not timed for that layer."""


def measure_conv_backward(config, args) -> list[dict]:
    """Gradient of one convolution w.r.t. input and weights, for each of `CONV_WEIGHT_GRADS` ("xla" = XLA's own
    backward-filter conv, "shift_dy" / "shift_x" = one matmul per kernel tap, "xla_chunks" = XLA's on chunks of
    the batch, "xla_nchw" = XLA's in the NCHW layout), for the resnet_md layer shapes at the config's size;
    batch `--conv-batch` pair-forwards (2 = the CPU micro-batch, 16 = the plain step of 2 cycles). The methods
    are timed interleaved in the same process. Each record also says which method "auto" picks for that layer
    here."""
    n = int(getattr(args, "conv_batch", None) or 2)
    recs = []
    for div, ci, co, stride, ksize, pad in CONV_LAYERS:
        h, w = max(1, int(config.height) // div), max(1, int(config.width) // div)
        rng = np.random.default_rng(0)
        x = jnp.asarray(rng.standard_normal((n, h, w, ci), np.float32))
        k = jnp.asarray(rng.standard_normal((ksize, ksize, ci, co), np.float32) * 0.05)
        y_shape = jax.eval_shape(lambda a, b: layers.conv_nhwc(a, b, stride, pad), x, k).shape
        g = jnp.asarray(rng.standard_normal(y_shape, np.float32))

        def loss(a, b, c, method, s=stride, p=pad):
            if method == "xla_nchw":
                y = lax.conv_general_dilated(a, b, (s, s), p, dimension_numbers=("NCHW", "OIHW", "NCHW"))
                return jnp.sum(y * c)
            with layers.weight_grad_method(method):
                return jnp.sum(layers.conv_nhwc(a, b, s, p) * c)

        # XLA may keep all kh*kw shifted copies alive at once: skip a method whose copies would not fit
        # (shift_dy on the 7x7 stride-2 stem at batch 16: 49 copies of dy at the input size, 26 GB).
        copies = {"shift_dy": ksize * ksize * n * h * w * co * 4,
                  "shift_x": ksize * ksize * int(np.prod(y_shape[:3])) * ci * 4}
        methods = [m for m in CONV_WEIGHT_GRADS if copies.get(m, 0) <= CONV_COPIES_MAX_BYTES]
        nchw = (jnp.transpose(x, (0, 3, 1, 2)), jnp.transpose(k, (3, 2, 0, 1)), jnp.transpose(g, (0, 3, 1, 2)))
        inputs = {m: nchw if m == "xla_nchw" else (x, k, g) for m in methods}
        fns = {m: jax.jit(jax.grad(functools.partial(loss, method=m), argnums=(0, 1))) for m in methods}
        timings = {m: [] for m in fns}
        for _ in range(2):  # interleaved halves: every method sees the same machine state
            for m, fn in fns.items():
                timings[m].append(time_calls(lambda i, fn=fn, a=inputs[m]: fn(*a), repeats=max(1, args.repeats // 2),
                                             warmup=max(1, args.warmup)))

        def weight_grad(m):  # HWIO
            dk = fns[m](*inputs[m])[1]
            return jnp.transpose(dk, (2, 3, 1, 0)) if m == "xla_nchw" else dk

        dks = {m: weight_grad(m) for m in methods}
        ref_dk = dks["xla"]
        auto = layers.resolve_weight_grad(x.shape, k.shape, stride, "auto")
        base = None
        for m in methods:
            t = timings[m]
            times = t[0]["times_s"] + t[1]["times_s"]
            rel = float(jnp.abs(dks[m] - ref_dk).max() / jnp.abs(ref_dk).max())
            flops = cost_flops(fns[m].lower(*inputs[m]).compile().cost_analysis())
            rec = dict(what="conv_backward", variant=f"{m} {n}x{h}x{w} {ci}->{co} k{ksize} s{stride}",
                       compile_s=None, median_s=round(statistics.median(times), 5), min_s=round(min(times), 5),
                       max_s=round(max(times), 5), times_s=times, first_call_s=t[0]["first_call_s"],
                       traces_timed=t[0]["traces_timed"] + t[1]["traces_timed"],
                       compiles_timed=t[0]["compiles_timed"] + t[1]["compiles_timed"],
                       recompiled=t[0]["recompiled"] or t[1]["recompiled"], flops=flops, flops_executed=flops,
                       flops_source="compiled cost_analysis", xla_temp_bytes=None,
                       rss_timed_peak_gib=t[1]["rss_timed_peak_gib"],
                       other_procs_cpu_frac=t[1]["other_procs_cpu_frac"], layer=[n, h, w, ci, co, stride],
                       kernel=ksize, padding=[list(q) for q in pad], weight_grad=m, auto_picks=auto,
                       dw_rel_diff_vs_xla=rel)
            if m == "xla":
                base = rec["min_s"]
            rec["min_time_vs_xla"] = round(rec["min_s"] / base, 3) if base else None
            recs.append(rec)
    return recs


def write_kitti_sized_raw(root: str, num_frames: int = 9, height: int = 375, width: int = 1242, seed: int = 0) -> str:
    """Writes a KITTI-raw-layout drive of synthetic PNG frames (default 1242×375, KITTI's size) under `root`."""
    drive = os.path.join(root, "2011_09_26", "2011_09_26_drive_0001_sync")
    for k in range(num_frames):
        s = synthetic.render_sample(synthetic.sample_seed(seed, k), height, width)
        for cam, frame in (("image_02", 0), ("image_03", 1)):
            kitti.write_image(os.path.join(drive, cam, "data", f"{k:010d}.png"), s["cycle"][frame])
    return root


def pipeline_rate(data: pipeline.DataConfig, *, batch: int, height: int, width: int, num_batches: int, warmup: int,
                  seed: int = 0) -> dict:
    """Cycles per second delivered by `pipeline.make_train_dataset` (decode + augment + resize + batch) here.

    Start-up (warm-up batches, worker spawn) is excluded from the rate. With num_workers=0 the main process does
    all the work, so main_cpu_ms_per_cycle is the pipeline's CPU cost per cycle (independent of machine load).
    """
    ds = pipeline.make_train_dataset(data, global_batch=batch, seed=seed, height=height, width=width,
                                     process_index=0, process_count=1)
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
    return {"cycles_per_s": num_batches * batch / (t2 - t1), "seconds": t2 - t1, "startup_s": t1 - t0,
            "main_cpu_ms_per_cycle": 1000.0 * (c2 - c1) / (num_batches * batch)}


def measure_pipeline(config, args) -> dict:
    """The config's input pipeline (`--pipeline-source kitti_sized`: KITTI-sized PNG files, kitti_raw source)."""
    run = bench_run(config)
    data = run.data
    with tempfile.TemporaryDirectory() as tmp:
        if getattr(args, "pipeline_source", "config") == "kitti_sized":
            data = dataclasses.replace(data, source="kitti_raw", data_dir=write_kitti_sized_raw(tmp), split="all")
        r = pipeline_rate(data, batch=run.global_batch, height=run.height, width=run.width,
                          num_batches=int(args.repeats), warmup=int(args.warmup))
    per_batch = r["seconds"] / max(1, int(args.repeats))
    return dict(what="pipeline", variant=f"{data.source} workers={data.num_workers}", compile_s=0.0,
                median_s=round(per_batch, 4), min_s=None, max_s=None, times_s=None, first_call_s=round(r["startup_s"], 4),
                traces_timed=0, compiles_timed=0, recompiled=False, flops=None, flops_executed=None,
                flops_source=None, xla_temp_bytes=None, rss_timed_peak_gib=None, other_procs_cpu_frac=None,
                cycles_per_s=round(r["cycles_per_s"], 3), main_cpu_ms_per_cycle=round(r["main_cpu_ms_per_cycle"], 2))
