"""A training config (`ml_collections.ConfigDict`, see `bridge_jax/configs/`) parsed and checked once.

    run = setup.parse(config)      # every check of the user's input, before anything is written
    run.model, run.loss, run.optimizer, run.data, run.loop, run.eval     # typed sections
    run.devices, run.micro_batch, run.rows_per_device          # resolved for this machine

The trainer, the demo and the benchmark consume the `Run`; nothing below reads ConfigDict fields. Every bad
setting is one `ConfigError` naming the option (the command line prints it as one line and exits 2).
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import io
import json
import math
import textwrap
import tokenize
from typing import Any, Optional, Sequence

import jax
import ml_collections
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import config_keys, cycle, losses, memory, models
from bridge_jax.data.pipeline import DataConfig
from bridge_jax.micro_batch import MicroBatchedStep
from bridge_jax.models.layers import WEIGHT_GRAD_METHODS
from bridge_jax.network import COMPUTE_DTYPES, REMAT_POLICIES, Network, compute_dtype
from bridge_jax.train_step import OptimizerConfig, make_train_step


class ConfigError(ValueError):
    """Bad user input (config, data, workdir, init_from): reported as one line, exit code 2."""


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """The network of a run: `config` is the full model description (`models.model_config`, what model.json
    stores), `separate` the paper's no-sharing variant (two networks), `dtype` the compute dtype name, `remat`
    the rematerialisation policy of the training gradient (`network.REMAT_POLICIES`), `conv_weight_grad` how
    the convolutions compute their weight gradients (`layers.WEIGHT_GRAD_METHODS`)."""

    config: dict
    separate: bool
    dtype: str
    remat: str = "none"
    conv_weight_grad: str = "auto"

    def network(self, graphdef) -> Network:
        return Network(graphdef, separate=self.separate, dtype=compute_dtype(self.dtype), remat=self.remat,
                       conv_weight_grad=self.conv_weight_grad)

    def model_json(self) -> dict:
        """What a workdir's model.json holds (the params-only loaders read it)."""
        return dict(self.config, **({"separate_networks": True} if self.separate else {}))


def _check(ok: bool, section: str, name: str, want: str, value) -> None:
    if not ok:
        raise ValueError(f"config.{section + '.' if section else ''}{name} must be {want}, got {value!r}")


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


# The integer fields that count or space something (steps, intervals, sizes, batches, workers), by dotted config
# key: (the smallest allowed value, {other allowed value: its meaning}). `check_counts` applies them to the typed
# record of every section (`SECTIONS`), so every refusal reads the same; a test checks that each integer field of
# those records has a rule here or is listed in NOT_COUNTS.
COUNT_RULES: dict[str, tuple[int, dict[int, str]]] = {
    "height": (1, {}), "width": (1, {}), "global_batch": (1, {}),
    "micro_batch": (0, {-1: "auto"}), "num_devices": (1, {-1: "all devices"}),
    "loss.num_scales": (1, {}), "loss.occlusion_start_step": (0, {}), "loss.self_supervision_start_step": (0, {}),
    "loss.self_supervision_crop": (0, {}),
    "data.num_workers": (0, {}), "data.prefetch": (0, {}), "data.read_threads": (1, {}),
    "data.worker_buffer_size": (1, {}), "data.max_skip": (0, {}), "data.synthetic_num": (1, {}),
    "data.num_epochs": (1, {}),  # or None (forever)
    "loop.num_train_steps": (1, {-1: "derive from the data"}), "loop.num_epochs": (1, {}),
    "loop.steps_per_epoch": (1, {-1: "derive from the data"}), "loop.log_every": (1, {}),
    "loop.checkpoint_every": (1, {}), "loop.eval_every": (0, {-1: "never"}), "loop.image_every": (0, {-1: "off"}),
    "loop.keep_checkpoints": (1, {}), "loop.max_nonfinite_in_row": (1, {}),
    "eval.num_samples": (0, {}), "eval.batch": (1, {}),
    "distributed.num_processes": (0, {}), "distributed.process_id": (0, {-1: "auto-detect"}),
}
# Integer fields that are not counts (any integer is a valid seed; smoothness_order is a choice of two).
NOT_COUNTS = ("seed", "eval.seed", "loss.smoothness_order")


