r"""Training: `bridge-train --config=NAME[:arg] --workdir=DIR [--config.KEY=VALUE ...]`.

    bridge-train --config=demo --workdir=work/demo          # the README's demo model (~11 min, CPU)
    bridge-train --config=default --workdir=work/default \
        --config.data.source=kitti_raw --config.data.data_dir=/data/kitti_raw --config.global_batch=8
    bridge-train --config=demo --workdir=work/mine \
        --config.data.source=folder --config.data.data_dir=my_video \
        --config.data.val_dir=my_video_heldout --config.init_from=demo  # fine-tune the shipped model on your video
    bridge-train --config=my_config.py:arg --workdir=DIR    # a config file of your own

`--config` is a config shipped in the package, by name from any directory (listed below; `:arg` picks a
variant, e.g. `full2:local`), or the path of a Python file with `get_config(arg)`. `--config.KEY=VALUE`
overrides any field (dotted, Python literals); `--list-config [NAME]` prints every field of a config with its
value and meaning. A run re-started with the same workdir resumes where it stopped, with the config it was
started with: a resume whose config differs from the workdir's config.json is refused with the fields listed
(`field old -> new`) unless `--allow-config-change`; the training length, the log / validation / checkpoint
intervals, the devices, micro-batching and caches may change without it (`RESUME_MAY_CHANGE`). One trainer per
workdir: a second one on a workdir in use is refused, naming the PID of the first (`.lock` below).

One run, top to bottom (sections of `train_and_evaluate`): parse and check the config (`setup.parse`) and build
the data pipeline (nothing is written to the workdir before every input is validated), create model +
optimiser, shard state and batches over a ('data',) mesh, resume from the newest readable checkpoint in the
workdir (train state and data-iterator state) or initialise (optionally params from `--config.init_from`: a
checkpoint path or a shipped model name), then loop: jitted step, guard against non-finite updates, async
checkpoints, metrics.jsonl / TensorBoard / progress bar, periodic validation on held-out data (synthetic frames
with exact ground truth, or your own held-out frames from `config.data.val_dir`, scored photometrically).

Workdir layout (`bridge_jax.workdir`):
    config.json, model.json         the run's config (as last started: a resume is compared with it) and the
                                    model description (params-only loaders)
    checkpoints/<step>/{state,data} orbax: train state (with `config.ema_decay` > 0 also the params' moving
                                    average, which every reader takes for the model) + grain iterator state
    metrics.jsonl                   one JSON object per log/eval event (one run's history, also after resumes)
    tensorboard/                    tensorboardX event files (scalars, images)
    images/                         the same pictures as PNG files
    status.json                     running | finished | interrupted | aborted | failed (with the reason), the
                                    step, steps/s, last checkpoint and a heartbeat, rewritten at every log
                                    interval; `bridge-train --status WORKDIR` prints it and says whether the
                                    run is stale (no heartbeat for 3 periods: its process is gone);
                                    "first_step_s" / "compile_s": time to this run's first step;
                                    "step_cache": hit / written / off (`executable_cache`)
    xla.log                         XLA's "Very slow compile?" banners, kept out of the console (not with
                                    --debug)
    .lock                           locked (fcntl.flock) by the trainer working in the workdir, its PID inside;
                                    the lock ends with that process, however it ends

XLA keeps its compiled train step in a per-user cache folder (`--config.compilation_cache_dir`: "auto" =
$BRIDGE_JAX_CACHE_DIR, else ~/.cache/bridge_jax/xla; "workdir" = <workdir>/xla_cache; "" = off), so a resumed
run, or the next run of the same shapes, skips most of the compile. A one-device run also keeps the compiled
train step whole there (`executable_cache`: keyed by the package's source, the config, the shapes and the
environment), so that the next run of the same code and config neither traces nor lowers it again.

Exit codes: 0 finished; 75 interrupted by SIGTERM/SIGINT with a checkpoint saved (run again to resume); 130 (143
for SIGTERM) a second signal: exits at once without saving (status "aborted"); 2 bad input or environment, a
full disk included (one line naming the option, file or folder; `--debug` or BRIDGE_JAX_DEBUG=1 shows the
traceback), a workdir in use by another trainer and a resume with another config included; 1 training diverged
(too many non-finite steps in a row); 141 the output pipe closed (`--list-config | head`): stopped quietly, as
git and the coreutils do.
"""

from __future__ import annotations

import contextlib
import json
import logging
import os
import signal
import sys
import threading
import time
from typing import Any, Optional, Sequence

import jax
import ml_collections
import numpy as np
from tqdm import tqdm

from bridge_jax import (checkpointing, cli, compile_cache, configs, console, files, inference, models, network, recipe,
                        setup, executable_cache, train_step)
from bridge_jax import workdir as workdir_mod, zoo
from bridge_jax.data import folders, pipeline
from bridge_jax.eval import photometric
from bridge_jax.eval.baselines import zero_method
from bridge_jax.eval.datasets import Frame, synthetic_frames
from bridge_jax.eval.methods import ModelMethod
from bridge_jax.eval.scoring import score_methods
from bridge_jax.setup import ConfigError  # noqa: F401  (re-exported: the trainer's user-error type)
from bridge_jax.workdir import MetricsLogger, RunStatus, last_validation, scalar


class TrainingDiverged(RuntimeError):
    """Too many non-finite steps in a row: reported as one line, exit code 1."""


XLA_LOG = "xla.log"  # in the workdir: what `console` keeps out of the console (XLA's slow-compile banners)
EXIT_FINISHED, EXIT_DIVERGED, EXIT_BAD_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 75  # 75 = EX_TEMPFAIL: "try again"


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


def _validation_data(run: setup.Run):
    """What validation runs on: ("synthetic", frames with exact ground truth), ("own", (N, 4, H, W, 3) held-out
    cycles of `config.data.val_dir`, scored photometrically), or None when validation is off. Read before the
    workdir is written, so a bad `val_dir` is one error and nothing else."""
    if not run.validates:
        return None
    if run.data.val_dir:
        try:
            cycles = photometric.val_cycles(run.data, run.height, run.width, run.eval.num_samples)
        except (ValueError, OSError) as e:
            msg = str(e)
            raise ConfigError(msg if photometric.OPTION in msg else f"{photometric.OPTION}: {msg}") from e
        return ("own", cycles)
    return ("synthetic", validation_frames(run))


