"""The test-time record (`testtime.TestTime`), the working-size value (`resizing.WorkingSize`), the polish's
config (`polish.PolishConfig`) and the command-line helpers that build them: validated once, hashable, read from
a card in one place, and keys of the compiled programs."""

import argparse

import numpy as np
import pytest

from bridge_jax import cli, inference, models, polish, testtime, zoo
from bridge_jax.inference import TestTime, WorkingSize


def test_a_test_time_record_is_checked_when_made():
    assert TestTime() == TestTime(0, "none", "none") and hash(TestTime(1)) == hash(TestTime(np.int64(1)))
    assert isinstance(TestTime(np.int64(2)).refine, int)
    for bad, message in [({"refine": 9}, r"refine 9: expected a whole number .* 0 to 8"),
                         ({"refine": 1.0}, r"refine 1.0: expected a whole number"),
                         ({"refine": True}, r"refine True"),
                         ({"symmetry": "mirror"}, r"symmetry 'mirror': expected one of none, flips, dihedral"),
                         ({"polish": "sharpen"}, r"polish 'sharpen': expected one of none, photometric")]:
        with pytest.raises(ValueError, match=message):
            TestTime(**bad)
    with pytest.raises(AttributeError):
        TestTime().refine = 1  # frozen: a predictor's record never changes under it


def test_given_settings_replace_a_default_record_and_errors_name_the_option():
    card = TestTime(1, "flips", "photometric")
    assert card.with_given({"refine": 0, "symmetry": None}) == TestTime(0, "flips", "photometric")
    with pytest.raises(ValueError, match=r"^--refine 12: "):
        card.with_given({"refine": 12}, testtime.OPTIONS)
    with pytest.raises(TypeError, match="unknown test-time setting"):
        card.with_given({"refines": 1})
    assert card.network_part == TestTime(1, "flips") and card.to_dict() == {"refine": 1, "symmetry": "flips",
                                                                           "polish": "photometric"}


def test_a_card_yields_one_record():
    for name in ("demo", "long"):
        meta = zoo.info(name)
        assert zoo.card_test_time(name) == TestTime(meta["default_refine"], meta["default_symmetry"],
                                                    meta["default_polish"])
    assert TestTime.from_card({}) == TestTime() and TestTime.from_card({"default_refine": 2}) == TestTime(2)


def test_the_cli_helper_builds_the_settings_and_reads_the_old_task_spelling(capsys):
    p = argparse.ArgumentParser()
    cli.add_test_time_options(p)
    cli.add_task_option(p, help="what a pair is")
    args = p.parse_args(["--refine", "2", "--pair-kind", "stereo"])
    assert cli.given_test_time(args) == {"refine": 2, "symmetry": None, "polish": None}
    assert args.task == "stereo"
    assert capsys.readouterr().err.strip() == "note: --pair-kind is now --task"
    assert p.parse_args([]).task == "flow" and capsys.readouterr().err == ""
    with pytest.raises(SystemExit):
        p.parse_args(["--polish", "sharpen"])


def test_the_working_size_is_one_value():
    size = WorkingSize(128, 256)
    assert (size.height, size.width, size.native, str(size)) == (128, 256, False, "128x256")
    assert size.for_input("pwc_lite", 500, 741) == (128, 256)
    native = WorkingSize(native=True)
    assert str(native) == "native" and native.for_input("pwc_lite", 500, 741) == (448, 704)
    with pytest.raises(ValueError, match="height 0 is not a positive whole number"):
        WorkingSize(0, 256)


def test_polish_config_is_hashable_and_checked():
    assert hash(polish.PolishConfig()) == hash(polish.PolishConfig(candidate_distances=[4, 8, 16, 24]))
    assert polish.PolishConfig(smooth_eps=1e3) != polish.PolishConfig()
    with pytest.raises(ValueError):
        polish.PolishConfig(candidate_distances=())


def test_the_predictor_holds_both_values_and_takes_no_loose_keywords():
    graphdef, params = models.init(0, "pwc_lite")
    cfg = models.model_config("pwc_lite")
    p = inference.Predictor(graphdef, params, size=WorkingSize(64, 128), test_time=TestTime(1, "none", "photometric"),
                            model_cfg=cfg)
    assert p.size == WorkingSize(64, 128) and p.test_time == TestTime(1, "none", "photometric")
    assert (p.height, p.width, p.native, p.refine, p.polish) == (64, 128, False, 1, "photometric")
    for loose in ({"height": 64}, {"native": True}, {"max_pixels": 4096}, {"refine": 1}, {"polish": "photometric"}):
        with pytest.raises(TypeError):
            inference.Predictor(graphdef, params, model_cfg=cfg, **loose)
    for loose in ({"working_size": (64, 128)}, {"width": 128}, {"symmetry": "flips"}):
        with pytest.raises(TypeError):  # refused before the checkpoint is looked at
            inference.load_predictor("no-such-checkpoint", **loose)
    assert p.settings() == {"working_size": "64x128", "refine": 1, "symmetry": "none", "polish": "photometric"}
