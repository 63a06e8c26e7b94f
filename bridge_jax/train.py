r"""Training: `python -m bridge_jax.train --config=bridge_jax/configs/<file>.py[:arg] --workdir=DIR`.

    python -m bridge_jax.train --config=bridge_jax/configs/default.py --workdir=work/default \
        [--config.global_batch=8 --config.data.source=kitti_raw --config.data.data_dir=...]

One run, top to bottom (sections of `train_and_evaluate`): parse and check the config (`setup.parse`) and build
the data pipeline (nothing is written to the workdir before every input is validated), create model +
optimiser, shard state and batches over a ('data',) mesh, resume from the latest checkpoint in the workdir
(train state and data-iterator state) or initialise (optionally params from `--config.init_from`), then loop:
jitted step, guards against non-finite updates, async checkpoints, metrics.jsonl / TensorBoard / tqdm,
periodic validation on held-out synthetic data. SIGTERM/SIGINT save a checkpoint and exit 0.

Workdir layout:
    config.json, model.json         the run's config and the model description (params-only loaders)
    checkpoints/<step>/{state,data} orbax: train state + grain iterator state
    metrics.jsonl                   one JSON object per log/eval event
    tensorboard/                    tensorboardX event files (scalars, images)
    images/                         the same pictures as PNG files
"""

from __future__ import annotations

import json
import math
import os
import signal
import sys
import threading
import time
from typing import Any

import cv2
import jax
import ml_collections
import numpy as np
from absl import app, flags
from ml_collections import config_flags
from tensorboardX import SummaryWriter
from tensorboardX.proto.summary_pb2 import Summary
from tqdm import tqdm

from bridge_jax import checkpointing, cli, files, inference, models, network, setup, train_step, visualize
from bridge_jax.data import pipeline
from bridge_jax.eval.baselines import zero_method
from bridge_jax.eval.datasets import Frame, synthetic_frames
from bridge_jax.eval.methods import ModelMethod
from bridge_jax.evaluate import score_methods
from bridge_jax.setup import ConfigError  # noqa: F401  (re-exported: the trainer's user-error type)


class TrainingDiverged(RuntimeError):
    """Too many non-finite steps in a row: reported as one line, exit code 1."""


# ##########################################################################################################
# Logging
# ##########################################################################################################

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
        rgb = np.ascontiguousarray(np.asarray(rgb, np.uint8))
        ok, png = cv2.imencode(".png", rgb[..., ::-1])
        if not ok:
            return
        img = Summary.Image(height=rgb.shape[0], width=rgb.shape[1], colorspace=3, encoded_image_string=png.tobytes())
        self.tb._get_file_writer().add_summary(Summary(value=[Summary.Value(tag=tag, image=img)]), int(step))
        os.makedirs(self.image_dir, exist_ok=True)
        visualize.write_image(os.path.join(self.image_dir, f"{tag.replace('/', '_')}_{int(step):07d}.png"), rgb)

    def close(self) -> None:
        if self.enabled:
            self.tb.close()
            self.jsonl.close()


# ##########################################################################################################
# Held-out validation: the predictor on synthetic frames, scored like `evaluate`
# ##########################################################################################################

def validation_frames(run: setup.Run) -> list[Frame]:
    """`run.eval.num_samples` synthetic frames with exact GT at the working size, from base seed `run.eval.seed`
    (training uses base seed `run.seed`); `synthetic.write_kitti_layout(dir, n, seed=run.eval.seed)` writes the
    same samples to disk (the demo's evaluation set)."""
    return synthetic_frames(run.eval.num_samples, run.eval.seed, run.height, run.width)


def validate(predictor: inference.Predictor, params, frames: list[Frame], batch: int,
             picture: bool = True) -> tuple[dict, Any]:
    """Validation metrics of `params` (per-image means: "flow_*", "disp_*", the zero-motion baseline's
    "zero_flow_epe_all" / "zero_disp_epe_all" (/ "zero_flow_epe_noc"), and the ratios "flow_epe_vs_zero" (and
    "flow_noc_vs_zero" where the frames have non-occluded masks)), and the first frame's picture panel."""
    model = ModelMethod(predictor.with_params(params), batch, occlusion=True)
    scored = score_methods((frames[i:i + batch] for i in range(0, len(frames), batch)),
                           {"model": model, "zero": zero_method}, num_pictures=int(picture), picture_method="model")
    prefixes = {"flow": "flow_", "disparity": "disp_"}
    out = scored.scores.per_image_means("model", prefixes)
    zero = scored.scores.per_image_means("zero", prefixes)
    out["zero_flow_epe_all"] = zero["flow_epe_all"]
    out["zero_disp_epe_all"] = zero["disp_epe_all"]
    out["flow_epe_vs_zero"] = out["flow_epe_all"] / max(zero["flow_epe_all"], 1e-12)
    if "flow_epe_noc" in out and "flow_epe_noc" in zero:
        out["zero_flow_epe_noc"] = zero["flow_epe_noc"]
        out["flow_noc_vs_zero"] = out["flow_epe_noc"] / max(zero["flow_epe_noc"], 1e-12)
    return out, (scored.pictures[0][1] if scored.pictures else None)


