"""Checkpoints on disk.

Layouts:
- **params-only** (convert / export / evaluate input): `DIR/model.json` (the model config, with "name") +
  `DIR/params/` (an orbax PyTree checkpoint of the params dict).
- **training workdir**: `WORKDIR/model.json`, `WORKDIR/config.json`, `WORKDIR/checkpoints/<step>/` written by an
  orbax CheckpointManager with items `state` = {"params", "opt_state", "step", "rng"} (+ "ema_params" when the
  run keeps a moving average of its params) and `data`.

`read_params(path)` accepts a params-only dir, a training workdir (newest readable step) or a step dir; from a
training checkpoint it reads the moving average where there is one (`MODEL_PARAMS`).

Broken checkpoints (truncated or garbled files, an empty step dir, a NaN train state) are never deleted: the
readers fall back to the newest step that reads completely and say which step they skipped and why
(`CheckpointFallbackWarning`); `TrainCheckpointer.restore_latest` moves the skipped step dirs aside to
`checkpoints/<step>.broken-<n>` before its next save writes (see there why then).
"""
from __future__ import annotations

import contextlib
import json
import logging
import os
import shutil
import sys
import time
import warnings
from pathlib import Path
from typing import Any, NamedTuple

import importlib

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import files, models


class _LazyModule:
    """A module imported at its first attribute access. orbax and grain take about 0.4 s to import; prediction
    from a shipped model (a .npz) never touches them, and that time counts in a first answer."""

    def __init__(self, name: str):
        self._name, self._module = name, None

    def __getattr__(self, attr: str):
        if self._module is None:
            self._module = importlib.import_module(self._name)
        return getattr(self._module, attr)


ocp = _LazyModule("orbax.checkpoint")
grain_ckpt = _LazyModule("grain.checkpoint")

MODEL_JSON = "model.json"
CONFIG_JSON = "config.json"  # a training workdir's config (beside its model.json)
PARAMS_DIR = "params"
# The train state's entries a model is read from: the params' moving average where the run kept one
# (`OptimizerConfig.ema_decay` > 0: what validation scored and what the next stage of a recipe starts from), else
# the params. `MODEL_PARAMS` is the subtree name that picks between them when a checkpoint is read.
EMA_PARAMS = "ema_params"
MODEL_PARAMS = "<model params>"
CHECKPOINTS_DIR = "checkpoints"
RECIPE_JSON = "recipe.json"  # a recipe workdir (`bridge_jax.recipe`): its stages, each a workdir under stages/
STAGES_DIR = "stages"
STATE_ITEM = "state"
BROKEN_SUFFIX = ".broken-"  # checkpoints/<step>.broken-<n>: a broken step dir moved aside (never deleted)


class CheckpointFallbackWarning(UserWarning):
    """A checkpoint step could not be used (unreadable, incomplete, not finite) and an older one was taken."""


def _reason(error: BaseException, limit: int = 300) -> str:
    """`Type: first line of the message`, capped (orbax/tensorstore messages embed whole JSON specs).

    orbax wraps a failed array read in "Encountered error while reading array index ... TensorStore
    details: <spec>", which says neither file nor problem: its cause (tensorstore's error) does."""
    while str(error).startswith("Encountered error while reading array index") and error.__cause__ is not None:
        error = error.__cause__
    text = str(error).strip()
    line = f"{type(error).__name__}: {text.splitlines()[0]}" if text else type(error).__name__
    return line if len(line) <= limit else line[:limit - 3] + "..."


def _is_failed_read_noise(args) -> bool:
    """Exceptions "ignored" in tensorstore/orbax threads after a restore failed: the other arrays' reads
    finish after orbax closed its event loop ("Event loop is closed" in asyncio's call_soon_threadsafe) or
    fail on the same broken file (orbax's "Encountered error while reading array index"). The failure
    itself has been raised (and reported) already; these would only print stray tracebacks later."""
    import traceback
    if args.exc_type is RuntimeError and str(args.exc_value) == "Event loop is closed":
        frames = traceback.extract_tb(args.exc_traceback)
        return bool(frames) and frames[-1].name == "_check_closed" and "asyncio" in frames[-1].filename
    return str(args.exc_value).startswith("Encountered error while reading array index")


_noise_filter_installed = False


