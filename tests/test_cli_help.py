"""Every entry point's --help teaches: an example command line from the module docstring, every option with a
help text, defaults shown; and every entry point is an installed console command."""
import importlib
import re
import tomllib
from pathlib import Path

import pytest

from bridge_jax import cli
from tests.train_helpers import REPO

ENTRY_POINTS = ["bridge_jax.train", "bridge_jax.evaluate", "bridge_jax.predict", "bridge_jax.bench.cli",
                "bridge_jax.convert", "bridge_jax.export", "bridge_jax.demo", "bridge_jax.data.synthetic", "bridge_jax.data.videos",
                "bridge_jax.zoo.__main__"]


@pytest.mark.parametrize("module", ENTRY_POINTS)
def test_help_has_an_example_and_every_option_explained(module):
    parser = importlib.import_module(module).build_parser()
    text = parser.format_help()
    prog = "bridge_jax.bench" if module == "bridge_jax.bench.cli" else module.replace(".__main__", "")
    command = cli.COMMANDS[prog]
    assert text.startswith(f"usage: {command} "), f"{module}: the usage line does not name {command}"
    # an indented example line (not the usage line) from the docstring's epilog, naming the console command
    assert re.search(rf"^\s+{re.escape(command)}\s+\S", text, re.M), f"{module}: no example in --help"
    for action in parser._actions:
        if action.option_strings and action.dest != "help":
            assert action.help, f"{module}: {action.option_strings} has no help text"


def test_every_entry_point_is_a_console_command():
    scripts = tomllib.loads(Path(REPO, "pyproject.toml").read_text())["project"]["scripts"]
    targets = {v.split(":")[0] for v in scripts.values()}
    assert targets == set(ENTRY_POINTS), targets ^ set(ENTRY_POINTS)
    named = {cli.COMMANDS["bridge_jax.bench" if t == "bridge_jax.bench.cli" else t.replace(".__main__", "")]: t
             for t in targets}
    assert named == {name: target.split(":")[0] for name, target in scripts.items()}  # usage lines name them right
    for target in scripts.values():
        module, func = target.split(":")
        assert callable(getattr(importlib.import_module(module), func)), target