def _validate_data(predictor: inference.Predictor, params, val_data, batch: int, first_only: bool = False):
    """(metrics, picture panel) of `params` on `_validation_data`'s result."""
    kind, data = val_data
    data = data[:1] if first_only else data
    if kind == "own":
        return photometric.photometric_validation(predictor, data, batch, params=params)
    return validate(predictor, params, data, batch)


# ##########################################################################################################
# Pieces of a run
# ##########################################################################################################

# Fields that a resumed run may set otherwise than the run it resumes (without --allow-config-change): how long
# to train (the lr schedule counts in epochs of `loop.steps_per_epoch`, not in the total, so extending a run does
# not change the steps already planned), how often to log, validate and checkpoint, and how the same step is
# computed and fed (another machine, more devices, another cache folder). Every other field changes what is
# trained or what the validation numbers mean.
RESUME_MAY_CHANGE = (
    "loop.num_train_steps", "loop.num_epochs", "loop.log_every", "loop.eval_every", "loop.image_every",
    "loop.eval_at_start", "loop.checkpoint_every", "loop.keep_checkpoints", "loop.async_checkpoints",
    "loop.progress_bar", "loop.max_nonfinite_in_row", "eval.batch", "compilation_cache_dir", "num_devices",
    "micro_batch", "remat", "conv_weight_grad", "data.prefetch", "data.read_threads", "data.worker_buffer_size",
    "data.prescan", "data.max_skip", "distributed.*")


def _may_change_on_resume(field: str) -> bool:
    return any(field == f or (f.endswith(".*") and field.startswith(f[:-1])) for f in RESUME_MAY_CHANGE)


def config_changes(old: dict, new: dict) -> dict[str, tuple[Any, Any]]:
    """{dotted field: (old value, new value)} of the fields whose values differ between two configs as JSON (a
    workdir's config.json and `setup.Run.config_json`), in the order of `new`. A field only one of them has
    (added or moved by another version of the package) is not compared."""
    before, after = recipe.flat_keys(old), recipe.flat_keys(new)
    return {k: (before[k], v) for k, v in after.items() if k in before and before[k] != v}


def describe_changes(changes: dict[str, tuple[Any, Any]], limit: int = 8) -> str:
    """The changes on one line, "lr 0.0001 -> 0.0002, seed 0 -> 1" (at most `limit` fields, then how many more)."""
    parts = [f"{k} {old!r} -> {new!r}" for k, (old, new) in list(changes.items())[:limit]]
    more = len(changes) - limit
    return ", ".join(parts) + (f" and {more} more" if more > 0 else "")


def _workdir_config(workdir: str) -> dict:
    """The config.json of `workdir` (the config it was last started with); {} when there is none readable."""
    try:
        with open(os.path.join(workdir, checkpointing.CONFIG_JSON)) as f:
            old = json.load(f)
    except (OSError, ValueError):
        return {}
    return old if isinstance(old, dict) else {}


def _config_changes(run: setup.Run, workdir: str) -> dict[str, tuple[Any, Any]]:
    """`config_changes` from the config.json of `workdir` (the config it was last started with) to this run's
    config; {} without a readable config.json."""
    old = _workdir_config(workdir)
    return config_changes(old, json.loads(json.dumps(run.config_json))) if old else {}


def _in_use_error(workdir: str, holder: str) -> ConfigError:
    return ConfigError(f"--workdir={workdir} is in use by another trainer ({holder}): two runs in one workdir would "
                       "overwrite each other's checkpoints and logs; wait for it to end or stop it "
                       f"(`bridge-train --status {workdir}` shows how far it is)")


def _lock_workdir(workdir: str, enabled: bool) -> workdir_mod.WorkdirLock:
    """The workdir's lock for this run (`workdir.WorkdirLock`: creates the workdir); ConfigError naming the
    holder's PID when another trainer has it. Process 0 locks for a multi-host run (`enabled`)."""
    try:
        return workdir_mod.WorkdirLock(workdir, enabled=enabled)
    except workdir_mod.WorkdirInUse as e:
        raise _in_use_error(workdir, e.holder) from None


def _refuse_if_locked(workdir: str) -> None:
    """ConfigError naming the holder's PID when another trainer holds `workdir` (`workdir.lock_holder`; reads
    only): said before the data and the model are built. The lock itself is taken at the first write."""
    holder = workdir_mod.lock_holder(workdir)
    if holder is not None:
        raise _in_use_error(workdir, holder)


def _check_workdir(run: setup.Run, workdir: str, allow_config_change: bool = False) -> bool:
    """Whether `workdir` holds a run to resume. Refused (ConfigError, nothing is written): a workdir of another
    model, and a resume with a config that differs from the workdir's config.json in fields outside
    `RESUME_MAY_CHANGE` unless `allow_config_change`."""
    if os.path.exists(workdir) and not os.path.isdir(workdir):
        raise ConfigError(f"--workdir={workdir} exists and is not a directory")
    if os.path.isfile(os.path.join(workdir, recipe.RECIPE_JSON)):
        raise ConfigError(f"--workdir={workdir} holds the stages of a recipe (its {recipe.RECIPE_JSON}); this config "
                          "is a single run: use a new workdir, or the recipe's config to resume it")
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
    if resuming:
        # the moving average is part of the train state: its checkpoints cannot be resumed with it switched on or off
        before = float(_workdir_config(workdir).get("ema_decay", 0.0) or 0.0)
        if (before > 0) != (run.optimizer.ema_decay > 0):
            raise ConfigError(f"config.ema_decay={run.optimizer.ema_decay!r}: --workdir={workdir} was trained with "
                              f"ema_decay={before!r}, and its checkpoints "
                              f"{'hold' if before > 0 else 'do not hold'} a moving average of the params; resume "
                              f"with the average {'on' if before > 0 else 'off'}, or train in a new workdir "
                              "(--config.init_from=" + workdir + " starts from its params)")
    if resuming and not allow_config_change:
        refused = {k: v for k, v in _config_changes(run, workdir).items() if not _may_change_on_resume(k)}
        if refused:
            raise ConfigError(f"--workdir={workdir} was started with another config (its {checkpointing.CONFIG_JSON}"
                              f"): {describe_changes(refused)}; resume with the same config, train in a new workdir, "
                              "or pass --allow-config-change to resume with these changes")
    return resuming


