r"""Training: `python -m bridge_jax.train --config=bridge_jax/configs/<file>.py[:arg] --workdir=DIR`.

    python -m bridge_jax.train --config=bridge_jax/configs/default.py --workdir=work/default \
        [--config.global_batch=8 --config.data.source=kitti_raw --config.data.data_dir=...]

One run, top to bottom (sections below): check the config and build the data pipeline (nothing is written
to the workdir before every input is validated), create model + optimiser, shard state and batches over a
('data',) mesh, resume from the latest checkpoint in the workdir (train state and data-iterator state) or
initialise (optionally params from `--config.init_from`), then loop: jitted step, guards against
non-finite updates, async checkpoints, metrics.jsonl / TensorBoard / tqdm, periodic validation on held-out
synthetic data. SIGTERM/SIGINT save a checkpoint and exit 0.

Workdir layout:
    config.json, model.json         the run's config and the model description (params-only loaders)
    checkpoints/<step>/{state,data} orbax: train state + grain iterator state
    metrics.jsonl                   one JSON object per log/eval event
    tensorboard/                    tensorboardX event files (scalars, images)
    images/                         the same pictures as PNG files
"""

from __future__ import annotations

import dataclasses
import json
import math
import os
import signal
import sys
import tempfile
import time
from typing import Any

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import checkpointing, cycle, losses, models, train_step

DTYPES = {"float32": jnp.float32, "bfloat16": jnp.bfloat16}


class ConfigError(ValueError):
    """Bad user input (config, data, workdir, init_from): reported as one line, exit code 2."""


class TrainingDiverged(RuntimeError):
    """Too many non-finite steps in a row: reported as one line, exit code 1."""


# ##########################################################################################################
# Config checks (everything that can be wrong with the user's input, before anything is written)
# ##########################################################################################################

def model_config_of(config) -> dict:
    """The full model description (models.model_config) from `config.model`."""
    try:
        return models.model_config(config.model.to_dict() if hasattr(config.model, "to_dict") else dict(config.model))
    except ValueError as e:
        raise ConfigError(f"config.model: {e}") from e


def loss_config_of(config) -> losses.LossConfig:
    try:
        return losses.LossConfig.from_dict(config.loss.to_dict())
    except (ValueError, TypeError) as e:
        raise ConfigError(f"config.loss: {e}") from e


def check_config(config, num_devices: int, num_processes: int = 1) -> None:
    """Raises ConfigError naming the option for every kind of bad setting."""
    mcfg = model_config_of(config)
    multiple = models.INPUT_MULTIPLE.get(mcfg["name"], 64)
    if config.height <= 0 or config.width <= 0 or config.height % multiple or config.width % multiple:
        raise ConfigError(f"config.height/config.width must be positive multiples of {multiple} for "
                          f"{mcfg['name']}, got {config.height}x{config.width}")
    if config.global_batch <= 0:
        raise ConfigError(f"config.global_batch must be positive, got {config.global_batch}")
    if config.global_batch % num_devices:
        raise ConfigError(f"config.global_batch={config.global_batch} is not divisible by the {num_devices} "
                          f"devices (batch is sharded over devices); use a multiple of {num_devices}")
    if config.global_batch % num_processes:
        raise ConfigError(f"config.global_batch={config.global_batch} is not divisible by the {num_processes} "
                          "processes")
    if config.dtype not in DTYPES:
        raise ConfigError(f"config.dtype must be one of {sorted(DTYPES)}, got {config.dtype!r}")
    lcfg = loss_config_of(config)
    rows_per_device = config.global_batch // num_devices * cycle.rows_per_cycle(lcfg.pairs)
    if config.micro_batch < -1 or (config.micro_batch > 0 and rows_per_device % config.micro_batch):
        raise ConfigError(f"config.micro_batch={config.micro_batch} must be 0 (no micro-batching), -1 (auto) or "
                          f"divide the {rows_per_device} pair-forwards per device")
    if config.steps_per_epoch == 0 or config.num_train_steps == 0:
        raise ConfigError("config.steps_per_epoch and config.num_train_steps must be positive (or -1 = derived)")
    for name in ("checkpoint_every", "keep_checkpoints", "log_every", "max_nonfinite_in_row"):
        if config[name] <= 0:
            raise ConfigError(f"config.{name} must be positive, got {config[name]}")


