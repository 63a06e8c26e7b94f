"""Recipes: one training run made of ordered stages, declared as data in a config file and run by one command.

    bridge-train --config=long --workdir=W          # every stage of the `long` recipe, from random init
    bridge-train --config=long --workdir=W          # again after a kill: resumes the stage it was in, at its step

A recipe config is an ordinary training config (the *base*) plus two fields:

    c.stages = ("coarse", "finish")                # the stages, in order
    c.stage_overrides.coarse = {...}               # what each stage sets on top of the base (nested like the
    c.stage_overrides.finish = {"height": 128, "width": 256, "lr": 2.5e-4, "loop": {"num_train_steps": 300}}

A stage's config is the base with its overrides applied (`stage_config`); it may set any field of the base
(working size, batch, lr and its schedule, data scene, loss switches, augmentation, steps, seed), but not
`init_from` after the first stage: stage k > 0 always starts from stage k - 1's final params. On the command line
`--config.KEY=VALUE` sets the base *and* every stage that sets KEY, so the command line wins everywhere
(`override_everywhere`); `--config.stage_overrides.NAME.KEY=VALUE` sets one stage only (any field of the base); `--config.stages=a,b` keeps
only those stages (the first one kept starts from the base's `init_from`, random init unless set).

Optimiser state at a stage boundary: a stage starts with fresh Adam moments and its own step counter, so its lr
schedule (`lr`, `lr_milestones`, `loop.steps_per_epoch`) counts from its own first step. The stages change what
the gradient sees (working size, scenes, loss terms), so moments accumulated for the previous stage's gradients
would scale the first steps of the next one wrongly; and a stage is then exactly a fine-tune from the previous
stage's params (`init_from`), which is how each stage can also be run, inspected or replaced on its own.

Workdir layout (W):

    recipe.json                   the stage names and each stage's config (written before the first stage runs)
    stages/<name>/                each stage's own training workdir (config.json, model.json, checkpoints/, images/)
    stages/<name>/finished.json   written when the stage has finished: a finished stage never runs again
    metrics.jsonl                 every record of every stage: "stage" (its name), "stage_step" (the step inside
                                  the stage) and "step" (counted across the recipe, so the curves continue)
    tensorboard/                  one event log across the recipe; `recipe/stage_index` steps up at each boundary
    status.json                   the running stage (its name, index and step); `bridge-train --status W`

Anywhere a checkpoint path is taken (predict, evaluate, export, `init_from`, `bridge-zoo build`), W stands for its
latest stage with a checkpoint (`checkpointing.model_dir`): the recipe's model once it has finished.
"""

from __future__ import annotations

import copy
import dataclasses
import json
import os
import re
from typing import Any, Optional, Sequence

import ml_collections

from bridge_jax import checkpointing, configs, files

RECIPE_JSON = checkpointing.RECIPE_JSON
STAGES_DIR = checkpointing.STAGES_DIR
FINISHED_JSON = "finished.json"
STAGE_NAME = re.compile(r"^[a-z][a-z0-9_]{0,31}$")


@dataclasses.dataclass(frozen=True)
class StageRun:
    """One stage of a recipe as the trainer runs it: where it logs (`log_dir`, the recipe workdir W), its name,
    its 0-based `index` of `count`, `offset`, the steps of the stages before it (so that the recipe's step
    counter continues across stages), and `seconds_before`, what earlier, stopped runs of this stage took
    (`workdir.stage_seconds_before`; written into status.json so that it adds up over several interruptions)."""

    name: str
    index: int
    count: int
    offset: int
    log_dir: str
    seconds_before: float = 0.0

    @property
    def label(self) -> str:
        return f"stage {self.index + 1}/{self.count} {self.name}"


def is_recipe(config: Any) -> bool:
    """Whether `config` (a ConfigDict) declares stages."""
    return isinstance(config, ml_collections.ConfigDict) and bool(config.get("stages", ()))


def stage_names(config: ml_collections.ConfigDict) -> tuple[str, ...]:
    """The stage names in order; ValueError naming `config.stages` when they are not unique lower-case names."""
    names = config.get("stages", ())
    if isinstance(names, str) or not all(isinstance(n, str) for n in names):
        raise ValueError(f"config.stages must be a tuple of stage names, got {names!r}")
    names = tuple(names)
    bad = [n for n in names if not STAGE_NAME.match(n)]
    if bad:
        raise ValueError(f"config.stages: {bad} are not stage names (lower-case letters, digits and '_', starting "
                         "with a letter, at most 32 characters)")
    if len(set(names)) != len(names):
        raise ValueError(f"config.stages: {list(names)} names a stage twice")
    overrides = config.get("stage_overrides", ml_collections.ConfigDict())
    extra = sorted(set(overrides.keys()) - set(names))
    if extra:
        raise ValueError(f"config.stage_overrides sets stages {extra} that config.stages {list(names)} does not name")
    return names