def count_rule_text(key: str) -> str:
    """What `COUNT_RULES[key]` allows, in words: "an integer >= 1, or -1 (derive from the data)"."""
    low, special = COUNT_RULES[key]
    return f"an integer >= {low}" + "".join(f", or {v} ({meaning})" for v, meaning in special.items())


def check_counts(record, section: str) -> None:
    """Refuses (ValueError "config.<key>=<value>: must be ...") the first count or interval field of `record` (a
    section's dataclass) outside its `COUNT_RULES` range; None stands for "unset" and passes."""
    for f in dataclasses.fields(record):
        key = f"{section}.{f.name}" if section else f.name
        value = getattr(record, f.name)
        if key not in COUNT_RULES or value is None:
            continue
        low, special = COUNT_RULES[key]
        if not _is_int(value) or not (value >= low or value in special):
            raise ValueError(f"config.{key}={value!r}: must be {count_rule_text(key)}")


# Every float reaches float32 arithmetic (the loss, Adam, the data augmentation), where a value beyond float32's
# largest overflows to inf and a positive one below its smallest normal number may flush to 0.
FLOAT32_MAX = float(np.finfo(np.float32).max)
FLOAT32_TINY = float(np.finfo(np.float32).tiny)

# The float fields, by dotted config key: (low, high, ends, why). The value must lie in the interval from `low`
# to `high`, `ends` saying which ends belong to it ("[]" both, "[)" low only, "(]" high only, "()" neither);
# high = inf means "up to float32's largest", and an open low end of 0 means "at least float32's smallest normal
# number". NaN and inf never pass. `why` says what the range follows from (it ends the refusal, in parentheses).
# `check_floats` applies them to the values of every section (`SECTIONS`) before its record is built, so every
# refusal reads like the integers' ("config.<key>=<value>: must be ..."); a test checks that each float field
# of those records has a rule here.
FLOAT_RULES: dict[str, tuple[float, float, str, str]] = {
    # Adam and its schedule (train_step.make_optimizer): b1 = 1 or b2 = 1 divide by 1 - b^t = 0 in the bias
    # correction; eps = 0 divides 0 by 0 wherever a gradient and its moments are 0.
    "lr": (0.0, math.inf, "()", "Adam's learning rate"),
    "lr_decay": (0.0, 1.0, "(]", "the lr factor at each milestone; 1 = constant"),
    "adam_b1": (0.0, 1.0, "[)", "Adam's first-moment decay"),
    "adam_b2": (0.0, 1.0, "[)", "Adam's second-moment decay"),
    "adam_eps": (0.0, math.inf, "()", "keeps Adam's denominator above 0 where a gradient is 0"),
    "clip_grad_norm": (0.0, math.inf, "[)", "a global L2 norm; 0 = off"),
    "ema_decay": (0.0, 1.0, "[)", "the moving average's decay; 0 = off, 1 would never move"),
    # The loss (losses.total_loss, geometry.occlusion_mask): weights and edge constants of eq. 5-13.
    "loss.alpha": (0.0, 1.0, "[]", "the SSIM share of the SSIM + L1 photometric error"),
    "loss.beta": (0.0, math.inf, "[)", "edge constant of exp(-beta |dI|); 0 = no edge weighting"),
    "loss.beta1": (0.0, math.inf, "[)", "edge constant of exp(-beta1 |dI|); 0 = no edge weighting"),
    "loss.lambda_sm": (0.0, math.inf, "[)", "a weight of the total loss; 0 = term off"),
    "loss.lambda_sm1": (0.0, math.inf, "[)", "a weight of the total loss; 0 = term off"),
    "loss.lambda_lr": (0.0, math.inf, "[)", "a weight of the total loss; 0 = term off"),
    "loss.lambda_2warp": (0.0, math.inf, "[)", "a weight of the total loss; 0 = term off"),
    "loss.self_supervision": (0.0, math.inf, "[)", "a weight of the total loss; 0 = off"),
    "loss.occlusion_fill": (0.0, math.inf, "[)", "a weight of the total loss; 0 = off"),
    # |D + W(D')|^2 <= 2 (|D|^2 + |W(D')|^2): from alpha1 = 2 on the paper's test never marks a pixel occluded
    "loss.occ_alpha1": (0.0, 2.0, "[)", "the relative part of the occlusion threshold, eq. 6; from 2 on no pixel "
                                        "is ever occluded"),
    "loss.occ_alpha2": (0.0, math.inf, "[)", "the constant part of the occlusion threshold in pixels^2, eq. 6"),
    # the band is cut from both sides: half the height would leave no pixel in the mask
    "loss.border_ratio": (0.0, 0.5, "[)", "the fraction of the height left out on every side of the masks"),
    # masked means divide by the mask's sum: a floor of 0 divides by 0 where every pixel is occluded
    "loss.mask_floor": (0.0, 1.0, "(]", "added to every occlusion mask value, which lies in [0, 1]"),
    "loss.smooth_scale": (0.0, math.inf, "()", "the map's factor before the smoothness term; lambda_sm = 0 turns "
                                               "the term off"),
    # The augmentation (data.pipeline): the crops must stay inside the frame.
    "data.augment_zoom": (0.1, 1.0, "[]", "the smallest zoom-crop scale; 1 = off"),
    "data.augment_shift": (0.0, 0.25, "[]", "a fraction of the height; 0 = off"),
    "data.augment_t1_zoom": (0.0, 0.2, "[]", "the largest relative zoom between t and t+1; 0 = off"),
}


