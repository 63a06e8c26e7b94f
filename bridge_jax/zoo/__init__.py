"""Models by name: the weights shipped inside the package and a registry of other known checkpoints.

    bridge-predict --checkpoint demo frame0.png frame1.png --out out/    # from any directory
    from bridge_jax.inference import load_predictor
    pred = load_predictor("demo")                    # the shipped demo model, at the size it was trained at
    bridge-zoo                         # lists the names
    bridge-zoo build demo --from work/demo/train   # regenerate the shipped weights (maintainers)

Wherever a command takes `--checkpoint` (predict, evaluate, export) or a config takes `init_from`, a registry
name works as well as a path. Kinds of entry:

* **shipped** (`demo`): float32 params in `bridge_jax/zoo/<name>.npz` (one array per parameter, keys are the
  parameter paths joined by "/") and `<name>.json` (model description, working size, how it was trained, its
  validation numbers and the npz's SHA-256). Nothing is downloaded.
* **local** (`upstream_ver_a/b/c`): the upstream authors' released PyTorch weights, converted once with
  `bridge-convert` to a params folder under `$BRIDGE_JAX_HOME` (default `~/.cache/bridge_jax`);
  the entry says where to download the `.pth` file and the exact command. Until converted, using the name is one
  error naming that command.

`register(name, path)` adds a name for a checkpoint folder of your own (this process only).
"""
from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import os
from pathlib import Path
from collections.abc import Sequence
from typing import Any, Optional

import numpy as np

from bridge_jax import cli
from bridge_jax.testtime import TestTime

HOME_ENV = "BRIDGE_JAX_HOME"
ZOO_DIR = Path(__file__).resolve().parent
UPSTREAM_DOWNLOAD = "https://drive.google.com/drive/folders/1l6HLF2Dq1ObsTjdJaAPKK6NOAZDOI0Rs"


def home() -> Path:
    """Where converted / downloaded weights live: `$BRIDGE_JAX_HOME`, default `~/.cache/bridge_jax`."""
    return Path(os.environ.get(HOME_ENV) or "~/.cache/bridge_jax").expanduser()


@dataclasses.dataclass(frozen=True)
class Entry:
    """One named model. `kind`: "shipped" (npz + json in this folder) or "local" (a checkpoint folder,
    `path`, that `how` creates from the file at `download`)."""

    name: str
    kind: str
    description: str
    path: Optional[str] = None
    download: Optional[str] = None
    how: Optional[str] = None

    def local_path(self) -> Path:
        return Path(self.path).expanduser() if os.path.isabs(os.path.expanduser(self.path)) else home() / self.path


_ENTRIES: dict[str, Entry] = {
    "demo": Entry("demo", "shipped", "pwc_lite (374 k params) trained by `make demo` on the built-in synthetic "
                  "stereo video (the `demo` recipe: 1,750 steps at 64x128, then its `finish` stage: 300 steps at "
                  "128x256); a starting point, not a KITTI model; by default at 192x384 with one "
                  "--refine pass and --polish photometric"),
    "long": Entry("long", "shipped", "pwc_lite fine-tuned from an earlier, one-phase `demo` model, "
                  "at 128x256, then 256x512, on the synthetic "
                  "scenes that carry over to real images (photo textures, slanted and rotating objects, varied rigs, "
                  "per-camera photometric differences, vertical motion), with self-supervision and the census loss "
                  "(five stages run by hand, the recipe `long:legacy`: `bridge-zoo show long`); for "
                  "your own images; by default at --working-size native with one --refine pass, --symmetry "
                  "flips and --polish photometric+fill"),
    **{f"upstream_ver_{v}": Entry(
        f"upstream_ver_{v}", "local",
        f"the upstream authors' released resnet_md weights `monodepth_ver_{v}.pth` (retrained after the paper; "
        f"variant full-{i}), converted to bridge_jax",
        path=f"upstream_ver_{v}", download=UPSTREAM_DOWNLOAD,
        how=f"bridge-convert --from monodepth_ver_{v}.pth --out {{path}}")
       for i, v in enumerate("abc", start=1)},
}


def names() -> list[str]:
    return sorted(_ENTRIES)


def entry(name: str) -> Entry:
    """The registry entry `name`; ValueError naming the close matches when unknown."""
    if name not in _ENTRIES:
        close = difflib.get_close_matches(name, names(), n=3)
        hint = f" (did you mean {', '.join(close)}?)" if close else ""
        raise ValueError(f"{name!r} is neither an existing path nor a model name{hint}; model names: "
                         f"{', '.join(names())}")
    return _ENTRIES[name]


