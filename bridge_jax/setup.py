"""A training config (`ml_collections.ConfigDict`, see `bridge_jax/configs/`) parsed and checked once.

    run = setup.parse(config)      # every check of the user's input, before anything is written
    run.model, run.loss, run.optimizer, run.data, run.eval     # typed sections
    run.devices, run.micro_batch, run.rows_per_device          # resolved for this machine

The trainer, the demo and the benchmark consume the `Run`; nothing below reads ConfigDict fields. Every bad
setting is one `ConfigError` naming the option (the command line prints it as one line and exits 2).
"""

from __future__ import annotations

import dataclasses
import json
from typing import Any, Optional, Sequence

import jax
import ml_collections
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import cycle, losses, models
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


@dataclasses.dataclass(frozen=True)
class EvalConfig:
    """Held-out synthetic validation during training: `num_samples` cycles from base seed `seed` (disjoint from
    training's), `batch` cycles per predictor call, every `every` steps (0: only at the end, -1: never), a
    picture every `image_every` steps (<= 0: with validations only)."""

    num_samples: int
    seed: int
    batch: int
    every: int
    image_every: int

    @property
    def enabled(self) -> bool:
        return self.every >= 0 and self.num_samples > 0


@dataclasses.dataclass(frozen=True)
class LoopConfig:
    """Checkpoints, logging and guards of the training loop."""

    checkpoint_every: int
    keep_checkpoints: int
    async_checkpoints: bool
    log_every: int
    progress_bar: bool
    max_nonfinite_in_row: int


@dataclasses.dataclass(frozen=True)
class DistributedConfig:
    """Multi-host: `jax.distributed.initialize` arguments (empty = auto-detect on TPU / SLURM / ...)."""

    enabled: bool
    coordinator_address: str
    num_processes: int
    process_id: int


