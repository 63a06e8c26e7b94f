"""Train state, optimiser and the training step.

The train state is a plain pytree

    {"params": ..., "opt_state": ..., "step": int32 (), "rng": uint32 (2,)}

(plus "ema_params", the exponential moving average of the params, when `OptimizerConfig.ema_decay` > 0)

and one training step on a batch of cycles (B, 4, H, W, 3) float32 in [0, 1] (`train_step`) is:

1. the B * 2P ordered pair inputs (`cycle.batch_pair_inputs`; P = 4 pairs for flow+stereo),
2. the network on all of them (forward and backward maps, 4 scales),
3. the cycle loss (`losses.cycle_loss`, vmapped over cycles) and its gradient (with self-supervision on, the
   network also runs on the cropped cycles: `student_inputs`),
4. Adam with the step-based MultiStepLR schedule,
5. with `ema_decay` > 0, the moving average of the new params (`ema_update`), and
6. a guard: a non-finite loss, gradient, update or new parameter leaves the state unchanged (the step is "skipped").

`make_train_step` jits it once per input shape with the state donated (the default on GPU/TPU);
`bridge_jax.micro_batch` computes the same update maps-first in small jitted pieces for XLA:CPU, and
`setup.build_step` picks one of the two for a run.
"""

from __future__ import annotations

import collections
import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import optax
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import cycle, losses
from bridge_jax.network import Network

# How often each jitted function was traced, by name. Tests use it to prove there is exactly one trace per
# input shape (a retrace on every step would be a silent 10x slowdown).
TRACE_COUNTS: collections.Counter = collections.Counter()


def count_trace(name: str) -> None:
    TRACE_COUNTS[name] += 1


# ##########################################################################################################
# Optimiser
# ##########################################################################################################

@dataclasses.dataclass(frozen=True)
class OptimizerConfig:
    """Adam and its step-based learning-rate schedule (upstream: 1e-4, betas (0.9, 0.999), eps 1e-8, no weight
    decay, the rate multiplied by `lr_decay` at the start of each epoch in `lr_milestones`)."""

    lr: float = 1e-4  # Adam learning rate
    lr_milestones: tuple[int, ...] = (4, 7, 10, 13)  # epochs at whose start the lr is multiplied by lr_decay
    lr_decay: float = 0.5  # lr factor at each milestone
    adam_b1: float = 0.9  # Adam beta1
    adam_b2: float = 0.999  # Adam beta2
    adam_eps: float = 1e-8  # Adam epsilon
    # Clip the gradient to this global L2 norm before Adam (0 = off, the paper). Beyond the paper: large
    # early gradients of a correlation model can otherwise throw its maps far from zero motion.
    clip_grad_norm: float = 0.0  # clip the gradient to this global L2 norm (0 = off, the paper)
    # Beyond the paper: keep an exponential moving average of the params (`ema_update`) and let it stand for the
    # model (every reader of a checkpoint, validation, the next stage of a recipe). 0 = off.
    ema_decay: float = 0.0  # decay of the params' moving average (e.g. 0.99); 0 = no average


    def __post_init__(self):
        if not (isinstance(self.lr, (int, float)) and math.isfinite(self.lr) and self.lr > 0):
            raise ValueError(f"lr must be a finite number > 0, got {self.lr!r}")
        if not self.clip_grad_norm >= 0:
            raise ValueError(f"clip_grad_norm must be >= 0 (0 = off), got {self.clip_grad_norm!r}")
        if not 0 <= self.ema_decay < 1:
            raise ValueError(f"ema_decay must be in [0, 1) (0 = off), got {self.ema_decay!r}")


def lr_schedule(opt: OptimizerConfig, steps_per_epoch: int) -> optax.Schedule:
    """Step-based equivalent of upstream's MultiStepLR (stepped at the start of each epoch).

    lr(step) = opt.lr * lr_decay ** #{m in lr_milestones : step >= m * steps_per_epoch}; with the paper's
    settings 1e-4 for epochs 0-3, 5e-5 for 4-6, 2.5e-5 for 7-9, 1.25e-5 for 10-12, 6.25e-6 from epoch 13.
    """
    if steps_per_epoch <= 0:
        raise ValueError(f"steps_per_epoch must be positive, got {steps_per_epoch}")
    boundaries: dict[int, float] = {}
    for m in opt.lr_milestones:  # milestones in the same epoch multiply
        b = int(m) * int(steps_per_epoch)
        boundaries[b] = boundaries.get(b, 1.0) * float(opt.lr_decay)
    return optax.piecewise_constant_schedule(float(opt.lr), boundaries)