# ##########################################################################################################
# Pieces of a run
# ##########################################################################################################

def _check_workdir(run: setup.Run, workdir: str) -> bool:
    """Whether `workdir` holds a run to resume; a workdir of another model is refused (nothing is written)."""
    if os.path.exists(workdir) and not os.path.isdir(workdir):
        raise ConfigError(f"--workdir={workdir} exists and is not a directory")
    resuming = checkpointing.find_train_step_dir(workdir) is not None
    old_model = os.path.join(workdir, checkpointing.MODEL_JSON)
    if resuming and os.path.exists(old_model):
        with open(old_model) as f:
            prev = json.load(f)
        try:  # fill keys added since that run was written (e.g. `coords`) with their defaults before comparing
            prev = dict(models.model_config({k: v for k, v in prev.items() if k != "separate_networks"}),
                        **({"separate_networks": True} if prev.get("separate_networks") else {}))
        except (ValueError, TypeError):
            pass  # not a model this version knows: the comparison below refuses it
        want = run.model.model_json()
        if prev != json.loads(json.dumps(want)):
            raise ConfigError(f"--workdir={workdir} holds a run of a different model ({prev}); this config builds "
                              f"{want}. Use a new workdir (or the same model config) to resume.")
    return resuming


def _make_dataset(run: setup.Run, process_index: int, process_count: int):
    try:
        return pipeline.make_train_dataset(run.data, global_batch=run.global_batch, seed=run.seed, height=run.height,
                                           width=run.width, process_index=process_index, process_count=process_count)
    except (ValueError, FileNotFoundError, NotADirectoryError) as e:
        raise ConfigError(f"config.data: {e}") from e


def _load_init_params(path: str, spec: setup.ModelSpec, abstract_params):
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
    want = {k: v for k, v in spec.config.items() if k not in ignore}
    try:
        src = {k: v for k, v in models.model_config(src).items() if k not in ignore}
    except ValueError:
        pass
    if src != want:
        raise ConfigError(f"config.init_from={path!r} holds a different architecture: {src} (this run: {want})")
    params = jax.tree.map(np.asarray, params)
    if spec.separate and not src_separate:  # flow+stereo weights to start both networks of the no-sharing variant
        params = {"stereo": params, "flow": params}
    if jax.tree.structure(params) != jax.tree.structure(abstract_params) or any(
            a.shape != b.shape for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(abstract_params))):
        raise ConfigError(f"config.init_from={path!r}: parameter tree/shapes do not match the model {want['name']}")
    return params


def _global_array(sharding, local: np.ndarray, global_shape):
    return jax.make_array_from_process_local_data(sharding, local, global_shape)


class _NonFiniteGuard:
    """Counts skipped (non-finite) steps; too many in a row stop the run with the last good checkpoint named."""

    def __init__(self, max_in_row: int, logger: Logger, ckpt: checkpointing.TrainCheckpointer, is_main: bool):
        self.max_in_row, self.logger, self.ckpt, self.is_main = max_in_row, logger, ckpt, is_main
        self.in_row = self.total = 0

    def skipped(self, step: int, metrics: dict) -> bool:
        """True if the step was skipped by the train step's guard (the state did not move)."""
        if not int(metrics["nonfinite"]):
            self.in_row = 0
            return False
        self.in_row += 1
        self.total += 1
        self.logger.scalars(step, {"nonfinite_total": self.total, "loss": metrics["loss"]}, kind="skip")
        if self.is_main:
            print(f"step {step}: non-finite loss/gradient, update skipped ({self.in_row} in a row, {self.total} in "
                  "total)", file=sys.stderr, flush=True)
        if self.in_row >= self.max_in_row:
            self.ckpt.wait()
            last = self.ckpt.latest_step()
            where = f"{self.ckpt.directory}/{last}" if last is not None else "none saved yet"
            raise TrainingDiverged(f"stopping: {self.in_row} non-finite steps in a row at step {step} "
                                   f"(config.max_nonfinite_in_row={self.max_in_row}); last good checkpoint: {where}")
        return True