def register(name: str, path: str | os.PathLike, description: str = "") -> None:
    """Names a checkpoint folder of your own (params dir, training workdir or step dir) for this process."""
    _ENTRIES[name] = Entry(name, "local", description or f"registered: {path}", path=os.path.abspath(path))


def is_name(spec: Any) -> bool:
    """True when `spec` should be looked up in the registry: a plain name (no path separator, no ".") that is
    not an existing file or folder in the current directory."""
    s = os.fspath(spec) if isinstance(spec, (str, os.PathLike)) else None
    return bool(s) and os.sep not in s and "/" not in s and not s.startswith(".") and not os.path.exists(s)


def _shipped_files(name: str) -> tuple[Path, Path]:
    return ZOO_DIR / f"{name}.npz", ZOO_DIR / f"{name}.json"


def info(name: str) -> dict:
    """The shipped model's description (`<name>.json`): {"model", "height", "width", "config", "steps",
    "validation", "sha256", ...}; for a local entry {"path", "download", "how"}."""
    e = entry(name)
    if e.kind == "shipped":
        return json.loads(_shipped_files(name)[1].read_text())
    return {"path": str(e.local_path()), "download": e.download, "how": (e.how or "").format(path=e.local_path())}


def local_checkpoint(name: str) -> Optional[Path]:
    """The checkpoint folder of a local entry (ValueError with the conversion command when it is missing);
    None for a shipped entry."""
    e = entry(name)
    if e.kind == "shipped":
        return None
    p = e.local_path()
    if not p.exists():
        how = f"; create it with: {e.how.format(path=p)}" if e.how else ""
        where = f" (download from {e.download})" if e.download else ""
        raise ValueError(f"model {name!r} is not on this machine: {p} does not exist{how}{where}")
    return p


def _unflatten(flat: dict[str, np.ndarray]) -> dict:
    tree: dict = {}
    for key, value in flat.items():
        node = tree
        *parents, leaf = key.split("/")
        for part in parents:
            node = node.setdefault(part, {})
        node[leaf] = value
    return tree


def _flatten(tree: dict, prefix: str = "") -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    for k, v in tree.items():
        if "/" in str(k):
            raise ValueError(f"parameter key {k!r} contains '/'")
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + "/"))
        else:
            out[key] = np.asarray(v, np.float32)
    return out


def load_shipped(name: str) -> tuple[dict, dict]:
    """(model config, params as nested dict of float32 numpy arrays) of a shipped model, checked against its
    recorded SHA-256 and against the model's parameter shapes."""
    from bridge_jax import models  # heavy import (flax) only when weights are loaded

    npz, _ = _shipped_files(name)
    meta = info(name)
    data = npz.read_bytes()
    digest = hashlib.sha256(data).hexdigest()
    if digest != meta.get("sha256"):
        raise ValueError(f"{npz}: SHA-256 {digest[:12]}… differs from {name}.json's {str(meta.get('sha256'))[:12]}… "
                         "(a damaged install: reinstall bridge_jax)")
    with np.load(npz, allow_pickle=False) as z:
        params = _unflatten({k: z[k] for k in z.files})
    cfg = models.model_config(meta["model"])
    _, abstract = models.abstract_init(cfg)
    import jax
    want = jax.tree.map(lambda a: tuple(a.shape), abstract)
    got = jax.tree.map(lambda a: tuple(a.shape), params)
    if want != got:
        raise ValueError(f"{npz}: params do not match model {cfg['name']} (a damaged install: reinstall bridge_jax)")
    return cfg, params


def load_params(spec: str | os.PathLike) -> tuple[dict, dict]:
    """`checkpointing.read_params` that also takes a registry name: (model config, params)."""
    from bridge_jax import checkpointing

    if is_name(spec):
        e = entry(os.fspath(spec))
        if e.kind == "shipped":
            import jax
            cfg, params = load_shipped(e.name)
            # device_put of the whole tree: jnp.asarray on a numpy leaf compiles a small XLA program per shape
            return cfg, jax.device_put(_map(params, lambda a: np.asarray(a, np.float32)))
        spec = local_checkpoint(e.name)
    return checkpointing.read_params(spec)


def _map(tree, fn):
    return {k: _map(v, fn) if isinstance(v, dict) else fn(v) for k, v in tree.items()}


