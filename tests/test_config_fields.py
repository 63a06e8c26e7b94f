"""Every config section is a dataclass parsed the same way: the listing (`bridge-train --list-config`) names every
field with a meaning, and the flat keys of the loop section still work (with a note naming the new key)."""

from __future__ import annotations

import dataclasses
import importlib
import re
import typing
from typing import Optional

import jax
import ml_collections
import pytest

from bridge_jax import configs, recipe, setup, train

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
    for item, match in (("loop.log_every=0", r"config.loop.log_every=0: must be an integer >= 1$"),
                        ("loop.steps_per_epoch=0", r"config.loop.steps_per_epoch=0: must be an integer >= 1, or -1"),
                        ("dtype=float16", "config.dtype must be one of")):
        config = configs.load("default:local")
        configs.override(config, [item])
        with pytest.raises(setup.ConfigError, match=match):
            setup.parse(config, devices=jax.devices()[:1])
    config = configs.load("default:local")
    config.eval = ml_collections.ConfigDict(dict(config.eval.to_dict(), batch=2.5))  # a config file's own section
    with pytest.raises(setup.ConfigError, match="config.eval.batch must be an integer"):
        setup.parse(config, devices=jax.devices()[:1])


@pytest.mark.parametrize("item, match", [
    ("loop.num_train_steps=-5", r"^config.loop.num_train_steps=-5: must be an integer >= 1, or -1 \(derive from the "
                                r"data\)$"),
    ("loop.eval_every=-3", r"^config.loop.eval_every=-3: must be an integer >= 0, or -1 \(never\)$"),
    ("loop.image_every=-2", r"^config.loop.image_every=-2: must be an integer >= 0, or -1"),
    ("eval.batch=0", r"^config.eval.batch=0: must be an integer >= 1$"),
    ("eval.num_samples=-1", r"^config.eval.num_samples=-1: must be an integer >= 0$"),
    ("data.read_threads=0", r"^config.data.read_threads=0: must be an integer >= 1$"),
    ("data.max_skip=-1", r"^config.data.max_skip=-1: must be an integer >= 0$"),
    ("loss.num_scales=0", r"^config.loss.num_scales=0: must be an integer >= 1$"),
    ("num_devices=-4", r"^config.num_devices=-4: must be an integer >= 1, or -1 \(all devices\)$"),
    ("global_batch=0", r"^config.global_batch=0: must be an integer >= 1$"),
    ("distributed.process_id=-2", r"^config.distributed.process_id=-2: must be an integer >= 0, or -1"),
])
def test_counts_and_intervals_out_of_range_are_one_line_naming_field_value_and_rule(item, match):
    config = configs.load("default:local")
    configs.override(config, [item])
    with pytest.raises(setup.ConfigError, match=match) as info:
        setup.parse(config, devices=jax.devices()[:1])
    assert "\n" not in str(info.value)


def _fields_of_type(sections, kind) -> list[str]:
    """The dotted keys of the fields of `sections` ((section, dataclass) pairs) typed `kind` or Optional[kind]."""
    keys = []
    for section, cls in sections:
        hints = typing.get_type_hints(cls)
        for f in dataclasses.fields(cls):
            if hints[f.name] in (kind, typing.Optional[kind]):
                keys.append(f"{section}.{f.name}" if section else f.name)
    return keys


def test_every_integer_field_of_the_config_records_has_a_count_rule_or_is_declared_not_a_count():
    for key in _fields_of_type(setup.SECTIONS, int):
        assert key in setup.COUNT_RULES or key in setup.NOT_COUNTS, key


def _floats_without_a_rule(sections, rules) -> list[str]:
    return [key for key in _fields_of_type(sections, float) if key not in rules]


def test_every_float_field_of_the_config_records_has_a_float_rule():
    floats = _fields_of_type(setup.SECTIONS, float)
    assert {"lr", "adam_eps", "loss.lambda_sm", "loss.mask_floor", "data.augment_zoom"} <= set(floats)
    assert _floats_without_a_rule(setup.SECTIONS, setup.FLOAT_RULES) == []
    assert sorted(set(setup.FLOAT_RULES) - set(floats)) == []  # no rule outlives its field


def test_a_new_float_field_without_a_rule_is_found():
    @dataclasses.dataclass(frozen=True)
    class Section:
        ruled: float = 0.85
        unruled: Optional[float] = None
        count: int = 1

    assert _floats_without_a_rule((("loss", Section),), {"loss.ruled": (0.0, 1.0, "[]", "")}) == ["loss.unruled"]


