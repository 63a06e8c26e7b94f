"""Train state, optimiser and the jitted training step (plain and maps-first micro-batched).

The train state is a plain pytree

    {"params": ..., "opt_state": ..., "step": int32 (), "rng": uint32 (2,)}

and one training step on a batch of cycles (B, 4, H, W, 3) float32 in [0, 1] is:

1. build the B * 2P ordered pair inputs (cycle.batch_pair_inputs; P = 4 pairs for flow+stereo),
2. run the network on all of them (forward and backward maps, 4 scales),
3. the cycle loss vmapped over cycles (losses.batch_cycle_loss),
4. gradients, Adam with the step-based MultiStepLR schedule, and
5. a guard: a non-finite loss or gradient leaves the state unchanged (the step is "skipped").

`make_train_step` returns that as one `jax.jit` function with the state donated (the default, best on
GPU/TPU). `MicroBatchedStep` computes exactly the same update maps-first for XLA:CPU, where a Python loop
of small jitted calls is both faster and much leaner than one big jit (and `lax.scan` is very slow, see
notes/xla-cpu-performance.md): since the losses couple all maps of a cycle (occlusion masks, left-right
consistency, 2-warp), it first runs the network per micro-batch to get every map, takes the gradient of the
loss with respect to the maps, then re-runs each micro-batch under `jax.vjp` with those cotangents and sums
the parameter gradients into a donated accumulator.
"""

from __future__ import annotations

import collections
import dataclasses
from typing import Any, Callable, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import cycle

# How often each jitted function was traced, by name. Tests use it to prove there is exactly one trace per
# input shape (a retrace on every step would be a silent 10x slowdown).
TRACE_COUNTS: collections.Counter = collections.Counter()


def _count_trace(name: str) -> None:
    TRACE_COUNTS[name] += 1


# ---------------------------------------------------------------------------------------------------------
# Optimiser
# ---------------------------------------------------------------------------------------------------------

def lr_schedule(config, steps_per_epoch: int) -> optax.Schedule:
    """Step-based equivalent of upstream's MultiStepLR (stepped at the start of each epoch).

    lr(step) = config.lr * lr_decay ** #{m in lr_milestones : step >= m * steps_per_epoch}; with the paper's
    settings 1e-4 for epochs 0-3, 5e-5 for 4-6, 2.5e-5 for 7-9, 1.25e-5 for 10-12, 6.25e-6 from epoch 13.
    """
    if steps_per_epoch <= 0:
        raise ValueError(f"steps_per_epoch must be positive, got {steps_per_epoch}")
    boundaries = {}
    for m in config.lr_milestones:
        b = int(m) * int(steps_per_epoch)
        boundaries[b] = boundaries.get(b, 1.0) * float(config.lr_decay)
    base = float(config.lr)

    def schedule(step):
        lr = jnp.asarray(base, jnp.float32)
        for b, scale in sorted(boundaries.items()):
            lr = jnp.where(step >= b, lr * scale, lr)
        return lr

    return schedule


def make_optimizer(config, steps_per_epoch: int):
    """Adam (upstream: 1e-4, betas (0.9, 0.999), eps 1e-8, no weight decay) with `lr_schedule`."""
    schedule = lr_schedule(config, steps_per_epoch)
    tx = optax.adam(schedule, b1=config.adam_b1, b2=config.adam_b2, eps=config.adam_eps)
    return tx, schedule


# ---------------------------------------------------------------------------------------------------------
# Network: shared or separate (paper's "without sharing weights") stereo/flow networks
# ---------------------------------------------------------------------------------------------------------

def row_is_stereo(pairs: Sequence[int], num_rows: int, offset: int = 0) -> tuple[bool, ...]:
    """Which of `num_rows` consecutive pair-input rows (starting at cycle-row `offset`) are stereo pairs.

    Rows follow cycle.batch_pair_inputs: per cycle 2P rows, the P forward rows of `pairs` then the P
    backward rows.
    """
    p = len(pairs)
    return tuple(cycle.IS_STEREO[pairs[(offset + i) % (2 * p) % p]] for i in range(num_rows))