def make_optimizer(opt: OptimizerConfig, steps_per_epoch: int):
    """(Adam with `lr_schedule`, preceded by global-norm clipping when `opt.clip_grad_norm` > 0; the schedule)."""
    schedule = lr_schedule(opt, steps_per_epoch)
    adam = optax.adam(schedule, b1=opt.adam_b1, b2=opt.adam_b2, eps=opt.adam_eps)
    if opt.clip_grad_norm > 0:
        return optax.chain(optax.clip_by_global_norm(float(opt.clip_grad_norm)), adam), schedule
    return adam, schedule


# ##########################################################################################################
# Train state and the update
# ##########################################################################################################

def create_train_state(params, tx, rng, *, ema: bool = False) -> dict:
    """The train state pytree; params are float32 (also under bf16 compute). With `ema`, "ema_params" starts as
    a copy of the params.

    Built by one jitted function: run eagerly, the optimiser's per-leaf zeros compiled one small XLA program per
    parameter shape (~0.7 s of every training start on 2 cores)."""

    def build(params, rng):
        params = jax.tree.map(lambda p: jnp.asarray(p, jnp.float32), params)
        state = {"params": params, "opt_state": tx.init(params), "step": jnp.zeros((), jnp.int32),
                 "rng": jnp.asarray(rng, jnp.uint32)}
        if ema:
            state["ema_params"] = jax.tree.map(jnp.copy, params)
        return state

    return jax.jit(build)(params, rng)


def ema_rate(step, decay: float):
    """The weight of the old average at update number `step` (0-based): decay (1 - decay^step) / (1 - decay^(step+1)).

    This is the bias-corrected moving average (as `optax.ema(debias=True)`): after T updates the average is
    sum_t decay^(T-t) p_t / sum_t decay^(T-t) over the params p_1 .. p_T after each update, so the params a run
    started from get no weight (rate 0 at the first update) and the average spans about 1 / (1 - decay) updates
    however long the run is."""
    step = jnp.asarray(step, jnp.float32)
    d = jnp.float32(decay)
    return d * (1.0 - d ** step) / (1.0 - d ** (step + 1.0))


def ema_update(ema_params, new_params, step, decay: float):
    """ema <- r * ema + (1 - r) * new params, r = `ema_rate(step, decay)`; `step` = the update's number before
    it is applied (the state's "step")."""
    r = ema_rate(step, decay)
    return jax.tree.map(lambda e, p: r * e + (1.0 - r) * p, ema_params, new_params)


def model_params(state: dict):
    """The params that stand for the model of a train state: the moving average when the state keeps one."""
    return state.get("ema_params", state["params"])


def apply_gradients(state: dict, loss, terms: dict, grads, tx, schedule, ema_decay: float = 0.0):
    """Adam update (and, when the state keeps "ema_params", their `ema_update` with `ema_decay`) with the
    non-finite guard. Returns (new_state, metrics).

    If the loss, the gradient, the update or the new params hold a NaN/Inf the returned state equals `state`
    (nothing moves, not even `step` or the optimiser's moments) and metrics["nonfinite"] = 1. Checking the
    update and the new params too matters: finite gradients can still give a poisoned update (an infinite
    learning rate, an overflowing step), and a NaN state once accepted is saved as "good".

    The test is on the global L2 norms the metrics report anyway (a norm is NaN/Inf exactly when some element
    is, or when the values are beyond ~1e19, far past any usable weights): per-leaf `isfinite` reductions over
    the four trees made XLA:CPU compile the paper's full2 step in 161 s instead of 38 s.
    """
    params, opt_state = state["params"], state["opt_state"]
    updates, new_opt_state = tx.update(grads, opt_state, params)
    new_params = optax.apply_updates(params, updates)
    grad_norm, update_norm = optax.tree.norm(grads), optax.tree.norm(updates)
    ok = (jnp.isfinite(loss) & jnp.isfinite(grad_norm) & jnp.isfinite(update_norm)
          & jnp.isfinite(optax.tree.norm(new_params)))
    new_state = {"params": new_params, "opt_state": new_opt_state, "step": state["step"] + 1,
                 "rng": jax.random.fold_in(state["rng"], 0)}
    if "ema_params" in state:
        if not 0 < ema_decay < 1:
            raise ValueError(f"the train state keeps ema_params but ema_decay={ema_decay!r} (expected 0 < decay < 1)")
        new_state["ema_params"] = ema_update(state["ema_params"], new_params, state["step"], ema_decay)
    new_state = jax.tree.map(lambda new, old: jnp.where(ok, new, old), new_state, state)
    metrics = {"loss": loss, **{f"loss/{k}": v for k, v in terms.items()},
               "grad_norm": grad_norm, "param_norm": optax.tree.norm(new_state["params"]),
               "update_norm": jnp.where(ok, update_norm, 0.0),
               "lr": schedule(state["step"]), "nonfinite": (~ok).astype(jnp.int32)}
    return new_state, metrics