# Hand-derived from what each float field means (see the comments of setup.FLOAT_RULES): values a run must refuse,
# and values at the edges of its range that it must take. 1e39 and 1e300 are beyond float32's largest (3.4e38),
# 1e-40 below its smallest normal number (1.2e-38: a float32 zero on XLA's flush-to-zero devices).
FLOAT_CASES = {
    "lr": (["0.0", "-1e-4", "1e300", "1e-40", "nan", "inf"], ["1e-4", "1e30"]),
    "lr_decay": (["0.0", "1.5", "-0.5", "nan"], ["1.0", "0.1"]),
    "adam_b1": (["1.0", "-0.1", "nan"], ["0.0", "0.99"]),
    "adam_b2": (["1.0", "1.5", "nan"], ["0.0", "0.999"]),
    "adam_eps": (["0.0", "-1e-8", "1e-40", "inf"], ["1e-8", "1.0"]),
    "clip_grad_norm": (["-1.0", "1e39", "nan"], ["0.0", "5.0"]),
    "ema_decay": (["1.0", "-0.1", "nan"], ["0.0", "0.999"]),
    "loss.alpha": (["-0.1", "1.5", "nan"], ["0.0", "1.0"]),
    "loss.beta": (["-10.0", "inf"], ["0.0", "10.0"]),
    "loss.beta1": (["-1.0", "nan"], ["0.0", "10.0"]),
    "loss.lambda_sm": (["-10.0", "nan", "inf", "1e39"], ["0.0", "10.0"]),
    "loss.lambda_sm1": (["-4.0", "nan"], ["0.0", "4.0"]),
    "loss.lambda_lr": (["-0.5", "-inf"], ["0.0", "0.5"]),
    "loss.lambda_2warp": (["-0.2", "nan"], ["0.0", "0.2"]),
    "loss.self_supervision": (["-0.3", "nan"], ["0.0", "0.3"]),
    "loss.occlusion_fill": (["-1.0", "inf"], ["0.0", "0.5"]),
    "loss.occ_alpha1": (["-0.01", "2.0", "nan"], ["0.0", "1.99"]),
    "loss.occ_alpha2": (["-0.5", "inf"], ["0.0", "0.5"]),
    "loss.border_ratio": (["-0.1", "0.5", "nan"], ["0.0", "0.49"]),
    "loss.mask_floor": (["0.0", "-1e-3", "1.5", "1e-40", "nan"], ["1e-3", "1.0"]),
    "loss.smooth_scale": (["0.0", "-0.05", "nan"], ["0.05", "1.0"]),
    "data.augment_zoom": (["0.05", "1.5", "nan"], ["0.1", "1.0"]),
    "data.augment_shift": (["-0.1", "0.3", "nan"], ["0.0", "0.25"]),
    "data.augment_t1_zoom": (["-0.1", "0.25", "nan"], ["0.0", "0.2"]),
}


def test_every_float_rule_has_hand_derived_cases():
    assert sorted(FLOAT_CASES) == sorted(setup.FLOAT_RULES)


@pytest.mark.parametrize("key, text", [(k, v) for k, (bad, _) in FLOAT_CASES.items() for v in bad])
def test_a_float_out_of_its_range_is_one_line_naming_field_value_and_rule(key, text):
    config = configs.load("default:local")
    configs.override(config, [f"{key}={text}"])
    want = rf"^config\.{re.escape(key)}={re.escape(repr(float(text)))}: must be a number "
    with pytest.raises(setup.ConfigError, match=want) as info:
        setup.parse(config, devices=jax.devices()[:1])
    assert "\n" not in str(info.value) and str(info.value).endswith(f"({setup.FLOAT_RULES[key][3]})")


@pytest.mark.parametrize("key, text", [(k, v) for k, (_, good) in FLOAT_CASES.items() for v in good])
def test_a_float_at_the_edge_of_its_range_is_taken(key, text):
    config = configs.load("default:local")
    configs.override(config, [f"{key}={text}"])
    run = setup.parse(config, devices=jax.devices()[:1])
    section, _, name = key.rpartition(".")
    record = {"": run.optimizer, "loss": run.loss, "data": run.data}[section]
    assert getattr(record, name) == float(text)


