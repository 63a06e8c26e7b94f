"""Training configs: `default.py` (the paper's settings), one file per paper variant, `demo.py` (the README's main
job). Each module has `get_config(arg=None)` returning an `ml_collections.ConfigDict`.

    configs.load("full2:local")                 # by name (any directory), or a path "my/config.py[:arg]"
    configs.override(config, ["loss.two_warp=full2", "height=128"])

Fields are listed with their defaults and meanings by `bridge-train --list-config [NAME]` (`setup.list_config`).
"""

from __future__ import annotations

import ast
import difflib
import importlib
import importlib.util
import os
import re
from typing import Callable, Sequence

import ml_collections

from bridge_jax.config_keys import MOVED_KEYS, leaf_keys, move_flat_keys, moved_key  # noqa: F401

CONFIG_DIR = os.path.dirname(os.path.abspath(__file__))

def names() -> list[str]:
    """The configs shipped in the package."""
    return sorted(f[:-3] for f in os.listdir(CONFIG_DIR) if f.endswith(".py") and not f.startswith("_"))


def summary(name: str) -> str:
    """The first sentence of a shipped config's docstring (read from the file, without importing it)."""
    with open(os.path.join(CONFIG_DIR, f"{name}.py")) as f:
        doc = ast.get_docstring(ast.parse(f.read())) or ""
    first = " ".join(doc.split("\n\n")[0].split())
    return re.split(r"\.\s+(?=[A-Z])", first)[0].rstrip(".")  # "et al. (CVPR" does not end it


def load(spec: str) -> ml_collections.ConfigDict:
    """A config by name (`default`, `full2:local`, see `names()`) or by path (`dir/file.py[:arg]`).

    Raises ValueError naming the config (unknown name, missing file, or an argument its get_config refuses).
    """
    name, _, arg = spec.partition(":")
    if name.endswith(".py") or os.sep in name:
        if not os.path.isfile(name):
            close = difflib.get_close_matches(os.path.basename(name)[:-3], names(), n=1) if name.endswith(".py") else []
            hint = f" (or the shipped config by name: --config={close[0]})" if close else ""
            raise ValueError(f"--config {spec}: no such config file {name!r}{hint}")
        mod_spec = importlib.util.spec_from_file_location("bridge_jax_user_config", name)
        module = importlib.util.module_from_spec(mod_spec)
        mod_spec.loader.exec_module(module)
    elif name in names():
        module = importlib.import_module(f"bridge_jax.configs.{name}")
    else:
        close = difflib.get_close_matches(name, names(), n=3)
        hint = f"; did you mean {', '.join(close)}?" if close else ""
        raise ValueError(f"--config {spec}: unknown config {name!r}{hint} (shipped: {', '.join(names())}; or a "
                         f"path to a .py file)")
    try:
        return module.get_config(arg or None)
    except (ValueError, TypeError) as e:
        raise ValueError(f"--config {spec}: {e}") from e


def _literal(text: str):
    try:
        return ast.literal_eval(text)
    except (ValueError, SyntaxError):
        return text


def override(config: ml_collections.ConfigDict, items: Sequence[str], *,
             hint_prefix: str = "") -> ml_collections.ConfigDict:
    """Sets `KEY=VALUE` items (dotted keys, Python literals; text where the field is a string) in place; a moved
    flat key (`MOVED_KEYS`) sets its new field, with a note on stderr.

    Raises ValueError naming the item: not KEY=VALUE, no such field (with the close matches among the fields,
    each written as `hint_prefix + key`, e.g. "--config.model.name"), or a value of the wrong type.
    """
    def no_field(item: str, key: str) -> ValueError:
        close = difflib.get_close_matches(key, leaf_keys(config), n=3, cutoff=0.75)
        hint = f"; did you mean {', '.join(hint_prefix + c for c in close)}?" if close else ""
        return ValueError(f"{item!r}: config has no field {key!r}{hint}")

    for item in items:
        key, eq, text = item.partition("=")
        if not eq:
            raise ValueError(f"{item!r}: expected KEY=VALUE (e.g. loss.two_warp=full2)")
        key = moved_key(key, config)
        *path, last = key.split(".")
        node = config
        for part in path:
            if not isinstance(node, ml_collections.ConfigDict) or part not in node:
                raise no_field(item, key)
            node = node[part]
        if not isinstance(node, ml_collections.ConfigDict) or last not in node:
            raise no_field(item, key)
        value = text if isinstance(node[last], str) else _literal(text)
        if isinstance(node[last], float) and isinstance(value, str):
            try:  # "inf", "nan", "1e-4 " (ast cannot read the first two)
                value = float(value)
            except ValueError:
                pass
        try:
            node[last] = value
        except (TypeError, ValueError) as e:
            raise ValueError(f"{item!r}: {e}") from e
    return config
