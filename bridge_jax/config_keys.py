"""The keys of a training config (`ml_collections.ConfigDict`): its leaf fields, and the flat keys that moved
into a section (read with a note). Shared by `bridge_jax.configs` and `bridge_jax.setup`, which import this
module and not each other."""

from __future__ import annotations

import copy
import sys
from typing import Callable

import ml_collections

# Fields that moved from the top level into the `loop` section: the flat keys (`--config.eval_every=...`, or
# `c.eval_every = ...` in a config file) still work in this release, with a note naming the new key.
MOVED_KEYS = {name: f"loop.{name}" for name in (
    "num_train_steps", "num_epochs", "steps_per_epoch", "log_every", "checkpoint_every", "eval_every", "image_every",
    "keep_checkpoints", "async_checkpoints", "progress_bar", "max_nonfinite_in_row")}


def _note_moved(old: str, new: str) -> None:
    print(f"note: config.{old} is now config.{new} (the flat key is accepted until the next release)",
          file=sys.stderr, flush=True)


def moved_key(key: str, config: ml_collections.ConfigDict, note: Callable[[str, str], None] = _note_moved) -> str:
    """`key`, or its new name when it is a flat key that moved (`MOVED_KEYS`) and `config` has the new one;
    `note(old, new)` is called for a moved key."""
    new = MOVED_KEYS.get(key)
    if new is None or key in config:
        return key
    section, _, field = new.partition(".")
    if section not in config or field not in config[section]:
        return key
    note(key, new)
    return new


def move_flat_keys(config: ml_collections.ConfigDict,
                   note: Callable[[str, str], None] = _note_moved) -> ml_collections.ConfigDict:
    """`config`, or a copy of it with the moved flat keys set at the top level (a config file written for the
    previous release) moved to their section, each with a note."""
    flat = [k for k in MOVED_KEYS if k in config and "loop" in config]
    if not flat:
        return config
    config = copy.deepcopy(config)
    for key in flat:
        note(key, MOVED_KEYS[key])
        config.loop[key.rpartition(".")[2]] = config[key]
        del config[key]
    return config


def leaf_keys(config: ml_collections.ConfigDict, prefix: str = "") -> list[str]:
    """The dotted names of the settable (leaf) fields, e.g. "model.name", "loss.two_warp"."""
    out = []
    for k, v in config.items():
        if isinstance(v, ml_collections.ConfigDict):
            out.extend(leaf_keys(v, f"{prefix}{k}."))
        else:
            out.append(prefix + k)
    return out