def test_float_refusals_read_like_the_integer_ones(tmp_path, capsys):
    config = configs.load("default:local")
    configs.override(config, ["loss.lambda_sm=-10"])
    with pytest.raises(setup.ConfigError) as info:
        setup.parse(config, devices=jax.devices()[:1])
    assert str(info.value) == ("config.loss.lambda_sm=-10.0: must be a number >= 0 float32 can hold, at most "
                               "3.4e+38 (a weight of the total loss; 0 = term off)")
    # a config file's own section: a bool or a text is not a number either
    for value in (True, "10"):
        config = configs.load("default:local")
        config.loss = ml_collections.ConfigDict(dict(config.loss.to_dict(), lambda_sm=value))
        with pytest.raises(setup.ConfigError, match=rf"^config.loss.lambda_sm={re.escape(repr(value))}: must be a "
                                                    r"number >= 0"):
            setup.parse(config, devices=jax.devices()[:1])
    # the command line: it trained to exit 0 before; now one line, exit 2 and no workdir
    code = train.main(["--config=demo:short", f"--workdir={tmp_path / 'w'}", "--config.loss.lambda_sm=-10"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip().splitlines() == [
        "error: stage coarse: config.loss.lambda_sm=-10.0: must be a number >= 0 float32 can hold, at most 3.4e+38 "
        "(a weight of the total loss; 0 = term off)"]
    assert not (tmp_path / "w").exists()


def _shipped_configs():
    """(name, argument) of every shipped config: each file plain, with `:local` where it takes it, and with each
    argument of its own (`ARGS`: the demo's and the long recipe's variants)."""
    out = []
    for name in configs.names():
        out.append((name, None))
        module = importlib.import_module(f"bridge_jax.configs.{name}")
        out += [(name, arg) for arg in getattr(module, "ARGS", ("local",))]
    return out


@pytest.mark.parametrize("name, arg", _shipped_configs())
def test_every_shipped_config_and_each_stage_of_a_recipe_still_parses(name, arg, tmp_path):
    config = configs.load(f"{name}:{arg}" if arg else name)
    config.data.data_dir = str(tmp_path)  # long:finetune trains on a folder of the user's own video
    stages = [recipe.stage_config(config, s) for s in recipe.stage_names(config)] if recipe.is_recipe(config) \
        else [config]
    for cfg in stages:
        run = setup.parse(cfg, devices=jax.devices()[:1])
        for key in setup.FLOAT_RULES:
            section, _, field = key.rpartition(".")
            assert setup.float_allowed(key, cfg[field] if not section else cfg[section][field]), key
        assert run.height * run.width > 0


def test_minus_one_still_derives_the_step_count():
    config = configs.load("default:local")
    configs.override(config, ["loop.num_train_steps=-1", "loop.steps_per_epoch=7", "loop.num_epochs=3"])
    run = setup.parse(config, devices=jax.devices()[:1])
    assert run.steps(None) == (7, 21)


def test_train_cli_refuses_a_negative_step_count_in_one_line(tmp_path, capsys):
    from bridge_jax import train
    code = train.main(["--config=demo:short", f"--workdir={tmp_path / 'w'}", "--config.loop.num_train_steps=-5"])
    err = capsys.readouterr().err
    assert code == 2 and err.strip().splitlines() == [
        # demo is a recipe: the error names the first stage whose config refuses the value
        "error: stage coarse: config.loop.num_train_steps=-5: must be an integer >= 1, or -1 (derive from the data)"]
    assert not (tmp_path / "w").exists()


@pytest.mark.parametrize("batch, used", [(16, 8), (8, 8), (6, 6), (9, 3), (7, 7), (1, 1)])
def test_all_devices_means_those_that_divide_the_global_batch(batch, used):
    """num_devices=-1 in one process on this 8-device session: the mesh is the most devices that divide
    global_batch (a batch of 9 cycles: 3 devices of 3), all 8 when they do; an explicit count is never changed."""
    cfg = recipe.single_run(configs.load("demo"))
    cfg.global_batch = batch
    assert cfg.num_devices == -1 and len(jax.devices()) == 8
    run = setup.parse(cfg)
    assert run.num_devices == used and run.devices == tuple(jax.devices()[:used])
    cfg.num_devices = 8
    if batch % 8:
        with pytest.raises(setup.ConfigError, match=rf"config.global_batch={batch} is not divisible by the 8 devices"):
            setup.parse(cfg)
