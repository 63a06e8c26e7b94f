"""Checkpoints on disk.

Layouts:
- **params-only** (convert / export / evaluate input): `DIR/model.json` (the model config, with "name") +
  `DIR/params/` (an orbax PyTree checkpoint of the params dict).
- **training workdir**: `WORKDIR/model.json`, `WORKDIR/config.json`, `WORKDIR/checkpoints/<step>/` written by an
  orbax CheckpointManager with items `state` = {"params", "opt_state", "step", "rng"} and `data`.

`load_params(path)` accepts a params-only dir, a training workdir (latest step) or a step dir.
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import orbax.checkpoint as ocp
from grain import checkpoint as grain_ckpt

from bridge_jax import files, models

MODEL_JSON = "model.json"
CONFIG_JSON = "config.json"  # a training workdir's config (beside its model.json)
PARAMS_DIR = "params"
CHECKPOINTS_DIR = "checkpoints"
STATE_ITEM = "state"


# ==========================================================================================================
# Params-only checkpoints
# ==========================================================================================================

def _to_numpy_tree(tree: Any) -> Any:
    return jax.tree.map(lambda x: np.asarray(x), tree)


def save_params(directory: str | os.PathLike, params: dict, model_cfg: dict, *, overwrite: bool = False) -> Path:
    """Write a params-only checkpoint: `directory/model.json` + `directory/params/` (orbax PyTree).

    Written to a temporary sibling directory first and renamed into place, so a crash never leaves a
    half-written checkpoint at `directory`.

    Args:
      directory: output directory (created; must not exist unless `overwrite`).
      params: nested dict of arrays (float32).
      model_cfg: JSON-serialisable model config with a "name" key (see `bridge_jax.models.model_config`).
    Raises:
      FileExistsError: `directory` exists and `overwrite` is False.
    """
    out = Path(directory).absolute()
    if "name" not in model_cfg:
        raise ValueError("model_cfg must contain 'name'")
    if out.exists() and not overwrite:
        raise FileExistsError(f"{out} already exists (pass overwrite=True / --overwrite to replace it)")
    with files.staged_dir(out, overwrite=True) as tmp:
        files.write_json(Path(tmp) / MODEL_JSON, dict(model_cfg))
        with ocp.PyTreeCheckpointer() as ckptr:
            ckptr.save(Path(tmp) / PARAMS_DIR, _to_numpy_tree(params))
    return out


def _read_model_json(path: Path) -> dict:
    try:
        cfg = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: unreadable model config ({e})") from e
    if not isinstance(cfg, dict) or "name" not in cfg:
        raise ValueError(f"{path}: model config must be a JSON object with 'name'")
    return cfg


class _DropItemDirMetadataWarning(logging.Filter):
    """orbax warns "Metadata file does not exist: <step>/state/_CHECKPOINT_METADATA" when an item dir of a
    CheckpointManager step is read directly: that file lives one level up, in the step dir, so for our
    layouts the warning is noise that every `predict` / `evaluate` on a training workdir would print."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not str(record.msg).startswith("Metadata file does not exist")


@contextlib.contextmanager
def _quiet_item_dir_metadata():
    logger, flt = logging.getLogger("absl"), _DropItemDirMetadataWarning()
    logger.addFilter(flt)
    try:
        yield
    finally:
        logger.removeFilter(flt)


def _restore_tree(path: Path, subtree: str | None = None) -> Any:
    """Restore an orbax PyTree checkpoint at `path` as numpy arrays (optionally only the top-level `subtree`)."""
    with _quiet_item_dir_metadata(), ocp.PyTreeCheckpointer() as ckptr:
        meta = ckptr.metadata(path)
        tree = meta.item_metadata.tree if hasattr(meta, "item_metadata") else meta.tree
        if subtree is not None:
            if not isinstance(tree, dict) or subtree not in tree:
                keys = list(tree) if isinstance(tree, dict) else type(tree).__name__
                raise ValueError(f"{path}: checkpoint has no '{subtree}' entry (found {keys})")
            tree = {subtree: tree[subtree]}
        restore_args = jax_tree_map_meta(lambda m: ocp.RestoreArgs(restore_type=np.ndarray), tree)
        out = ckptr.restore(path, args=ocp.args.PyTreeRestore(item=tree, restore_args=restore_args,
                                                               partial_restore=subtree is not None))
    return out[subtree] if subtree is not None else out