def _shipped_info(spec: str | os.PathLike) -> Optional[dict]:
    """`info(spec)` when `spec` names a shipped model, else None (a path, or a local entry)."""
    if is_name(spec) and os.fspath(spec) in _ENTRIES and _ENTRIES[os.fspath(spec)].kind == "shipped":
        return info(os.fspath(spec))
    return None


def trained_size(spec: str | os.PathLike) -> Optional[tuple[int, int]]:
    """(height, width) a shipped model was trained at; None for anything else (paths are handled by
    `inference.trained_working_size`)."""
    meta = _shipped_info(spec)
    return None if meta is None else (int(meta["height"]), int(meta["width"]))


LINEAGE_DEPTH = 16  # at most this many init_from links are followed back to a shipped model


def _recorded_init_from(spec: str | os.PathLike, seen: set[str]) -> Optional[str]:
    """The "init_from" recorded in the config.json of the training workdir that `spec` stands for (a recipe
    workdir: its latest stage, `checkpointing.model_dir`; a step dir `checkpoints/<step>`: its workdir); None
    when there is none (random init, a params-only dir, no such path, unreadable) or that workdir is in `seen`
    (a cycle), which it is added to."""
    from bridge_jax import checkpointing  # heavy import (jax) only for paths

    try:
        p = checkpointing.model_dir(spec)
    except (ValueError, OSError):  # a recipe workdir without a checkpoint yet: reading its params says so
        return None
    if p.parent.name == checkpointing.CHECKPOINTS_DIR and p.name.isdigit():
        p = p.parent.parent
    key = os.path.realpath(p)
    if key in seen:
        return None
    seen.add(key)
    try:
        value = json.loads((p / checkpointing.CONFIG_JSON).read_text()).get("init_from")
    except (OSError, ValueError, AttributeError):
        return None
    return value if isinstance(value, str) and value else None


def card_lineage(spec: str | os.PathLike) -> list[str]:
    """How `spec` descends from a shipped model, whose card's recommended test-time settings then stand for it:
    [spec, what it was initialised from, ..., the shipped name] — [name] for a shipped name itself; a checkpoint
    path (or a local entry's folder) is followed through its workdir's recorded `init_from` (paths as recorded,
    at most `LINEAGE_DEPTH` links). [] when the chain ends elsewhere: random init, a params-only dir, an unknown
    name, a missing path, a cycle."""
    chain: list[str] = []
    seen: set[str] = set()
    current: Optional[str] = os.fspath(spec)
    for _ in range(LINEAGE_DEPTH + 1):
        if current is None:
            return []
        chain.append(current)
        where: str | os.PathLike = current
        if is_name(current):
            e = _ENTRIES.get(current)
            if e is None:
                return []
            if e.kind == "shipped":
                return chain
            where = e.local_path()
        current = _recorded_init_from(where, seen)
    return []


def defaults_source(spec: str | os.PathLike) -> Optional[str]:
    """The shipped model whose card gives `spec`'s default test-time settings (`card_working_size`,
    `card_test_time`): `spec` itself when it names one, the one a checkpoint was fine-tuned from
    (`card_lineage`), else None (the plain defaults)."""
    chain = card_lineage(spec)
    return chain[-1] if chain else None


def _card(spec: str | os.PathLike) -> dict:
    """The card of the shipped model `spec` is or descends from (`defaults_source`), or {} (none)."""
    source = defaults_source(spec)
    return (None if source is None else _shipped_info(source)) or {}


def card_working_size(spec: str | os.PathLike) -> Optional[str | tuple[int, int]]:
    """The working size the card of the shipped model `spec` is or was fine-tuned from (`defaults_source`)
    recommends, chosen by its real-image checks: "native", "trained" or a fixed (H, W) (the card's "HxW"); None
    (no card entry, or no shipped model in its lineage)."""
    value = _card(spec).get("default_working_size")
    return None if value is None else cli.parse_working_size(value)


def card_polish_resolution(spec: str | os.PathLike) -> Optional[str]:
    """Where the card of the shipped model `spec` is or was fine-tuned from (`defaults_source`) runs its polish
    ("input" or "working", `polish.PolishConfig.resolution`), chosen by its real-image checks; None (no card
    entry: the polish's own default)."""
    return _card(spec).get("default_polish_resolution")


