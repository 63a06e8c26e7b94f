"""The maps-first micro-batched training step: the same update as `train_step.train_step`, for XLA:CPU.

On XLA:CPU a Python loop of small jitted calls is both faster and much leaner than one big jit of the whole
step, and `lax.scan` over micro-batches is very slow. The losses couple all maps of a cycle (occlusion masks,
left-right consistency, 2-warp), so the network cannot simply be run and differentiated micro-batch by
micro-batch. Instead, per step (`MicroBatchedStep.phases` lists them):

  split       the B * 2P pair inputs into M micro-batches of `micro_batch` rows per device;
  forward     the network on each micro-batch -> every map of the batch;
  loss        the cycle loss of the whole batch and its gradient with respect to the maps;
  accumulate  each micro-batch again under `jax.vjp`, pulled back with its maps' cotangents, summed into a
              donated gradient accumulator;
  update      Adam and the non-finite guard (`train_step.apply_gradients`), state donated.

Cost: one extra network forward per step; memory: the activations of one micro-batch plus all maps.

With self-supervision on (`LossConfig.self_supervision > 0`) the cropped cycles' pair inputs
(`train_step.student_inputs`) are split, forwarded (only their scale-0 pixel maps are kept), given cotangents by
the loss and pulled back the same way, in micro-batches of the same row count (a second shape of the forward and
accumulate phases).

Rows are split per device, so that every micro-batch stays evenly sharded over the ('data',) mesh: with D
devices each holding L = B * 2P / D rows, micro-batch m is rows [m*k, (m+1)*k) of every device's shard.
"""

from __future__ import annotations

import dataclasses
import functools
from collections.abc import Iterator
from typing import Any

import jax
import jax.numpy as jnp
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import cycle, losses
from bridge_jax.network import Network
from bridge_jax.train_step import apply_gradients, count_trace, sharding_mesh, student_inputs


@dataclasses.dataclass(frozen=True)
class MicroBatches:
    """How the pair-input rows of a batch are cut: `size` rows per device per call, `num_devices` devices."""

    size: int
    num_devices: int = 1
    pairs: tuple[int, ...] = tuple(range(4))

    def count(self, num_rows: int) -> int:
        """Micro-batches per step for `num_rows` pair inputs; ValueError if `size` does not divide them."""
        d, k = self.num_devices, self.size
        local = num_rows // d
        if num_rows % d or local % k:
            rows = cycle.rows_per_cycle(self.pairs)
            raise ValueError(
                f"micro_batch={k} must divide the pair-forwards per device ({num_rows} rows of "
                f"{num_rows // rows} cycles over {d} devices = {num_rows / d:g} per device)")
        return local // k

    def split(self, x) -> tuple:
        """(D*M*k, ...) rows -> M micro-batches of (D*k, ...), each holding k rows of every device's shard."""
        d, k = self.num_devices, self.size
        m = self.count(x.shape[0])
        x = x.reshape((d, m, k) + x.shape[1:])
        return tuple(x[:, i].reshape((d * k,) + x.shape[3:]) for i in range(m))

    def merge(self, parts):
        """Inverse of `split`: M x (D*k, ...) -> (D*M*k, ...)."""
        d, k = self.num_devices, self.size
        m = len(parts)
        y = jnp.stack(parts)  # (M, D*k, ...)
        y = y.reshape((m, d, k) + y.shape[2:])
        y = jnp.swapaxes(y, 0, 1)
        return y.reshape((d * m * k,) + y.shape[3:])

    def tasks(self, i: int) -> tuple[str, ...]:
        """The task of each row of micro-batch `i` (the same pattern on every device's shard)."""
        return cycle.row_tasks(self.pairs, self.size, offset=i * self.size) * self.num_devices


# ---------------------------------------------------------------------------------------------- the phases
def split(cycles, *, batches: MicroBatches):
    count_trace("micro/split")
    return batches.split(cycle.batch_pair_inputs(cycles, batches.pairs))


def split_student(cycles, rng, *, batches: MicroBatches, loss_cfg: losses.LossConfig):
    """(micro-batches of the self-supervision student's pair inputs, crop offsets (B, 2)); `rng` = the state's
    (None: centre crops)."""
    count_trace("micro/split_student")
    x, offsets = student_inputs(cycles, loss_cfg, rng)
    return batches.split(x), offsets


def forward(params, x, tasks, *, net: Network):
    """Maps of one micro-batch; `tasks` = `Network.static_tasks` of its rows (static)."""
    count_trace("micro/forward")
    return net(params, x, tasks)


def forward_student(params, x, tasks, *, net: Network):
    """The scale-0 pixel maps of one micro-batch of the student's cropped pair inputs."""
    count_trace("micro/forward_student")
    return net(params, x, tasks)["px"][0]


def loss_and_map_grads(map_parts, cycles, step, student_parts=(), offsets=None, *, batches: MicroBatches,
                       loss_cfg: losses.LossConfig):
    """(loss, terms, d loss / d maps of each micro-batch, d loss / d student maps of each student micro-batch) of
    the whole batch at training step `step` (or None); the student parts are () when self-supervision is off."""
    count_trace("micro/loss")

    def objective(parts, sparts):
        maps = jax.tree.map(lambda *p: batches.merge(p), *parts)
        student = losses.Student(batches.merge(sparts), offsets) if sparts else None
        return losses.cycle_loss(maps, cycles, loss_cfg, step=step, student=student)

    (loss, terms), (dmaps, dstudent) = jax.value_and_grad(objective, argnums=(0, 1), has_aux=True)(
        map_parts, student_parts)
    return loss, terms, dmaps, dstudent


