"""Recipes (`bridge_jax.recipe`, configs/long.py, configs/demo.py): stages declared as data and run by one command,
each from the previous stage's final params, resumable at any step, a boundary included."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time

import ml_collections
import numpy as np
import pytest

from bridge_jax import checkpointing, recipe, setup, train, workdir as workdir_mod, zoo
from bridge_jax.configs import demo, long

from tests.train_helpers import REPO, enable_compilation_cache, subprocess_env, tiny_config


# ------------------------------------------------------------------------------------------------------------
# Stage configs
# ------------------------------------------------------------------------------------------------------------

def _toy_recipe():
    return ml_collections.ConfigDict({
        "lr": 1e-3, "height": 64, "seed": 0, "loop": {"num_train_steps": 10, "eval_every": 5},
        "stages": ("first", "second"),
        "stage_overrides": {"first": {}, "second": {"lr": 2e-4, "height": 128, "loop": {"num_train_steps": 3}}}})


def test_a_stage_is_the_base_with_its_settings_and_the_command_line_wins_everywhere():
    c = _toy_recipe()
    first, second = recipe.stage_config(c, "first"), recipe.stage_config(c, "second")
    assert (first.lr, first.height, first.loop.num_train_steps, first.loop.eval_every) == (1e-3, 64, 10, 5)
    assert (second.lr, second.height, second.loop.num_train_steps, second.loop.eval_every) == (2e-4, 128, 3, 5)
    assert "stages" not in second and "stage_overrides" not in second
    # KEY=VALUE sets the base and every stage that sets KEY; stage_overrides.NAME.KEY one stage, any field
    recipe.override_everywhere(c, ["lr=5e-4", "loop.eval_every=7", "stage_overrides.first.height=32"])
    first, second = recipe.stage_config(c, "first"), recipe.stage_config(c, "second")
    assert (first.lr, second.lr) == (5e-4, 5e-4)
    assert (first.loop.eval_every, second.loop.eval_every) == (7, 7)
    assert (first.height, second.height) == (32, 128)
    with pytest.raises(ValueError, match="no field 'nosuch'"):
        recipe.override_everywhere(c, ["stage_overrides.second.nosuch=1"])
    with pytest.raises(ValueError, match="NAME one of \\['first', 'second'\\]"):
        recipe.override_everywhere(c, ["stage_overrides.third.lr=1"])


def test_stage_names_are_checked():
    c = _toy_recipe()
    c.stages = ("first", "first")
    with pytest.raises(ValueError, match="names a stage twice"):
        recipe.stage_names(c)
    c.stages = ("First", "second")
    with pytest.raises(ValueError, match="not stage names"):
        recipe.stage_names(c)
    c.stages = ("second",)
    with pytest.raises(ValueError, match="sets stages \\['first'\\]"):
        recipe.stage_names(c)
    with pytest.raises(setup.ConfigError, match="recipe of stages"):
        setup.parse(_toy_recipe())


def test_the_command_line_can_keep_some_stages():
    c = _toy_recipe()
    recipe.override_everywhere(c, ["stages=second", "loop.num_train_steps=4"])
    assert c.stages == ("second",) and set(c.stage_overrides.keys()) == {"second"}
    only = recipe.stage_config(c, "second")
    assert (only.lr, only.height, only.loop.num_train_steps) == (2e-4, 128, 4)
    c = _toy_recipe()
    recipe.override_everywhere(c, ["stages=(second, first)"])  # the recipe's order is kept
    assert c.stages == ("first", "second")
    for bad, msg in (("stages=third", "\\['third'\\] are not among them"), ("stages=first,first", "twice"),
                     ("stages=", "comma-separated list")):
        with pytest.raises(ValueError, match=msg):
            recipe.override_everywhere(_toy_recipe(), [bad])
    with pytest.raises(setup.ConfigError, match="--config.stages=nope: .*\\['coarse', 'finish'\\]"):
        train.load_config("demo", ["stages=nope"])


def test_only_the_first_stage_may_set_init_from(tmp_path):
    c = tiny_config()
    c.stages = ("a", "b")
    c.stage_overrides = ml_collections.ConfigDict({"a": {}, "b": {"init_from": "demo"}})
    with pytest.raises(setup.ConfigError, match="stage_overrides.b.init_from: stage b starts from the stage before"):
        train.train_and_evaluate(c, str(tmp_path / "wd"))
    assert not (tmp_path / "wd").exists()


def test_long_recipe_declares_its_stages_in_order():
    c = long.get_config()
    assert recipe.stage_names(c) == ("coarse", "main", "hires")
    runs = [setup.parse(recipe.stage_config(c, n)) for n in recipe.stage_names(c)]
    assert [(r.height, r.width) for r in runs] == [(64, 128), (128, 256), (256, 512)]
    assert [r.data.synthetic_scene for r in runs] == ["real_motion"] * 3
    assert [r.loss.photometric for r in runs] == ["ssim_l1", "census", "census"]
    assert [r.loss.self_supervision for r in runs] == [0.0, 1.0, 1.0]
    assert [r.loss.occlusion_fill for r in runs] == [0.0, 3.0, 3.0]
    assert [r.loss.stereo_occlusion for r in runs] == [False, True, True]
    assert runs[0].init_from == "" and runs[0].model.config["name"] == "pwc_lite"
    # fine-tuning: the last stage's settings from the shipped weights, on a folder, validating at step 0
    ft = long.get_config("finetune")
    assert recipe.stage_names(ft) == ("finetune",)
    ft_cfg, last = recipe.stage_config(ft, "finetune"), recipe.stage_config(c, "hires")
    assert (ft_cfg.init_from, ft_cfg.data.source, ft_cfg.loop.eval_at_start) == ("long", "folder", True)
    for key in ("height", "width", "global_batch"):
        assert ft_cfg[key] == last[key], key
    # at the lr fine-tuning was measured at, with the last stage's moving average
    assert (ft_cfg.lr, ft_cfg.ema_decay, last.ema_decay) == (long.FINETUNE_LR, 0.99, 0.99)
    # ... and the loss of the last stage as the shipped weights were trained: stereo pairs unmasked,
    # self-supervision 0.3, no fill term
    assert ft_cfg.loss.to_dict() == dict(last.loss.to_dict(), stereo_occlusion=False, self_supervision=0.3,
                                         occlusion_fill=0.0)
    assert ft_cfg.data.synthetic_scene == last.data.synthetic_scene
    # the legacy chain: each stage keeps what the stages before it set
    legacy = long.get_config("legacy")
    assert recipe.stage_names(legacy) == ("demo", "real", "selfsup", "motion", "census", "hires")
    hires = recipe.stage_config(legacy, "hires")
    assert (hires.height, hires.global_batch, hires.loss.photometric, hires.loss.self_supervision,
            hires.data.synthetic_scene, hires.lr, hires.loop.num_train_steps) == (
        256, 2, "census", 0.3, "real_motion", 1.25e-4, 250)
    with pytest.raises(ValueError, match="unknown config argument"):
        long.get_config("nosuch")


def test_demo_is_a_two_stage_recipe():
    c = demo.get_config()
    assert recipe.stage_names(c) == ("coarse", "finish")
    coarse, finish = (recipe.stage_config(c, n) for n in ("coarse", "finish"))
    assert (coarse.height, coarse.width, coarse.lr, coarse.loop.num_train_steps) == (64, 128, 1e-3, 1750)
    assert (finish.height, finish.width, finish.lr, finish.loop.num_train_steps) == (128, 256, 2.5e-4, 300)
    assert finish.loop.steps_per_epoch == 300 and finish.init_from == coarse.init_from == ""
    # the second stage continues the first's schedule: the lr of the halving where the first ends
    halvings = sum(1 for e in coarse.lr_milestones if e * coarse.loop.steps_per_epoch <= coarse.loop.num_train_steps)
    assert halvings == 2 and finish.lr == pytest.approx(coarse.lr / 2 ** halvings)
    assert finish.loss.to_dict() == coarse.loss.to_dict() and finish.data.to_dict() == coarse.data.to_dict()
    short = demo.get_config("short")
    assert [recipe.stage_config(short, n).loop.num_train_steps for n in ("coarse", "finish")] == [30, 10]
    assert recipe.stage_config(short, "finish").loop.steps_per_epoch == 300
    with pytest.raises(ValueError, match="'finish' is gone"):
        demo.get_config("finish")


# ------------------------------------------------------------------------------------------------------------
# Running a recipe
# ------------------------------------------------------------------------------------------------------------

def _tiny_recipe():
    """Two stages of the tiny training config: 4 steps, then 3 more from its params with other data (seed)."""
    c = tiny_config(num_train_steps=4)
    c.stages = ("a", "b")
    c.stage_overrides = ml_collections.ConfigDict({"a": {}, "b": {"seed": 1, "loop": {"num_train_steps": 3}}})
    return c


def _records(wd):
    with open(os.path.join(wd, workdir_mod.METRICS_JSONL)) as f:
        return [json.loads(line) for line in f]


def _params(path):
    _, params = checkpointing.read_params(path)
    return {"/".join(str(k) for k in key): np.asarray(v) for key, v in _flat_items(params)}


def _flat_items(tree, prefix=()):
    for k, v in tree.items():
        if isinstance(v, dict):
            yield from _flat_items(v, prefix + (k,))
        else:
            yield prefix + (k,), v


def test_recipe_stages_start_from_the_previous_stage_and_resume_at_a_boundary(tmp_path, monkeypatch):
    restore = enable_compilation_cache()
    try:
        ref = str(tmp_path / "ref")
        res = train.train_and_evaluate(_tiny_recipe(), ref, config_name="tiny.py")
        assert res["step"] == 7 and [s["name"] for s in res["stages"]] == ["a", "b"]
        assert [s["steps"] for s in res["stages"]] == [4, 3]
        recs = _records(ref)
        train_recs = [r for r in recs if r["kind"] == "train"]
        assert [r["step"] for r in train_recs] == list(range(1, 8))  # the step continues across stages
        assert [(r["stage"], r["stage_step"]) for r in train_recs] == [("a", i) for i in range(1, 5)] + [
            ("b", i) for i in range(1, 4)]
        assert [r["recipe/stage_index"] for r in train_recs] == [1.0] * 4 + [2.0] * 3
        starts = [r for r in recs if r["kind"] == "stage_start"]
        assert [(r["stage"], r["step"], r["stage_index"], r["num_stages"]) for r in starts] == [
            ("a", 0, 1, 2), ("b", 4, 2, 2)]
        # stage b starts from stage a's final params: the sum of squares the trainer recorded at b's start is the
        # one numpy computes from a's last checkpoint
        a_dir = recipe.stage_dir(ref, "a")
        assert starts[1]["init_from"] == a_dir
        a_final = _params(a_dir)
        assert checkpointing.find_train_step_dir(a_dir).endswith("/4")
        want = sum(float(np.sum(np.square(v.astype(np.float64)))) for v in a_final.values())
        assert starts[1]["params_sq_sum"] == pytest.approx(want, rel=1e-12)
        assert starts[0]["params_sq_sum"] != want  # stage a's own start (random init) is another tree
        # the recipe workdir stands for its last stage wherever a checkpoint is read
        assert checkpointing.model_dir(ref) == checkpointing.Path(recipe.stage_dir(ref, "b"))
        b_final = _params(ref)
        assert all(np.array_equal(b_final[k], v) for k, v in _params(recipe.stage_dir(ref, "b")).items())
        # what a zoo card built from it says: the one command, each stage's steps and seconds, their total
        card = zoo.recipe_summary(ref, machine="m")
        assert card["rebuild"] == "bridge-train --config=tiny.py --workdir=WORKDIR"
        assert [(st["stage"], st["steps"], st["height"]) for st in card["recipe"]] == [("a", 4, 64), ("b", 3, 64)]
        # each stage's final validation, as its finished.json recorded it (the card's per-stage numbers)
        assert [st["validation"] for st in card["recipe"]] == [recipe.finished(ref, n)["validation"] for n in "ab"]
        assert card["training"]["total_seconds"] == pytest.approx(sum(st["seconds"] for st in res["stages"]), abs=0.2)
        assert card["training"]["first_step"] == 1 and card["training"]["last_step"] == 7
        line, stale = workdir_mod.describe_status(ref)
        assert line.startswith(f"{ref}: stage 2/2 b finished, step 3/3") and not stale

        # killed at the boundary: stage a saved its last checkpoint, but died before its finished.json
        wd = str(tmp_path / "killed")
        real_mark = recipe.mark_finished

        def die(*args, **kwargs):
            raise SystemExit("killed at the boundary")

        monkeypatch.setattr(recipe, "mark_finished", die)
        with pytest.raises(SystemExit):
            train.train_and_evaluate(_tiny_recipe(), wd)
        monkeypatch.setattr(recipe, "mark_finished", real_mark)
        res2 = train.train_and_evaluate(_tiny_recipe(), wd)  # the same command again
        assert res2["step"] == 7
        got = _params(wd)
        assert set(got) == set(b_final) and all(np.array_equal(got[k], b_final[k]) for k in got)  # bitwise
        strip = [(r["step"], r["kind"], r.get("stage"), r.get("loss")) for r in _records(wd)]
        assert strip == [(r["step"], r["kind"], r.get("stage"), r.get("loss")) for r in recs]  # no record twice
        # a finished recipe run again trains nothing
        res3 = train.train_and_evaluate(_tiny_recipe(), wd)
        assert res3["step"] == 7 and len(_records(wd)) == len(recs)
    finally:
        restore()


def test_recipe_workdir_refuses_another_recipe_or_a_single_run(tmp_path):
    wd = tmp_path / "wd"
    (wd / "checkpoints").mkdir(parents=True)
    with pytest.raises(setup.ConfigError, match="holds a single training run"):
        train.train_and_evaluate(_tiny_recipe(), str(wd))
    other = tmp_path / "other"
    other.mkdir()
    (other / recipe.RECIPE_JSON).write_text(json.dumps({"stages": ["x"], "configs": {}}))
    with pytest.raises(setup.ConfigError, match="holds a recipe of the stages \\['x'\\]"):
        train.train_and_evaluate(_tiny_recipe(), str(other))
    with pytest.raises(setup.ConfigError, match="holds the stages of a recipe"):
        train.train_and_evaluate(tiny_config(), str(other))


def _stage_starts(wd):
    return {r["stage"]: r for r in _records(wd) if r["kind"] == "stage_start"}


def _run_long_short(wd, timeout=600):
    cmd = [sys.executable, "-m", "bridge_jax.train", "--config=long:short", f"--workdir={wd}"]
    return subprocess.run(cmd, cwd=REPO, env=subprocess_env(1), capture_output=True, text=True, timeout=timeout)


def test_long_short_runs_every_stage_end_to_end(tmp_path):
    """`bridge-train --config=long:short`: every stage of the `long` recipe at toy scale, each starting from the
    previous stage's final params (the trainer's record at each stage start against numpy's sum of squares of
    the previous stage's last checkpoint)."""
    wd = str(tmp_path / "long")
    t0 = time.time()
    proc = _run_long_short(wd)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    print(f"long:short took {time.time() - t0:.0f} s")
    names = list(recipe.stage_names(long.get_config("short")))
    starts = _stage_starts(wd)
    assert list(starts) == names and starts[names[0]]["init_from"] == ""
    for prev, name in zip(names, names[1:]):
        assert starts[name]["init_from"] == recipe.stage_dir(wd, prev)
        final = _params(recipe.stage_dir(wd, prev))
        want = sum(float(np.sum(np.square(v.astype(np.float64)))) for v in final.values())
        assert starts[name]["params_sq_sum"] == pytest.approx(want, rel=1e-12), name
    for name in names:
        assert recipe.finished(wd, name)["steps"] == 4
    status = subprocess.run([sys.executable, "-m", "bridge_jax.train", "--status", wd], cwd=REPO,
                            env=subprocess_env(1), capture_output=True, text=True)
    assert f"stage 3/3 {names[-1]} finished" in status.stdout
    # the code the recipe ran is recorded, and a card built from it names that commit
    head = subprocess.run(["git", "-C", REPO, "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        assert recipe.read_record(wd)["commit"].split("-")[0] == head.stdout.strip()
        assert zoo.recipe_summary(wd, machine="m")["commit"] == recipe.read_record(wd)["commit"]


def test_the_recipe_record_keeps_the_commit_it_started_at(tmp_path):
    """recipe.json names the code's commit; a run resumed on other code keeps the first and lists the others once
    (what a card then says beside its rebuild command)."""
    wd = str(tmp_path)
    recipe.write_record(wd, ["a"], {"a": {}}, "long", "c1")
    recipe.write_record(wd, ["a"], {"a": {}}, "long", "c1")
    assert recipe.read_record(wd)["commit"] == "c1" and "resumed_at_commits" not in recipe.read_record(wd)
    recipe.write_record(wd, ["a"], {"a": {}}, "long", "c2-dirty")
    recipe.write_record(wd, ["a"], {"a": {}}, "long", "c2-dirty")
    recipe.write_record(wd, ["a"], {"a": {}}, "long", "c3")
    record = recipe.read_record(wd)
    assert record["commit"] == "c1" and record["resumed_at_commits"] == ["c2-dirty", "c3"]
    assert recipe.read_record(str(tmp_path / "none")) is None
    # a record written before commits were recorded does not take the commit of the code that resumes it
    old = tmp_path / "old"
    old.mkdir()
    (old / recipe.RECIPE_JSON).write_text(json.dumps({"stages": ["a"], "configs": {"a": {}}, "config_name": "long"}))
    recipe.write_record(str(old), ["a"], {"a": {}}, "long", "c4")
    assert recipe.read_record(str(old))["commit"] is None
    assert recipe.read_record(str(old))["resumed_at_commits"] == ["c4"]
    # outside a git checkout there is no commit to record (an installed wheel)
    commit = recipe.code_commit()
    head = subprocess.run(["git", "-C", REPO, "rev-parse", "HEAD"], capture_output=True, text=True)
    if head.returncode == 0:
        assert commit is not None and commit.split("-")[0] == head.stdout.strip()


@pytest.mark.slow
@pytest.mark.parametrize("when", ["mid_stage", "boundary"])
def test_sigkill_anywhere_in_long_short_resumes_bitwise(tmp_path, when):
    """kill -9 inside the second stage, or just as it starts (the first stage finished), then the same command:
    the final params equal an uninterrupted run's bit for bit and no stage runs twice."""
    ref = str(tmp_path / "ref")
    assert _run_long_short(ref).returncode == 0
    wd = str(tmp_path / "wd")
    cmd = [sys.executable, "-m", "bridge_jax.train", "--config=long:short", f"--workdir={wd}"]
    proc = subprocess.Popen(cmd, cwd=REPO, env=subprocess_env(1), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    try:
        deadline = time.time() + 600
        while time.time() < deadline and proc.poll() is None:
            if os.path.exists(os.path.join(wd, workdir_mod.METRICS_JSONL)):
                recs = _records(wd)
                main = [r for r in recs if r.get("stage") == "main" and r["kind"] == "train"]
                if (when == "boundary" and any(r["kind"] == "stage_start" and r["stage"] == "main" for r in recs)) \
                        or (when == "mid_stage" and len(main) >= 2):
                    proc.send_signal(signal.SIGKILL)
                    break
            time.sleep(0.05)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    assert recipe.finished(wd, "coarse") is not None and recipe.finished(wd, "hires") is None
    killed_run = workdir_mod.stage_seconds_before(wd, "main")  # the killed run of stage main, from its status.json
    assert killed_run > 0 or when == "boundary"  # killed just as it started, it may not have written a heartbeat
    assert _run_long_short(wd).returncode == 0
    assert recipe.finished(wd, "main")["seconds"] > killed_run  # the stage's seconds include the killed run's
    got, want = _params(wd), _params(ref)
    assert set(got) == set(want) and all(np.array_equal(got[k], want[k]) for k in got)
    stage_starts = [r["stage"] for r in _records(wd) if r["kind"] == "stage_start"]
    assert stage_starts == ["coarse", "main", "hires"]


def test_a_resumed_stage_counts_the_seconds_of_its_earlier_runs(tmp_path):
    """`workdir.stage_seconds_before`: the seconds of earlier, stopped runs of a stage, from the recipe's
    status.json (its start to its last heartbeat or end, plus what the runs before it had), hand-written here."""
    wd = str(tmp_path)
    assert workdir_mod.stage_seconds_before(wd, "main") == 0.0  # no status yet
    path = os.path.join(wd, workdir_mod.STATUS_JSON)

    def status(**fields):
        with open(path, "w") as f:
            json.dump(fields, f)

    # killed: no "ended", its last heartbeat 700 s after its start, after two earlier runs of 1234.5 s in all
    status(status="running", stage="main", started=1000.0, heartbeat=1700.0, time=1700.0, stage_seconds_before=1234.5)
    assert workdir_mod.stage_seconds_before(wd, "main") == pytest.approx(1934.5)
    assert workdir_mod.stage_seconds_before(wd, "hires") == 0.0  # the status is another stage's
    # interrupted (SIGTERM): it ended 30 s after its last heartbeat
    status(status="interrupted", stage="main", started=1000.0, heartbeat=1700.0, ended=1730.0)
    assert workdir_mod.stage_seconds_before(wd, "main") == pytest.approx(730.0)
    status(status="running", stage="main", started="garbled")
    assert workdir_mod.stage_seconds_before(wd, "main") == 0.0