def float_rule_text(key: str) -> str:
    """What `FLOAT_RULES[key]` allows, in words: "a number in [0, 1) (Adam's first-moment decay)"."""
    low, high, ends, why = FLOAT_RULES[key]
    tiny = ends[0] == "(" and low == 0  # "> 0" is "at least float32's smallest normal number"
    if high == math.inf:
        bound = f">= {low:g}" if ends[0] == "[" else f"> {low:g}"
        limits = f"{FLOAT32_TINY:.2g} to {FLOAT32_MAX:.2g}" if tiny else f"at most {FLOAT32_MAX:.2g}"
        text = f"a number {bound} float32 can hold, {limits}"
    else:
        text = f"a number in {ends[0]}{low:g}, {high:g}{ends[1]}"
        if tiny:
            text += f", at least {FLOAT32_TINY:.2g} for float32"
    return f"{text} ({why})" if why else text


def float_allowed(key: str, value) -> bool:
    """Whether `value` (an int or float, not a bool) passes `FLOAT_RULES[key]`."""
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        return False
    value = float(value)
    if not math.isfinite(value) or abs(value) > FLOAT32_MAX:
        return False
    low, high, ends, _ = FLOAT_RULES[key]
    if ends[0] == "(" and low == 0:
        low_ok = value >= FLOAT32_TINY
    else:
        low_ok = value >= low if ends[0] == "[" else value > low
    return low_ok and (value <= high if ends[1] == "]" else value < high)


def check_floats(values: dict, section: str) -> None:
    """Refuses (ValueError "config.<key>=<value>: must be ...") the first float field of `values` (a section's
    fields by name) outside its `FLOAT_RULES` range."""
    for name, value in values.items():
        key = f"{section}.{name}" if section else name
        if key in FLOAT_RULES and not float_allowed(key, value):
            raise ValueError(f"config.{key}={value!r}: must be {float_rule_text(key)}")