def jax_tree_map_meta(fn, tree):
    """tree.map over orbax metadata trees (their leaves are metadata objects, not arrays)."""
    return jax.tree.map(fn, tree, is_leaf=lambda x: not isinstance(x, (dict, list, tuple)))


def _latest_step(ckpt_dir: Path) -> Path:
    steps = sorted((int(p.name), p) for p in ckpt_dir.iterdir() if p.is_dir() and p.name.isdigit())
    if not steps:
        raise ValueError(f"{ckpt_dir}: no step directories (expected {CHECKPOINTS_DIR}/<step>/)")
    return steps[-1][1]


def resolve_checkpoint(path: str | os.PathLike) -> tuple[Path, Path, str | None]:
    """Find `(model.json path, orbax tree path, subtree)` for any accepted checkpoint layout."""
    p = Path(path).absolute()
    if not p.exists():
        raise ValueError(f"checkpoint {path} does not exist")
    if (p / PARAMS_DIR).is_dir() and (p / MODEL_JSON).is_file():
        return p / MODEL_JSON, p / PARAMS_DIR, None
    if (p / CHECKPOINTS_DIR).is_dir():
        step = _latest_step(p / CHECKPOINTS_DIR)
        return p / MODEL_JSON, step / STATE_ITEM, "params"
    if p.parent.name == CHECKPOINTS_DIR and p.name.isdigit():
        return p.parent.parent / MODEL_JSON, p / STATE_ITEM, "params"
    raise ValueError(f"{path} is not a bridge_jax checkpoint: expected a params dir (model.json + params/), "
                     f"a training workdir (model.json + checkpoints/<step>/) or a step dir checkpoints/<step>")


def load_params(path: str | os.PathLike) -> tuple[dict, dict]:
    """Load `(model_cfg, params)` from a params-only dir, a training workdir (latest step) or a step dir.

    Params come back as a nested dict of float32 `jax.Array`s and are checked against the model's shapes.
    A model.json with `"separate_networks": true` (separate stereo / flow networks) gives params
    `{"stereo": ..., "flow": ...}` and that key is kept in the returned config.
    Raises:
      ValueError naming the path when it is missing, of an unknown layout, or garbled.
    """
    model_json, tree_path, subtree = resolve_checkpoint(path)
    if not model_json.is_file():
        raise ValueError(f"{path}: missing {model_json}")
    cfg = _read_model_json(model_json)
    separate = bool(cfg.pop("separate_networks", False))  # the no-sharing variant: 2 networks
    try:
        cfg = models.model_config(cfg)
    except ValueError as e:
        raise ValueError(f"{model_json}: {e}") from e
    if not tree_path.is_dir():
        raise ValueError(f"{path}: missing {tree_path}")
    try:
        params = _restore_tree(tree_path, subtree)
    except ValueError:
        raise
    except Exception as e:  # orbax raises a variety of types on garbled data
        raise ValueError(f"{path}: cannot read checkpoint at {tree_path} ({type(e).__name__}: {e})") from e
    _, abstract = models.abstract_init(cfg)
    if separate:
        abstract = {"stereo": abstract, "flow": abstract}
        cfg["separate_networks"] = True
    want = jax.tree.map(lambda a: tuple(a.shape), abstract)
    try:
        got = jax.tree.map(lambda a: tuple(np.shape(a)), params)
    except Exception:
        got = None
    if got != want:
        raise ValueError(f"{path}: params do not match model {cfg['name']} (different tree structure or shapes)")
    return cfg, jax.tree.map(lambda a: jnp.asarray(a, jnp.float32), params)


# ==========================================================================================================
# Training checkpoints: WORKDIR/checkpoints/<step>/ with items `state` (train state pytree) and `data` (grain
# iterator state, one JSON file per process).
# ==========================================================================================================

DATA_ITEM = "data"