def base_config(config: ml_collections.ConfigDict) -> ml_collections.ConfigDict:
    """A copy of `config` without its recipe fields (what every stage starts from)."""
    base = copy.deepcopy(config)
    with base.unlocked():
        for key in ("stages", "stage_overrides"):
            if key in base:
                del base[key]
    return base


def flat_keys(tree: dict, prefix: str = "") -> dict[str, Any]:
    """{dotted key: value} of the leaves of a nested dict."""
    out = {}
    for k, v in tree.items():
        if isinstance(v, dict):
            out.update(flat_keys(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def stage_settings(config: ml_collections.ConfigDict, name: str) -> dict[str, Any]:
    """{dotted key: value} that stage `name` sets on top of the base."""
    overrides = config.get("stage_overrides", ml_collections.ConfigDict())
    return flat_keys(overrides[name].to_dict()) if name in overrides else {}


def stage_config(config: ml_collections.ConfigDict, name: str) -> ml_collections.ConfigDict:
    """Stage `name`'s training config: the base with the stage's settings applied. ValueError naming
    `config.stage_overrides.<name>.<key>` for a field the base does not have, or a value of the wrong type."""
    stage = base_config(config)
    for key, value in stage_settings(config, name).items():
        where = f"config.stage_overrides.{name}.{key}"
        *path, last = key.split(".")
        node = stage
        for part in path:
            if not isinstance(node, ml_collections.ConfigDict) or part not in node:
                raise ValueError(f"{where}: the config has no field {key!r}")
            node = node[part]
        if not isinstance(node, ml_collections.ConfigDict) or last not in node:
            raise ValueError(f"{where}: the config has no field {key!r}")
        try:
            node[last] = tuple(value) if isinstance(value, list) else value
        except (TypeError, ValueError) as e:
            raise ValueError(f"{where}: {e}") from e
    return stage


def single_run(config: ml_collections.ConfigDict, stage: Optional[str] = None) -> ml_collections.ConfigDict:
    """A config of one training run: `config` itself when it declares no stages, else the config of its stage
    `stage` (default: the first), for tools that run one step or one run (the benchmark, ablations)."""
    if not is_recipe(config):
        return config
    names = stage_names(config)
    if stage is not None and stage not in names:
        raise ValueError(f"the recipe has no stage {stage!r} (its stages: {', '.join(names)})")
    return stage_config(config, stage or names[0])


def override_everywhere(config: ml_collections.ConfigDict, items: Sequence[str]) -> ml_collections.ConfigDict:
    """`configs.override` for a recipe: `KEY=VALUE` sets the base and every stage that sets KEY (the command
    line wins over the recipe's stages); `stage_overrides.NAME.KEY=VALUE` sets (or adds) KEY for stage NAME,
    checked against the base. ValueError naming the item as `configs.override` does."""
    names = stage_names(config)
    for item in items:
        key, eq, text = item.partition("=")
        if key == "stages" and eq:
            names = select_stages(config, text)
            continue
        if key.startswith("stage_overrides.") and eq:
            parts = key.split(".", 2)
            if len(parts) < 3 or parts[1] not in names or not parts[2]:
                raise ValueError(f"{item!r}: expected stage_overrides.NAME.KEY=VALUE with NAME one of {list(names)}")
            name, field = parts[1], configs.moved_key(parts[2], config, note=_quiet)
            probe = stage_config(config, name)
            configs.override(probe, [f"{field}={text}"], hint_prefix="--config.")  # checks the field and its type
            _set_stage(config, name, field, _get(probe, field))
            continue
        configs.override(config, [item], hint_prefix="--config.")
        if not eq:
            continue
        key = configs.moved_key(key, config, note=_quiet)
        for name in names:
            if key in stage_settings(config, name):
                _set_stage(config, name, key, _get(config, key))
    return config


def select_stages(config: ml_collections.ConfigDict, text: str) -> tuple[str, ...]:
    """`--config.stages=a,b`: keep only the recipe's stages `a`, `b` (a comma-separated list, in the recipe's
    order; "(a, b)" is read the same), dropping the others and their overrides, e.g. `stages=coarse` to time or
    inspect one stage; the first stage kept starts from the base's `init_from`. ValueError naming the item when a name is not one of the recipe's stages."""
    names = stage_names(config)
    chosen = [n.strip().strip("'\"") for n in text.strip().strip("()[]").split(",")]
    chosen = [n for n in chosen if n]
    unknown = [n for n in chosen if n not in names]
    if not chosen or unknown:
        raise ValueError(f"'stages={text}': expected a comma-separated list of this recipe's stages "
                         f"{list(names)}" + (f"; {unknown} are not among them" if unknown else ""))
    if len(set(chosen)) != len(chosen):
        raise ValueError(f"'stages={text}': names a stage twice")
    kept = tuple(n for n in names if n in chosen)
    with config.unlocked():
        config.stages = kept
        for name in names:
            if name not in kept and name in config.get("stage_overrides", {}):
                del config.stage_overrides[name]
    return kept


def _quiet(old: str, new: str) -> None:  # noqa: ARG001  (configs.override already noted a moved key once)
    pass


def _get(config: ml_collections.ConfigDict, key: str):
    node = config
    for part in key.split("."):
        node = node[part]
    return node


def _set_stage(config: ml_collections.ConfigDict, name: str, key: str, value) -> None:
    with config.unlocked():
        if "stage_overrides" not in config:
            config.stage_overrides = ml_collections.ConfigDict()
        if name not in config.stage_overrides:
            config.stage_overrides[name] = ml_collections.ConfigDict()
        node = config.stage_overrides[name]
        *path, last = key.split(".")
        for part in path:
            if part not in node:
                node[part] = ml_collections.ConfigDict()
            node = node[part]
        if last in node:
            del node[last]
        node[last] = copy.deepcopy(value)


# ----------------------------------------------------------------------------------------------------------
# The recipe workdir
# ----------------------------------------------------------------------------------------------------------

def stage_dir(workdir: str, name: str) -> str:
    return os.path.join(workdir, STAGES_DIR, name)


def read_record(workdir: str) -> Optional[dict]:
    """W/recipe.json, or None when W is not a recipe workdir."""
    path = os.path.join(workdir, RECIPE_JSON)
    if not os.path.isfile(path):
        return None
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError) as e:
        raise ValueError(f"{path}: unreadable ({e})") from None


def code_commit() -> Optional[str]:
    """The git commit of the checkout `bridge_jax` is imported from ("-dirty" appended when tracked files differ
    from it), or None when it is not a git checkout (an installed wheel) or git is missing."""
    import subprocess

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    try:
        head = subprocess.run(["git", "-C", root, "rev-parse", "HEAD"], capture_output=True, text=True, timeout=30)
        if head.returncode != 0:
            return None
        dirty = subprocess.run(["git", "-C", root, "diff", "--quiet", "HEAD", "--"], capture_output=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    return head.stdout.strip() + ("-dirty" if dirty.returncode == 1 else "")


def write_record(workdir: str, names: Sequence[str], stage_configs: dict[str, dict],
                 config_name: Optional[str] = None, commit: Optional[str] = None) -> None:
    """W/recipe.json: the stage names in order, each stage's config, the `--config` the recipe was run with
    (what `bridge-zoo build` writes on a card as the command that rebuilds the model), and the code's `commit`
    (`code_commit`). A resumed run keeps the commit the recipe started at and lists any other it resumed at
    under "resumed_at_commits", so a card says when a model's stages ran on different code."""
    earlier = read_record(workdir) or {}
    # a record written before commits were recorded started on unknown code: it stays without one
    record = {"stages": list(names), "configs": stage_configs, "config_name": config_name,
              "commit": earlier.get("commit") if earlier else commit}
    resumed = list(earlier.get("resumed_at_commits") or [])
    if earlier and commit != record["commit"] and commit not in resumed:
        resumed.append(commit)
    if resumed:
        record["resumed_at_commits"] = resumed
    files.write_json(os.path.join(workdir, RECIPE_JSON), record)


def finished(workdir: str, name: str) -> Optional[dict]:
    """The stage's finished.json ({"steps", "seconds", "validation"}), or None while it has not finished."""
    path = os.path.join(stage_dir(workdir, name), FINISHED_JSON)
    try:
        with open(path) as f:
            return json.load(f)
    except (OSError, ValueError):
        return None


def mark_finished(workdir: str, name: str, steps: int, seconds: float, validation: dict) -> None:
    files.write_json(os.path.join(stage_dir(workdir, name), FINISHED_JSON),
                     {"steps": int(steps), "seconds": round(float(seconds), 1), "validation": validation})