@dataclasses.dataclass(frozen=True)
class Network:
    """The function pair inputs -> maps used by training.

    `apply_fn(graphdef, params, x (N, H, W, 6), dtype=...) -> maps` is bridge_jax.models.apply. With
    `separate=True` params are {"stereo": ..., "flow": ...} and each row goes through the network of its
    task (which rows are stereo is static: `is_stereo`).
    """

    apply_fn: Callable
    graphdef: Any
    separate: bool = False
    dtype: Any = None

    def __call__(self, params, x, is_stereo: Sequence[bool]):
        """x: (N, H, W, 6) float32 pair inputs -> maps {"px": 4 x (N, h, w, 2), "frac": ...} float32."""
        if not self.separate:
            return self._one(params, x)
        is_stereo = np.asarray(is_stereo, bool)
        if is_stereo.shape != (x.shape[0],):
            raise ValueError(f"is_stereo has {is_stereo.shape} entries for {x.shape[0]} rows")
        idx_s, idx_f = np.nonzero(is_stereo)[0], np.nonzero(~is_stereo)[0]
        parts, order = [], []
        if idx_s.size:
            parts.append(self._one(params["stereo"], x[idx_s]))
            order.append(idx_s)
        if idx_f.size:
            parts.append(self._one(params["flow"], x[idx_f]))
            order.append(idx_f)
        if len(parts) == 1:
            return parts[0]
        inverse = np.argsort(np.concatenate(order))
        return jax.tree.map(lambda a, b: jnp.concatenate([a, b], axis=0)[inverse], parts[0], parts[1])

    def _one(self, params, x):
        if self.dtype is not None and self.dtype != jnp.float32:
            maps = self.apply_fn(self.graphdef, params, x.astype(self.dtype), dtype=self.dtype)
        else:
            maps = self.apply_fn(self.graphdef, params, x)
        return jax.tree.map(lambda m: m.astype(jnp.float32), maps)


# ---------------------------------------------------------------------------------------------------------
# Train state and the update (shared by both step variants)
# ---------------------------------------------------------------------------------------------------------

def create_train_state(params, tx, rng) -> dict:
    """The train state pytree; params are float32 (also under bf16 compute)."""
    params = jax.tree.map(lambda p: jnp.asarray(p, jnp.float32), params)
    return {"params": params, "opt_state": tx.init(params), "step": jnp.zeros((), jnp.int32),
            "rng": jnp.asarray(rng, jnp.uint32)}


def _all_finite(tree) -> jax.Array:
    leaves = jax.tree.leaves(tree)
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(x)) for x in leaves])) if leaves else jnp.array(True)


def apply_gradients(state: dict, loss, terms: dict, grads, tx, schedule):
    """Adam update with the non-finite guard. Returns (new_state, metrics).

    If the loss or any gradient is NaN/Inf the returned state equals `state` (nothing moves, not even
    `step` or the optimiser's moments) and metrics["nonfinite"] = 1.
    """
    ok = jnp.isfinite(loss) & _all_finite(grads)
    params, opt_state = state["params"], state["opt_state"]
    updates, new_opt_state = tx.update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    new_state = {"params": new_params, "opt_state": new_opt_state, "step": state["step"] + 1,
                 "rng": jax.random.fold_in(state["rng"], 0)}
    new_state = jax.tree.map(lambda new, old: jnp.where(ok, new, old), new_state, state)
    metrics = {"loss": loss, **{f"loss/{k}": v for k, v in terms.items()},
               "grad_norm": optax.tree.norm(grads), "param_norm": optax.tree.norm(new_state["params"]),
               "update_norm": jnp.where(ok, optax.tree.norm(updates), 0.0),
               "lr": schedule(state["step"]), "nonfinite": (~ok).astype(jnp.int32)}
    return new_state, metrics


def _loss_fn(loss_module, loss_cfg):
    def fn(maps, cycles):
        total, terms = loss_module.batch_cycle_loss(maps, cycles, loss_cfg)
        return total, terms
    return fn


# ---------------------------------------------------------------------------------------------------------
# The plain step: everything in one jit
# ---------------------------------------------------------------------------------------------------------