def _quiet_failed_read_noise() -> None:
    """Installs (once, after the first failed checkpoint read) a sys.unraisablehook dropping only the
    `_is_failed_read_noise` leftovers; everything else goes to the hook that was there before."""
    global _noise_filter_installed
    if _noise_filter_installed:
        return
    previous = sys.unraisablehook

    def hook(args):
        if not _is_failed_read_noise(args):
            previous(args)

    sys.unraisablehook = hook
    _noise_filter_installed = True


# ==========================================================================================================
# Finite checks
# ==========================================================================================================

def _nonfinite_count(x: Any) -> int:
    """Number of NaN/Inf entries of one leaf; 0 for integer, bool and PRNG-key leaves."""
    if isinstance(x, jax.Array):
        if not jnp.issubdtype(x.dtype, jnp.inexact):
            return 0
        # on device: also works for arrays sharded over several hosts (the sum comes back replicated)
        return int(jnp.sum(~jnp.isfinite(x)))
    a = np.asarray(x)
    if not jnp.issubdtype(a.dtype, jnp.inexact):  # jnp's issubdtype also knows ml_dtypes' bfloat16
        return 0
    return int(np.count_nonzero(~np.isfinite(a)))


def first_nonfinite(tree: Any) -> tuple[str, int] | None:
    """`(leaf path, count)` of the first leaf (in tree order) holding NaN/Inf, else None.

    The path is the key path joined by "/", e.g. `encoder/conv1/kernel` (sequence indices and named-tuple
    fields appear as their index / name: `0/mu/conv1/kernel` for an optax state)."""
    for kp, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]:
        n = _nonfinite_count(leaf)
        if n:
            return jax.tree_util.keystr(kp, simple=True, separator="/"), n
    return None


def check_finite_params(params: Any, what: str) -> None:
    """Refuse params holding NaN/Inf: ValueError naming the first bad leaf in tree order.

    Args:
      params: a pytree of arrays (numpy or jax, any shapes; non-float leaves are ignored).
      what: names the source in the message (a path, `config.init_from=...`).
    Raises:
      ValueError: "<what>: parameter <path/to/leaf> has N non-finite values (NaN/Inf); ...".
    """
    bad = first_nonfinite(params)
    if bad is not None:
        leaf, n = bad
        raise ValueError(f"{what}: parameter {leaf} has {n} non-finite values (NaN/Inf); these weights are unusable "
                         f"(the run that wrote them diverged, or the file is corrupt)")


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
        # "Failed to get item metadata ...": a garbled _METADATA, which the reader's own error then names
        return not str(record.msg).startswith(("Metadata file does not exist", "Failed to get item metadata"))


@contextlib.contextmanager
def _quiet_item_dir_metadata():
    logger, flt = logging.getLogger("absl"), _DropItemDirMetadataWarning()
    logger.addFilter(flt)
    try:
        yield
    finally:
        logger.removeFilter(flt)


def _restore_tree(path: Path, subtree: str | None = None) -> Any:
    """Restore an orbax PyTree checkpoint at `path` as numpy arrays (optionally only the top-level `subtree`;
    `MODEL_PARAMS` = the params that stand for the model: "ema_params" where the state keeps them, else "params")."""
    with _quiet_item_dir_metadata(), ocp.PyTreeCheckpointer() as ckptr:
        meta = ckptr.metadata(path)
        tree = getattr(meta.item_metadata if hasattr(meta, "item_metadata") else meta, "tree", None)
        if tree is None:  # orbax logs a warning and returns no item metadata for a missing / garbled _METADATA
            raise ValueError(f"{path}: unreadable checkpoint metadata (a file in it is missing, truncated or garbled)")
        if subtree == MODEL_PARAMS:
            subtree = EMA_PARAMS if isinstance(tree, dict) and EMA_PARAMS in tree else "params"
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


def _step_dirs(ckpt_dir: Path) -> list[Path]:
    """`checkpoints/<step>` dirs, newest first (moved-aside `<step>.broken-<n>` and orbax tmp dirs excluded)."""
    try:
        entries = list(ckpt_dir.iterdir())
    except FileNotFoundError:
        return []
    steps = [(int(p.name), p) for p in entries if p.name.isdigit() and p.is_dir()]
    return [p for _, p in sorted(steps, reverse=True)]


def _latest_step(ckpt_dir: Path) -> Path:
    steps = _step_dirs(ckpt_dir)
    if not steps:
        raise ValueError(f"{ckpt_dir}: no step directories (expected {CHECKPOINTS_DIR}/<step>/)")
    return steps[0]