@dataclasses.dataclass(frozen=True)
class RunOptions:
    """The top-level fields of a training config (beside the optimizer's, `train_step.OptimizerConfig`)."""

    height: int = 256  # working height in pixels (a multiple of the model's input multiple)
    width: int = 512  # working width in pixels (a multiple of the model's input multiple)
    global_batch: int = 2  # cycles per step, all devices and processes together
    seed: int = 0  # parameter init, shuffling and augmentation seed
    dtype: str = "float32"  # compute dtype: float32 | bfloat16 (params and optimizer stay float32)
    remat: str = "none"  # rematerialisation in the gradient: none | conv_outputs | nothing (network.REMAT_POLICIES)
    conv_weight_grad: str = "auto"  # how convolutions compute weight gradients (layers.WEIGHT_GRAD_METHODS)
    separate_networks: bool = False  # two networks (stereo, flow): the paper's no-sharing ablation
    micro_batch: int = -1  # pair-forwards per device per call: 0 = one jitted step, -1 = auto (2 on CPU)
    init_from: str = ""  # initial params: a checkpoint folder or a shipped model name ("" = random init)
    compilation_cache_dir: str = "auto"  # XLA cache: auto = per user, workdir = <workdir>/xla_cache, "" = off, a folder
    num_devices: int = -1  # devices of the ('data',) mesh: -1 = all (single process: all that divide global_batch),
    # N = the first N (single process)

    def __post_init__(self):
        for name in ("height", "width", "global_batch", "seed", "micro_batch", "num_devices"):
            _check(_is_int(getattr(self, name)), "", name, "an integer", getattr(self, name))
        _check(self.dtype in COMPUTE_DTYPES, "", "dtype", f"one of {sorted(COMPUTE_DTYPES)}", self.dtype)
        _check(self.remat in REMAT_POLICIES, "", "remat", f"one of {sorted(REMAT_POLICIES)}", self.remat)
        _check(self.conv_weight_grad in WEIGHT_GRAD_METHODS, "", "conv_weight_grad",
               f"one of {list(WEIGHT_GRAD_METHODS)}", self.conv_weight_grad)
        _check(isinstance(self.compilation_cache_dir, str), "", "compilation_cache_dir",
               "a folder, 'auto', 'workdir' or '' (off)", self.compilation_cache_dir)
        _check(isinstance(self.init_from, str), "", "init_from", "a checkpoint folder, a model name or ''",
               self.init_from)


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """The `loop` section: how long training runs, and how often it logs, checkpoints, validates and draws."""

    num_train_steps: int = -1  # total steps; -1 = num_epochs * steps_per_epoch
    num_epochs: int = 80  # epochs (when num_train_steps is -1); the lr schedule counts in epochs
    steps_per_epoch: int = -1  # steps of one epoch; -1 = the data source's size / global_batch
    log_every: int = 50  # steps between metrics.jsonl / TensorBoard records
    checkpoint_every: int = 1000  # steps between checkpoints (one more at the end)
    eval_every: int = 2000  # steps between validations; 0 = only at the end, -1 = never
    eval_at_start: bool = False  # validate before the first step too (a fine-tune shows where it starts)
    image_every: int = 1000  # steps between prediction pictures; <= 0 = with validations only
    keep_checkpoints: int = 3  # newest checkpoints kept in the workdir
    async_checkpoints: bool = True  # write checkpoints in the background while training goes on
    progress_bar: bool = True  # tqdm progress bar on stderr
    max_nonfinite_in_row: int = 20  # non-finite steps in a row (skipped) before the run stops as diverged

    def __post_init__(self):
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            if f.type == "bool":
                _check(isinstance(value, bool), "loop", f.name, "True or False", value)
            else:
                _check(_is_int(value), "loop", f.name, "an integer", value)


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """The `eval` section: the held-out validation set of training (synthetic frames with exact ground truth, or
    the user's `data.val_dir`); how often it runs is `loop.eval_every`."""

    num_samples: int = 16  # validation cycles
    seed: int = 1_000_003  # base seed of the synthetic validation frames (disjoint from training's `seed`)
    batch: int = 4  # cycles per predictor call

    def __post_init__(self):
        for f in dataclasses.fields(self):
            _check(_is_int(getattr(self, f.name)), "eval", f.name, "an integer", getattr(self, f.name))