def card_polish_settings(spec: str | os.PathLike) -> dict:
    """The `polish.PolishConfig` fields the card of the shipped model `spec` is or was fine-tuned from
    (`defaults_source`) sets, chosen by its real-image checks: its "default_polish_settings" ({field: value})
    and, as "resolution", its `card_polish_resolution`; {} = the polish's own defaults. ValueError naming the
    card for a field `PolishConfig` does not have."""
    from bridge_jax.polish import PolishConfig
    card = _card(spec)
    settings = dict(card.get("default_polish_settings") or {})
    unknown = sorted(set(settings) - {f.name for f in dataclasses.fields(PolishConfig)})
    if unknown:
        raise ValueError(f"the card of {defaults_source(spec)!r}: default_polish_settings names {unknown}, which "
                         f"polish.PolishConfig does not have")
    if card.get("default_polish_resolution"):
        settings["resolution"] = card["default_polish_resolution"]
    return settings


def card_polish_config(spec: str | os.PathLike, **overrides):
    """The `polish.PolishConfig` the card of the shipped model `spec` is or was fine-tuned from was measured with:
    the polish's defaults with the card's fields (`card_polish_settings`), then `overrides`, on top."""
    from bridge_jax.polish import DEFAULT_CONFIG
    return dataclasses.replace(DEFAULT_CONFIG, **{**card_polish_settings(spec), **overrides})


def card_test_time(spec: str | os.PathLike) -> TestTime:
    """The test-time stages the card of the shipped model `spec` is or was fine-tuned from (`defaults_source`)
    recommends, chosen by its real-image checks (`TestTime.from_card`); `TestTime()` without such a card."""
    return TestTime.from_card(_card(spec))


def resolve_path(spec: str | os.PathLike) -> str:
    """A registry name of a local entry → its folder; a path → itself; a shipped name → ValueError (it has no
    folder: use `load_params`)."""
    if is_name(spec):
        p = local_checkpoint(os.fspath(spec))
        if p is None:
            raise ValueError(f"model {spec!r} is shipped inside the package and has no checkpoint folder")
        return str(p)
    return os.fspath(spec)


def training_summary(workdir: str | os.PathLike) -> dict:
    """How a training workdir's run went, from its metrics log: {"first_step", "last_step", "seconds" (wall time
    between its first and last logged training steps, resumptions included)}; {} without a log."""
    first = last = None
    try:
        with open(Path(workdir) / "metrics.jsonl") as f:
            for line in f:
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                if rec.get("kind") == "train" and "time" in rec:
                    first = first or rec
                    last = rec
    except OSError:
        return {}
    if first is None:
        return {}
    return {"first_step": int(first["step"]), "last_step": int(last["step"]),
            "seconds": round(float(last["time"]) - float(first["time"]), 1)}


def stage_summary(config: str, workdir: str | os.PathLike, machine: Optional[str] = None) -> dict:
    """One earlier stage of a shipped model (a run whose weights the shipped run started from): {"config" (the
    `--config` it ran, as given), "steps" (its last checkpoint), "init_from", "lr", "seconds", "machine"}, read from
    its finished training workdir."""
    run_cfg, steps = _finished_run(workdir, f"earlier stage {config}")
    return {"config": config, "steps": steps, "init_from": run_cfg.get("init_from", ""),
            "lr": run_cfg.get("lr"), "seconds": training_summary(workdir).get("seconds", 0.0),
            "machine": machine or _this_machine()}


def shipped_stages(config: str, name: str) -> list[dict]:
    """The stages of shipped model `name` as earlier stages of a run that continued from its weights: the earlier
    stages its card lists, then `name` itself as the newest, with `config` (the `--config` it ran) — what
    `stage_summary` would have read from its workdir, read from its card instead (the workdir of a model shipped
    by an earlier session need not be at hand)."""
    meta = info(name)
    cfg, training = meta.get("config") or {}, meta.get("training") or {}
    itself = {"config": config, "steps": meta.get("steps"), "init_from": cfg.get("init_from", ""),
              "lr": cfg.get("lr"), "seconds": training.get("seconds", 0.0), "machine": training.get("machine", "?")}
    return [dict(s) for s in meta.get("earlier_stages") or []] + [itself]


def _finished_run(workdir: str | os.PathLike, what: str) -> tuple[dict, int]:
    """(the recorded config, the step of the newest checkpoint) of a finished training workdir; ValueError naming
    `what` when it is not one."""
    from bridge_jax import checkpointing  # heavy import only for maintainers

    step_dir = checkpointing.find_train_step_dir(workdir)
    cfg_path = checkpointing.model_dir(workdir) / checkpointing.CONFIG_JSON  # a recipe: its last stage's
    if step_dir is None or not cfg_path.is_file():
        raise ValueError(f"{what}: {workdir} is not a finished training workdir (expected "
                         f"{checkpointing.CONFIG_JSON} and a checkpoint under checkpoints/)")
    return json.loads(cfg_path.read_text()), int(Path(step_dir).name)


