"""A model fine-tuned from a shipped one keeps that model's recommended test-time settings (`zoo.card_lineage`,
`zoo.defaults_source`, `zoo.card_working_size`, `zoo.card_test_time`), and `bridge-predict` says which settings
it uses and why."""
import json
import os
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from bridge_jax import checkpointing, inference, predict, zoo

LONG_CARD = json.loads((Path(zoo.__file__).parent / "long.json").read_text())  # read here, not through zoo
LONG = (LONG_CARD["default_working_size"], LONG_CARD["default_refine"], LONG_CARD["default_symmetry"],
        LONG_CARD["default_polish"])
FALLBACK = (None, 0, "none", "none")


def _defaults(spec):
    size = zoo.card_working_size(spec)
    chosen = zoo.card_test_time(spec)
    return (size if size is None or isinstance(size, str) else f"{size[0]}x{size[1]}", chosen.refine,
            chosen.symmetry, chosen.polish)


def _workdir(path, init_from, step=None):
    """A fake training workdir: config.json with `init_from` (None: no config.json), and a step dir
    checkpoints/<step>/state when `step` is given."""
    path = Path(path)
    path.mkdir(parents=True, exist_ok=True)
    if init_from is not None:
        (path / "config.json").write_text(json.dumps({"init_from": init_from, "height": 64, "width": 128}))
    if step is not None:
        (path / "checkpoints" / str(step) / "state").mkdir(parents=True)
    return str(path)


def test_long_card_has_recommendations():
    assert LONG != FALLBACK and LONG_CARD["default_refine"] >= 1
    assert _defaults("long") == LONG and zoo.defaults_source("long") == "long"
    assert zoo.card_lineage("long") == ["long"]


def test_a_workdir_fine_tuned_from_long_and_its_step_dir(tmp_path):
    ft = _workdir(tmp_path / "ft", "long", step=20)
    assert _defaults(ft) == LONG and zoo.defaults_source(ft) == "long"
    assert zoo.card_lineage(ft) == [ft, "long"]
    step = os.path.join(ft, "checkpoints", "20")  # a step dir: the config.json two levels up
    assert _defaults(step) == LONG and zoo.defaults_source(step) == "long"


def test_a_chain_of_two_paths_ending_in_long(tmp_path):
    first = _workdir(tmp_path / "first", "long")
    second = _workdir(tmp_path / "second", first)
    third = _workdir(tmp_path / "third", os.path.join(second, "checkpoints", "7"))  # init_from a step dir
    (tmp_path / "second" / "checkpoints" / "7" / "state").mkdir(parents=True)
    assert _defaults(second) == LONG and zoo.card_lineage(second) == [second, first, "long"]
    assert _defaults(third) == LONG and zoo.defaults_source(third) == "long"