class _Throughput:
    """Cycles per second and seconds per step since the last logged step."""

    def __init__(self, cycles_per_step: int):
        self.cycles_per_step = cycles_per_step
        self.t, self.steps = time.perf_counter(), 0

    def step(self) -> None:
        self.steps += 1

    def window(self) -> dict:
        dt = time.perf_counter() - self.t
        out = {"cycles_per_s": self.steps * self.cycles_per_step / max(dt, 1e-9), "step_time_s": dt / max(1, self.steps)}
        self.t, self.steps = time.perf_counter(), 0
        return out


def _restore(ckpt: checkpointing.TrainCheckpointer, state, data_iter, is_main: bool):
    """(state, step) of the latest checkpoint in the workdir (data iterator restored too), else (state, 0)."""
    latest = ckpt.latest_step()
    if latest is None:
        return state, 0
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)
    state, data_state = ckpt.restore(latest, abstract)
    if data_state:
        data_iter.set_state(data_state)
    start_step = int(jax.device_get(state["step"]))
    if is_main:
        print(f"Resuming from {ckpt.directory}/{latest} (step {start_step}).", flush=True)
    return state, start_step


class _StopSignals:
    """SIGTERM / SIGINT set `received` instead of killing the run (the loop then saves and exits)."""

    def __init__(self):
        self.received = None
        self._old = {}

    def __enter__(self):
        if sys.platform != "win32" and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._old[sig] = signal.signal(sig, self._on_signal)
        return self

    def _on_signal(self, signum, frame):  # noqa: ARG002
        self.received = signum

    def __exit__(self, *exc):
        for sig, handler in self._old.items():
            signal.signal(sig, handler)
        return False


# ##########################################################################################################
# Train and evaluate
# ##########################################################################################################

def train_and_evaluate(config: ml_collections.ConfigDict | setup.Run, workdir: str) -> dict:
    """Trains (or resumes) in `workdir`; returns a summary dict (final step, last metrics, validation, state).

    `config`: a training config, or the `setup.Run` parsed from one."""
    ##### Check the input: nothing in the workdir is touched before this section passes ####################
    run = setup.parse(config)
    proc, nproc = jax.process_index(), jax.process_count()
    is_main = proc == 0
    workdir = os.path.abspath(workdir)
    resuming = _check_workdir(run, workdir)
    dataset = _make_dataset(run, proc, nproc)
    try:
        dataset_size = len(dataset)
    except TypeError:  # a source of unknown size
        dataset_size = None
    steps_per_epoch, num_steps = run.steps(dataset_size)

    ##### Create model & optimizer ############################################################################
    init_rng, state_rng = jax.random.split(jax.random.key(run.seed))
    graphdef, params = network.init_params(init_rng, run.model.config, run.model.separate)
    if run.init_from and not resuming:
        params = _load_init_params(run.init_from, run.model, params)
    tx, schedule = train_step.make_optimizer(run.optimizer, steps_per_epoch)
    net = run.model.network(graphdef)

    ##### Shard & transfer #####################################################################################
    host_state = jax.tree.map(np.asarray, train_step.create_train_state(params, tx, jax.random.key_data(state_rng)))
    mesh, state_sharding, batch_sharding = setup.data_parallel(run, host_state)
    state = jax.tree.map(lambda x, s: jax.make_array_from_callback(x.shape, s, lambda idx: x[idx]),
                         host_state, state_sharding)
    del host_state, params

    ##### Workdir: config, checkpoints, resume ##############################################################
    os.makedirs(workdir, exist_ok=True)
    if is_main:
        files.write_json(os.path.join(workdir, checkpointing.CONFIG_JSON), run.config_json)
        files.write_json(os.path.join(workdir, checkpointing.MODEL_JSON), run.model.model_json())
    loop = run.loop
    ckpt = checkpointing.TrainCheckpointer(workdir, save_every=loop.checkpoint_every, keep=loop.keep_checkpoints,
                                           async_save=loop.async_checkpoints)
    data_iter = iter(dataset)
    state, start_step = _restore(ckpt, state, data_iter, is_main)

    ##### Update step and validation ###########################################################################
    step_fn = setup.build_step(run, net, tx, schedule, state_sharding=state_sharding, batch_sharding=batch_sharding)
    predictor = inference.Predictor(graphdef, state["params"], height=run.height, width=run.width,
                                    dtype=run.model.dtype, model_cfg=run.model.config, separate=run.model.separate,
                                    mesh=mesh)
    val_frames = validation_frames(run) if run.eval.enabled else []
    logger = Logger(workdir, is_main)
    global_shape = (run.global_batch, 4, run.height, run.width, 3)

    def run_validation(step, frames, log_metrics=True):
        res, panel = validate(predictor, state["params"], frames, max(1, run.eval.batch))
        if log_metrics:
            logger.scalars(step, res, kind="val")
        if panel is not None and is_main:
            logger.image(step, "val/prediction", panel)
        return res

    ##### Train loop ###########################################################################################
    step, last_metrics, val, interrupted = start_step, {}, {}, False
    guard, meter = _NonFiniteGuard(loop.max_nonfinite_in_row, logger, ckpt, is_main), _Throughput(run.global_batch)
    with _StopSignals() as stop, tqdm(total=num_steps, initial=start_step, unit="step", dynamic_ncols=True,
                                      file=sys.stderr, disable=not (is_main and loop.progress_bar)) as bar:
        try:
            while step < num_steps:
                if stop.received is not None:
                    interrupted = True
                    break
                local = np.asarray(next(data_iter)["cycle"], np.float32)
                state, metrics = step_fn(state, _global_array(batch_sharding, local, global_shape))
                metrics = jax.device_get(metrics)
                if guard.skipped(step, metrics):
                    continue
                step += 1
                meter.step()
                last_metrics = metrics
                ckpt.save(step, state, data_iter.get_state())

                if step % loop.log_every == 0 or step == num_steps:
                    extra = {**meter.window(), "nonfinite_total": guard.total, "epoch": step / steps_per_epoch}
                    logger.scalars(step, {**{k: v for k, v in metrics.items() if k != "nonfinite"}, **extra})
                    bar.set_postfix(loss=f"{_scalar(metrics['loss']):.4f}", cycles_s=f"{extra['cycles_per_s']:.2f}",
                                    refresh=False)
                bar.update(1)
                if val_frames and run.eval.every > 0 and step % run.eval.every == 0 and step < num_steps:
                    val = run_validation(step, val_frames)
                elif is_main and run.eval.image_every > 0 and step % run.eval.image_every == 0 and val_frames:
                    run_validation(step, val_frames[:1], log_metrics=False)

            if interrupted:
                if is_main:
                    print(f"\nReceived signal {stop.received}: saving a checkpoint at step {step} and exiting.",
                          file=sys.stderr, flush=True)
            elif val_frames:
                val = run_validation(step, val_frames)
            ckpt.save(step, state, data_iter.get_state(), force=True)
            ckpt.wait()
        finally:
            ckpt.close()
            logger.close()

    latest = ckpt.latest_step()
    return {"start_step": start_step, "workdir": workdir, "step": step, "interrupted": interrupted,
            "nonfinite_total": guard.total, "last_metrics": {k: _scalar(v) for k, v in last_metrics.items()},
            "validation": val, "checkpoint": os.path.join(ckpt.directory, str(latest)) if latest is not None else None,
            "state": state}


