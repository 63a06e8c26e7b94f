r"""Paper settings: the flow+stereo model of Lai et al. (CVPR 2019) without 2-warp terms.

ResNet-50 Monodepth network shared by stereo and flow, 512x256 working size, 2 cycles per step (16
pair-forwards), Adam 1e-4 halved at the starts of epochs 4, 7, 10 and 13 (upstream MultiStepLR; the paper
says "every 3 epochs, 5 times"), 80 epochs, lambda_sm 10, lambda_lr 0.5. Data: the built-in synthetic stereo
video unless `--config.data.source` says otherwise.

    bridge-train --config=bridge_jax/configs/default.py --workdir=work/default

    # KITTI raw cycles instead of the synthetic video:
    bridge-train --config=bridge_jax/configs/default.py --workdir=work/kitti \
            --config.data.source=kitti_raw --config.data.data_dir=$HOME/kitti_raw

The optional argument `:local` shrinks everything for a quick laptop smoke run.
"""

import dataclasses

import ml_collections

from bridge_jax import losses, models
from bridge_jax.data.pipeline import DataConfig
from bridge_jax.setup import DistributedConfig, EvalConfig, LoopConfig, RunOptions
from bridge_jax.train_step import OptimizerConfig

# Upstream's KITTI-split list has 28,968 cycles; at 2 cycles a step that is one epoch. The synthetic video
# is endless, so this only fixes the epoch length the learning-rate schedule counts in.
KITTI_SPLIT_CYCLES = 28968


def model_section(name: str) -> ml_collections.ConfigDict:
    """models.model_config(name) as a ConfigDict; lists become tuples so that the command line can override
    them (`--config.model.planes='(16, 32, 64, 64)'`)."""
    cfg = models.model_config(name)
    return ml_collections.ConfigDict({k: tuple(v) if isinstance(v, list) else v for k, v in cfg.items()})


def get_config(arg=None):
    """Returns the paper's default training config (see module docstring)."""
    c = ml_collections.ConfigDict()
    # Every section is its dataclass's fields with their defaults (`bridge-train --list-config` prints them with
    # their meanings); a section's own settings here differ from those defaults on purpose.

    # Top level: working size, batch, seed, devices, compute (setup.RunOptions). `separate_networks` = the
    # paper's "without sharing weights" ablation. `remat`: same gradients; on XLA:CPU neither policy saved memory
    # (measured with bridge-bench), on accelerators it can. `conv_weight_grad` "auto" = on XLA:CPU one matmul per
    # kernel tap where that is faster than XLA's own backward (>= 64 input channels) and XLA's in batch chunks for
    # the 7x7 stem, XLA's elsewhere and on GPU/TPU; same gradients to float32 rounding. `micro_batch` -1 = auto: 2
    # on CPU, where a Python loop of small jitted calls is faster and much leaner than one big jit, 0 elsewhere.
    # `compilation_cache_dir` "auto" (the per-user folder of every command, bridge_jax.compile_cache) lets a
    # resumed run (after SIGTERM, preemption or a crash) or the next run of the same shapes reuse the compiled
    # train step; "workdir" keeps it in <workdir>/xla_cache; JAX_COMPILATION_CACHE_DIR, if set, wins.
    c.update(dataclasses.asdict(RunOptions()))

    # Network: every key of models.model_config (so any of them can be overridden from the command line).
    c.model = model_section("resnet_md")

    # Loss: every field of losses.LossConfig, with its defaults (the paper's choices; each paper/upstream
    # difference is a switch there). Type 0 = no 2-warp term = the "flow+stereo" model.
    c.loss = ml_collections.ConfigDict(dataclasses.asdict(losses.LossConfig()))

    # Data: every field of data.pipeline.DataConfig. The default source is the built-in synthetic stereo video
    # (procedural, exact ground truth); data_dir/split are for kitti_raw | folder | tfds.
    c.data = ml_collections.ConfigDict(dataclasses.asdict(DataConfig()))

    # Optimisation: every field of train_step.OptimizerConfig (Adam lr, adam_b1/b2/eps; lr_milestones = epochs at
    # whose start the lr is multiplied by lr_decay), at the top level.
    c.update(dataclasses.asdict(OptimizerConfig()))

    # Steps, logging, checkpoints and when to validate (setup.LoopConfig). One epoch = upstream's KITTI split.
    c.loop = ml_collections.ConfigDict(dataclasses.asdict(LoopConfig(steps_per_epoch=KITTI_SPLIT_CYCLES // 2)))
    # Held-out validation set (setup.EvalConfig): base seed disjoint from training's `seed`.
    c.eval = ml_collections.ConfigDict(dataclasses.asdict(EvalConfig()))
    # Multi-host (setup.DistributedConfig): call jax.distributed.initialize() first.
    c.distributed = ml_collections.ConfigDict(dataclasses.asdict(DistributedConfig()))

    if arg == "local":
        local(c)
    elif arg:
        raise ValueError(f"default.py: unknown config argument {arg!r} (expected nothing or 'local')")
    return c


def local(c):
    """Shrinks a config for a minutes-long CPU smoke run (the `:local` argument of every config)."""
    c.model = model_section("resnet_md_tiny")
    c.height, c.width = 128, 256
    c.loop.update(num_train_steps=20, steps_per_epoch=5, checkpoint_every=10, log_every=1, image_every=10,
                  eval_every=10)
    c.eval.num_samples = 4
    return c


def variant(name, arg, **loss_overrides):
    """The default config with other loss settings (used by the variant files; `name` is the file's name)."""
    c = get_config(None)
    c.loss.update(loss_overrides)
    if arg == "local":
        local(c)
    elif arg:
        raise ValueError(f"{name}.py: unknown config argument {arg!r} (expected nothing or 'local')")
    return c