def make_loss_and_grads(net: Network, loss_module, loss_cfg, pairs: Sequence[int]):
    """Jitted `(params, cycles) -> ((loss, terms), grads)` of the whole batch in one go (the plain step's core)."""
    pairs = tuple(pairs)
    loss_fn = _loss_fn(loss_module, loss_cfg)

    def fn(params, cycles):
        x = cycle.batch_pair_inputs(cycles, pairs)
        is_stereo = row_is_stereo(pairs, x.shape[0])
        return jax.value_and_grad(lambda p: loss_fn(net(p, x, is_stereo), cycles), has_aux=True)(params)

    return jax.jit(fn)


def make_train_step(net: Network, loss_module, loss_cfg, pairs: Sequence[int], tx, schedule, *,
                    state_sharding=None, batch_sharding=None):
    """One jitted step `(state, cycles (B, 4, H, W, 3)) -> (new_state, metrics)`; `state` is donated."""
    pairs = tuple(pairs)
    loss_fn = _loss_fn(loss_module, loss_cfg)

    def step(state, cycles):
        _count_trace("train_step")
        x = cycle.batch_pair_inputs(cycles, pairs)
        is_stereo = row_is_stereo(pairs, x.shape[0])

        def objective(params):
            maps = net(params, x, is_stereo)
            return loss_fn(maps, cycles)

        (loss, terms), grads = jax.value_and_grad(objective, has_aux=True)(state["params"])
        return apply_gradients(state, loss, terms, grads, tx, schedule)

    kw = {}
    if state_sharding is not None:
        replicated = NamedSharding(state_sharding_mesh(state_sharding), P())
        kw = dict(in_shardings=(state_sharding, batch_sharding), out_shardings=(state_sharding, replicated))
    return jax.jit(step, donate_argnums=(0,), **kw)


def state_sharding_mesh(state_sharding):
    return jax.tree.leaves(state_sharding)[0].mesh


# ---------------------------------------------------------------------------------------------------------
# The maps-first micro-batched step (XLA:CPU)
# ---------------------------------------------------------------------------------------------------------