# ##########################################################################################################
# Small helpers: atomic writes, logging
# ##########################################################################################################

def _write_json_atomic(path: str, obj: Any) -> None:
    d = os.path.dirname(path)
    fd, tmp = tempfile.mkstemp(dir=d, prefix=".tmp_", suffix=".json")
    with os.fdopen(fd, "w") as f:
        json.dump(obj, f, indent=2, sort_keys=True, default=str)
        f.write("\n")
    os.replace(tmp, path)


def _scalar(v) -> float:
    return float(np.asarray(v))


class Logger:
    """metrics.jsonl + TensorBoard (tensorboardX) on process 0; no-ops elsewhere."""

    def __init__(self, workdir: str, enabled: bool):
        self.enabled = enabled
        self.image_dir = os.path.join(workdir, "images")
        self.tb = None
        self.jsonl = None
        if enabled:
            from tensorboardX import SummaryWriter
            self.tb = SummaryWriter(os.path.join(workdir, "tensorboard"))
            self.jsonl = open(os.path.join(workdir, "metrics.jsonl"), "a")

    def scalars(self, step: int, values: dict, kind: str = "train") -> None:
        if not self.enabled:
            return
        clean = {k: _scalar(v) for k, v in values.items()}
        rec = {"step": int(step), "kind": kind, "time": time.time(), **clean}
        self.jsonl.write(json.dumps(rec, allow_nan=True) + "\n")
        self.jsonl.flush()
        for k, v in clean.items():
            if math.isfinite(v):
                self.tb.add_scalar(k if "/" in k and kind == "train" else f"{kind}/{k}", v, int(step))

    def image(self, step: int, tag: str, rgb: np.ndarray) -> None:
        """An RGB uint8 (H, W, 3) picture; PNG-encoded with OpenCV (tensorboardX's add_image needs PIL)."""
        if not self.enabled:
            return
        import cv2
        from tensorboardX.proto.summary_pb2 import Summary
        rgb = np.ascontiguousarray(np.asarray(rgb, np.uint8))
        ok, png = cv2.imencode(".png", rgb[..., ::-1])
        if not ok:
            return
        img = Summary.Image(height=rgb.shape[0], width=rgb.shape[1], colorspace=3, encoded_image_string=png.tobytes())
        self.tb._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=img)]), int(step))
        if self.image_dir:
            from bridge_jax import visualize
            os.makedirs(self.image_dir, exist_ok=True)
            visualize.write_image(os.path.join(self.image_dir, f"{tag.replace('/', '_')}_{int(step):07d}.png"), rgb)

    def close(self) -> None:
        if self.enabled:
            self.tb.close()
            self.jsonl.close()


# ##########################################################################################################
# Held-out validation on synthetic data (flow EPE, disparity EPE/D1 with bridge_jax.metrics)
# ##########################################################################################################

# Rows evaluated per validation sample: stereo_t forward (disparity), flow_left forward and backward
# (flow + occlusion picture).
_EVAL_PAIRS = ((cycle.STEREO_T, False), (cycle.FLOW_LEFT, False), (cycle.FLOW_LEFT, True))


def make_validation_set(config) -> list[dict]:
    """Renders `config.eval.num_samples` synthetic samples with exact GT.

    Sample i uses seed sample_seed(config.eval.seed, i), exactly like `write_kitti_layout(dir, n, seed=config.eval.seed)`
    (so the demo's on-disk validation set is the same data); training uses base seed `config.seed`.
    """
    from bridge_jax.data import synthetic
    return [synthetic.render_sample(synthetic.sample_seed(int(config.eval.seed), i), height=config.height,
                                    width=config.width) for i in range(int(config.eval.num_samples))]


