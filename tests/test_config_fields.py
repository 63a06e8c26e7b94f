"""Every config section is a dataclass parsed the same way: the listing (`bridge-train --list-config`) names every
field with a meaning, and the flat keys of the loop section still work (with a note naming the new key)."""

from __future__ import annotations

import dataclasses

import jax
import ml_collections
import pytest

from bridge_jax import configs, setup, train

NOT_A_FIELD = "(not a field of this version"


def _listed(text: str) -> dict[str, str]:
    """{key: meaning} of `setup.list_config`'s lines ("key = value   meaning")."""
    out = {}
    for line in text.splitlines():
        key, _, rest = line.partition(" = ")
        out[key] = rest.split("  ", 1)[1].strip() if "  " in rest else ""
    return out


def test_the_listing_covers_every_field_of_every_section_with_a_meaning():
    listed = _listed(setup.list_config(configs.load("default")))
    for section, cls in setup.SECTIONS:
        for f in dataclasses.fields(cls):
            key = f"{section}.{f.name}" if section else f.name
            assert key in listed, f"{key} ({cls.__name__}) is not in the default config"
            assert listed[key] and not listed[key].startswith(NOT_A_FIELD), f"{key}: no meaning (a comment on its line)"
    # and nothing in the default config is outside the sections (the model's keys point to its module)
    assert [k for k, m in listed.items() if m.startswith(NOT_A_FIELD)] == []


def test_a_field_without_a_comment_has_no_meaning():
    @dataclasses.dataclass(frozen=True)
    class Section:
        documented: int = 1  # what it means
        undocumented: int = 2

    assert setup._line_comments(Section) == {"documented": "what it means"}


def test_list_config_on_the_command_line(capsys):
    assert train.main(["--list-config", "demo", "--config.loop.eval_every=7"]) == 0
    listed = _listed(capsys.readouterr().out)
    assert listed["model.name"].startswith("the network")
    assert "loop.eval_every" in listed and len(listed) > 60
    assert "--list-config" in train.build_parser().format_help()


@pytest.mark.parametrize("key", sorted(configs.MOVED_KEYS))
def test_a_flat_key_sets_its_new_field_with_a_note(key, capsys):
    config = configs.load("default")
    new = configs.MOVED_KEYS[key]
    value = not config.loop[new.split(".")[1]] if isinstance(config.loop[new.split(".")[1]], bool) else 7
    configs.override(config, [f"{key}={value}"])
    assert config.loop[new.split(".")[1]] == value and key not in config
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"config.{key} is now config.{new}" in err


def test_a_config_file_with_flat_keys_is_moved_by_parse(capsys):
    config = configs.load("default:local")
    config.eval_every = 3  # a config file written for the previous release
    config.num_train_steps = 11
    run = setup.parse(config, devices=jax.devices()[:1])
    assert (run.loop.eval_every, run.loop.num_train_steps) == (3, 11)
    assert "eval_every" in config  # the caller's config is left alone
    err = capsys.readouterr().err
    assert "config.eval_every is now config.loop.eval_every" in err and "config.loop.num_train_steps" in err


def test_bad_loop_and_eval_values_name_the_option():
    for item, match in (("loop.log_every=0", "config.loop.log_every must be positive"),
                        ("loop.steps_per_epoch=0", r"config.loop.steps_per_epoch must be positive \(or -1"),
                        ("dtype=float16", "config.dtype must be one of")):
        config = configs.load("default:local")
        configs.override(config, [item])
        with pytest.raises(setup.ConfigError, match=match):
            setup.parse(config, devices=jax.devices()[:1])
    config = configs.load("default:local")
    config.eval = ml_collections.ConfigDict(dict(config.eval.to_dict(), batch=2.5))  # a config file's own section
    with pytest.raises(setup.ConfigError, match="config.eval.batch must be an integer"):
        setup.parse(config, devices=jax.devices()[:1])