@dataclasses.dataclass(frozen=True)
class DistributedConfig:
    """The `distributed` section: `jax.distributed.initialize` arguments (empty = auto-detect on TPU, SLURM...)."""

    enabled: bool = False  # join a multi-host cluster before training
    coordinator_address: str = ""  # host:port of process 0 ("" = auto-detect)
    num_processes: int = 0  # processes in the cluster (0 = auto-detect)
    process_id: int = -1  # this process's index (-1 = auto-detect)


@dataclasses.dataclass(frozen=True)
class Run:
    """Everything a training run needs, checked. `loop.steps_per_epoch` and `loop.num_train_steps` may still be
    -1 (derived from the data source's size, see `steps`)."""

    model: ModelSpec
    loss: losses.LossConfig
    optimizer: OptimizerConfig
    data: DataConfig
    eval: EvalConfig
    loop: LoopConfig
    distributed: DistributedConfig
    height: int
    width: int
    global_batch: int
    seed: int
    devices: tuple
    num_processes: int
    micro_batch: int
    init_from: str
    compilation_cache_dir: str
    config_json: dict  # the whole config as JSON (the workdir's config.json)

    @property
    def num_devices(self) -> int:
        return len(self.devices)

    @property
    def rows_per_device(self) -> int:
        """Pair-forwards per device per step: 2P rows per cycle, the batch sharded over the devices."""
        return self.global_batch // self.num_devices * cycle.rows_per_cycle(self.loss.pairs)

    @property
    def validates(self) -> bool:
        """Whether training validates (`loop.eval_every` >= 0 and a non-empty validation set)."""
        return self.loop.eval_every >= 0 and self.eval.num_samples > 0

    def steps(self, dataset_size: Optional[int]) -> tuple[int, int]:
        """(steps per epoch, total steps), resolving -1 (= derived) with the data source's size."""
        loop = self.loop
        steps_per_epoch = loop.steps_per_epoch
        if steps_per_epoch < 0:
            if dataset_size is None:
                raise ConfigError("config.loop.steps_per_epoch=-1 needs a data source of known size; set it "
                                  "explicitly")
            steps_per_epoch = max(1, dataset_size // self.global_batch)
        num_steps = loop.num_train_steps if loop.num_train_steps > 0 else loop.num_epochs * steps_per_epoch
        return steps_per_epoch, num_steps


# The sections of a training config and the dataclass each is parsed into ("" = the top level, which also holds
# the optimizer's fields). `model` is `models.model_config`'s dict (its keys depend on the model).
SECTIONS = (("", RunOptions), ("", OptimizerConfig), ("loss", losses.LossConfig), ("data", DataConfig),
            ("loop", LoopConfig), ("eval", EvalConfig), ("distributed", DistributedConfig))


def _typed(cls, values: dict, name: str):
    """`cls(**values)`; unknown fields and refused values are one ConfigError naming `config.<name>`."""
    where = f"config.{name}: " if name else "config."  # top-level fields: "config.lr must be ..."
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(f"{where}unknown field(s) {unknown}; known fields: {sorted(known)}")
    try:
        check_floats(values, name)  # before the record: its own checks would name a NaN less clearly
        record = cls(**values)
        check_counts(record, name)
        return record
    except (TypeError, ValueError) as e:
        raise ConfigError(str(e) if str(e).startswith("config.") else f"{where}{e}") from e


def _values(config, name: str, cls) -> dict:
    """The values of section `name` of `config` ("" = `cls`'s fields at the top level)."""
    if name:
        return config[name].to_dict()
    return {f.name: config[f.name] for f in dataclasses.fields(cls)}


def _initialize_distributed(d: DistributedConfig) -> None:
    if not d.enabled or jax.distributed.is_initialized():
        return
    kw: dict[str, Any] = {}
    if d.coordinator_address:
        kw["coordinator_address"] = d.coordinator_address
    if d.num_processes > 0:
        kw["num_processes"] = int(d.num_processes)
    if d.process_id >= 0:
        kw["process_id"] = int(d.process_id)
    jax.distributed.initialize(**kw)


def _mesh_devices(num_devices: int, num_processes: int, global_batch: int) -> tuple:
    """All devices (num_devices = -1) or the first N local ones (single process only).

    With -1 in a single process, a global batch that the devices do not divide (the demo's one cycle per step on
    a 2-GPU machine) runs on the most devices that divide it, not on all: the batch is sharded over the mesh,
    so more devices than that could not be used anyway."""
    if num_devices == -1:
        devices = tuple(jax.devices())
        if num_processes == 1 and global_batch > 0 and global_batch % len(devices):
            devices = devices[:max(n for n in range(1, len(devices) + 1) if global_batch % n == 0)]
        return devices
    if num_processes > 1:
        raise ConfigError("config.num_devices must be -1 (all devices) in a multi-process run")
    if not 1 <= num_devices <= jax.local_device_count():
        raise ConfigError(f"config.num_devices={num_devices}: this machine has {jax.local_device_count()} devices "
                          "(use -1 for all)")
    return tuple(jax.local_devices()[:num_devices])


def resolve_micro_batch(micro_batch: int, rows_per_device: int, backend: str) -> int:
    """`micro_batch` with -1 = auto: 2 pair-forwards per call on CPU (fastest and leanest there), the whole batch
    in one jitted step (0) on GPU/TPU."""
    if micro_batch != -1:
        return micro_batch
    return 2 if backend == "cpu" and rows_per_device % 2 == 0 and rows_per_device > 2 else 0


def _check_self_supervision_crop(name: str, height: int, width: int, crop: int) -> None:
    """The self-supervision student runs the model on the working size less 2 * crop: that must be a valid
    working size of the model too (2 * crop a multiple of its input multiple, and big enough)."""
    def fits(c):
        try:
            models.check_working_size(name, height - 2 * c, width - 2 * c)
            return True
        except ValueError:
            return False

    if fits(crop):
        return
    multiple = models.INPUT_MULTIPLE[name]
    ok = [c for c in range(multiple // 2, min(height, width) // 2, multiple // 2) if fits(c)]
    hint = f"e.g. {ok[0]}" if ok else f"none fits the working size {height}x{width}"
    raise ConfigError(f"config.loss.self_supervision_crop={crop}: the student's crop of the {height}x{width} (height "
                      f"x width) working size is {height - 2 * crop}x{width - 2 * crop}, not a working size of model "
                      f"{name} (2 * crop must be a multiple of {multiple} and leave a big enough size); {hint}")


def _check_training_memory(height: int, width: int, devices: tuple, rows_per_device: int,
                           cycles_per_device: int) -> None:
    """Refuses (ConfigError naming config.height/config.width) a working size whose train step cannot fit in the
    memory of one device of the mesh (`memory.training_bytes`, a lower bound). CPU devices share this machine's
    RAM, so there the rows of all of this process's devices count together."""
    device = devices[0]
    share = 1
    if device.platform == "cpu":
        share = max(1, sum(1 for d in devices if d.process_index == jax.process_index()))
    rows, cycles = rows_per_device * share, cycles_per_device * share
    needed = memory.training_bytes(height, width, rows, cycles)
    what = (f"a train step of {rows} pair-forwards{' on this machine' if share > 1 else ''} (at least "
            f"{memory.TRAIN_BYTES_PER_PIXEL} bytes per pixel each)")
    try:
        memory.check_fits("config.height/config.width", height, width, needed, what, device)
    except ValueError as e:
        raise ConfigError(str(e)) from e


def parse(config: ml_collections.ConfigDict, *, devices: Optional[Sequence] = None,
          num_processes: Optional[int] = None) -> Run:
    """Check a training config and return its `Run` (raises ConfigError naming the option).

    `devices`: the devices to shard over; None (the trainer) = `config.num_devices` of this process's view,
    after joining the cluster of a multi-host config (`config.distributed`). Fields of the `loop` section set
    at the top level (their place before that section existed) are moved there, with a note.
    """
    if isinstance(config, Run):
        return config
    if isinstance(config, ml_collections.ConfigDict) and config.get("stages", ()):
        raise ConfigError("this config is a recipe of stages (config.stages): run it with bridge-train or "
                          "train.train_and_evaluate, which parse each stage (bridge_jax.recipe.stage_config)")
    config = config_keys.move_flat_keys(config)
    try:
        model_values = config["model"].to_dict()
        values = {cls: _values(config, name, cls) for name, cls in SECTIONS}
    except (AttributeError, KeyError) as e:
        raise ConfigError(f"the config has no field {e} (configs are built from bridge_jax/configs/default.py)") from e
    values[OptimizerConfig]["lr_milestones"] = tuple(int(m) for m in values[OptimizerConfig]["lr_milestones"])
    typed = {cls: _typed(cls, values[cls], name) for name, cls in SECTIONS if cls is not losses.LossConfig}
    try:
        check_floats(values[losses.LossConfig], "loss")
        typed[losses.LossConfig] = losses.LossConfig.from_dict(values[losses.LossConfig])
        check_counts(typed[losses.LossConfig], "loss")
    except (ValueError, TypeError) as e:
        raise ConfigError(str(e) if str(e).startswith("config.") else f"config.loss: {e}") from e
    opts, loss_cfg = typed[RunOptions], typed[losses.LossConfig]
    try:
        model_cfg = models.model_config(model_values)
    except ValueError as e:
        raise ConfigError(f"config.model: {e}") from e
    try:
        models.check_working_size(model_cfg["name"], opts.height, opts.width, "config.height/config.width")
    except ValueError as e:
        raise ConfigError(str(e)) from e
    if loss_cfg.self_supervision > 0:
        _check_self_supervision_crop(model_cfg["name"], opts.height, opts.width, loss_cfg.self_supervision_crop)

    if devices is None:
        _initialize_distributed(typed[DistributedConfig])
        nproc = jax.process_count() if num_processes is None else num_processes
        devices = _mesh_devices(opts.num_devices, nproc, opts.global_batch)
    else:
        nproc = 1 if num_processes is None else num_processes
    devices = tuple(devices)
    num_devices, batch = len(devices), opts.global_batch
    if batch <= 0:
        raise ConfigError(f"config.global_batch must be positive, got {batch}")
    if batch % num_devices:
        raise ConfigError(f"config.global_batch={batch} is not divisible by the {num_devices} devices (batch is "
                          f"sharded over devices); use a multiple of {num_devices}")
    if batch % nproc:
        raise ConfigError(f"config.global_batch={batch} is not divisible by the {nproc} processes")
    rows_per_device = batch // num_devices * cycle.rows_per_cycle(loss_cfg.pairs)
    micro_batch = opts.micro_batch
    if micro_batch < -1 or (micro_batch > 0 and rows_per_device % micro_batch):
        raise ConfigError(f"config.micro_batch={micro_batch} must be 0 (no micro-batching), -1 (auto) or divide the "
                          f"{rows_per_device} pair-forwards per device")
    _check_training_memory(opts.height, opts.width, devices, rows_per_device, batch // num_devices)

    return Run(
        model=ModelSpec(model_cfg, opts.separate_networks, opts.dtype, opts.remat, opts.conv_weight_grad),
        loss=loss_cfg, optimizer=typed[OptimizerConfig], data=typed[DataConfig], eval=typed[EvalConfig],
        loop=typed[LoopConfig], distributed=typed[DistributedConfig], height=opts.height, width=opts.width,
        global_batch=batch, seed=opts.seed, devices=devices, num_processes=nproc,
        micro_batch=resolve_micro_batch(micro_batch, rows_per_device, devices[0].platform),
        init_from=opts.init_from, compilation_cache_dir=opts.compilation_cache_dir,
        config_json=json.loads(config.to_json_best_effort()))


def data_parallel(run: Run, state) -> tuple[jax.sharding.Mesh, Any, NamedSharding]:
    """(mesh, state sharding, batch sharding) of the run's data parallelism: a 1-D ('data',) mesh of its devices,
    the state replicated, batches split along their leading axis. Auto axis type: XLA propagates the batch
    sharding (the model code has no sharding annotations)."""
    mesh = jax.make_mesh((run.num_devices,), ("data",), axis_types=(jax.sharding.AxisType.Auto,), devices=run.devices)
    replicated = NamedSharding(mesh, P())
    return mesh, jax.tree.map(lambda _: replicated, state), NamedSharding(mesh, P("data"))


def build_step(run: Run, net: Network, tx, schedule, *, state_sharding=None, batch_sharding=None):
    """The run's training step: plain (one jit, `run.micro_batch == 0`) or maps-first micro-batched."""
    if run.micro_batch:
        return MicroBatchedStep(net, run.loss, tx, schedule, micro_batch=run.micro_batch,
                                num_devices=run.num_devices, state_sharding=state_sharding,
                                batch_sharding=batch_sharding, ema_decay=run.optimizer.ema_decay)
    return make_train_step(net, run.loss, tx, schedule, state_sharding=state_sharding, batch_sharding=batch_sharding,
                           ema_decay=run.optimizer.ema_decay)


# ----------------------------------------------------------------------------------------------------------
# The config's fields and their meanings (`bridge-train --list-config`)
# ----------------------------------------------------------------------------------------------------------

def _line_comments(cls) -> dict[str, str]:
    """{field: the comment that ends its line in `cls`'s source} (a field's one line of meaning)."""
    try:
        source = textwrap.dedent(inspect.getsource(cls))
    except (OSError, TypeError):  # no source shipped: the listing still has every field, without meanings
        return {}
    comments = {tok.start[0]: tok.string.lstrip("#").strip()
                for tok in tokenize.generate_tokens(io.StringIO(source).readline) if tok.type == tokenize.COMMENT}
    body = ast.parse(source).body[0].body
    return {node.target.id: comments[node.end_lineno] for node in body
            if isinstance(node, ast.AnnAssign) and isinstance(node.target, ast.Name) and node.end_lineno in comments}


def field_help() -> dict[str, str]:
    """{dotted config key: one line of meaning} for every field of every section dataclass (`SECTIONS`); a field
    without a comment on its line maps to ""."""
    out = {}
    for section, cls in SECTIONS:
        comments = _line_comments(cls)
        for f in dataclasses.fields(cls):
            out[f"{section}.{f.name}" if section else f.name] = comments.get(f.name, "")
    return out


def list_config(config: ml_collections.ConfigDict) -> str:
    """Every field of `config` with its value and one line of meaning: the top level, then the sections in the
    order `model`, `SECTIONS`; the `model` section's keys depend on the model and point to its module."""
    meanings = field_help()
    model = config["model"]["name"] if "model" in config and "name" in config["model"] else "?"
    meanings["model.name"] = f"the network: {' | '.join(models.NAMES)}"
    order = ["", "model"] + [name for name, _ in SECTIONS if name] + ["stage_overrides"]
    def section(key: str) -> str:
        return "stage_overrides" if key.startswith("stage_overrides.") else key.rpartition(".")[0]

    keys = sorted(config_keys.leaf_keys(config), key=lambda k: (order.index(section(k)) if section(k) in order
                                                            else len(order), k))
    rows = []
    for key in keys:
        node = config
        for part in key.split("."):
            node = node[part]
        if key == "stages":
            meaning = "the recipe's stages, in order (bridge_jax.recipe): each trains from the one before"
        elif key.startswith("stage_overrides."):
            stage, _, field = key[len("stage_overrides."):].partition(".")
            meaning = f"stage {stage}'s {field} (on top of the base: " + (meanings.get(field) or "see above") + ")"
        elif key.startswith("model."):
            meaning = meanings.get(key) or f"a setting of model {model} (bridge_jax.models.{model.split('_tiny')[0]})"
        else:
            meaning = meanings.get(key) or "(not a field of this version: parse refuses or ignores it)"
        rows.append((key, repr(node), meaning))
    width = max(len(k) + len(v) + 3 for k, v, _ in rows)
    return "\n".join(f"{f'{k} = {v}':{width}s}  {m}" for k, v, m in rows)