def _make_dataset(run: setup.Run, process_index: int, process_count: int):
    """(the training dataset, the number of cycles its source holds after the pre-scan)."""
    try:
        source = pipeline.make_source(run.data, height=run.height, width=run.width, seed=run.seed)
        dataset = pipeline.make_train_dataset(run.data, global_batch=run.global_batch, seed=run.seed,
                                              height=run.height, width=run.width, process_index=process_index,
                                              process_count=process_count, source=source)
    except (ValueError, FileNotFoundError, NotADirectoryError) as e:
        raise ConfigError(f"config.data: {e}") from e
    try:
        return dataset, len(source)
    except TypeError:  # a source of unknown size
        return dataset, None


def _load_init_params(spec: str, model: setup.ModelSpec, abstract_params):
    """Params from `config.init_from` (a shipped model name such as "demo", a params-only dir, a training
    workdir or a step dir); architecture checked and every value finite."""
    if not zoo.is_name(spec) and not os.path.exists(spec):
        raise ConfigError(f"config.init_from={spec!r}: no such file or directory (or a model name: "
                          f"{', '.join(zoo.names())})")
    try:
        src_cfg, params = zoo.load_params(spec)
        checkpointing.check_finite_params(params, f"config.init_from={spec!r}")
    except (ValueError, OSError) as e:
        msg = str(e)
        raise ConfigError(msg if msg.startswith("config.init_from") else f"config.init_from={spec!r}: {msg}") from e
    # Keys that do not change the architecture (compute dtype, how fresh params are drawn) are not compared.
    ignore = ("dtype", "head_init")
    src = {k: v for k, v in src_cfg.items() if k not in ignore}
    src_separate = bool(src.pop("separate_networks", False))
    want = {k: v for k, v in model.config.items() if k not in ignore}
    try:
        src = {k: v for k, v in models.model_config(src).items() if k not in ignore}
    except ValueError:
        pass
    if src != want:
        raise ConfigError(f"config.init_from={spec!r} holds a different architecture: {src} (this run: {want})")
    params = jax.tree.map(np.asarray, params)
    if model.separate and not src_separate:  # flow+stereo weights to start both networks of the no-sharing variant
        params = {"stereo": params, "flow": params}
    if jax.tree.structure(params) != jax.tree.structure(abstract_params) or any(
            a.shape != b.shape for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(abstract_params))):
        raise ConfigError(f"config.init_from={spec!r}: parameter tree/shapes do not match the model {want['name']}")
    return params


def _global_array(sharding, local: np.ndarray, global_shape):
    return jax.make_array_from_process_local_data(sharding, local, global_shape)


class _NonFiniteGuard:
    """Counts skipped (non-finite) steps; too many in a row stop the run with the last good checkpoint named."""

    def __init__(self, max_in_row: int, logger: MetricsLogger, ckpt: checkpointing.TrainCheckpointer, is_main: bool):
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
        if self.is_main and self.in_row == 1:  # the first of a row; the rest are counted (metrics.jsonl, the error)
            print(f"step {step}: non-finite loss/gradient, update skipped ({self.total} in total; the run stops after "
                  f"{self.max_in_row} in a row)", file=sys.stderr, flush=True)
        if self.in_row >= self.max_in_row:
            self.ckpt.wait()
            last = self.ckpt.latest_step()
            where = f"{self.ckpt.directory}/{last}" if last is not None else "none saved yet"
            raise TrainingDiverged(f"stopping: {self.in_row} non-finite steps in a row at step {step} "
                                   f"(config.loop.max_nonfinite_in_row={self.max_in_row}); last good checkpoint: {where}")
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
    """(state, step) of the newest checkpoint in the workdir that reads completely (data iterator restored too),
    else (state, 0). A broken newer step (torn save, garbage, empty folder, NaN state) is warned about by name
    and moved aside to `<step>.broken-<n>` at the next save, never deleted; all broken is one ConfigError."""
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)
    try:
        found = ckpt.restore_latest(abstract, warn=is_main)
    except ValueError as e:
        raise ConfigError(str(e)) from e
    if found is None:
        return state, 0
    if found.data_state:
        data_iter.set_state(found.data_state)
    start_step = int(jax.device_get(found.state["step"]))
    if is_main:
        skipped = "".join(f"; skipped broken step {s} (see the warning)" for s, _ in found.broken)
        print(f"Resuming from {ckpt.directory}/{found.step} (step {start_step}){skipped}.", flush=True)
    return found.state, start_step


class _StopSignals:
    """SIGTERM / SIGINT set `received` instead of killing the run (the loop then saves and exits). A second signal
    ends the process at once, even inside a long compilation or validation (nothing more is saved; the previous
    checkpoint stays): `on_abort(signum)` runs first (the trainer writes status.json "aborted"), then the
    process exits with 128 + signum (130 for Ctrl-C). The main thread runs Python's signal handlers only between
    bytecodes, so a watcher thread reads the signal numbers from a wake-up pipe (`signal.set_wakeup_fd`) and
    acts on the second one while the main thread is busy in XLA."""

    def __init__(self, announce: bool = True, on_abort=None):
        self.received = None
        self.announce = announce
        self.on_abort = on_abort
        self._old = {}
        self._pipe = None
        self._old_fd = -1
        self._count = 0
        self._lock = threading.Lock()

    def __enter__(self):
        if sys.platform != "win32" and threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGTERM, signal.SIGINT):
                self._old[sig] = signal.signal(sig, self._on_signal)
            r, w = os.pipe()
            os.set_blocking(w, False)
            self._old_fd = signal.set_wakeup_fd(w, warn_on_full_buffer=False)
            self._pipe = (r, w)
            threading.Thread(target=self._watch, args=(r,), name="bridge_jax-signals", daemon=True).start()
        return self

    def _watch(self, fd: int) -> None:
        while True:
            try:
                data = os.read(fd, 64)
            except OSError:
                return
            if not data or 0 in data:  # 0: __exit__'s "stop" byte
                os.close(fd)
                return
            for signum in data:
                if signum in (signal.SIGTERM, signal.SIGINT):
                    self._count_signal(signum)

    def _count_signal(self, signum: int) -> None:
        """Counts each signal once (the handler and the watcher both see it); the second one aborts."""
        with self._lock:
            self._count += 1
            second = self._count >= 2
        if second:
            self._abort(signum)

    def _on_signal(self, signum, frame):  # noqa: ARG002
        if self.received is not None:
            if self._pipe is None:  # no watcher (e.g. a test's subclass): the handler counts
                self._abort(signum)
            return
        self.received = signum
        if self._pipe is None:
            self._count = 1
        if self.announce:
            print(f"\nReceived signal {signum}: stopping after this step and saving a checkpoint (send it again "
                  "to exit now without saving).", file=sys.stderr, flush=True)

    def _abort(self, signum: int) -> None:
        try:
            if self.on_abort is not None:
                self.on_abort(signum)
        finally:
            os._exit(128 + int(signum))

    def __exit__(self, *exc):
        if self._pipe is not None:
            signal.set_wakeup_fd(self._old_fd)
            r, w = self._pipe
            os.set_blocking(w, True)
            os.write(w, b"\0")  # stops the watcher (it closes the read end)
            self._pipe = None
            os.close(w)
        for sig, handler in self._old.items():
            signal.signal(sig, handler)
        return False


