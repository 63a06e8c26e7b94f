"""Warm starts without tracing: the train step's lowered program kept beside the compilation cache.

XLA's persistent compilation cache (`compile_cache`) keeps what XLA compiled, but a new process still has to
*trace* the train step in Python and lower it to StableHLO before it can look the executable up: on a 2-core
VM that is 3.4 s of tracing and 1.0 s of lowering for the demo's 128x256 step, about half of a warm first step.
`cached_step` keeps the lowered step itself (`jax.export`, serialised StableHLO) in the same cache folder, so
that the next run of the same code, config and shapes deserialises it and calls it: no tracing, and the
compile is the usual cache hit.

An entry is used only when everything that shapes the step is the same: the source of every bridge_jax module
(a hash of the files), the jax and jaxlib versions, the run's config, the shapes, dtypes and shardings of the
state and the batch, the platform and CPU vector ISA (the convolution gradient rules depend on it) and the
XLA/JAX/bridge_jax environment variables. Anything else gives another key, and the step is traced as before.
Entries are files named `<key>-step-cache` in the compilation cache folder, trimmed with its other entries.

Single-device runs only: a data-parallel step (several devices, a sharded state) or the micro-batched step is
returned as it is.
"""
from __future__ import annotations

import functools
import hashlib
import json
import os
import pickle
import warnings
from typing import Any, Callable, Optional

import jax

from bridge_jax import files
from bridge_jax.models import layers

SUFFIX = "-step-cache"
"""File name ending of an entry (the compilation cache's trimming keeps every `*-cache` file under its cap)."""
FORMAT = 1
"""Version of the entry layout; entries of another version are ignored (and overwritten)."""
ENV_PREFIXES = ("XLA_", "JAX_", "BRIDGE_JAX_")
"""Environment variables that can change the compiled step: they are part of the key."""


@functools.lru_cache(maxsize=1)
def source_fingerprint() -> str:
    """sha256 of every `.py` file of the bridge_jax package (path and contents) and the jax / jaxlib versions:
    any code change gives new keys, so an entry never outlives the code that traced it."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256(f"jax {jax.__version__} jaxlib {jax.lib.__version__}".encode())
    for folder, dirs, names in os.walk(root):
        dirs.sort()
        for name in sorted(names):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()


def _leaf_signature(x) -> str:
    sharding = getattr(x, "sharding", None)
    return f"{tuple(x.shape)}:{x.dtype}:{sharding}"


def step_key(config: dict, state, batch) -> str:
    """The entry key of a train step: hex sha256 over the source fingerprint, `config`, the state's and the
    batch's tree structure, shapes, dtypes and shardings, the devices and ISA, and the environment
    (`ENV_PREFIXES`)."""
    env = {k: v for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIXES)}
    parts = {"source": source_fingerprint(), "config": config, "env": env,
             "state_tree": str(jax.tree.structure(state)),
             "leaves": [_leaf_signature(x) for x in jax.tree.leaves((state, batch))],
             "devices": [str(d.device_kind) for d in jax.devices()], "platform": jax.default_backend(),
             "isa": layers.cpu_vector_isa()}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _single_device(tree) -> bool:
    return all(len(x.sharding.device_set) == 1 for x in jax.tree.leaves(tree) if hasattr(x, "sharding"))


def _export(step_fn: Callable, state, batch):
    """Trace and lower `step_fn(state, batch)` once as a function of the flat leaves -> (exported, in_tree,
    out_tree)."""
    leaves, in_tree = jax.tree.flatten((state, batch))
    out_tree = []

    def flat(*xs):
        out = step_fn(*jax.tree.unflatten(in_tree, xs))
        out_leaves, tree = jax.tree.flatten(out)
        out_tree.append(tree)
        return out_leaves

    avals = [jax.ShapeDtypeStruct(x.shape, x.dtype) for x in leaves]
    exported = jax.export.export(jax.jit(flat))(*avals)
    return exported, in_tree, out_tree[0]


def _load(path: str):
    """(exported, in_tree, out_tree) from an entry, or None when it is missing, of another format or unreadable."""
    try:
        with open(path, "rb") as f:
            entry = pickle.load(f)
        if entry.get("format") != FORMAT:
            return None
        return jax.export.deserialize(bytearray(entry["exported"])), entry["in_tree"], entry["out_tree"]
    except FileNotFoundError:
        return None
    except Exception as e:  # noqa: BLE001 - a damaged entry is re-made, never a reason to fail a run
        warnings.warn(f"ignoring an unreadable train-step cache entry {path} ({type(e).__name__}: {e}); "
                      "tracing the step instead", stacklevel=3)
        return None


def cached_step(step_fn: Callable, state, batch, *, config: dict, folder: Optional[str],
                stats: Optional[dict] = None) -> Callable:
    """`step_fn` (a jitted `(state, batch) -> (new_state, metrics)` that donates its state) as a function that
    skips tracing when `folder` holds its entry (`step_key`), or that writes the entry on its first call.

    Returns `step_fn` itself when `folder` is None (no cache), when the state or batch lives on more than one
    device, when `step_fn` is not a jitted function (the micro-batched step), or when `jax.export` cannot
    lower it (then `stats` has "step_cache_error"). `stats`, if given, gets "step_cache" = "hit", "written" or
    "off" and "step_cache_key".
    The returned function takes the same `(state, batch)`, donates the state and returns the same trees.
    """
    stats = {} if stats is None else stats
    if folder is None or not hasattr(step_fn, "lower") or not _single_device((state, batch)):
        stats["step_cache"] = "off"
        return step_fn
    key = step_key(config, state, batch)
    path = os.path.join(folder, key + SUFFIX)
    stats["step_cache_key"] = key
    loaded = _load(path)
    if loaded is None:
        try:
            exported, in_tree, out_tree = _export(step_fn, state, batch)
        except Exception as e:  # noqa: BLE001 - a step jax.export cannot serialise is traced as before
            stats.update(step_cache="off", step_cache_error=f"{type(e).__name__}: {e}"[:500])
            return step_fn
        try:
            files.write_bytes(path, pickle.dumps({"format": FORMAT, "exported": bytes(exported.serialize()),
                                                  "in_tree": in_tree, "out_tree": out_tree}))
            stats["step_cache"] = "written"
        except OSError as e:  # a full or read-only cache folder: this run still uses what it just lowered
            warnings.warn(f"could not write the train-step cache entry {path}: {e}", stacklevel=2)
            stats["step_cache"] = "off"
    else:
        exported, in_tree, out_tree = loaded
        stats["step_cache"] = "hit"
    num_state = len(jax.tree.leaves(state))
    call = jax.jit(exported.call, donate_argnums=tuple(range(num_state)))

    def step(state, batch):
        leaves, tree = jax.tree.flatten((state, batch))
        if tree != in_tree:
            raise ValueError(f"train step called with another state/batch structure than it was exported for: "
                             f"{tree} vs {in_tree}")
        return jax.tree.unflatten(out_tree, call(*leaves))

    return step


__all__ = ["cached_step", "step_key", "source_fingerprint", "SUFFIX"]