def model_dir(path: str | os.PathLike) -> Path:
    """The training workdir whose params stand for `path`: for a recipe workdir (a `recipe.json` beside
    `stages/<name>/`), its latest stage that holds a checkpoint (the last stage once the recipe finished); any
    other path as it is (absolute)."""
    p = Path(path).absolute()
    recipe = p / RECIPE_JSON
    if not recipe.is_file():
        return p
    try:
        names = [str(n) for n in json.loads(recipe.read_text())["stages"]]
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{recipe}: not a readable recipe record ({_reason(e)})") from e
    for name in reversed(names):
        stage = p / STAGES_DIR / name
        if _step_dirs(stage / CHECKPOINTS_DIR):
            return stage
    raise ValueError(f"{p}: a recipe workdir none of whose stages ({', '.join(names)}) has a checkpoint yet")


def resolve_checkpoint(path: str | os.PathLike) -> tuple[Path, Path, str | None]:
    """Find `(model.json path, orbax tree path, subtree)` for any accepted checkpoint layout (a recipe workdir
    stands for its latest stage, `model_dir`).

    For a training workdir the tree path is the newest step's, readable or not: `read_params` is the reader
    that skips broken steps; this is for callers that only need the model.json beside it."""
    if not Path(path).exists():
        raise ValueError(f"checkpoint {path} does not exist")
    p = model_dir(path)
    if (p / PARAMS_DIR).is_dir() and (p / MODEL_JSON).is_file():
        return p / MODEL_JSON, p / PARAMS_DIR, None
    if (p / CHECKPOINTS_DIR).is_dir():
        step = _latest_step(p / CHECKPOINTS_DIR)
        return p / MODEL_JSON, step / STATE_ITEM, MODEL_PARAMS
    if p.parent.name == CHECKPOINTS_DIR and p.name.isdigit():
        return p.parent.parent / MODEL_JSON, p / STATE_ITEM, MODEL_PARAMS
    raise ValueError(f"{path} is not a bridge_jax checkpoint: expected a params dir (model.json + params/), "
                     f"a training workdir (model.json + checkpoints/<step>/) or a step dir checkpoints/<step>")


# How often read_params re-lists a live workdir whose steps changed under it (a running training deletes old
# steps, keep-K), and how long it lets a deletion in progress finish before re-listing.
LOAD_ATTEMPTS = 3
_SETTLE_S = 0.5


def _read_params(tree_path: Path, subtree: str | None, want: Any, model_name: str, require_finite: bool) -> Any:
    """Params (numpy) of one orbax tree, checked against the model's shapes `want` (a tree of shape tuples).

    Raises ValueError(reason) for anything that makes them unusable; FileNotFoundError passes through (the
    caller tells a step deleted under it from a broken one)."""
    if not tree_path.is_dir():
        raise ValueError(f"missing {tree_path.name}/ (an incomplete checkpoint)")
    try:
        params = _restore_tree(tree_path, subtree)
    except FileNotFoundError:
        raise
    except Exception as e:  # orbax / tensorstore / json raise a variety of types on garbled data
        _quiet_failed_read_noise()
        own = f"{tree_path}: "  # _restore_tree's own errors start with the path: not twice in the message
        detail = str(e)[len(own):] if type(e) is ValueError and str(e).startswith(own) else _reason(e)
        raise ValueError(f"cannot read {tree_path} ({detail})") from e
    try:
        got = jax.tree.map(lambda a: tuple(np.shape(a)), params)
    except Exception:
        got = None
    if got != want:
        raise ValueError(f"params do not match model {model_name} (different tree structure or shapes)")
    if require_finite:
        bad = first_nonfinite(params)
        if bad is not None:
            raise ValueError(f"params not finite: {bad[0]} has {bad[1]} non-finite values (NaN/Inf)")
    return params