# ##########################################################################################################
# Train and evaluate
# ##########################################################################################################

def describe_validation(step: int, res: dict) -> str:
    """One line of validation numbers (synthetic ground truth, or photometric on the user's own frames)."""
    parts = []
    if "flow_epe_all" in res:
        parts.append(f"flow EPE {res['flow_epe_all']:.3f} px ({res.get('flow_epe_vs_zero', float('nan')):.2f}x "
                     "zero motion)")
    if "disp_epe_all" in res:
        parts.append(f"disparity EPE {res['disp_epe_all']:.3f} px, D1 {res.get('disp_d1_all', float('nan')):.1f} %")
    parts += photometric.describe(res)
    return f"step {step} validation: " + ("; ".join(parts) if parts else "no metrics")


def train_and_evaluate(config: ml_collections.ConfigDict | setup.Run, workdir: str, *,
                       enable_cache: bool = False, config_name: Optional[str] = None,
                       stage: Optional[recipe.StageRun] = None, allow_config_change: bool = False) -> dict:
    """Trains (or resumes) in `workdir`; returns a summary dict (final step, last metrics, validation, state).

    `config`: a training config, or the `setup.Run` parsed from one; a recipe config (`config.stages`) runs
    each of its stages in turn (`run_recipe`). `enable_cache`: turn on the persistent
    compilation cache (`compile_cache.enable` with `config.compilation_cache_dir`) once the inputs are checked
    (the command line does; JAX keeps the first cache folder of a process, so a library caller usually does
    not). `config_name`: how the config was named, for the start-up line. `stage`: set by `run_recipe` for one
    of its stages: metrics, TensorBoard and status.json go to the recipe's workdir, tagged with the stage.
    `allow_config_change`: resume even when the config differs from the workdir's config.json in fields outside
    `RESUME_MAY_CHANGE` (the changes are printed and recorded in metrics.jsonl either way).

    The run holds the workdir's lock (`workdir.WorkdirLock`) from its first write to its return: a second
    trainer on the same workdir is refused (ConfigError naming the holder's PID). A recipe's stage locks its
    own stage workdir; `run_recipe` holds the recipe's."""
    if recipe.is_recipe(config):
        return run_recipe(config, workdir, enable_cache=enable_cache, config_name=config_name,
                          allow_config_change=allow_config_change)
    global _RUNS_STARTED
    # The first run of a process counts its first step from the process's start (imports included); a later run
    # in the same process (bridge-demo's second phase) from its own start.
    origin = None if _RUNS_STARTED == 0 else compile_cache.process_age_s()
    _RUNS_STARTED += 1
    ##### Check the input: nothing in the workdir is touched before this section passes ####################
    run = setup.parse(config)
    proc, nproc = jax.process_index(), jax.process_count()
    is_main = proc == 0
    workdir = os.path.abspath(workdir)
    if is_main:  # process 0 alone locks (the others would find its lock taken)
        _refuse_if_locked(workdir)
    resuming = _check_workdir(run, workdir, allow_config_change)
    dataset, dataset_size = _make_dataset(run, proc, nproc)
    steps_per_epoch, num_steps = run.steps(dataset_size)
    val_data = _validation_data(run)
    if enable_cache:
        compile_cache.enable(run.compilation_cache_dir, workdir, option="config.compilation_cache_dir")

    ##### Create model & optimizer ############################################################################
    init_rng, state_rng = jax.random.split(jax.random.key(run.seed))
    graphdef, params = network.init_params(init_rng, run.model.config, run.model.separate)
    if run.init_from and not resuming:
        params = _load_init_params(run.init_from, run.model, params)
    tx, schedule = train_step.make_optimizer(run.optimizer, steps_per_epoch)
    net = run.model.network(graphdef)

    ##### Shard & transfer #####################################################################################
    host_state = jax.tree.map(np.asarray, train_step.create_train_state(params, tx, jax.random.key_data(state_rng),
                                                                        ema=run.optimizer.ema_decay > 0))
    mesh, state_sharding, batch_sharding = setup.data_parallel(run, host_state)
    state = jax.tree.map(lambda x, s: jax.make_array_from_callback(x.shape, s, lambda idx: x[idx]),
                         host_state, state_sharding)
    del host_state, params

    ##### Workdir: lock, config, checkpoints, resume ########################################################
    # The first write: the lock (it creates the workdir). The checks above saw the workdir unlocked; they are
    # repeated under the lock, since a run that held it meanwhile may have changed what is there.
    lock = _lock_workdir(workdir, is_main)
    try:
        if _check_workdir(run, workdir, allow_config_change) != resuming:
            raise ConfigError(f"--workdir={workdir} changed while this run was starting (another trainer ran in it "
                              "meanwhile); run the same command again")
        changes = _config_changes(run, workdir) if resuming else {}  # read before config.json is rewritten
        os.makedirs(workdir, exist_ok=True)  # processes > 0 hold no lock file
        log_dir = stage.log_dir if stage else workdir  # a recipe's stages log into the recipe's workdir
        stage_fields = ({"stage": stage.name, "stage_index": stage.index + 1, "num_stages": stage.count,
                         "stage_seconds_before": round(stage.seconds_before, 1)}
                        if stage else {})
        run_status = RunStatus(log_dir, is_main, step=0, num_steps=num_steps, **stage_fields)
    except BaseException:
        lock.release()
        raise
    ckpt = None
    try:
        if is_main:
            files.write_json(os.path.join(workdir, checkpointing.CONFIG_JSON), run.config_json)
            files.write_json(os.path.join(workdir, checkpointing.MODEL_JSON), run.model.model_json())
        loop = run.loop
        ckpt = checkpointing.TrainCheckpointer(workdir, save_every=loop.checkpoint_every, keep=loop.keep_checkpoints,
                                               async_save=loop.async_checkpoints)
        data_iter = iter(dataset)
        state, start_step = _restore(ckpt, state, data_iter, is_main)
        if is_main:
            print(("" if stage is None else f"{stage.label}: ")
                  + _startup_line(run, config_name, dataset_size, val_data, workdir, start_step, num_steps), flush=True)
        if is_main and changes and start_step > 0:
            print(f"resuming with config changes: {describe_changes(changes, limit=len(changes))}", flush=True)
        run_status.update(step=start_step, start_step=start_step, last_checkpoint=ckpt.latest_step())

        ##### Update step and validation ###########################################################################
        step_fn = setup.build_step(run, net, tx, schedule, state_sharding=state_sharding, batch_sharding=batch_sharding)
        # validation, and every reader of the checkpoints, see the moving average when the run keeps one
        predictor = inference.Predictor(graphdef, train_step.model_params(state),
                                        size=inference.WorkingSize(run.height, run.width),
                                        dtype=run.model.dtype, model_cfg=run.model.config, separate=run.model.separate,
                                        mesh=mesh)
        logger = MetricsLogger(log_dir, is_main, resume_step=start_step,
                               stage={"name": stage.name, "offset": stage.offset} if stage else None)
        if changes and start_step > 0:  # config.json now holds the new values: the history keeps the old ones
            logger.record(start_step, "config_change", {"changes": {k: list(v) for k, v in changes.items()}})
        if stage and start_step == 0:
            # what the stage starts from: the init_from path and the sum of squares of the initial params, so the
            # record shows that stage k starts from stage k - 1's final params
            logger.stage_start(stage.index, stage.count, init_from=run.init_from,
                               params_sq_sum=params_square_sum(state["params"]))
        global_shape = (run.global_batch, 4, run.height, run.width, 3)

        def run_validation(step, log_metrics=True, first_only=False):
            res, panel = _validate_data(predictor, train_step.model_params(state), val_data, max(1, run.eval.batch),
                                        first_only)
            if log_metrics:
                logger.scalars(step, res, kind="val")
                if is_main:
                    tqdm.write(describe_validation(step, res), file=sys.stdout)
            if panel is not None and is_main:
                logger.image(step, "val/prediction", panel)
            return res

        ##### Train loop ###########################################################################################
        step, last_metrics, val, interrupted, first_step = start_step, {}, {}, False, True
        guard, meter = _NonFiniteGuard(loop.max_nonfinite_in_row, logger, ckpt, is_main), _Throughput(run.global_batch)
        finished_before = resuming and start_step >= num_steps
        status = "failed"
        def abort(signum):  # a second signal: the process exits at once (see _StopSignals)
            run_status.end("aborted", signal=int(signum), reason=f"signal {int(signum)} received twice: exited at once "
                           "without saving; run the same command to resume from the last checkpoint")

        with _StopSignals(announce=is_main, on_abort=abort) as stop, \
                tqdm(total=num_steps, initial=start_step, unit="step", dynamic_ncols=True, file=sys.stderr,
                     disable=not (is_main and loop.progress_bar), desc=stage.label if stage else None) as bar:
            try:
                if val_data and loop.eval_at_start and start_step == 0 and num_steps > 0:
                    val = run_validation(0)  # where the run starts from (a fine-tune's starting point)
                while step < num_steps:
                    if stop.received is not None:
                        interrupted = True
                        break
                    local = np.asarray(next(data_iter)["cycle"], np.float32)
                    batch = _global_array(batch_sharding, local, global_shape)
                    if first_step:
                        state, metrics, step_fn = _first_step(step_fn, state, batch, run, run_status, is_main, origin,
                                                              {"config": run.config_json, "num_steps": num_steps,
                                                               "steps_per_epoch": steps_per_epoch})
                        first_step = False
                    else:
                        state, metrics = step_fn(state, batch)
                    metrics = jax.device_get(metrics)
                    if guard.skipped(step, metrics):
                        continue
                    step += 1
                    run_status.progress(step)
                    meter.step()
                    last_metrics = metrics
                    ckpt.save(step, state, data_iter.get_state())

                    if step % loop.log_every == 0 or step == num_steps:
                        extra = {**meter.window(), "nonfinite_total": guard.total, "epoch": step / steps_per_epoch,
                                 **({"recipe/stage_index": stage.index + 1} if stage else {})}
                        logger.scalars(step, {**{k: v for k, v in metrics.items() if k != "nonfinite"}, **extra})
                        run_status.update(step=step, steps_per_s=1.0 / max(extra["step_time_s"], 1e-9),
                                          last_checkpoint=ckpt.latest_step())
                        bar.set_postfix(loss=f"{scalar(metrics['loss']):.4f}", cycles_s=f"{extra['cycles_per_s']:.2f}",
                                        refresh=False)
                    bar.update(1)
                    if stop.received is not None:  # no long phase (validation) once asked to stop
                        continue
                    if val_data and loop.eval_every > 0 and step % loop.eval_every == 0 and step < num_steps:
                        val = run_validation(step)
                    elif is_main and loop.image_every > 0 and step % loop.image_every == 0 and val_data:
                        run_validation(step, log_metrics=False, first_only=True)

                if interrupted:
                    if is_main:
                        print(f"\nSaving a checkpoint at step {step} and exiting.", file=sys.stderr, flush=True)
                elif finished_before:
                    val = last_validation(log_dir, stage.name if stage else None)
                elif val_data:
                    val = run_validation(step)
                skips = dataset.skips.report()
                if is_main and skips.get("cycles"):
                    logger.record(step, "data_skips", skips)
                    print(f"data: {skips['cycles']} cycles skipped (unreadable or inconsistent files), e.g. "
                          f"{'; '.join(f'{k}: {v}' for k, v in list(skips.get('causes', {}).items())[:3])} "
                          "(all of them in metrics.jsonl)", file=sys.stderr, flush=True)
                ckpt.save(step, state, data_iter.get_state(), force=True)
                ckpt.wait()
                status = "interrupted" if interrupted else "finished"
            finally:
                try:
                    ckpt.close()
                finally:
                    logger.close()
            run_status.end(status, step=step, last_checkpoint=ckpt.latest_step(),
                           **({"signal": int(stop.received)} if interrupted else {}))

        latest = ckpt.latest_step()
        return {"start_step": start_step, "workdir": workdir, "step": step, "interrupted": interrupted,
                "nonfinite_total": guard.total, "last_metrics": {k: scalar(v) for k, v in last_metrics.items()},
                "validation": val,
                "checkpoint": os.path.join(ckpt.directory, str(latest)) if latest is not None else None,
                "skipped_data": dataset.skips.report(), "state": state}
    except BaseException as e:  # every way out that is not a return: status.json says what happened
        # the checkpoint that exists now (a failed save, e.g. on a full disk, keeps the one before it)
        last = {}
        if ckpt is not None:
            with contextlib.suppress(Exception):
                last = {"last_checkpoint": ckpt.latest_step()}
        if isinstance(e, (KeyboardInterrupt, SystemExit)):
            run_status.end("aborted", reason=f"{type(e).__name__}: exited without saving", **last)
        else:
            text = str(e).strip()
            run_status.end("failed", reason=text.splitlines()[0] if text else type(e).__name__, **last)
        raise
    finally:
        lock.release()