class _IteratorSnapshot:
    """A grain iterator state frozen at save time, in the shape grain's orbax handler expects.

    grain's handler calls `get_state()` when it writes, which for async saves can be after training moved
    on; handing it this snapshot (JSON bytes) instead of the live iterator keeps state and data in step. On
    restore it receives the bytes through `set_state` and the trainer applies them to the real iterator.
    grain's handler writes one file per process, so multi-host runs resume every host's own shard.
    """

    def __init__(self, state: bytes = b""):
        self.state = state

    def get_state(self) -> bytes:
        return self.state

    def set_state(self, state: bytes) -> None:
        self.state = state

    def start_prefetch(self) -> None:  # called by grain's handler after restoring
        pass


class TrainCheckpointer:
    """Thin layer over orbax CheckpointManager for WORKDIR/checkpoints/<step>/.

    Every checkpoint holds `state` (the train state {"params", "opt_state", "step", "rng"}, orbax
    StandardCheckpointHandler, sharded arrays welcome) and `data` (the grain iterator state), so a restart
    resumes the exact batch sequence. Saves are asynchronous (the device->host copy happens in `save`, so the
    state may be donated right after); `wait()` blocks until the last one is on disk; the last `keep` are kept.
    """

    def __init__(self, workdir: str | os.PathLike, *, save_every: int = 1000, keep: int | None = 3,
                 async_save: bool = True):
        self.directory = str(Path(workdir).absolute() / CHECKPOINTS_DIR)
        self.save_every = int(save_every)
        options = ocp.CheckpointManagerOptions(
            max_to_keep=int(keep) if keep and int(keep) > 0 else None,
            enable_async_checkpointing=bool(async_save), create=True)
        self.manager = ocp.CheckpointManager(
            self.directory, options=options, item_names=(STATE_ITEM, DATA_ITEM),
            item_handlers={STATE_ITEM: ocp.StandardCheckpointHandler(), DATA_ITEM: grain_ckpt.CheckpointHandler()})

    def latest_step(self) -> int | None:
        return self.manager.latest_step()

    def all_steps(self) -> list[int]:
        return list(self.manager.all_steps())

    def save(self, step: int, state: Any, data_state: dict | None = None, *, force: bool = False) -> bool:
        """Starts saving step `step` if due (`step % save_every == 0`) or forced; False if not saved."""
        step = int(step)
        due = force or (self.save_every > 0 and step % self.save_every == 0)
        if not due or step in self.manager.all_steps():
            return False
        snapshot = _IteratorSnapshot(json.dumps(data_state if data_state is not None else {}).encode())
        return bool(self.manager.save(step, args=ocp.args.Composite(
            **{STATE_ITEM: ocp.args.StandardSave(state), DATA_ITEM: grain_ckpt.CheckpointSave(snapshot)}),
            force=True))

    def restore(self, step: int, abstract_state: Any) -> tuple[Any, dict]:
        """Restores step `step` into the structure/shardings of `abstract_state` -> (state, data_state dict)."""
        holder = _IteratorSnapshot()
        out = self.manager.restore(int(step), args=ocp.args.Composite(
            **{STATE_ITEM: ocp.args.StandardRestore(abstract_state), DATA_ITEM: grain_ckpt.CheckpointRestore(holder)}))
        return out[STATE_ITEM], (json.loads(holder.state.decode()) if holder.state else {})

    def wait(self) -> None:
        self.manager.wait_until_finished()

    def close(self) -> None:
        self.manager.wait_until_finished()
        self.manager.close()


def find_train_step_dir(path: str | os.PathLike) -> str | None:
    """Latest `checkpoints/<step>` dir (with a `state` item) of a workdir, or `path` itself if it is a step dir."""
    p = Path(path).absolute()
    if p.parent.name == CHECKPOINTS_DIR and p.name.isdigit() and (p / STATE_ITEM).is_dir():
        return str(p)
    ckpts = p / CHECKPOINTS_DIR
    if not ckpts.is_dir():
        return None
    steps = sorted((int(q.name), q) for q in ckpts.iterdir()
                   if q.is_dir() and q.name.isdigit() and (q / STATE_ITEM).is_dir())
    return str(steps[-1][1]) if steps else None


def restore_train_params(step_dir: str | os.PathLike) -> dict:
    """Only the `params` of a training step dir, as numpy arrays."""
    return _restore_tree(Path(step_dir).absolute() / STATE_ITEM, "params")