def crop_key(rng):
    """The PRNG key of a step's self-supervision crop windows, from the state's `rng` (independent of the
    `fold_in(rng, 0)` the next state gets)."""
    return None if rng is None else jax.random.fold_in(rng, 1)


def student_inputs(cycles, loss_cfg: losses.LossConfig, rng=None):
    """(pair inputs of the cropped cycles (B * 2P, H - 2c, W - 2c, 6), crop offsets (B, 2)) of the
    self-supervision student: a random window per cycle from `rng` (the state's), the centre one when None."""
    c = loss_cfg.self_supervision_crop
    offsets = losses.self_supervision_offsets(cycles.shape[0], c, crop_key(rng))
    return cycle.batch_pair_inputs(losses.crop_cycles(cycles, offsets, c), loss_cfg.pairs), offsets


def loss_and_grads(params, cycles, *, net: Network, loss_cfg: losses.LossConfig, step=None, rng=None):
    """((loss, terms), d loss / d params) of a batch of cycles (B, 4, H, W, 3), the whole batch at once; `step`
    (int32 scalar) is the training step the loss's step-dependent switches read. With self-supervision on
    (`loss_cfg.self_supervision > 0`) the network also runs on the cropped cycles (`student_inputs`; `rng` = the
    state's, None = centre crops) and the loss compares those maps with the full-frame ones."""
    x = cycle.batch_pair_inputs(cycles, loss_cfg.pairs)
    tasks = cycle.row_tasks(loss_cfg.pairs, x.shape[0])
    student = loss_cfg.self_supervision > 0
    if student:
        x_crop, offsets = student_inputs(cycles, loss_cfg, rng)

    def objective(p):
        s = losses.Student(net(p, x_crop, tasks)["px"][0], offsets) if student else None
        return losses.cycle_loss(net(p, x, tasks), cycles, loss_cfg, step=step, student=s)

    return jax.value_and_grad(objective, has_aux=True)(params)


def train_step(state: dict, cycles, *, net: Network, loss_cfg: losses.LossConfig, tx, schedule,
               ema_decay: float = 0.0):
    """One training step: `(state, cycles (B, 4, H, W, 3)) -> (new_state, metrics)` (a pure function)."""
    count_trace("train_step")
    (loss, terms), grads = loss_and_grads(state["params"], cycles, net=net, loss_cfg=loss_cfg, step=state["step"],
                                          rng=state["rng"])
    return apply_gradients(state, loss, terms, grads, tx, schedule, ema_decay)


def make_train_step(net: Network, loss_cfg: losses.LossConfig, tx, schedule, *, state_sharding=None,
                    batch_sharding=None, ema_decay: float = 0.0):
    """`train_step` jitted (one compilation per input shape) with the state donated, optionally sharded: the
    state as `state_sharding`, the batch as `batch_sharding`, the metrics replicated."""
    fn = functools.partial(train_step, net=net, loss_cfg=loss_cfg, tx=tx, schedule=schedule, ema_decay=ema_decay)
    kw = {}
    if state_sharding is not None:
        replicated = NamedSharding(sharding_mesh(state_sharding), P())
        kw = dict(in_shardings=(state_sharding, batch_sharding), out_shardings=(state_sharding, replicated))
    return jax.jit(fn, donate_argnums=(0,), **kw)


def sharding_mesh(sharding_tree) -> jax.sharding.Mesh:
    """The mesh of a pytree of NamedShardings."""
    return jax.tree.leaves(sharding_tree)[0].mesh


__all__ = ["TRACE_COUNTS", "OptimizerConfig", "lr_schedule", "make_optimizer", "create_train_state",
           "ema_rate", "ema_update", "model_params", "apply_gradients", "crop_key", "student_inputs",
           "loss_and_grads", "train_step", "make_train_step",
           "sharding_mesh"]