# ##########################################################################################################
# Command line
# ##########################################################################################################

def enable_compilation_cache(path: str, workdir: str) -> str | None:
    """Turns on JAX's persistent compilation cache for this process (`config.compilation_cache_dir`).

    `path`: "auto" = <workdir>/xla_cache, "" = off, else a folder. Only the command-line entry points call this:
    JAX opens the cache at the process's first compilation and keeps it, so a library caller (or a test running
    several workdirs in one process) configures it itself. Returns the cache folder, or None when off. An
    environment variable JAX_COMPILATION_CACHE_DIR wins.
    """
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        return os.environ["JAX_COMPILATION_CACHE_DIR"]
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
    if len(argv) > 1:
        raise SystemExit(f"error: unexpected arguments {argv[1:]} (options are --config=..., --workdir=...)")
    FLAGS = flags.FLAGS
    try:
        run = setup.parse(FLAGS.config)
        enable_compilation_cache(run.compilation_cache_dir, FLAGS.workdir)
        result = train_and_evaluate(run, FLAGS.workdir)
    except ConfigError as e:
        raise SystemExit(cli.report_error(e))
    except TrainingDiverged as e:
        raise SystemExit(cli.report_error(e, code=1))
    msg = "interrupted; checkpoint saved" if result["interrupted"] else "done"
    print(f"{msg}: step {result['step']}, checkpoint {result['checkpoint']}, metrics "
          f"{os.path.join(result['workdir'], 'metrics.jsonl')}", flush=True)


def _define_flags():
    config_flags.DEFINE_config_file("config", None, "Training config file, e.g. bridge_jax/configs/default.py[:arg].",
                                    lock_config=True)
    flags.DEFINE_string("workdir", None, "Directory for checkpoints, logs and metrics (resumed if it has any).")
    flags.mark_flags_as_required(["config", "workdir"])


if __name__ == "__main__":
    _define_flags()
    app.run(main)
