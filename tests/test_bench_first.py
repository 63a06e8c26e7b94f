"""bridge_jax.bench.first: fresh-process timings (first_prediction, first_step) with tiny stand-in commands.

The real commands take minutes on 2 cores; here `time_cold_warm` times a `python -c` child that logs the cache
folder it was given, sleeps a known time and writes a status.json with a known first_step_s, so the recorded
numbers, the cold / warm / off cache folders, the child's environment and the error of a failing child are checked
without training or predicting. The real command lines are checked by parsing them with their own CLIs.
"""

from __future__ import annotations

import json
import os
import sys

import cv2
import jax
import numpy as np
import pytest

from bridge_jax import bench, predict, recipe, setup, train
from bridge_jax.bench import cli, first

SLEEP_S = 0.3
FIRST_STEP_S = 0.125

# The stand-in child: logs what it saw (the cache folder, whether it was empty, the compilation-cache variable),
# leaves a file in the cache folder (as a real cache entry would), writes status.json into its run folder, sleeps.
FAKE = """
import json, os, sys, time
log, run_dir, first_step, sleep_s = sys.argv[1:5]
cache = os.environ.get("BRIDGE_JAX_CACHE_DIR")
seen = dict(cache=cache, empty=bool(cache) and not os.listdir(cache),
            jax_cache=os.environ.get("JAX_COMPILATION_CACHE_DIR"))
with open(log, "a") as f:
    f.write(json.dumps(seen) + "\\n")
if cache:
    open(os.path.join(cache, "entry" + str(os.getpid())), "w").close()
os.makedirs(run_dir)
status = {"status": "finished", "step": 2}
if first_step != "none":
    status["first_step_s"] = float(first_step)
with open(os.path.join(run_dir, "status.json"), "w") as f:
    json.dump(status, f)
time.sleep(float(sleep_s))
"""


def fake_command(log, first_step="%g" % FIRST_STEP_S):
    return lambda run_dir: [sys.executable, "-c", FAKE, str(log), run_dir, first_step, str(SLEEP_S)]


def _seen(log):
    return [json.loads(line) for line in log.read_text().splitlines()]


def test_cold_runs_get_fresh_empty_folders_warm_runs_reuse_one(tmp_path, monkeypatch):
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", str(tmp_path / "must_not_reach_the_child"))
    log = tmp_path / "log.jsonl"
    rec = first.time_cold_warm(fake_command(log), repeats=2, label="fake", off=True, status_json=True)
    seen = _seen(log)
    assert len(seen) == 5  # 2 cold, 2 warm, 1 off, in that order
    cold, warm, off = seen[:2], seen[2:4], seen[4]
    assert all(s["jax_cache"] is None for s in seen)
    assert all(s["empty"] for s in cold) and cold[0]["cache"] != cold[1]["cache"]
    assert [s["cache"] for s in warm] == [cold[1]["cache"]] * 2 and not any(s["empty"] for s in warm)
    assert off["cache"] == ""
    assert not os.path.exists(cold[0]["cache"])  # the temporary folders are gone
    for kind, n in (("cold", 2), ("warm", 2), ("off", 1)):
        assert len(rec[f"{kind}_times_s"]) == n
        assert SLEEP_S <= rec[f"{kind}_s"] < SLEEP_S + 20
    assert rec["first_step_cold_s"] == rec["first_step_warm_s"] == FIRST_STEP_S
    assert rec["first_step_times_s"] == {"cold": [FIRST_STEP_S] * 2, "warm": [FIRST_STEP_S] * 2, "off": [FIRST_STEP_S]}
    assert set(rec["cpu_s"]) == {"cold", "warm", "off"} and rec["children_peak_rss_gib"] > 0


def test_missing_first_step_key_is_null_and_off_is_optional(tmp_path):
    log = tmp_path / "log.jsonl"
    rec = first.time_cold_warm(fake_command(log, "none"), repeats=1, label="fake", status_json=True)
    assert len(_seen(log)) == 2 and rec["off_s"] is None and "off_times_s" not in rec
    assert rec["first_step_cold_s"] is None and rec["first_step_warm_s"] is None
    assert rec["cold_s"] >= SLEEP_S and rec["warm_s"] >= SLEEP_S
    rec = first.time_cold_warm(fake_command(log), repeats=1, label="fake")  # no status.json wanted: no keys
    assert "first_step_cold_s" not in rec


def test_failing_child_is_one_clear_error(tmp_path):
    cmd = [sys.executable, "-c", "import sys; print('some progress', file=sys.stderr); "
                                 "sys.exit('predict: error: no model named nope')"]
    with pytest.raises(bench.BenchError) as e:
        first.time_cold_warm(lambda run_dir: cmd, repeats=1, label="first_prediction")
    msg = str(e.value)
    assert "first_prediction (cold cache)" in msg and "exit 1" in msg
    assert "predict: error: no model named nope" in msg and "\n" not in msg
    with pytest.raises(bench.BenchError, match="--repeats must be >= 1"):
        first.time_cold_warm(lambda run_dir: cmd, repeats=0, label="x")


def test_photo_pair_is_512x256_and_deterministic(tmp_path):
    (tmp_path / "1").mkdir()
    (tmp_path / "2").mkdir()
    a, b = first.write_photo_pair(str(tmp_path / "1"))
    a2, _ = first.write_photo_pair(str(tmp_path / "2"))
    img_a, img_b = cv2.imread(a), cv2.imread(b)
    assert img_a.shape == img_b.shape == (256, 512, 3)
    assert np.array_equal(img_a, cv2.imread(a2)) and not np.array_equal(img_a, img_b)