def params_square_sum(params) -> float:
    """The sum of squares of every parameter, in float64 on the host: a fingerprint of a parameter tree."""
    return float(sum(np.sum(np.square(np.asarray(jax.device_get(x), np.float64))) for x in jax.tree.leaves(params)))


_RUNS_STARTED = 0
"""Training runs started in this process (`train_and_evaluate` calls)."""


def _recipe_runs(config: ml_collections.ConfigDict, workdir: str) -> dict[str, setup.Run]:
    """{stage name: its checked `setup.Run`}, in order: stage k > 0 starts from stage k - 1's workdir. Every
    stage's config is checked before anything is written (ConfigError naming the stage's field)."""
    try:
        names = recipe.stage_names(config)
        configs_by_stage = {name: recipe.stage_config(config, name) for name in names}
    except ValueError as e:
        raise ConfigError(str(e)) from e
    runs = {}
    for i, name in enumerate(names):
        cfg = configs_by_stage[name]
        if i > 0:
            if "init_from" in recipe.stage_settings(config, name):
                raise ConfigError(f"config.stage_overrides.{name}.init_from: stage {name} starts from the stage "
                                  f"before it ({names[i - 1]}); only the first stage may set init_from")
            cfg.init_from = recipe.stage_dir(workdir, names[i - 1])
        try:
            runs[name] = setup.parse(cfg)
        except ConfigError as e:
            raise ConfigError(f"stage {name}: {e}") from e
    return runs