def _read_newest_step(workdir: Path, want: Any, model_name: str, require_finite: bool) -> tuple[Path, Any]:
    """`(step dir, params)` of the newest step of `workdir/checkpoints` whose params read completely.

    Resolving the newest step and reading it are one unit: a training run may delete steps (keep-K) between
    the two. A step that disappeared while being read, or a listing that changed while steps failed, makes
    it list again (`LOAD_ATTEMPTS` times); a step that is still there and fails is broken: it is skipped with
    a CheckpointFallbackWarning (never deleted) and the next older one is tried.
    """
    ckpt_dir = workdir / CHECKPOINTS_DIR
    retried: set[Path] = set()  # steps that lost a file while read once: a second time, they are broken
    for _ in range(LOAD_ATTEMPTS):
        listing = _step_dirs(ckpt_dir)
        if not listing:
            raise ValueError(f"{ckpt_dir}: no step directories (expected {CHECKPOINTS_DIR}/<step>/)")
        broken: list[tuple[Path, str]] = []
        relist = False
        found = None
        for step_dir in listing:
            try:
                found = _read_params(step_dir / STATE_ITEM, MODEL_PARAMS, want, model_name, require_finite)
                break
            except (ValueError, FileNotFoundError) as e:
                if not step_dir.is_dir() or (isinstance(e, FileNotFoundError) and step_dir not in retried):
                    # deleted (or being deleted) while we read it: keep-K of a live run. The newest step may be
                    # another one now, so list again rather than fall back to an older step.
                    retried.add(step_dir)
                    relist = True
                    break
                broken.append((step_dir, str(e) if isinstance(e, ValueError) else _reason(e)))
        if relist:
            time.sleep(_SETTLE_S)  # let a deletion in progress finish before listing again
            continue
        if broken:
            time.sleep(_SETTLE_S)  # a deletion in progress looks like a broken step until it completes
            if _step_dirs(ckpt_dir) != listing:
                continue
        if found is None:
            newest, why = broken[0]
            raise ValueError(f"{ckpt_dir}: no readable checkpoint step; the newest, {newest.name}, is broken ({why})"
                             + (f"; {len(broken) - 1} older step(s) are broken too" if len(broken) > 1 else ""))
        for bad_dir, why in broken:
            warnings.warn(f"{bad_dir}: skipped a broken checkpoint ({why}); using the older step "
                          f"{step_dir.name} (the broken directory is left as it is)", CheckpointFallbackWarning,
                          stacklevel=3)
        return step_dir, found
    raise ValueError(f"{ckpt_dir}: checkpoint steps kept changing (deleted while being read) in {LOAD_ATTEMPTS} "
                     "attempts; try again, or read a step dir that the training run keeps")