class MicroBatchedStep:
    """Same update as `make_train_step`, network run in micro-batches of `micro_batch` rows per device.

    Rows are split per device so that every micro-batch stays evenly sharded over the ('data',) mesh:
    with D devices each holding L = B * 2P / D rows, micro-batch m is rows [m*k, (m+1)*k) of every device's
    shard (k = micro_batch). Cost: one extra network forward per step; memory: activations of one
    micro-batch plus all maps.

    Calls, in order (each its own jit, driven from Python):
      split(cycles) -> M pair-input micro-batches;   forward(params, x_m) -> maps_m (M times);
      loss_and_map_grads(maps_1..M, cycles) -> loss, terms, d loss / d maps_m;
      zeros(params) -> accumulator;   accumulate(acc, params, x_m, dmaps_m) (M times, acc donated);
      update(state, acc, loss, terms) -> (new_state, metrics) (state and acc donated).
    """

    def __init__(self, net: Network, loss_module, loss_cfg, pairs: Sequence[int], tx, schedule, *,
                 micro_batch: int, num_devices: int = 1, state_sharding=None, batch_sharding=None):
        self.net, self.pairs, self.k, self.d = net, tuple(pairs), int(micro_batch), int(num_devices)
        if self.k <= 0:
            raise ValueError(f"micro_batch must be positive, got {micro_batch}")
        loss_fn = _loss_fn(loss_module, loss_cfg)
        rows = cycle.rows_per_cycle(self.pairs)
        d, k = self.d, self.k
        self.state_sharding = state_sharding
        if state_sharding is not None:
            mesh = state_sharding_mesh(state_sharding)
            rep = NamedSharding(mesh, P())
            param_sh = state_sharding["params"]
            data_sh = batch_sharding
        else:
            rep = param_sh = data_sh = None

        def jit(f, **kw):
            if state_sharding is None:
                kw.pop("in_shardings", None)
                kw.pop("out_shardings", None)
            return jax.jit(f, **kw)

        def num_micro(num_rows):
            local = num_rows // d
            if num_rows % d or local % k:
                raise ValueError(
                    f"micro_batch={k} must divide the pair-forwards per device ({num_rows} rows of "
                    f"{num_rows // rows} cycles over {d} devices = {num_rows / d:g} per device)")
            return local // k

        self._num_micro = num_micro

        def split(cycles):
            _count_trace("micro/split")
            x = cycle.batch_pair_inputs(cycles, self.pairs)
            m = num_micro(x.shape[0])
            x = x.reshape((d, m, k) + x.shape[1:])
            return tuple(x[:, i].reshape((d * k,) + x.shape[3:]) for i in range(m))

        def merge(parts):
            """Inverse of split's row order: M x (D*k, ...) -> (D*M*k, ...)."""
            m = len(parts)
            y = jnp.stack(parts)  # (M, D*k, ...)
            y = y.reshape((m, d, k) + y.shape[2:])
            y = jnp.swapaxes(y, 0, 1)
            return y.reshape((d * m * k,) + y.shape[3:])

        def is_stereo(i):
            pattern = row_is_stereo(self.pairs, k, offset=i * k)
            return pattern * d

        self._is_stereo = is_stereo

        def forward(params, x, i):
            _count_trace("micro/forward")
            return net(params, x, is_stereo(i))

        def loss_and_map_grads(maps_parts, cycles):
            _count_trace("micro/loss")

            def objective(parts):
                maps = jax.tree.map(lambda *p: merge(p), *parts)
                return loss_fn(maps, cycles)

            (loss, terms), dmaps = jax.value_and_grad(objective, has_aux=True)(maps_parts)
            return loss, terms, dmaps

        def zeros(params):
            _count_trace("micro/zeros")
            return jax.tree.map(jnp.zeros_like, params)

        def accumulate(acc, params, x, dmaps, i):
            _count_trace("micro/accumulate")
            _, vjp = jax.vjp(lambda p: net(p, x, is_stereo(i)), params)
            (g,) = vjp(dmaps)
            return jax.tree.map(jnp.add, acc, g)

        def update(state, grads, loss, terms):
            _count_trace("micro/update")
            return apply_gradients(state, loss, terms, grads, tx, schedule)

        # A shared network does not care which rows are stereo: one compiled forward for all micro-batches.
        self._split = jit(split, in_shardings=(data_sh,))
        self._forward = jit(forward, static_argnums=(2,)) if net.separate else jit(
            lambda p, x: forward(p, x, 0))
        self._loss = jit(loss_and_map_grads)
        self._zeros = jit(zeros, out_shardings=param_sh)
        acc_fn = accumulate if net.separate else (lambda acc, p, x, dm: accumulate(acc, p, x, dm, 0))
        self._accumulate = jit(acc_fn, donate_argnums=(0,), static_argnums=(4,) if net.separate else ())
        # Only the state is donated: the gradient accumulator has no output of its shape left to alias.
        self._update = jit(update, donate_argnums=(0,),
                           out_shardings=(state_sharding, rep) if state_sharding is not None else None)

    def loss_and_grads(self, params, cycles):
        """((loss, terms), grads) of the batch, computed maps-first in micro-batches."""
        xs = self._split(cycles)
        if self.net.separate:
            maps = [self._forward(params, x, i) for i, x in enumerate(xs)]
        else:
            maps = [self._forward(params, x) for x in xs]
        loss, terms, dmaps = self._loss(tuple(maps), cycles)
        del maps
        acc = self._zeros(params)
        for i, (x, dm) in enumerate(zip(xs, dmaps)):
            if self.net.separate:
                acc = self._accumulate(acc, params, x, dm, i)
            else:
                acc = self._accumulate(acc, params, x, dm)
        return (loss, terms), acc

    def __call__(self, state, cycles):
        """(state, cycles (B, 4, H, W, 3)) -> (new_state, metrics); `state` is donated like the plain step."""
        (loss, terms), grads = self.loss_and_grads(state["params"], cycles)
        return self._update(state, grads, loss, terms)


def build_step(net: Network, loss_module, loss_cfg, pairs, tx, schedule, *, micro_batch: int = 0,
               num_devices: int = 1, state_sharding=None, batch_sharding=None):
    """The plain jitted step (micro_batch == 0) or the maps-first micro-batched one."""
    if micro_batch:
        return MicroBatchedStep(net, loss_module, loss_cfg, pairs, tx, schedule, micro_batch=micro_batch,
                                num_devices=num_devices, state_sharding=state_sharding,
                                batch_sharding=batch_sharding)
    return make_train_step(net, loss_module, loss_cfg, pairs, tx, schedule, state_sharding=state_sharding,
                           batch_sharding=batch_sharding)