def _check_recipe_workdir(workdir: str, names: Sequence[str]) -> None:
    """Refuses (ConfigError, nothing written) a workdir that holds a single run or another recipe."""
    if os.path.exists(workdir) and not os.path.isdir(workdir):
        raise ConfigError(f"--workdir={workdir} exists and is not a directory")
    if os.path.isdir(os.path.join(workdir, checkpointing.CHECKPOINTS_DIR)):
        raise ConfigError(f"--workdir={workdir} holds a single training run, not the stages of a recipe; use a new "
                          "workdir for the recipe")
    try:
        record = recipe.read_record(workdir)
    except ValueError as e:
        raise ConfigError(str(e)) from e
    if record is not None and list(record.get("stages", [])) != list(names):
        raise ConfigError(f"--workdir={workdir} holds a recipe of the stages {record.get('stages')}; this config's "
                          f"stages are {list(names)}. Use a new workdir (or the same recipe) to resume.")


def run_recipe(config: ml_collections.ConfigDict, workdir: str, *, enable_cache: bool = False,
               config_name: Optional[str] = None, allow_config_change: bool = False) -> dict:
    """Runs the stages of a recipe config (`bridge_jax.recipe`) in order in `workdir`, each in its own
    `stages/<name>/` workdir from the previous stage's final params; a finished stage is skipped, an interrupted
    one resumes at its step. Returns the last stage's `train_and_evaluate` summary with "step" counted across
    the recipe and "stages" ([{"name", "steps", "seconds", "validation"}] of the finished stages), or the
    interrupted stage's summary with "stage" naming it.

    The recipe's workdir is locked (`workdir.WorkdirLock`) from its first write until every stage has run, so a
    second trainer on it is refused; each stage locks its own `stages/<name>/` as well (another file: no
    deadlock), which keeps a single run started by hand in a stage's folder out too. `allow_config_change`: as
    in `train_and_evaluate`, for the stage that resumes."""
    workdir = os.path.abspath(workdir)
    runs = _recipe_runs(config, workdir)
    names = list(runs)
    _check_recipe_workdir(workdir, names)
    first = runs[names[0]]
    if enable_cache:
        compile_cache.enable(first.compilation_cache_dir, workdir, option="config.compilation_cache_dir")
    with _lock_workdir(workdir, jax.process_index() == 0):  # creates the workdir
        _check_recipe_workdir(workdir, names)  # again under the lock: a run that held it may have changed it
        return _run_stages(runs, workdir, config_name, allow_config_change)


def _run_stages(runs: dict[str, setup.Run], workdir: str, config_name: Optional[str],
                allow_config_change: bool) -> dict:
    """`run_recipe`'s work once the recipe's workdir is locked."""
    names = list(runs)
    os.makedirs(workdir, exist_ok=True)
    if jax.process_index() == 0:
        recipe.write_record(workdir, names, {name: run.config_json for name, run in runs.items()}, config_name,
                            recipe.code_commit())
    offset, stages, result = 0, [], None
    for i, name in enumerate(names):
        done = recipe.finished(workdir, name)
        if done is not None:
            print(f"stage {i + 1}/{len(names)} {name}: finished earlier ({done['steps']} steps), not run again",
                  flush=True)
        else:
            t0 = time.time()
            before = workdir_mod.stage_seconds_before(workdir, name)  # a resumed stage: its earlier runs' time
            result = train_and_evaluate(runs[name], recipe.stage_dir(workdir, name), config_name=config_name,
                                        stage=recipe.StageRun(name, i, len(names), offset, workdir, before),
                                        allow_config_change=allow_config_change)
            if result["interrupted"]:
                return dict(result, stage=name, step=offset + result["step"], workdir=workdir, stages=stages)
            done = {"steps": result["step"], "seconds": round(before + time.time() - t0, 1),
                    "validation": result["validation"]}
            if jax.process_index() == 0:
                recipe.mark_finished(workdir, name, **done)
        stages.append({"name": name, **done})
        offset += int(done["steps"])
    if result is None:  # every stage had finished before: nothing ran
        last = checkpointing.find_train_step_dir(recipe.stage_dir(workdir, names[-1]))
        result = {"start_step": offset, "interrupted": False, "nonfinite_total": 0, "last_metrics": {},
                  "checkpoint": last, "skipped_data": {}, "state": None}
    return dict(result, step=offset, workdir=workdir, stages=stages, validation=stages[-1]["validation"])