@dataclasses.dataclass(frozen=True)
class Run:
    """Everything a training run needs, checked. `steps_per_epoch` and `num_train_steps` may still be -1
    (derived from the data source's size, see `steps`)."""

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
    steps_per_epoch: int
    num_epochs: int
    num_train_steps: int
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

    def steps(self, dataset_size: Optional[int]) -> tuple[int, int]:
        """(steps per epoch, total steps), resolving -1 (= derived) with the data source's size."""
        steps_per_epoch = self.steps_per_epoch
        if steps_per_epoch < 0:
            if dataset_size is None:
                raise ConfigError("config.steps_per_epoch=-1 needs a data source of known size; set it explicitly")
            steps_per_epoch = max(1, dataset_size // self.global_batch)
        num_steps = self.num_train_steps if self.num_train_steps > 0 else self.num_epochs * steps_per_epoch
        return steps_per_epoch, num_steps


def _section(config, name: str) -> dict:
    return config[name].to_dict()


def _typed(cls, values: dict, name: str):
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(f"config.{name}: unknown field(s) {unknown}; known fields: {sorted(known)}")
    try:
        return cls(**values)
    except (TypeError, ValueError) as e:
        raise ConfigError(f"config.{name}: {e}") from e


def _positive(config, *names: str) -> None:
    for name in names:
        if config[name] <= 0:
            raise ConfigError(f"config.{name} must be positive, got {config[name]}")


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


def _mesh_devices(num_devices: int, num_processes: int) -> tuple:
    """All devices (num_devices = -1) or the first N local ones (single process only)."""
    if num_devices == -1:
        return tuple(jax.devices())
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
    raise ConfigError(f"config.loss.self_supervision_crop={crop}: the student's crop of the {height}x{width} working "
                      f"size is {height - 2 * crop}x{width - 2 * crop}, not a working size of model {name} (2 * crop "
                      f"must be a multiple of {multiple} and leave a big enough size); {hint}")


def parse(config: ml_collections.ConfigDict, *, devices: Optional[Sequence] = None,
          num_processes: Optional[int] = None) -> Run:
    """Check a training config and return its `Run` (raises ConfigError naming the option).

    `devices`: the devices to shard over; None (the trainer) = `config.num_devices` of this process's view,
    after joining the cluster of a multi-host config (`config.distributed`).
    """
    if isinstance(config, Run):
        return config
    try:
        model_values = _section(config, "model")
        data_values = _section(config, "data")
        loss_values = _section(config, "loss")
        eval_values = _section(config, "eval")
        distributed = _typed(DistributedConfig, _section(config, "distributed"), "distributed")
        optimizer_values = {f.name: config[f.name] for f in dataclasses.fields(OptimizerConfig)}
        optimizer_values["lr_milestones"] = tuple(int(m) for m in optimizer_values["lr_milestones"])
        fields = {name: config[name] for name in (
            "height", "width", "global_batch", "seed", "dtype", "remat", "conv_weight_grad", "separate_networks",
            "micro_batch",
            "steps_per_epoch", "num_epochs", "num_train_steps", "init_from", "compilation_cache_dir", "num_devices",
            "eval_every", "image_every", "checkpoint_every", "keep_checkpoints", "async_checkpoints", "log_every",
            "progress_bar", "max_nonfinite_in_row")}
    except (AttributeError, KeyError) as e:
        raise ConfigError(f"the config has no field {e} (configs are built from bridge_jax/configs/default.py)") from e

    try:
        model_cfg = models.model_config(model_values)
    except ValueError as e:
        raise ConfigError(f"config.model: {e}") from e
    try:
        models.check_working_size(model_cfg["name"], fields["height"], fields["width"], "config.height/config.width")
    except ValueError as e:
        raise ConfigError(str(e)) from e
    if fields["dtype"] not in COMPUTE_DTYPES:
        raise ConfigError(f"config.dtype must be one of {sorted(COMPUTE_DTYPES)}, got {fields['dtype']!r}")
    if fields["remat"] not in REMAT_POLICIES:
        raise ConfigError(f"config.remat must be one of {sorted(REMAT_POLICIES)}, got {fields['remat']!r}")
    if fields["conv_weight_grad"] not in WEIGHT_GRAD_METHODS:
        raise ConfigError(f"config.conv_weight_grad must be one of {list(WEIGHT_GRAD_METHODS)}, got "
                          f"{fields['conv_weight_grad']!r}")
    try:
        loss_cfg = losses.LossConfig.from_dict(loss_values)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"config.loss: {e}") from e
    if loss_cfg.self_supervision > 0:
        _check_self_supervision_crop(model_cfg["name"], int(fields["height"]), int(fields["width"]),
                                     loss_cfg.self_supervision_crop)
    data = _typed(DataConfig, data_values, "data")
    try:
        optimizer = OptimizerConfig(**optimizer_values)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"config.{e}") from e
    if not isinstance(fields["compilation_cache_dir"], str):
        raise ConfigError(f"config.compilation_cache_dir must be a folder, 'auto' or '' (off), got "
                          f"{fields['compilation_cache_dir']!r}")
    if fields["steps_per_epoch"] == 0 or fields["num_train_steps"] == 0:
        raise ConfigError("config.steps_per_epoch and config.num_train_steps must be positive (or -1 = derived)")
    _positive(config, "checkpoint_every", "keep_checkpoints", "log_every", "max_nonfinite_in_row")
    eval_cfg = _typed(EvalConfig, dict(eval_values, every=int(fields["eval_every"]),
                                       image_every=int(fields["image_every"])), "eval")

    if devices is None:
        _initialize_distributed(distributed)
        nproc = jax.process_count() if num_processes is None else num_processes
        devices = _mesh_devices(int(fields["num_devices"]), nproc)
    else:
        nproc = 1 if num_processes is None else num_processes
    devices = tuple(devices)
    num_devices, batch = len(devices), int(fields["global_batch"])
    if batch <= 0:
        raise ConfigError(f"config.global_batch must be positive, got {batch}")
    if batch % num_devices:
        raise ConfigError(f"config.global_batch={batch} is not divisible by the {num_devices} devices (batch is "
                          f"sharded over devices); use a multiple of {num_devices}")
    if batch % nproc:
        raise ConfigError(f"config.global_batch={batch} is not divisible by the {nproc} processes")
    rows_per_device = batch // num_devices * cycle.rows_per_cycle(loss_cfg.pairs)
    micro_batch = int(fields["micro_batch"])
    if micro_batch < -1 or (micro_batch > 0 and rows_per_device % micro_batch):
        raise ConfigError(f"config.micro_batch={micro_batch} must be 0 (no micro-batching), -1 (auto) or divide the "
                          f"{rows_per_device} pair-forwards per device")

    return Run(
        model=ModelSpec(model_cfg, bool(fields["separate_networks"]), str(fields["dtype"]), str(fields["remat"]),
                        str(fields["conv_weight_grad"])),
        loss=loss_cfg, optimizer=optimizer, data=data, eval=eval_cfg,
        loop=LoopConfig(int(fields["checkpoint_every"]), int(fields["keep_checkpoints"]),
                        bool(fields["async_checkpoints"]), int(fields["log_every"]), bool(fields["progress_bar"]),
                        int(fields["max_nonfinite_in_row"])),
        distributed=distributed, height=int(fields["height"]), width=int(fields["width"]), global_batch=batch,
        seed=int(fields["seed"]), devices=devices, num_processes=nproc,
        micro_batch=resolve_micro_batch(micro_batch, rows_per_device, devices[0].platform),
        steps_per_epoch=int(fields["steps_per_epoch"]), num_epochs=int(fields["num_epochs"]),
        num_train_steps=int(fields["num_train_steps"]), init_from=str(fields["init_from"]),
        compilation_cache_dir=fields["compilation_cache_dir"],
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
                                batch_sharding=batch_sharding)
    return make_train_step(net, run.loss, tx, schedule, state_sharding=state_sharding, batch_sharding=batch_sharding)
