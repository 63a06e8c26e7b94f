"""Shared set-up of the training tests: tiny configs and a persistent XLA compilation cache.

The cycle loss takes tens of seconds to compile on 2 cores; every test that builds the same step shape
reuses one compiled executable through JAX's persistent cache (also across the subprocess tests, which get
the same cache directory and 8 fake CPU devices through the environment).
"""

from __future__ import annotations

import functools
import os
import sys
import tempfile

import jax
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import configs, losses, models, network, train_step
from bridge_jax.configs import default
from bridge_jax.micro_batch import MicroBatchedStep

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CACHE_DIR = os.environ.get("BRIDGE_JAX_TEST_JAX_CACHE",
                           os.path.join(tempfile.gettempdir(), "bridge_jax_test_jax_cache"))
H, W = 64, 128


def enable_compilation_cache():
    """Turns on the persistent cache; returns a function restoring the previous settings."""
    names = ("jax_compilation_cache_dir", "jax_persistent_cache_min_compile_time_secs",
             "jax_persistent_cache_min_entry_size_bytes")
    old = {n: getattr(jax.config, n) for n in names}
    os.makedirs(CACHE_DIR, exist_ok=True)
    jax.config.update("jax_compilation_cache_dir", CACHE_DIR)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.5)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)

    def restore():
        for n, v in old.items():
            jax.config.update(n, v)

    return restore


def tiny_config(**overrides):
    """default.py:local shrunk to a few 64x128 steps of the tiny ResNet-MD (2 cycles on 2 devices), no validation.
    `overrides`: dotted keys; the fields of the `loop` section also by their own names."""
    c = default.get_config("local")
    c.height, c.width = H, W
    c.num_devices = 2  # of the 8 fake CPU devices: sharded, but a cheap step
    c.global_batch = 2
    c.micro_batch = 0
    c.loop.update(num_train_steps=4, steps_per_epoch=100, checkpoint_every=2, log_every=1, image_every=-1,
                  eval_every=-1, progress_bar=False)
    c.eval.num_samples = 2
    c.eval.batch = 2
    c.data.synthetic_num = 32
    c.data.prefetch = 0
    for key, value in overrides.items():
        key = configs.MOVED_KEYS.get(key, key)  # loop fields by their short names: tiny_config(num_train_steps=6)
        node = c
        *path, last = key.split(".")
        for p in path:
            node = node[p]
        node[last] = value
    return c


def subprocess_env(num_devices: int = 8) -> dict:
    """Environment for `python -m bridge_jax.train` subprocesses: CPU, N fake devices, shared compile cache."""
    env = dict(os.environ)
    env.update(JAX_PLATFORMS="cpu", JAX_NUM_CPU_DEVICES=str(num_devices), JAX_COMPILATION_CACHE_DIR=CACHE_DIR,
               JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0.5", JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0",
               PYTHONPATH=REPO + os.pathsep + env.get("PYTHONPATH", ""))
    return env


def train_cli(workdir: str, *overrides: str, config: str = "bridge_jax/configs/default.py:local") -> list[str]:
    """The command line of a tiny training run (same shapes as tiny_config)."""
    base = [f"--config.height={H}", f"--config.width={W}", "--config.num_devices=2", "--config.global_batch=2", "--config.micro_batch=0", "--config.loop.steps_per_epoch=100",
            "--config.loop.log_every=1", "--config.loop.image_every=-1", "--config.loop.eval_every=-1",
            "--config.loop.progress_bar=False", "--config.data.synthetic_num=32", "--config.data.prefetch=0"]
    return [sys.executable, "-m", "bridge_jax.train", f"--config={os.path.join(REPO, config)}",
            f"--workdir={workdir}", *base, *overrides]


def make_step(*, num_devices=None, micro_batch=0, lr=1e-3, separate=False, model="resnet_md_tiny", loss_cfg=None,
              dtype=None):
    """(state, step, net, loss_cfg, shardings) of a training step built from the library's pieces: the plain jitted
    step, or the micro-batched one with `micro_batch` rows per device; on a mesh of `num_devices` fake devices."""
    mcfg = models.model_config(model)
    lcfg = loss_cfg or losses.LossConfig()
    graphdef, params = network.init_params(jax.random.key(0), mcfg, separate)
    tx, schedule = train_step.make_optimizer(train_step.OptimizerConfig(lr=lr), 100)
    net = network.Network(graphdef, separate=separate, dtype=dtype)
    state = train_step.create_train_state(params, tx, jax.random.key_data(jax.random.key(2)))
    kw = {}
    if num_devices is not None:
        mesh = jax.make_mesh((num_devices,), ("data",), axis_types=(jax.sharding.AxisType.Auto,),
                             devices=jax.devices()[:num_devices])
        rep = NamedSharding(mesh, P())
        kw = dict(state_sharding=jax.tree.map(lambda _: rep, state), batch_sharding=NamedSharding(mesh, P("data")))
        state = jax.device_put(state, kw["state_sharding"])
    if micro_batch:
        step = MicroBatchedStep(net, lcfg, tx, schedule, micro_batch=micro_batch, num_devices=num_devices or 1, **kw)
    else:
        step = train_step.make_train_step(net, lcfg, tx, schedule, **kw)
    return state, step, net, lcfg, kw


def plain_loss_and_grads(net, loss_cfg):
    """The whole-batch `(params, cycles) -> ((loss, terms), grads)` of the plain step, jitted."""
    return jax.jit(functools.partial(train_step.loss_and_grads, net=net, loss_cfg=loss_cfg))