def build_shipped(name: str, workdir: str | os.PathLike, *, validation: Optional[dict] = None,
                  card: Optional[dict] = None, machine: Optional[str] = None,
                  earlier_stages: Sequence[tuple[str, str | os.PathLike]] = (),
                  after_shipped: Optional[tuple[str, str]] = None) -> Path:
    """Writes `<name>.npz` + `<name>.json` from a finished training workdir (maintainers: after the `demo`
    config changes, retrain with `make demo` and run `bridge-zoo build demo --from
    work/demo/train`). The json records the run's config so a test notices when the config moved on, and its
    card: the training time (`training_summary`) on `machine` (default: this one), plus the entries of `card`
    (e.g. {"real_images": the numbers of its real-image checks}) that `bridge-zoo show` prints.
    `earlier_stages`: (config, workdir) of the runs this one was initialised from, oldest first
    (`stage_summary`); `after_shipped`: (config, name) of a shipped model those runs (or this one) continued,
    whose own stages come first (`shipped_stages`, read before its files are overwritten)."""
    import io

    from bridge_jax import checkpointing, files, workdir as run_workdir  # heavy imports only for maintainers

    workdir = Path(workdir).absolute()
    cfg, params = checkpointing.read_params(workdir)
    checkpointing.check_finite_params(params, str(workdir))
    run_cfg, step = _finished_run(workdir, "--from")
    buf = io.BytesIO()
    np.savez_compressed(buf, **_flatten(_map(params, np.asarray)))
    data = buf.getvalue()
    meta = {"name": name, "model": cfg, "height": int(run_cfg["height"]), "width": int(run_cfg["width"]),
            "config": run_cfg, "steps": step, "sha256": hashlib.sha256(data).hexdigest(),
            "validation": validation if validation is not None else run_workdir.last_validation(str(workdir)),
            "training": dict(training_summary(workdir), machine=machine or _this_machine())}
    stages = shipped_stages(*after_shipped) if after_shipped else []
    stages += [stage_summary(c, d, machine) for c, d in earlier_stages]
    if stages:
        meta["earlier_stages"] = stages
    meta.update(recipe_summary(workdir, machine))
    meta.update(card or {})
    npz, js = _shipped_files(name)
    files.write_bytes(npz, data)
    files.write_json(js, meta)
    return npz


def recipe_summary(workdir: str | os.PathLike, machine: Optional[str] = None) -> dict:
    """For a recipe workdir (`bridge_jax.recipe`): {"rebuild": the one command that trains it again from nothing,
    "commit" (and "resumed_at_commits") of the code it ran, where the workdir recorded one, "recipe": [{"stage",
    "steps", "seconds", "height", "width", "global_batch", "lr", "validation" (the stage's last, at its own size)}
    per stage], and "training": {"total_seconds": the stages' seconds added up, "machine"}}; {} for any other
    workdir."""
    from bridge_jax import recipe  # heavy import only for maintainers

    record = recipe.read_record(os.fspath(workdir))
    if record is None:
        return {}
    stages = []
    for name in record["stages"]:
        done = recipe.finished(os.fspath(workdir), name)
        if done is None:
            raise ValueError(f"--from {workdir}: stage {name} of the recipe has not finished")
        cfg = record.get("configs", {}).get(name, {})
        stages.append({"stage": name, "steps": done["steps"], "seconds": done["seconds"],
                       **{k: cfg.get(k) for k in ("height", "width", "global_batch", "lr")},
                       "validation": done.get("validation") or {}})
    command = f"bridge-train --config={record.get('config_name') or '?'} --workdir=WORKDIR"
    code = {k: record[k] for k in ("commit", "resumed_at_commits") if record.get(k)}
    return {"rebuild": command, **code, "recipe": stages,
            "training": dict(training_summary(workdir), machine=machine or _this_machine(),
                             total_seconds=round(sum(s["seconds"] for s in stages), 1))}


def _this_machine() -> str:
    from bridge_jax import host
    return host.machine()