def _eval_inputs(sample: dict) -> np.ndarray:
    frames = sample["cycle"].astype(np.float32) / 255.0
    rows = []
    for k, backward in _EVAL_PAIRS:
        a, b = frames[cycle.PAIRS[k].former], frames[cycle.PAIRS[k].latter]
        rows.append(np.concatenate([b, a] if backward else [a, b], axis=-1))
    return np.stack(rows)


class Predictor:
    """Full-resolution pixel maps for arbitrary rows, sharded over the mesh (pads to the device count)."""

    def __init__(self, net: train_step.Network, mesh, replicated, data_sharding):
        self.mesh, self.data_sharding, self.n_dev = mesh, data_sharding, mesh.size

        def fwd(params, x, is_stereo):
            return net(params, x, is_stereo)["px"][0]

        self._fwd = jax.jit(fwd, static_argnums=(2,), out_shardings=replicated)

    def __call__(self, params, x: np.ndarray, is_stereo: tuple) -> np.ndarray:
        n = x.shape[0]
        pad = (-n) % self.n_dev
        if pad:
            x = np.concatenate([x, np.repeat(x[-1:], pad, 0)])
            is_stereo = tuple(is_stereo) + (is_stereo[-1],) * pad
        xg = jax.make_array_from_callback(x.shape, self.data_sharding, lambda idx: x[idx])
        return np.asarray(self._fwd(params, xg, tuple(bool(s) for s in is_stereo)))[:n]


def evaluate_params(predict: Predictor, params, samples: list[dict], batch: int) -> tuple[dict, list]:
    """Validation metrics (per-image means) and the predictions of the first sample (for pictures)."""
    from bridge_jax import metrics as M
    acc, zero = M.MetricAccumulator(), M.MetricAccumulator()
    first = None
    per = len(_EVAL_PAIRS)
    for start in range(0, len(samples), batch):
        chunk = samples[start:start + batch]
        x = np.concatenate([_eval_inputs(s) for s in chunk])
        is_stereo = tuple(cycle.PAIRS[k].is_stereo for k, _ in _EVAL_PAIRS) * len(chunk)
        px = predict(params, x, is_stereo)
        for j, s in enumerate(chunk):
            d_map, f_map, f_back = px[j * per], px[j * per + 1], px[j * per + 2]
            disp = cycle.disparity_from_stereo_map(d_map)
            flow_sums = M.flow_sums(f_map, s["flow"], s["valid_flow"], s.get("noc_flow"))
            disp_sums = M.disparity_sums(disp, s["disp_t"], s["valid_disp_t"], s.get("noc_disp_t"))
            acc.add({f"flow_{k}": v for k, v in flow_sums.items()})
            acc.add({f"disp_{k}": v for k, v in disp_sums.items()})
            zero.add({f"flow_{k}": v for k, v in M.flow_sums(np.zeros_like(f_map), s["flow"], s["valid_flow"]).items()})
            zero.add({f"disp_{k}": v for k, v in M.disparity_sums(np.zeros_like(disp), s["disp_t"], s["valid_disp_t"]).items()})
            if first is None:
                first = (s, d_map, f_map, f_back)
    out = acc.per_image_mean()
    z = zero.per_image_mean()
    out["zero_flow_epe_all"] = z["flow_epe_all"]
    out["zero_disp_epe_all"] = z["disp_epe_all"]
    out["flow_epe_vs_zero"] = out["flow_epe_all"] / max(z["flow_epe_all"], 1e-12)
    return out, first


def prediction_panel(first) -> np.ndarray:
    """Input | predicted flow | GT flow | predicted disparity | GT disparity | flow occlusion mask."""
    from bridge_jax import geometry, visualize as V
    s, d_map, f_map, f_back = first
    occ, _ = geometry.forward_backward_occlusion(jnp.asarray(f_map)[None], jnp.asarray(f_back)[None])
    max_flow = max(V.flow_magnitude_max(s["flow"], s["valid_flow"]), 1e-3)
    vmax = float(np.percentile(s["disp_t"][s["valid_disp_t"]], 99)) if s["valid_disp_t"].any() else None
    disp = cycle.disparity_from_stereo_map(d_map)
    tiles = [s["cycle"][0], V.flow_to_color(f_map, max_flow), V.flow_to_color(s["flow"], max_flow, s["valid_flow"]),
             V.disparity_to_color(disp, vmax), V.disparity_to_color(s["disp_t"], vmax, valid=s["valid_disp_t"]),
             np.repeat(np.asarray(occ[0]), 3, axis=-1)]
    labels = ["left_t", "flow", "flow GT", "disparity", "disparity GT", "occluded (flow)"]
    return V.panel(tiles, labels, ncols=3)