def test_a_relative_init_from_is_read_as_given(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    _workdir(tmp_path / "work" / "base", "long")
    ft = _workdir(tmp_path / "work" / "ft", "work/base")
    assert _defaults("work/ft") == LONG and zoo.card_lineage("work/ft") == ["work/ft", "work/base", "long"]
    assert _defaults(ft) == LONG


def test_a_recipe_workdir_stands_for_its_latest_stage_with_a_checkpoint(tmp_path):
    recipe = tmp_path / "recipe"
    recipe.mkdir()
    (recipe / checkpointing.RECIPE_JSON).write_text(json.dumps({"stages": ["low", "high"]}))
    _workdir(recipe / "stages" / "low", "long", step=100)
    _workdir(recipe / "stages" / "high", "", step=None)  # not started: no checkpoint yet
    assert _defaults(str(recipe)) == LONG
    shutil.rmtree(recipe / "stages" / "high")
    _workdir(recipe / "stages" / "high", "", step=5)  # its latest stage now: random init
    assert _defaults(str(recipe)) == FALLBACK and zoo.defaults_source(str(recipe)) is None
    # a stage initialised from its recipe's earlier stage, which came from long
    shutil.rmtree(recipe / "stages" / "high")
    _workdir(recipe / "stages" / "high", str(recipe / "stages" / "low"), step=5)
    assert _defaults(str(recipe)) == LONG


def test_random_init_params_only_unknown_and_missing_give_the_fallbacks(tmp_path):
    assert _defaults(_workdir(tmp_path / "scratch", "", step=3)) == FALLBACK
    assert _defaults(_workdir(tmp_path / "params_only", None)) == FALLBACK
    assert _defaults(_workdir(tmp_path / "odd", "no-such-model")) == FALLBACK
    assert _defaults(_workdir(tmp_path / "gone", str(tmp_path / "missing"))) == FALLBACK
    assert _defaults(str(tmp_path / "missing")) == FALLBACK and _defaults("no-such-name") == FALLBACK
    (tmp_path / "garbled").mkdir()
    (tmp_path / "garbled" / "config.json").write_text("{not json")
    assert _defaults(str(tmp_path / "garbled")) == FALLBACK
    assert zoo.defaults_source(str(tmp_path / "scratch")) is None and zoo.card_lineage(str(tmp_path)) == []


def test_a_cycle_ends_with_the_fallbacks(tmp_path):
    a, b = str(tmp_path / "a"), str(tmp_path / "b")
    _workdir(a, b)
    _workdir(b, a)
    assert _defaults(a) == FALLBACK and zoo.card_lineage(a) == []
    _workdir(tmp_path / "self", str(tmp_path / "self"))
    assert _defaults(str(tmp_path / "self")) == FALLBACK


def test_the_chain_is_bounded(tmp_path):
    n = zoo.LINEAGE_DEPTH
    links = [str(tmp_path / f"w{i}") for i in range(n + 1)]
    for i, link in enumerate(links):  # w0 <- w1 <- ... <- wN; w0 from long
        _workdir(link, "long" if i == 0 else links[i - 1])
    assert zoo.defaults_source(links[n - 1]) == "long"  # n links back to long: followed
    assert zoo.defaults_source(links[n]) is None        # n + 1 links: too deep


def test_load_predictor_and_the_predict_line_follow_the_lineage(tiny_checkpoint, tmp_path):
    """A (params-only) checkpoint whose config.json says it was fine-tuned from long loads with long's
    settings; options given explicitly win, and `settings_line` names the card and what was given."""
    ft = str(tmp_path / "ft")
    shutil.copytree(tiny_checkpoint, ft)
    _workdir(ft, "long")
    pred = inference.load_predictor(ft)
    assert (pred.native, pred.refine, pred.symmetry, pred.polish) == (LONG[0] == "native",) + LONG[1:]
    line = predict.settings_line(ft, pred)
    assert line == (f"test-time settings: working size native, refine {LONG[1]}, symmetry {LONG[2]}, polish "
                    f"{LONG[3]} (the card of 'long', which {ft} was fine-tuned from; "
                    "--working-size/--refine/--symmetry/--polish override)")
    pred = inference.load_predictor(ft, test_time={"refine": 0, "symmetry": "none"})
    assert (pred.refine, pred.symmetry, pred.polish) == (0, "none", LONG[3])
    assert "refine 0 (--refine), symmetry none (--symmetry), polish" in predict.settings_line(
        ft, pred, ["--refine", "--symmetry"])
    plain = inference.load_predictor(tiny_checkpoint, size=(64, 128))
    assert predict.settings_line(tiny_checkpoint, plain, ["--working-size"]) == (
        "test-time settings: working size 64x128 (--working-size), refine 0, symmetry none, polish none "
        "(defaults; --working-size/--refine/--symmetry/--polish override)")
    chain = str(tmp_path / "ft2")
    shutil.copytree(tiny_checkpoint, chain)
    _workdir(chain, ft)
    assert f"(the card of 'long', which {chain} was fine-tuned from (through {ft});" in predict.settings_line(
        chain, inference.load_predictor(chain, test_time={"refine": 0}))


def test_predict_cli_prints_the_settings_line(tiny_checkpoint, tmp_path, capsys):
    ft = str(tmp_path / "ft")
    shutil.copytree(tiny_checkpoint, ft)
    _workdir(ft, "long")
    rng = np.random.default_rng(0)
    img = rng.integers(0, 255, (64, 128, 3), dtype=np.uint8)
    a, b = str(tmp_path / "a.png"), str(tmp_path / "b.png")
    cv2.imwrite(a, img)
    cv2.imwrite(b, np.roll(img, 2, axis=1))
    # the cheap settings given (a random tiny net): the line marks them and names the card the defaults come from
    args = ["--checkpoint", ft, a, b, "--out", str(tmp_path / "out"), "--working-size", "64x128", "--refine", "0",
            "--symmetry", "none", "--polish", "none", "--no-progress", "--raw", "none"]
    assert predict.main(args) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0] == ("test-time settings: working size 64x128 (--working-size), refine 0 (--refine), symmetry "
                      f"none (--symmetry), polish none (--polish) (the card of 'long', which {ft} was fine-tuned from; "
                      "--working-size/--refine/--symmetry/--polish override)")
    desc = json.loads((tmp_path / "out" / "predict.json").read_text())
    assert (desc["refine"], desc["symmetry"], desc["polish"]) == (0, "none", "none")