def zeros_like_params(params):
    count_trace("micro/zeros")
    return jax.tree.map(jnp.zeros_like, params)


def accumulate(acc, params, x, dmaps, tasks, *, net: Network, student: bool = False):
    """acc + the parameter gradient of one micro-batch (its forward again under `jax.vjp`, pulled back); with
    `student`, of a student micro-batch (`dmaps` = the cotangent of its scale-0 pixel maps)."""
    count_trace("micro/accumulate_student" if student else "micro/accumulate")
    fn = (lambda p: net(p, x, tasks)["px"][0]) if student else (lambda p: net(p, x, tasks))
    _, vjp = jax.vjp(fn, params)
    (g,) = vjp(dmaps)
    return jax.tree.map(jnp.add, acc, g)


def update(state, grads, loss, terms, *, tx, schedule, ema_decay=0.0):
    count_trace("micro/update")
    return apply_gradients(state, loss, terms, grads, tx, schedule, ema_decay)


class MicroBatchedStep:
    """`(state, cycles) -> (new_state, metrics)` like `train_step.make_train_step`'s function, computed maps-first
    with `micro_batch` pair-forwards per device per call (see the module docstring). `state` is donated."""

    def __init__(self, net: Network, loss_cfg: losses.LossConfig, tx, schedule, *, micro_batch: int,
                 num_devices: int = 1, state_sharding=None, batch_sharding=None, ema_decay: float = 0.0):
        if int(micro_batch) <= 0:
            raise ValueError(f"micro_batch must be positive, got {micro_batch}")
        self.net = net
        self.batches = MicroBatches(int(micro_batch), int(num_devices), tuple(loss_cfg.pairs))
        sharded = state_sharding is not None
        rep = NamedSharding(sharding_mesh(state_sharding), P()) if sharded else None
        param_sharding = state_sharding["params"] if sharded else None
        shard = lambda **kw: kw if sharded else {}  # jit's sharding arguments, only when there is a mesh
        self._split = jax.jit(functools.partial(split, batches=self.batches), **shard(in_shardings=(batch_sharding,)))
        self._forward = jax.jit(functools.partial(forward, net=net), static_argnums=(2,))
        self.student = loss_cfg.self_supervision > 0
        if self.student:
            self._split_student = jax.jit(functools.partial(split_student, batches=self.batches, loss_cfg=loss_cfg))
            self._forward_student = jax.jit(functools.partial(forward_student, net=net), static_argnums=(2,))
            self._accumulate_student = jax.jit(functools.partial(accumulate, net=net, student=True),
                                               donate_argnums=(0,), static_argnums=(4,))
        self._loss = jax.jit(functools.partial(loss_and_map_grads, batches=self.batches, loss_cfg=loss_cfg))
        self._zeros = jax.jit(zeros_like_params, **shard(out_shardings=param_sharding))
        self._accumulate = jax.jit(functools.partial(accumulate, net=net), donate_argnums=(0,), static_argnums=(4,))
        # Only the state is donated: the gradient accumulator has no output of its shape left to alias.
        self._update = jax.jit(functools.partial(update, tx=tx, schedule=schedule, ema_decay=ema_decay),
                               donate_argnums=(0,),
                               **shard(out_shardings=(state_sharding, rep)))

    def _tasks(self, i: int) -> tuple[str, ...]:
        return self.net.static_tasks(self.batches.tasks(i))

    def phases(self, state: dict, cycles) -> Iterator[tuple[str, Any]]:
        """One step, phase by phase: yields (name, output) after "split", "forward", "loss", "accumulate" and
        "update" (whose output is (new_state, metrics)). Nothing blocks in between: a benchmark times a phase by
        blocking on its output. `state` is donated to the last phase."""
        params = state["params"]
        xs = self._split(cycles)
        xs_student, offsets = self._split_student(cycles, state.get("rng")) if self.student else ((), None)
        yield "split", (xs, xs_student) if self.student else xs
        maps = [self._forward(params, x, self._tasks(i)) for i, x in enumerate(xs)]
        student = tuple(self._forward_student(params, x, self._tasks(i)) for i, x in enumerate(xs_student))
        yield "forward", (maps, student) if self.student else maps
        loss, terms, dmaps, dstudent = self._loss(tuple(maps), cycles, state.get("step"), student, offsets)
        del maps, student
        yield "loss", (loss, terms, dmaps)
        acc = self._zeros(params)
        for i, (x, dm) in enumerate(zip(xs, dmaps)):
            acc = self._accumulate(acc, params, x, dm, self._tasks(i))
        for i, (x, dm) in enumerate(zip(xs_student, dstudent)):
            acc = self._accumulate_student(acc, params, x, dm, self._tasks(i))
        yield "accumulate", acc
        yield "update", self._update(state, acc, loss, terms)

    def loss_and_grads(self, params, cycles, step=None):
        """((loss, terms), grads) of the batch at training step `step` (None: as `losses.cycle_loss` reads None, after
        any occlusion or self-supervision start step), computed maps-first (the step without its update); the
        self-supervision crops are the centre windows, as `train_step.loss_and_grads` without `rng`."""
        out = {}
        state = {"params": params} if step is None else {"params": params, "step": jnp.asarray(step, jnp.int32)}
        for name, value in self.phases(state, cycles):
            out[name] = value
            if name == "accumulate":
                break
        loss, terms, _ = out["loss"]
        return (loss, terms), out["accumulate"]

    def __call__(self, state: dict, cycles):
        for _, out in self.phases(state, cycles):
            pass
        return out
