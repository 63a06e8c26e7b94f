"""The network as training and inference call it: pair inputs -> correspondence maps, shared or separate.

The paper trains one network P for stereo and flow pairs (shared weights); its "without sharing weights"
ablation has one network per task. `Network` hides the difference: with `separate=True` the params are
`{"stereo": ..., "flow": ...}` and every input row goes through the network of its task (which rows are stereo
is static, see `cycle.row_tasks`). Params stay float32; `dtype` only changes the compute dtype.
"""
from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from typing import Any, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import models
from bridge_jax.cycle import check_task
from bridge_jax.models import layers

COMPUTE_DTYPES = {"float32": None, "bfloat16": jnp.bfloat16}
"""Names of the compute dtypes (None = float32, the models' own dtype)."""
_ALIASES = {None: "float32", "fp32": "float32", "bf16": "bfloat16"}

REMAT_POLICIES = {
    "none": None,
    "conv_outputs": jax.checkpoint_policies.dots_saveable,
    "nothing": jax.checkpoint_policies.nothing_saveable,
}
"""Rematerialisation of the network's forward in the gradient (`jax.checkpoint` policies): "none" keeps every
activation; "conv_outputs" keeps the outputs of convolutions and matmuls and recomputes the elementwise ops
between them (activations, bias adds, concatenations, upsampling); "nothing" recomputes the whole forward.
Gradients are the same; what changes is peak memory and time (`bridge-bench --what train_step` measures both)."""


def compute_dtype(dtype: Any):
    """`None` (float32) or `jnp.bfloat16` from a name ("float32", "bfloat16", "fp32", "bf16"), None or a dtype.

    Raises ValueError for anything else.
    """
    if dtype is None or isinstance(dtype, str):
        name = _ALIASES.get(dtype, dtype)
        if name not in COMPUTE_DTYPES:
            raise ValueError(f"dtype must be one of {sorted(COMPUTE_DTYPES)}, got {dtype!r}")
        return COMPUTE_DTYPES[name]
    d = jnp.dtype(dtype)
    if d == jnp.float32:
        return None
    if d == jnp.bfloat16:
        return jnp.bfloat16
    raise ValueError(f"dtype must be float32 or bfloat16, got {dtype!r}")


def init_params(rng: jax.Array, model_cfg: Mapping, separate: bool = False) -> tuple[Any, dict]:
    """(graphdef, params) of a new network; with `separate`, two independently drawn networks
    `{"stereo": ..., "flow": ...}` (the flow network's key is `fold_in(rng, 1)`)."""
    graphdef, params = models.init(rng, model_cfg)
    if separate:
        _, params_flow = models.init(jax.random.fold_in(rng, 1), model_cfg)
        params = {"stereo": params, "flow": params_flow}
    return graphdef, params


def check_separate_params(params: Any, separate: bool) -> None:
    """A separate-networks model needs params {"stereo": ..., "flow": ...}."""
    if separate and not (isinstance(params, Mapping) and set(params) == {"stereo", "flow"}):
        raise ValueError("separate stereo/flow networks need params {'stereo': ..., 'flow': ...}")


@dataclasses.dataclass(frozen=True)
class Network:
    """Pair inputs -> maps, for training and inference.

    Attributes:
      graphdef: the static NNX graph (`models.init` / `models.abstract_init`).
      separate: params are {"stereo": ..., "flow": ...} and rows go through the network of their task.
      dtype: compute dtype (None = float32, or jnp.bfloat16); outputs are float32 either way.
      remat: a `REMAT_POLICIES` name: which activations the gradient keeps and which it recomputes.
      conv_weight_grad: how the convolutions' weight gradients are computed (`layers.WEIGHT_GRAD_METHODS`;
        "auto" = the formulation measured fastest for each layer on the backend). Same gradients either way.
    """

    graphdef: Any
    separate: bool = False
    dtype: Any = None
    remat: str = "none"
    conv_weight_grad: str = "auto"

    def __post_init__(self):
        if self.remat not in REMAT_POLICIES:
            raise ValueError(f"remat must be one of {sorted(REMAT_POLICIES)}, got {self.remat!r}")
        if self.conv_weight_grad not in layers.WEIGHT_GRAD_METHODS:
            raise ValueError(f"conv_weight_grad must be one of {list(layers.WEIGHT_GRAD_METHODS)}, "
                             f"got {self.conv_weight_grad!r}")

    def __call__(self, params, x, tasks: Sequence[str] = ()):
        """x: (N, H, W, 6) float32 pair inputs -> maps {"px": 4 x (N, h, w, 2), "frac": ...} float32.

        `tasks` (N static strings, "stereo" / "flow", the task of each row) is read only when the networks are
        separate.
        """
        if not self.separate:
            return self._one(params, x)
        if len(tasks) != x.shape[0]:
            raise ValueError(f"tasks has {len(tasks)} entries for {x.shape[0]} rows")
        stereo = np.array([check_task(t, "tasks") == "stereo" for t in tasks], bool)
        idx_s, idx_f = np.nonzero(stereo)[0], np.nonzero(~stereo)[0]
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
        if self.remat != "none":
            return jax.checkpoint(self._forward, policy=REMAT_POLICIES[self.remat])(params, x)
        return self._forward(params, x)

    def _forward(self, params, x):
        # The method is read while the forward is traced; the backward pass it defines is traced with it.
        with layers.weight_grad_method(self.conv_weight_grad):
            if self.dtype is not None and self.dtype != jnp.float32:
                maps = models.apply(self.graphdef, params, x.astype(self.dtype), dtype=self.dtype)
            else:
                maps = models.apply(self.graphdef, params, x)
        return jax.tree.map(lambda m: m.astype(jnp.float32), maps)

    def static_tasks(self, tasks: Sequence[str]) -> tuple[str, ...]:
        """The `tasks` to pass to a jitted call as a static argument: () for a shared network, which does not
        look at them (so all row patterns share one compiled function)."""
        return tuple(str(t) for t in tasks) if self.separate else ()