def read_params(path: str | os.PathLike, *, require_finite: bool = False) -> tuple[dict, dict]:
    """Load `(model_cfg, params)` from a params-only dir, a training workdir (newest readable step) or a step dir.

    Params come back as a nested dict of float32 `jax.Array`s and are checked against the model's shapes.
    A model.json with `"separate_networks": true` (separate stereo / flow networks) gives params
    `{"stereo": ..., "flow": ...}` and that key is kept in the returned config.

    A training workdir: broken steps (unreadable, incomplete, wrong shapes; with `require_finite` also NaN/Inf
    params) are skipped with a `CheckpointFallbackWarning` naming each, newest first, and the newest step
    that reads completely is used; steps that a running training deletes meanwhile are handled (re-listed).
    Params holding NaN/Inf are returned as they are unless `require_finite` (evaluating a diverged run is a
    legitimate use; `check_finite_params` is the check).
    A recipe workdir reads as its latest stage (`model_dir`).
    Raises:
      ValueError naming the path when it is missing, of an unknown layout, or garbled (for a workdir: when no
      step reads, naming the newest step's problem); with `require_finite`, when the params are not finite.
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
    _, abstract = models.abstract_init(cfg)
    if separate:
        abstract = {"stereo": abstract, "flow": abstract}
    want = jax.tree.map(lambda a: tuple(a.shape), abstract)
    p = model_dir(path)
    if subtree is not None and (p / CHECKPOINTS_DIR).is_dir():  # a training workdir (not one step dir)
        _, params = _read_newest_step(p, want, cfg["name"], require_finite)
    else:
        try:
            params = _read_params(tree_path, subtree, want, cfg["name"], require_finite)
        except FileNotFoundError as e:
            raise ValueError(f"{path}: cannot read checkpoint at {tree_path} ({_reason(e)})") from e
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from e
    if separate:
        cfg["separate_networks"] = True
    # one device_put of the tree: jnp.asarray on a numpy leaf compiles a small XLA program per leaf shape
    return cfg, jax.device_put(jax.tree.map(lambda a: np.asarray(a, np.float32), params))


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


class Restored(NamedTuple):
    """What `TrainCheckpointer.restore_latest` found: the newest step that reads completely."""

    state: Any  # the train state, in the structure / shardings of the abstract state asked for
    data_state: dict  # the grain iterator state saved with it ({} if none was saved)
    step: int  # the step number (the name of its dir checkpoints/<step>)
    broken: list[tuple[int, str]]  # newer steps skipped, newest first: (step, reason)


class CheckpointSaveError(OSError):
    """Writing a checkpoint failed (a full disk, no permission, ...): one line naming the folder, the space a
    checkpoint needs and what is free; the partial step was removed and the last good checkpoint kept."""


# How orbax / tensorstore report a failed write from their writer threads (as ValueError / RuntimeError text).
_IO_ERROR_MARKS = ("RESOURCE_EXHAUSTED", "PERMISSION_DENIED", "os_error_code", "No space left", "Disk quota",
                   "Read-only file system", "Permission denied", "Input/output error")
TMP_SUFFIX = ".orbax-checkpoint-tmp"  # orbax's name for a step dir being written (renamed when complete)


def is_save_io_error(error: BaseException) -> bool:
    """Whether `error` (or an exception it was raised from) is a failed write to the disk."""
    seen = 0
    while error is not None and seen < 10:
        if isinstance(error, OSError) or any(m in str(error) for m in _IO_ERROR_MARKS):
            return True
        error, seen = error.__cause__ or error.__context__, seen + 1
    return False


def _io_cause(error: BaseException) -> str:
    """The operating system's words for a failed write ("No space left on device"), else the error's first line."""
    text = str(error)
    for mark in ("No space left on device", "Disk quota exceeded", "Read-only file system", "Permission denied",
                 "Input/output error"):
        if mark in text:
            return mark
    if isinstance(error, OSError) and error.strerror:
        return error.strerror
    return _reason(error, 160)


def _tree_size(path: Path) -> int:
    total = 0
    for root, _, names in os.walk(path):
        for n in names:
            with contextlib.suppress(OSError):
                total += os.lstat(os.path.join(root, n)).st_size
    return total


def _free_bytes(path: str) -> int | None:
    with contextlib.suppress(OSError):
        return shutil.disk_usage(path).free
    return None


def _mib(n: int) -> str:
    return f"{n / 2**20:.1f} MiB" if n >= 2**20 else f"{max(1, round(n / 1024))} KiB"


def _save_noise(record: logging.LogRecord) -> bool:
    """A log record that only repeats a failed checkpoint write (already reported as one line): orbax's errors
    from its writer threads, asyncio's "exception was never retrieved" of their futures."""
    text = record.getMessage()
    if record.exc_info and record.exc_info[1] is not None:
        text += " " + str(record.exc_info[1])
    if record.name == "asyncio":
        return "never retrieved" in text and any(m in text for m in _IO_ERROR_MARKS)
    return any(m in text for m in _IO_ERROR_MARKS + ("Save Finalize thread (save_finalize) failed",
                                                     "Commit callback in background save thread"))