def _first_step(step_fn, state, batch, run: setup.Run, run_status: RunStatus, is_main: bool,
                origin: Optional[float], step_config: dict):
    """The run's first train step, which compiles: announced in one line before, and timed (status.json
    "first_step_s": seconds from the start of the process, or from `origin` (its age in seconds when a later run
    of the same process started), to the end of this step; "compile_s": of those, the seconds JAX spent tracing,
    lowering and compiling or loading from the cache, or loading the kept step). Waits for the step to finish,
    which later steps never do here.

    With a compilation cache folder, the step goes through `executable_cache.cached_compile` (keyed by
    `step_config`, what shapes the step besides the shapes): a warm start loads the compiled step instead of
    tracing, lowering and looking it up.
    status.json "step_cache" says which ("hit", "written" or "off"). Returns (state, metrics, the step function
    the later steps call)."""
    folder = compile_cache.active_dir()

    def announce(kept: bool) -> None:
        if not is_main:
            return
        if kept:
            line = f"loading the compiled train step for {run.height}x{run.width} ({compile_cache.describe()})"
        else:
            cache = f"first run only: {compile_cache.describe()}" if folder else compile_cache.describe()
            line = f"compiling the train step for {run.height}x{run.width} ({cache})"
        tqdm.write(line, file=sys.stdout)

    stats: dict = {}
    with compile_cache.CompileClock() as clock:
        t0 = time.perf_counter()
        step_fn = executable_cache.cached_compile(step_fn, (state, batch), config=step_config, folder=folder,
                                                  stats=stats, announce=announce)
        prepare_s = time.perf_counter() - t0  # compiled (and kept) or loaded; ~0 when the call below compiles
        state, metrics = step_fn(state, batch)
        jax.block_until_ready((state, metrics))
    # Round once: the console line prints the very numbers status.json records (rounding 80.149 to 80.15 and then
    # to one decimal would print 80.2 beside a recorded 80.1 otherwise).
    first_step_s = round(compile_cache.process_age_s() - (origin or 0.0), 1)
    compile_s = round(max(clock.seconds, prepare_s), 1)  # a loaded step is no JAX compile event
    error = {"step_cache_error": stats["cache_error"]} if "cache_error" in stats else {}
    run_status.update(first_step_s=first_step_s, compile_s=compile_s, step_cache=stats["cache"], **error)
    if is_main:
        how = "loading" if stats["cache"] == "hit" else "compiling"
        tqdm.write(f"train step ready after {first_step_s:.1f} s ({how} {compile_s:.1f} s of it)", file=sys.stdout)
    return state, metrics, step_fn


def _startup_line(run: setup.Run, config_name, dataset_size, val_data, workdir, start_step, num_steps) -> str:
    devices = f"{len(run.devices)} {run.devices[0].platform} device{'s' if len(run.devices) > 1 else ''}"
    data = run.data.source + (f" {run.data.data_dir}" if run.data.source != "synthetic" and run.data.data_dir else "")
    cycles = f"{dataset_size} cycles" if dataset_size is not None else "cycles of unknown number"
    val = ("off" if not val_data else f"{len(val_data[1])} {val_data[0]} cycles" if val_data[0] == "synthetic"
           else f"{len(val_data[1])} held-out cycles of {run.data.val_dir}")
    if val_data and val_data[0] == "synthetic" and run.data.source != "synthetic":
        # training on other data but validating on the built-in synthetic frames: worth saying
        val += " (synthetic frames, not your data: set --config.data.val_dir for held-out frames of your own)"
    start = (f"resuming at step {start_step}" if start_step else
             f"initialised from {run.init_from}" if run.init_from else "from scratch")
    return (f"train: config {config_name or '(given)'} | model {run.model.config['name']} | data {data}: {cycles} | "
            f"validation {val} | {devices} | {run.height}x{run.width}, batch {run.global_batch}, {num_steps} steps, "
            f"{start} | workdir {workdir}")


# ##########################################################################################################
# Command line
# ##########################################################################################################

def _config_epilog() -> str:
    lines = ["Configs shipped in the package (--config=NAME[:arg]):"]
    for name in configs.names():
        lines.append(f"  {name:14s} {configs.summary(name)}")
    lines += ["", "Data sources (--config.data.source=...):",
              "  synthetic      built-in procedural stereo video with exact ground truth, rendered on the fly (default)",
              "  folder         your own rectified stereo video: --config.data.data_dir=DIR, layouts:",
              *(f"                 {line}" for line in folders.LAYOUT_HELP.splitlines()),
              "  kitti_raw      KITTI raw drives (--config.data.data_dir=ROOT, --config.data.split=eigen|kitti|all)",
              "  tfds           the kitti_cycles TFDS ArrayRecord build (--config.data.data_dir=TFDS_DIR)"]
    return "\n".join(lines)