def test_commands_parse_with_their_own_clis(tmp_path):
    cmd = first.predict_command("a.png", "b.png", str(tmp_path / "out"), "demo", "native")
    assert cmd[:3] == [sys.executable, "-m", "bridge_jax.predict"]
    args = predict.build_parser().parse_args(cmd[3:])
    assert (args.checkpoint, args.task, args.inputs, args.working_size) == ("demo", "flow", ["a.png", "b.png"],
                                                                                 "native")
    assert "--working-size" not in first.predict_command("a.png", "b.png", "o", "demo")
    args = predict.build_parser().parse_args(first.predict_command("a.png", "b.png", "o", "long", None, "dihedral")[3:])
    assert (args.checkpoint, args.symmetry, args.working_size) == ("long", "dihedral", None)
    assert "--symmetry" not in first.predict_command("a.png", "b.png", "o", "demo")
    args = predict.build_parser().parse_args(first.predict_command("a.png", "b.png", "o", "long", None, None,
                                                                   "photometric")[3:])
    assert (args.polish, args.symmetry) == ("photometric", None)
    assert "--polish" not in first.predict_command("a.png", "b.png", "o", "demo")
    args = predict.build_parser().parse_args(first.predict_command("a.png", "b.png", "o", "long", confidence=True)[3:])
    assert args.confidence and args.polish is None
    assert "--confidence" not in first.predict_command("a.png", "b.png", "o", "demo")

    cmd = first.train_command(str(tmp_path / "wd"), "demo", 128, 256, extra=("--config.dtype=bfloat16",))
    assert cmd[:3] == [sys.executable, "-m", "bridge_jax.train"]
    rest, items = train.split_config_overrides(cmd[3:])
    args = train.build_parser().parse_args(rest)
    assert args.config == "demo" and args.workdir == str(tmp_path / "wd")
    config = train.load_config(args.config, items)
    assert config.stages == ("coarse",) and set(config.stage_overrides.keys()) <= {"coarse"}  # the demo's first stage
    run = setup.parse(recipe.single_run(config), devices=jax.devices()[:1], num_processes=1)
    assert (run.height, run.width, run.model.dtype) == (128, 256, "bfloat16")
    steps = first.FIRST_STEP_STEPS
    assert run.loop.num_train_steps == steps and run.loop.checkpoint_every > steps
    assert run.loop.eval_every == -1 and run.loop.image_every <= 0 and not run.validates


def test_defaults_and_all_leaves_them_out():
    args = cli.parse_args(["--what", "first_step"])
    assert (args.config, args.repeats) == ("demo", 1)
    args = cli.parse_args(["--what", "first_prediction", "--working-size", "trained"])
    assert (args.checkpoint, args.working_size, args.repeats) == ("demo", "trained", 1)
    args = cli.parse_args(["--what", "inference"])
    assert (args.config, args.repeats) == ("default", 3)
    assert not set(bench.PROCESS_WHATS) & set(bench.WHATS)


def test_cli_record_through_a_fake_child(tmp_path, monkeypatch, capsys):
    """`--what first_prediction` end to end with the predict command replaced: stdout table + JSON and --json."""
    log = tmp_path / "log.jsonl"
    made = []

    def fake_predict(a, b, out, checkpoint, working_size=None, symmetry=None, polish=None, confidence=False):
        made.append((a, b, checkpoint, working_size, symmetry, polish, confidence))
        return fake_command(log)(out)

    monkeypatch.setattr(first, "predict_command", fake_predict)
    out = tmp_path / "r.jsonl"
    assert bench.main(["--what", "first_prediction", "--checkpoint", "long", "--working-size", "native",
                       "--symmetry", "none", "--polish", "none", "--json", str(out)]) == 0
    (r,) = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(made) == 3 and made[0][2:] == ("long", "native", "none", "none", False)
    assert made[0][0].endswith("a.png")
    assert r["what"] == "first_prediction" and r["checkpoint"] == "long" and r["working_size"] == "native"
    assert r["symmetry"] == "none" and r["polish"] == "none" and r["confidence"] is False
    assert (r["height"], r["width"], r["repeats"]) == (256, 512, 1)
    assert r["cold_s"] >= SLEEP_S and r["warm_s"] >= SLEEP_S and r["off_s"] >= SLEEP_S
    for key in ("machine", "cpu_isa", "cpu_model", "date", "jax_version", "loadavg", "other_procs_cpu_frac"):
        assert key in r, key
    assert r["date"].endswith("Z") and r["machine"].startswith(f"{os.cpu_count()}-core")
    stdout = capsys.readouterr().out
    assert "| first_prediction | long working size native symmetry none polish none | 256x512 |" in stdout
    assert json.loads([line for line in stdout.splitlines() if line.startswith("{")][0])["cold_s"] == r["cold_s"]


def test_first_step_record_through_a_fake_child(tmp_path, monkeypatch):
    log = tmp_path / "log.jsonl"
    made = []

    def fake_train(workdir, config, height, width, *, steps=2, extra=()):
        made.append((config, height, width, extra))
        return fake_command(log)(workdir)

    monkeypatch.setattr(first, "train_command", fake_train)
    args = cli.parse_args(["--what", "first_step", "--height", "64", "--set", "loss.two_warp=full2"])
    (r,) = bench.run(args)
    assert made == [("demo", 64, 256, ("--config.loss.two_warp=full2",))] * 2
    assert r["what"] == "first_step" and r["config"] == "demo" and (r["height"], r["width"]) == (64, 256)
    assert r["first_step_cold_s"] == r["first_step_warm_s"] == FIRST_STEP_S and r["off_s"] is None
    assert r["cold_s"] >= SLEEP_S and "cpu_isa" in r
    assert "| first_step | demo 2 steps | 64x256 |" in bench.table([r])