def card_lines(name: str) -> list[str]:
    """A shipped model's card as text lines (what `bridge-zoo show NAME` prints): model, working size, recipe,
    steps, training time and machine, validation and real-image numbers."""
    meta = info(name)
    cfg = meta.get("config", {})
    loop = dict(cfg, **cfg.get("loop", {}))
    lines = [f"{name}: {meta['model']['name']} trained at {meta['height']}x{meta['width']}, {meta['steps']} steps",
             f"  data: {cfg.get('data', {}).get('source', '?')} scenes "
             f"{cfg.get('data', {}).get('synthetic_scene', 'demo')}; lr {cfg.get('lr')}, "
             f"{loop.get('num_train_steps')} steps planned; init_from {cfg.get('init_from') or 'scratch'}"]
    if meta.get("rebuild"):
        at = f" (trained at commit {meta['commit']})" if meta.get("commit") else ""
        if meta.get("resumed_at_commits"):
            at += f" (resumed at {', '.join(meta['resumed_at_commits'])})"
        lines.append(f"  rebuild: {meta['rebuild']}{at}")
    for stage in meta.get("recipe") or []:  # the stages of the recipe that trained it
        val = stage.get("validation") or {}
        ended = ", ".join(f"{k} {val[k]:.3f}" for k in ("flow_epe_all", "disp_epe_all")
                          if isinstance(val.get(k), (int, float)))
        lines.append(f"  stage {stage['stage']}: {stage['steps']} steps at {stage.get('height')}x{stage.get('width')}, "
                     f"batch {stage.get('global_batch')}, lr {stage.get('lr')}, in {stage['seconds'] / 3600:.2f} h"
                     + (f"; validation at its size {ended}" if ended else ""))
    for i, stage in enumerate(meta.get("earlier_stages") or [], 1):  # runs whose weights this one started from
        lines.append(f"  stage {i}: --config={stage.get('config', '?')}, {stage.get('steps', '?')} steps from "
                     f"{stage.get('init_from') or 'scratch'}, lr {stage.get('lr')}, in "
                     f"{stage.get('seconds', 0) / 3600:.2f} h on {stage.get('machine', '?')}")
    t = meta.get("training") or {}
    if t:
        hours = t.get("seconds", 0) / 3600
        total = (f"; the whole recipe {t['total_seconds'] / 3600:.2f} h" if t.get("total_seconds") is not None
                 else "")
        lines.append(f"  trained: steps {t.get('first_step', '?')}-{t.get('last_step', '?')} in {hours:.2f} h on "
                     f"{t.get('machine', '?')}{total}")
    val = meta.get("validation") or {}
    if val:
        lines.append("  validation (synthetic, trained size): " + ", ".join(
            f"{k} {val[k]:.3f}" for k in ("flow_epe_all", "flow_epe_vs_zero", "disp_epe_all", "disp_d1_all")
            if isinstance(val.get(k), (int, float))))
    if meta.get("default_working_size"):
        lines.append(f"  default working size: {meta['default_working_size']} (the size that beat each other size "
                     "measured on more of its real-image checks; --working-size overrides it)")
    chosen = TestTime.from_card(meta)
    if chosen.refine:
        lines.append(f"  default refinement: {chosen.refine} pass(es) (chosen by its real-image checks, whose "
                     "numbers below are with it; --refine overrides it)")
    if chosen.symmetry != "none":
        lines.append(f"  default symmetry averaging: {chosen.symmetry} (chosen by its real-image checks, "
                     "whose numbers below are with it; --symmetry overrides it)")
    if chosen.polish != "none":
        lines.append(f"  default polish: {chosen.polish} (chosen by its real-image checks, whose numbers "
                     "below are with it; --polish overrides it)")
    if meta.get("default_polish_resolution"):
        lines.append(f"  polish runs at the {meta['default_polish_resolution']} size (chosen by its real-image "
                     "checks; polish.PolishConfig.resolution)")
    if meta.get("default_polish_settings"):
        lines.append("  polish settings: " + ", ".join(f"{k} {v}" for k, v in meta["default_polish_settings"].items())
                     + " (chosen by its real-image checks; polish.PolishConfig)")
    baselines = meta.get("real_images_opencv") or {}  # which OpenCV method each check's "opencv" numbers are
    for check, by_size in (meta.get("real_images") or {}).items():
        for size, values in by_size.items():
            which = f" ({baselines[check]}, the strongest baseline)" if size == "opencv" and check in baselines else ""
            lines.append(f"  {check} @ {size}{which}: " + ", ".join(f"{k} {v:.3f}" for k, v in values.items()))
    for check, by_size in (meta.get("real_images_polish_none") or {}).items():  # the network's own maps
        for size, values in by_size.items():
            lines.append(f"  {check} @ {size}, polish none: " + ", ".join(f"{k} {v:.3f}" for k, v in values.items()))
    return lines
