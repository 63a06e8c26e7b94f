"""The README main job (`python -m bridge_jax.demo`), end to end in a subprocess, with its short config."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from bridge_jax import zoo
from tests.train_helpers import REPO


def test_demo_short_runs_end_to_end_and_keeps_a_compile_cache(tmp_path):
    wd = tmp_path / "demo"
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the per-user cache folder must be used
    env["BRIDGE_JAX_CACHE_DIR"] = str(tmp_path / "user_cache")
    env.pop("JAX_NUM_CPU_DEVICES", None)
    r = subprocess.run([sys.executable, "-m", "bridge_jax.demo", "--short", f"--workdir={wd}"], env=env, cwd=REPO,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((wd / "demo_summary.json").read_text())
    # both stages of the demo recipe ran: 30 steps at 64x128, then 10 at 128x256 from their weights, which are the
    # demo model (the recipe workdir WORKDIR/train stands for its last stage)
    assert summary["stage_steps"] == {"coarse": 30, "finish": 10} and summary["steps"] == 40
    assert not summary["interrupted"] and summary["train_dir"] == str(wd / "train")
    first = json.loads((wd / "train" / "stages" / "coarse" / "config.json").read_text())
    second = json.loads((wd / "train" / "stages" / "finish" / "config.json").read_text())
    assert (first["height"], first["width"], second["height"], second["width"]) == (64, 128, 128, 256)
    assert second["init_from"] == str(wd / "train" / "stages" / "coarse") and first["init_from"] == ""
    # the second stage of the process times its first step from its own start, not from the process's (which
    # would include the whole first stage: its cold compile alone is longer than the second stage after its first
    # step)
    st = json.loads((wd / "train" / "status.json").read_text())
    assert st["stage"] == "finish" and 0 < st["first_step_s"] <= st["ended"] - st["started"] + 5.0, st
    # The validation numbers are real EPEs against a positive zero-motion baseline, not placeholders.
    assert summary["zero_flow_epe"] > 0.5 and summary["zero_disp_epe"] > 0.5
    assert 0.2 < summary["val_flow_epe_vs_zero"] < 5.0
    # step 3 evaluates the model as the shipped demo answers by default, and its numbers are the tables'
    assert (summary["eval_refine"], summary["eval_polish"]) == (zoo.card_test_time("demo").refine,
                                                                zoo.card_test_time("demo").polish)
    scored = json.loads((wd / "eval" / "results.json").read_text())
    assert (scored["refine"], scored["polish"]) == (summary["eval_refine"], summary["eval_polish"])
    assert summary["eval_flow_epe"] == scored["methods"]["model"]["flow"]["per_image_mean"]["epe_all"]
    assert abs(summary["eval_flow_epe_vs_zero"] * summary["zero_flow_epe"] - summary["eval_flow_epe"]) < 1e-9
    assert "As `--checkpoint demo` answers by default" in r.stdout
    assert (wd / "eval" / "results.md").is_file() and os.listdir(wd / "eval" / "pictures")
    results = (wd / "eval" / "results.md").read_text()
    assert "zero" in results.lower() and "sgbm" in results.lower()
    cache = tmp_path / "user_cache"
    assert cache.is_dir() and os.listdir(cache), "the demo should keep its compiled functions in the user's cache"
    assert not (wd / "xla_cache").exists()
    assert "Where things are" in r.stdout


def test_demo_refuses_a_single_run_workdir_before_training(tmp_path):
    """A WORKDIR/train that holds one training run (the demo of before its recipe: checkpoints directly in it) is
    refused with one error naming the folder, before anything is trained or written."""
    from bridge_jax import demo
    (tmp_path / "train" / "checkpoints").mkdir(parents=True)
    (tmp_path / "train" / "config.json").write_text(json.dumps({"height": 128, "width": 256}))
    before = sorted(p.name for p in tmp_path.rglob("*"))
    try:
        demo.run(str(tmp_path), config_arg="short")
    except ValueError as e:
        assert str(tmp_path / "train") in str(e) and "single training run" in str(e), e
    else:
        raise AssertionError("a single-run WORKDIR/train was taken for the demo's recipe")
    assert sorted(p.name for p in tmp_path.rglob("*")) == before