def build_parser():
    p = cli.make_parser("bridge_jax.train", __doc__)
    p.epilog = (p.epilog or "") + "\n\n" + _config_epilog()
    p.add_argument("--config", metavar="NAME[:arg]|FILE.py[:arg]",
                   help=f"training config (required): a name ({', '.join(configs.names())}) or a Python file with "
                        "get_config()")
    p.add_argument("--workdir", help="folder for checkpoints, logs and metrics (required; resumed if it has any)")
    p.add_argument("--list-config", nargs="?", const="default", default=None, metavar="NAME",
                   help="print every field of config NAME (default: default) with its value and meaning, then exit")
    p.add_argument("--status", metavar="WORKDIR", default=None,
                   help="print the state of the run in WORKDIR (its status.json: step, speed, last checkpoint, "
                        "heartbeat) and whether it is stale, i.e. its process is gone: a 'running' run without a "
                        f"heartbeat for {workdir_mod.STALE_BEATS} heartbeat periods (a heartbeat comes at every log "
                        f"interval and at least every {workdir_mod.HEARTBEAT_S:g} s); exit code 0, 1 when stale or "
                        "failed, 2 without a status file")
    p.add_argument("--allow-config-change", action="store_true",
                   help="resume a run even though this config differs from the one the workdir was started with "
                        "(its config.json) in fields that change what is trained (lr, data, losses, seed, ...); "
                        "without it such a resume is refused with the fields listed. Training length, log, "
                        "validation and checkpoint intervals, devices and caches may change without it")
    p.add_argument("--verbosity", default="warning", choices=("debug", "info", "warning", "error"),
                   help="log level of the libraries (absl, orbax, grain); info shows orbax's checkpoint messages")
    cli.add_debug_flag(p)
    return p


def split_config_overrides(argv: Sequence[str]) -> tuple[list[str], list[str]]:
    """(other arguments, ["KEY=VALUE", ...]) from `--config.KEY=VALUE` / `--config.KEY VALUE` arguments."""
    rest, items, i = [], [], 0
    argv = list(argv)
    while i < len(argv):
        arg = argv[i]
        if arg.startswith("--config."):
            body = arg[len("--config."):]
            if "=" not in body:
                if i + 1 >= len(argv):
                    raise ConfigError(f"{arg}: expected {arg}=VALUE")
                body, i = f"{body}={argv[i + 1]}", i + 1
            items.append(body)
        else:
            rest.append(arg)
        i += 1
    return rest, items


def load_config(spec: str, overrides: Sequence[str]) -> ml_collections.ConfigDict:
    """The config `spec` (name or file) with `overrides` applied; ConfigError (one line) naming the config file,
    or the misspelt key and its close matches. In a recipe an override sets the base and every stage that sets
    the same key (`recipe.override_everywhere`)."""
    try:
        config = configs.load(spec)
        staged = recipe.is_recipe(config)
        if staged:
            recipe.stage_names(config)
    except ValueError as e:
        raise ConfigError(str(e) if str(e).startswith("--config") else f"--config {spec}: {e}") from e
    except Exception as e:  # an error inside the user's config file
        raise ConfigError(f"--config {spec}: the config file failed: {type(e).__name__}: {e}") from e
    for item in overrides:
        try:
            if staged:
                recipe.override_everywhere(config, [item])
            else:
                configs.override(config, [item], hint_prefix="--config.")
        except ValueError as e:
            raise ConfigError(f"--config.{item}: {str(e).split(': ', 1)[-1]}") from e
    return config


def _set_verbosity(level: str) -> None:
    """Logs (absl: orbax, grain; bridge_jax) at `level`: the default, warning, still shows skipped data and
    checkpoint fallbacks; info adds orbax's checkpoint messages and the data pre-scan."""
    from absl import logging as absl_logging
    num = getattr(logging, level.upper())
    absl_logging.set_verbosity(absl_logging.converter.standard_to_absl(num))
    logging.getLogger("absl").setLevel(num)
    if num < logging.WARNING:
        absl_logging.use_absl_handler()
    logging.getLogger("bridge_jax").setLevel(num)


@cli.entry_point
def main(argv: Optional[Sequence[str]] = None) -> int:
    """`bridge-train` / `bridge-train`; returns the exit code (see the module docstring)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    parser = build_parser()
    debug = cli.debug_enabled() or "--debug" in argv
    try:
        rest, items = split_config_overrides(argv)
    except ConfigError as e:
        return cli.report_error(e, debug=debug)
    args = parser.parse_args(rest)
    if args.list_config is not None:
        try:
            print(setup.list_config(load_config(args.list_config, items)))
        except ConfigError as e:
            return cli.report_error(e, code=EXIT_BAD_INPUT, debug=args.debug)
        return EXIT_FINISHED
    if args.status is not None:
        try:
            line, stale = workdir_mod.describe_status(args.status)
        except ValueError as e:
            return cli.report_error(e, code=EXIT_BAD_INPUT, debug=args.debug)
        print(line)
        return 1 if stale or line.split(", ", 1)[0].endswith((": failed", ": aborted")) else 0
    if not args.config or not args.workdir:
        parser.error("the following arguments are required: " + ", ".join(
            f"--{n}" for n in ("config", "workdir") if not getattr(args, n)))
    _set_verbosity(args.verbosity)
    if not args.debug:  # a failed checkpoint write is one line, not orbax's and asyncio's tracebacks too
        checkpointing.quiet_save_failure_noise()
    # XLA's "Very slow compile?" banner goes to <workdir>/xla.log, not into the progress bar
    console.install(os.path.join(os.path.abspath(args.workdir), XLA_LOG), enabled=not cli.debug_enabled(args))
    try:
        config = load_config(args.config, items)
        result = train_and_evaluate(config, args.workdir, enable_cache=True, config_name=args.config,
                                    allow_config_change=args.allow_config_change)
    except TrainingDiverged as e:
        return cli.report_error(e, code=EXIT_DIVERGED, debug=args.debug)
    except (ValueError, OSError) as e:  # ConfigError, unreadable data, a full disk, a broken checkpoint: one line
        return cli.report_error(e, code=EXIT_BAD_INPUT, debug=args.debug)
    except RuntimeError as e:  # orbax / tensorstore report a full disk from their writer threads like this
        if not any(t in str(e) for t in ("RESOURCE_EXHAUSTED", "No space left", "Disk quota")):
            raise
        return cli.report_error(RuntimeError(f"--workdir={args.workdir}: the disk is full "
                                             f"({str(e).strip().splitlines()[0][:200]})"), code=EXIT_BAD_INPUT,
                                debug=args.debug)
    msg = "interrupted; checkpoint saved (run the same command to resume)" if result["interrupted"] else "done"
    print(f"{msg}: step {result['step']}, checkpoint {result['checkpoint']}, metrics "
          f"{os.path.join(result['workdir'], 'metrics.jsonl')}", flush=True)
    return EXIT_INTERRUPTED if result["interrupted"] else EXIT_FINISHED


if __name__ == "__main__":
    sys.exit(main())