# ##########################################################################################################
# Train and evaluate
# ##########################################################################################################

def _maybe_initialize_distributed(config) -> None:
    d = config.get("distributed", None)
    if d is None or not d.enabled:
        return
    if jax.distributed.is_initialized():
        return
    kw = {}
    if d.coordinator_address:
        kw["coordinator_address"] = d.coordinator_address
    if d.num_processes > 0:
        kw["num_processes"] = int(d.num_processes)
    if d.process_id >= 0:
        kw["process_id"] = int(d.process_id)
    jax.distributed.initialize(**kw)


def _load_init_params(path: str, mcfg: dict, abstract_params, separate: bool):
    """Params from `config.init_from` (params-only dir, training workdir or step dir); architecture checked."""
    if not os.path.exists(path):
        raise ConfigError(f"config.init_from={path!r}: no such file or directory")
    try:
        src_cfg, params = checkpointing.load_params(path)
    except (ValueError, OSError) as e:
        raise ConfigError(f"config.init_from={path!r}: {e}") from e
    # Keys that do not change the architecture (compute dtype, how fresh params are drawn) are not compared.
    ignore = ("dtype", "head_init")
    src = {k: v for k, v in src_cfg.items() if k not in ignore}
    src_separate = bool(src.pop("separate_networks", False))
    want = {k: v for k, v in mcfg.items() if k not in ignore}
    try:
        src = {k: v for k, v in models.model_config(src).items() if k not in ignore}
    except ValueError:
        pass
    if src != want:
        raise ConfigError(f"config.init_from={path!r} holds a different architecture: {src} (this run: {want})")
    params = jax.tree.map(np.asarray, params)
    if separate and not src_separate:  # flow+stereo weights to start both networks of the no-sharing variant
        params = {"stereo": params, "flow": params}
    if jax.tree.structure(params) != jax.tree.structure(abstract_params) or any(
            a.shape != b.shape for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(abstract_params))):
        raise ConfigError(f"config.init_from={path!r}: parameter tree/shapes do not match the model {want['name']}")
    return params


def resolve_micro_batch(config, num_devices: int) -> int:
    """config.micro_batch, with -1 = auto: 2 pair-forwards per call on CPU (fastest and leanest there, see
    notes/xla-cpu-performance.md), the whole batch in one jitted step on GPU/TPU."""
    mb = int(config.micro_batch)
    if mb != -1:
        return mb
    rows = config.global_batch // num_devices * cycle.rows_per_cycle(loss_config_of(config).pairs)
    return 2 if jax.default_backend() == "cpu" and rows % 2 == 0 and rows > 2 else 0


def _mesh_devices(config, num_processes: int) -> list:
    """All devices (config.num_devices = -1, the default) or the first N local ones (single process only)."""
    n = int(config.get("num_devices", -1))
    if n == -1:
        return list(jax.devices())
    if num_processes > 1:
        raise ConfigError("config.num_devices must be -1 (all devices) in a multi-process run")
    if not 1 <= n <= jax.local_device_count():
        raise ConfigError(f"config.num_devices={n}: this machine has {jax.local_device_count()} devices "
                          "(use -1 for all)")
    return list(jax.local_devices()[:n])


def _make_dataset(config, process_index: int, process_count: int):
    from bridge_jax.data import pipeline
    try:
        return pipeline.make_train_dataset(
            config.data, global_batch=int(config.global_batch), seed=int(config.seed), height=int(config.height),
            width=int(config.width), process_index=process_index, process_count=process_count)
    except (ValueError, FileNotFoundError, NotADirectoryError) as e:
        raise ConfigError(f"config.data: {e}") from e