class _DropSaveNoise(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return not _save_noise(record)


_save_noise_quieted = False


def quiet_save_failure_noise() -> None:
    """Drops (once installed, for the process) what a failed checkpoint write prints besides its one error line:
    orbax's ERROR records and asyncio's "exception was never retrieved" about the same write, and the "Event loop
    is closed" tracebacks of its threads (`_quiet_failed_read_noise`). Other errors pass; the command line does
    not call it with --debug."""
    global _save_noise_quieted
    if _save_noise_quieted:
        return
    for name in ("absl", "asyncio"):
        logging.getLogger(name).addFilter(_DropSaveNoise())
    _quiet_failed_read_noise()
    _save_noise_quieted = True


def _first_bad_json(folder: Path) -> Path | None:
    """The first small JSON file of a checkpoint folder (orbax metadata, the data iterator's state) that does not
    parse: a JSONDecodeError says what is wrong but not in which file."""
    for root, _, names in sorted(os.walk(folder)):
        for name in sorted(names):
            path = Path(root) / name
            if name.endswith(".json") or name in ("_METADATA", "_CHECKPOINT_METADATA", "_sharding"):
                try:
                    if path.stat().st_size < 2**24:
                        json.loads(path.read_bytes() or b"?")
                except (OSError, ValueError):
                    return path
    return None


class TrainCheckpointer:
    """Thin layer over orbax CheckpointManager for WORKDIR/checkpoints/<step>/.

    Every checkpoint holds `state` (the train state {"params", "opt_state", "step", "rng"}, orbax
    StandardCheckpointHandler, sharded arrays welcome) and `data` (the grain iterator state), so a restart
    resumes the exact batch sequence. Saves are asynchronous (the device->host copy happens in `save`, so the
    state may be donated right after); `wait()` blocks until the last one is on disk; the last `keep` are kept.

    Broken steps: `restore_latest` skips them (newest first) and remembers them; the next due `save` first
    moves each of them aside to `checkpoints/<step>.broken-<n>` (renamed, never deleted). Not earlier, so
    restoring alone never changes the workdir; not later, because left in place a broken step would
    collide with the step number a resumed run saves next (orbax refuses an existing step), count as the
    "latest" step, and be deleted by orbax's keep-K clean-up like any old step (seen: gone after 3 saves).
    """

    def __init__(self, workdir: str | os.PathLike, *, save_every: int = 1000, keep: int | None = 3,
                 async_save: bool = True):
        self.directory = str(Path(workdir).absolute() / CHECKPOINTS_DIR)
        self.save_every = int(save_every)
        self.keep = int(keep) if keep and int(keep) > 0 else None
        options = ocp.CheckpointManagerOptions(
            max_to_keep=int(keep) if keep and int(keep) > 0 else None,
            enable_async_checkpointing=bool(async_save), create=True)
        with _quiet_item_dir_metadata():  # an empty or broken step dir: restore_latest says so, by name
            self.manager = ocp.CheckpointManager(
                self.directory, options=options, item_names=(STATE_ITEM, DATA_ITEM),
                item_handlers={STATE_ITEM: ocp.StandardCheckpointHandler(),
                               DATA_ITEM: grain_ckpt.CheckpointHandler()})
        self.broken: dict[int, str] = {}  # step -> reason, found by restore_latest and not yet moved aside
        self.failed: CheckpointSaveError | None = None  # a failed write: raised again by every later save / wait
        self._saving: int | None = None  # the step of the save in flight (async)
        self._state_bytes: int | None = None

    def latest_step(self) -> int | None:
        """The newest step whose save has finished (the last good checkpoint): known-broken steps, a save still
        in flight (orbax lists an async save's step as soon as it starts) and a failed one (no step dir) are
        excluded."""
        in_flight = self._saving if self._saving is not None and self.manager.is_saving_in_progress() else None
        steps = [s for s in self.manager.all_steps()
                 if s not in self.broken and s != in_flight and (Path(self.directory) / str(s)).is_dir()]
        return max(steps) if steps else None

    def all_steps(self) -> list[int]:
        return list(self.manager.all_steps())

    def save(self, step: int, state: Any, data_state: dict | None = None, *, force: bool = False) -> bool:
        """Starts saving step `step` if due (`step % save_every == 0`) or forced; False if not saved.

        Broken steps found by `restore_latest` are moved aside first (see the class doc), as is a dir
        `checkpoints/<step>` that orbax does not list as a checkpoint (it would collide with this save)."""
        step = int(step)
        due = force or (self.save_every > 0 and step % self.save_every == 0)
        if not due:
            return False
        step_dir = Path(self.directory) / str(step)
        if step_dir.exists() and step not in self.manager.all_steps() and step not in self.broken:
            self.broken[step] = "not a checkpoint orbax recognises"
        if self.broken:
            self._move_broken_aside()
        if step in self.manager.all_steps():
            return False
        snapshot = _IteratorSnapshot(json.dumps(data_state if data_state is not None else {}).encode())
        with self._save_errors(step):
            saved = bool(self.manager.save(step, args=ocp.args.Composite(
                **{STATE_ITEM: ocp.args.StandardSave(state), DATA_ITEM: grain_ckpt.CheckpointSave(snapshot)}),
                force=True))
        if saved:
            self._saving = step
            if self._state_bytes is None:
                self._state_bytes = sum(int(getattr(x, "nbytes", 0)) for x in jax.tree.leaves(state))
        return saved

    @contextlib.contextmanager
    def _save_errors(self, step: int | None = None):
        """Turns a failed write (here or reported from orbax's writer threads) into one CheckpointSaveError:
        the partial `<step>.orbax-checkpoint-tmp` dirs are removed and the message names the folder, the
        space one checkpoint takes and what is free. Other errors pass unchanged."""
        if self.failed is not None:
            raise self.failed
        try:
            yield
        except Exception as e:
            if not is_save_io_error(e):
                raise
            with contextlib.suppress(Exception):
                self.manager.wait_until_finished()  # no writer thread may still add files to what is removed
            self.failed = self._save_error(e, self._saving if self._saving is not None else step)
            raise self.failed from e

    def _save_error(self, error: BaseException, step: int | None) -> CheckpointSaveError:
        ckpt_dir = Path(self.directory)
        if jax.process_index() == 0:
            for p in ckpt_dir.glob(f"*{TMP_SUFFIX}*"):
                shutil.rmtree(p, ignore_errors=True)
        good = [s for s in self.manager.all_steps() if s not in self.broken and (ckpt_dir / str(s)).is_dir()]
        need = _tree_size(ckpt_dir / str(max(good))) if good else 0
        need = need or int(self._state_bytes or 0)
        free = _free_bytes(self.directory)
        rooms = (self.keep or 1) + 1  # the checkpoints kept and the one being written
        space = (f"; one checkpoint takes about {_mib(need)}, keeping {rooms - 1} needs room for {rooms}: about "
                 f"{_mib(need * rooms)}" if need else "") + (f"; {_mib(free)} is free" if free is not None else "")
        kept = f"the last good checkpoint, step {max(good)}, is kept" if good else "no checkpoint was saved yet"
        what = f"step {step}" if step is not None else "a checkpoint"
        return CheckpointSaveError(f"{self.directory}: cannot save {what} ({_io_cause(error)}){space}; "
                                   f"the partial step was removed and {kept}")

    def _move_broken_aside(self) -> None:
        """Renames every step dir in `self.broken` to `<step>.broken-<n>` (first free n), with a warning each."""
        self.manager.wait_until_finished()  # no async save or keep-K clean-up may run while dirs move
        if jax.process_index() == 0:  # one process renames; the others wait at the barrier below
            for step, why in sorted(self.broken.items()):
                src = Path(self.directory) / str(step)
                if not src.exists():
                    continue
                n = 1
                while (dst := src.with_name(f"{step}{BROKEN_SUFFIX}{n}")).exists():
                    n += 1
                os.rename(src, dst)
                warnings.warn(f"{src}: broken checkpoint ({why}) moved aside to {dst.name} before saving over its "
                              "step number", CheckpointFallbackWarning, stacklevel=3)
        if jax.process_count() > 1:
            ocp.multihost.sync_global_processes("bridge_jax_move_broken_checkpoints")
        self.broken = {}
        self.manager.reload()

    def restore(self, step: int, abstract_state: Any) -> tuple[Any, dict]:
        """Restores step `step` into the structure/shardings of `abstract_state` -> (state, data_state dict).

        Raises whatever orbax raises on unreadable data; ValueError if the data state is not a JSON object."""
        holder = _IteratorSnapshot()
        out = self.manager.restore(int(step), args=ocp.args.Composite(
            **{STATE_ITEM: ocp.args.StandardRestore(abstract_state), DATA_ITEM: grain_ckpt.CheckpointRestore(holder)}))
        data_state = json.loads(holder.state.decode()) if holder.state else {}
        if not isinstance(data_state, dict):
            raise ValueError(f"data iterator state is a JSON {type(data_state).__name__}, not an object")
        return out[STATE_ITEM], data_state

    def _unusable(self, step: int, abstract_state: Any) -> tuple[str, Any, dict]:
        """`(reason, state, data_state)` for one step; reason "" when it restored completely and is finite."""
        step_dir = Path(self.directory) / str(step)
        if not step_dir.is_dir():
            return "not a directory", None, {}
        if not any(step_dir.iterdir()):
            return "empty directory", None, {}
        missing = [item for item in (STATE_ITEM, DATA_ITEM) if not (step_dir / item).is_dir()]
        if missing:  # checked here: orbax's own message for it is a KeyError listing "available items"
            return f"incomplete: no {' / '.join(missing)} item", None, {}
        try:
            state, data_state = self.restore(step, abstract_state)
        except Exception as e:  # orbax / tensorstore / json raise many types on truncated or garbled files
            _quiet_failed_read_noise()
            bad = _first_bad_json(step_dir) if isinstance(e, json.JSONDecodeError) else None
            return (f"{bad}: " if bad else "") + _reason(e), None, {}
        # Resuming into NaN/Inf is useless (every step would be skipped): such a state counts as broken.
        parts = ([("params", state["params"])] + [(k, v) for k, v in state.items() if k != "params"]
                 if isinstance(state, dict) and "params" in state else [("state", state)])
        for name, tree in parts:
            bad = first_nonfinite(tree)
            if bad is not None:
                return f"{name} not finite: {bad[0]} has {bad[1]} non-finite values (NaN/Inf)", None, {}
        return "", state, data_state

    def restore_latest(self, abstract_state: Any, *, warn: bool = True) -> Restored | None:
        """The newest step that restores completely (state AND data item, finite state), or None if no step exists.

        Steps are tried newest first: those orbax lists and any other `checkpoints/<step>` dir (orbax may
        skip an empty or partial one). Each broken step (unreadable, truncated or garbled file, empty or
        incomplete dir, NaN/Inf in the state) gets a CheckpointFallbackWarning naming its dir and the reason
        (first line of the error), and is returned in `broken`; nothing is deleted (the next `save` moves
        them aside, see the class doc).
        Args:
          abstract_state: the train state's structure, e.g. a tree of `jax.ShapeDtypeStruct` with shardings.
          warn: emit the warnings (e.g. `warn=is_main`: every process finds the same broken steps).
        Raises:
          ValueError naming the checkpoints dir and the newest step's problem when no step is usable.
        """
        on_disk = {int(p.name) for p in _step_dirs(Path(self.directory))}
        steps = sorted(set(self.manager.all_steps()) | on_disk, reverse=True)
        if not steps:
            return None
        broken: list[tuple[int, str]] = []
        for step in steps:
            with _quiet_item_dir_metadata():
                why, state, data_state = self._unusable(step, abstract_state)
            if not why:
                break
            broken.append((step, why))
        else:
            more = f"; the {len(broken) - 1} older step(s) are broken too" if len(broken) > 1 else ""
            raise ValueError(f"{self.directory}: no usable checkpoint; the newest, step {steps[0]}, is broken "
                             f"({broken[0][1]}){more}. Nothing was changed: move the broken step dirs away to "
                             "start this workdir afresh, or train in a new workdir")
        for bad, why in broken if warn else []:
            warnings.warn(f"{self.directory}/{bad}: skipped a broken checkpoint ({why}); resuming from step {step} "
                          f"(the directory is kept, moved aside to {bad}{BROKEN_SUFFIX}<n> at the next save)",
                          CheckpointFallbackWarning, stacklevel=2)
        self.broken = dict(broken)
        return Restored(state, data_state, step, broken)

    def wait(self) -> None:
        with self._save_errors():
            self.manager.wait_until_finished()
        self._saving = None

    def close(self) -> None:
        """Waits for the last save and closes; after a failed save, only closes (the failure was raised)."""
        if self.failed is not None:
            with contextlib.suppress(Exception):
                self.manager.close()
            return
        try:
            self.wait()
        finally:
            with contextlib.suppress(Exception) if self.failed is not None else contextlib.nullcontext():
                self.manager.close()


def find_train_step_dir(path: str | os.PathLike) -> str | None:
    """Latest `checkpoints/<step>` dir (with a `state` item) of a workdir (of a recipe workdir's latest stage,
    `model_dir`), or `path` itself if it is a step dir."""
    p = Path(path).absolute()
    if (p / RECIPE_JSON).is_file():
        try:
            p = model_dir(p)
        except ValueError:
            return None
    if p.parent.name == CHECKPOINTS_DIR and p.name.isdigit() and (p / STATE_ITEM).is_dir():
        return str(p)
    ckpts = p / CHECKPOINTS_DIR
    if not ckpts.is_dir():
        return None
    steps = sorted((int(q.name), q) for q in ckpts.iterdir()
                   if q.is_dir() and q.name.isdigit() and (q / STATE_ITEM).is_dir())
    return str(steps[-1][1]) if steps else None


def restore_train_params(step_dir: str | os.PathLike) -> dict:
    """The params that stand for the model of a training step dir (`MODEL_PARAMS`: the moving average where the
    run kept one), as numpy arrays."""
    return _restore_tree(Path(step_dir).absolute() / STATE_ITEM, MODEL_PARAMS)