def _global_array(sharding, local: np.ndarray, global_shape):
    return jax.make_array_from_process_local_data(sharding, local, global_shape)


def train_and_evaluate(config: ml_collections.ConfigDict, workdir: str) -> dict:
    """Trains (or resumes) in `workdir`; returns a summary dict (final step, last metrics, validation)."""
    _maybe_initialize_distributed(config)
    proc, nproc = jax.process_index(), jax.process_count()
    is_main = proc == 0

    ##### Check the input: nothing in the workdir is touched before this section passes ####################
    devices = _mesh_devices(config, nproc)
    num_devices = len(devices)
    check_config(config, num_devices, nproc)
    mcfg = model_config_of(config)
    lcfg = loss_config_of(config)
    pairs = lcfg.pairs
    workdir = os.path.abspath(workdir)
    if os.path.exists(workdir) and not os.path.isdir(workdir):
        raise ConfigError(f"--workdir={workdir} exists and is not a directory")
    model_json = dict(mcfg, **({"separate_networks": True} if config.separate_networks else {}))
    old_model = os.path.join(workdir, checkpointing.MODEL_JSON)
    resuming = checkpointing.find_train_step_dir(workdir) is not None
    if resuming and os.path.exists(old_model):
        with open(old_model) as f:
            prev = json.load(f)
        if prev != json.loads(json.dumps(model_json)):
            raise ConfigError(f"--workdir={workdir} holds a run of a different model ({prev}); this config builds "
                              f"{model_json}. Use a new workdir (or the same model config) to resume.")

    dataset = _make_dataset(config, proc, nproc)
    steps_per_epoch = int(config.steps_per_epoch)
    if steps_per_epoch < 0:
        try:
            steps_per_epoch = max(1, len(dataset) // int(config.global_batch))
        except TypeError as e:
            raise ConfigError("config.steps_per_epoch=-1 needs a data source of known size; set it explicitly") from e
    num_steps = int(config.num_train_steps) if config.num_train_steps > 0 else int(config.num_epochs) * steps_per_epoch

    ##### Create model & optimizer ############################################################################
    rng = jax.random.key(int(config.seed))
    init_rng, state_rng = jax.random.split(rng)
    graphdef, params = models.init(init_rng, mcfg)
    if config.separate_networks:
        _, params_flow = models.init(jax.random.fold_in(init_rng, 1), mcfg)
        params = {"stereo": params, "flow": params_flow}
    if config.init_from and not resuming:
        params = _load_init_params(str(config.init_from), mcfg, params, bool(config.separate_networks))
    tx, schedule = train_step.make_optimizer(config, steps_per_epoch)
    net = train_step.Network(models.apply, graphdef, separate=bool(config.separate_networks),
                             dtype=DTYPES[config.dtype] if config.dtype != "float32" else None)

    ##### Shard & transfer #####################################################################################
    # Auto axis type: XLA propagates the batch sharding (the model code has no sharding annotations).
    mesh = jax.make_mesh((num_devices,), ("data",), axis_types=(jax.sharding.AxisType.Auto,), devices=devices)
    replicated = NamedSharding(mesh, P())
    batch_sharding = NamedSharding(mesh, P("data"))
    host_state = train_step.create_train_state(params, tx, jax.random.key_data(state_rng))
    host_state = jax.tree.map(np.asarray, host_state)
    state_sharding = jax.tree.map(lambda _: replicated, host_state)
    state = jax.tree.map(lambda x, s: jax.make_array_from_callback(x.shape, s, lambda idx: x[idx]),
                         host_state, state_sharding)
    del host_state, params

    ##### Workdir: config, checkpoints, resume ##############################################################
    os.makedirs(workdir, exist_ok=True)
    if is_main:
        _write_json_atomic(os.path.join(workdir, checkpointing.CONFIG_JSON), json.loads(config.to_json_best_effort()))
        _write_json_atomic(old_model, model_json)
    ckpt = checkpointing.TrainCheckpointer(workdir, save_every=config.checkpoint_every,
                                           keep=config.keep_checkpoints, async_save=config.async_checkpoints)
    data_iter = iter(dataset)
    start_step = 0
    latest = ckpt.latest_step()
    if latest is not None:
        abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)
        state, data_state = ckpt.restore(latest, abstract)
        if data_state:
            data_iter.set_state(data_state)
        start_step = int(jax.device_get(state["step"]))
        if is_main:
            print(f"Resuming from {ckpt.directory}/{latest} (step {start_step}).", flush=True)

    ##### Update step ##########################################################################################
    step_fn = train_step.build_step(net, losses, lcfg, pairs, tx, schedule,
                                    micro_batch=resolve_micro_batch(config, num_devices),
                                    num_devices=num_devices, state_sharding=state_sharding,
                                    batch_sharding=batch_sharding)
    predictor = Predictor(net, mesh, replicated, batch_sharding)
    val_samples = make_validation_set(config) if config.eval_every >= 0 and config.eval.num_samples > 0 else []
    eval_batch = max(1, int(config.eval.batch))
    logger = Logger(workdir, is_main)
    global_shape = (int(config.global_batch), 4, int(config.height), int(config.width), 3)

    stop = {"signal": None}
    old_handlers = {}

    def on_signal(signum, frame):  # noqa: ARG001
        stop["signal"] = signum

    if sys.platform != "win32" and _in_main_thread():
        for sig in (signal.SIGTERM, signal.SIGINT):
            old_handlers[sig] = signal.signal(sig, on_signal)

    def run_eval(step):
        res, first = evaluate_params(predictor, state["params"], val_samples, eval_batch)
        logger.scalars(step, res, kind="val")
        if first is not None and is_main:
            logger.image(step, "val/prediction", prediction_panel(first))
        return res

    bar = None
    if is_main and config.progress_bar:
        from tqdm import tqdm
        bar = tqdm(total=num_steps, initial=start_step, unit="step", dynamic_ncols=True, file=sys.stderr)

    summary: dict = {"start_step": start_step, "workdir": workdir}
    step = start_step
    nonfinite_in_row = nonfinite_total = 0
    last_metrics: dict = {}
    val = {}
    window_t, window_cycles = time.perf_counter(), 0
    interrupted = False
    try:
        ##### Train loop ######################################################################################
        while step < num_steps:
            if stop["signal"] is not None:
                interrupted = True
                break
            batch = next(data_iter)
            local = np.asarray(batch["cycle"], np.float32)
            cycles = _global_array(batch_sharding, local, global_shape)
            state, metrics = step_fn(state, cycles)
            metrics = jax.device_get(metrics)
            if int(metrics["nonfinite"]):
                nonfinite_in_row += 1
                nonfinite_total += 1
                logger.scalars(step, {"nonfinite_total": nonfinite_total, "loss": metrics["loss"]}, kind="skip")
                if is_main:
                    print(f"step {step}: non-finite loss/gradient, update skipped "
                          f"({nonfinite_in_row} in a row, {nonfinite_total} in total)", file=sys.stderr, flush=True)
                if nonfinite_in_row >= config.max_nonfinite_in_row:
                    ckpt.wait()
                    last = ckpt.latest_step()
                    where = f"{ckpt.directory}/{last}" if last is not None else "none saved yet"
                    raise TrainingDiverged(
                        f"stopping: {nonfinite_in_row} non-finite steps in a row at step {step} "
                        f"(config.max_nonfinite_in_row={config.max_nonfinite_in_row}); last good checkpoint: {where}")
                continue
            nonfinite_in_row = 0
            step += 1
            window_cycles += int(config.global_batch)
            last_metrics = metrics
            ckpt.save(step, state, data_iter.get_state())

            if step % config.log_every == 0 or step == num_steps:
                dt = time.perf_counter() - window_t
                extra = {"cycles_per_s": window_cycles / max(dt, 1e-9), "step_time_s": dt / max(1, window_cycles // int(config.global_batch)),
                         "nonfinite_total": nonfinite_total, "epoch": step / steps_per_epoch}
                logger.scalars(step, {**{k: v for k, v in metrics.items() if k != "nonfinite"}, **extra})
                window_t, window_cycles = time.perf_counter(), 0
                if bar is not None:
                    bar.set_postfix(loss=f"{_scalar(metrics['loss']):.4f}",
                                    cycles_s=f"{extra['cycles_per_s']:.2f}", refresh=False)
            if bar is not None:
                bar.update(1)
            if val_samples and config.eval_every > 0 and step % config.eval_every == 0 and step < num_steps:
                val = run_eval(step)
            elif is_main and config.image_every > 0 and step % config.image_every == 0 and val_samples:
                _, first = evaluate_params(predictor, state["params"], val_samples[:1], 1)
                logger.image(step, "val/prediction", prediction_panel(first))

        if interrupted:
            if is_main:
                print(f"\nReceived signal {stop['signal']}: saving a checkpoint at step {step} and exiting.",
                      file=sys.stderr, flush=True)
        elif val_samples:
            val = run_eval(step)
        ckpt.save(step, state, data_iter.get_state(), force=True)
        ckpt.wait()
    finally:
        if bar is not None:
            bar.close()
        for sig, h in old_handlers.items():
            signal.signal(sig, h)
        ckpt.close()
        logger.close()

    summary.update(step=step, interrupted=interrupted, nonfinite_total=nonfinite_total,
                   last_metrics={k: _scalar(v) for k, v in last_metrics.items()}, validation=val,
                   checkpoint=os.path.join(ckpt.directory, str(ckpt.latest_step())) if ckpt.latest_step() is not None else None)
    summary["state"] = state
    return summary


def _in_main_thread() -> bool:
    import threading
    return threading.current_thread() is threading.main_thread()


# ##########################################################################################################
# Command line
# ##########################################################################################################

def enable_compilation_cache(config, workdir: str) -> str | None:
    """Turns on JAX's persistent compilation cache for this process (`config.compilation_cache_dir`).

    Only the command-line entry points call this: JAX opens the cache at the process's first compilation and
    keeps it, so a library caller (or a test running several workdirs in one process) configures it itself.
    Returns the cache folder, or None when off. An environment variable JAX_COMPILATION_CACHE_DIR wins.
    """
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]
    path = config.get("compilation_cache_dir", "auto")
    if not isinstance(path, str):
        raise ConfigError(f"config.compilation_cache_dir must be a folder, 'auto' or '' (off), got {path!r}")
    if not path:
        return None
    if path == "auto":
        path = os.path.join(workdir, "xla_cache")
    path = os.path.abspath(os.path.expanduser(path))
    jax.config.update("jax_compilation_cache_dir", path)
    # Only executables that took >= 1 s to compile are stored (the train step, eval/inference functions).
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)
    return path


def main(argv):
    from absl import flags
    if len(argv) > 1:
        raise SystemExit(f"error: unexpected arguments {argv[1:]} (options are --config=..., --workdir=...)")
    FLAGS = flags.FLAGS
    try:
        enable_compilation_cache(FLAGS.config, FLAGS.workdir)
        result = train_and_evaluate(FLAGS.config, FLAGS.workdir)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(2)
    except TrainingDiverged as e:
        print(f"error: {e}", file=sys.stderr)
        raise SystemExit(1)
    msg = "interrupted; checkpoint saved" if result["interrupted"] else "done"
    print(f"{msg}: step {result['step']}, checkpoint {result['checkpoint']}, metrics "
          f"{os.path.join(result['workdir'], 'metrics.jsonl')}", flush=True)


def _define_flags():
    from absl import flags
    from ml_collections import config_flags
    config_flags.DEFINE_config_file("config", None, "Training config file, e.g. bridge_jax/configs/default.py[:arg].",
                                    lock_config=True)
    flags.DEFINE_string("workdir", None, "Directory for checkpoints, logs and metrics (resumed if it has any).")
    flags.mark_flags_as_required(["config", "workdir"])


if __name__ == "__main__":
    from absl import app
    _define_flags()
    app.run(main)
