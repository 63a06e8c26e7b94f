"""The trainer's front door and reliability: config by name, one-line errors, quiet output, metrics.jsonl after
resumes, signals, the non-finite update guard, status.json, no cache folder before the input check."""
from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bridge_jax import train, train_step
from bridge_jax.workdir import STATUS_JSON, truncate_metrics
from tests.train_helpers import CACHE_DIR, enable_compilation_cache, subprocess_env, tiny_config


@pytest.fixture(scope="module", autouse=True)
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


def _jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


# --------------------------------------------------------------------------------------------------------
# Parsing
# --------------------------------------------------------------------------------------------------------

def test_config_overrides_are_split_in_both_spellings():
    rest, items = train.split_config_overrides(["--config=demo", "--config.height=128", "--workdir", "w",
                                                "--config.loss.two_warp", "full2"])
    assert rest == ["--config=demo", "--workdir", "w"]
    assert items == ["height=128", "loss.two_warp=full2"]
    with pytest.raises(train.ConfigError, match="--config.height: expected --config.height=VALUE"):
        train.split_config_overrides(["--config.height"])


def test_config_by_name_from_any_directory_and_typos_name_close_matches(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    cfg = train.load_config("demo:short", ["height=128", "loss.two_warp=full2"])
    assert cfg.height == 128 and cfg.loss.two_warp == "full2" and cfg.model.name == "pwc_lite"
    with pytest.raises(train.ConfigError, match=r"--config.model.nmae=x: .*did you mean --config.model.name"):
        train.load_config("demo", ["model.nmae=x"])
    with pytest.raises(train.ConfigError, match=r"unknown config 'dmeo'; did you mean demo\?"):
        train.load_config("dmeo", [])
    with pytest.raises(train.ConfigError, match=r"no such config file 'configs/full9.py'"):
        train.load_config("configs/full9.py", [])
    bad = tmp_path / "broken.py"
    bad.write_text("def get_config(arg=None):\n    return 1 / 0\n")
    with pytest.raises(train.ConfigError, match=r"broken.py: the config file failed: ZeroDivisionError"):
        train.load_config(str(bad), [])


def test_main_bad_input_is_one_line_exit_2_and_writes_nothing(tmp_path, capsys):
    wd = tmp_path / "wd"
    for argv, match in (
            (["--config=dmeo"], "unknown config 'dmeo'"),
            (["--config=default:local", "--config.model.nmae=1"], "did you mean --config.model.name"),
            (["--config=default:local", "--config.lr=inf"], "config.lr=inf: must be a number > 0 float32 can hold"),
            (["--config=default:local", "--config.lr=0.0"], "config.lr=0.0: must be a number > 0")):
        rc = train.main([*argv, f"--workdir={wd}"])
        err = capsys.readouterr().err.strip().splitlines()
        assert rc == 2 and len(err) == 1 and err[0].startswith("error: ") and match in err[0], err
        assert not wd.exists()


def test_help_shows_examples_configs_sources_and_layouts(capsys):
    with pytest.raises(SystemExit) as e:
        train.main(["--help"])
    assert e.value.code == 0
    out = capsys.readouterr().out
    assert "bridge-train --config=demo --workdir=work/demo" in out and "--list-config" in out
    for name in ("default", "demo", "full2", "no_sharing", "stereo_only"):
        assert f"\n  {name} " in out, name
    assert "Data sources" in out and "folder" in out and "left/" in out and "right/" in out
    assert "Exit codes" in out and "(default: warning)" in out


def test_xla_cache_is_not_created_when_the_input_check_fails(tmp_path, monkeypatch):
    calls = []
    monkeypatch.setattr(train.compile_cache, "enable", lambda *a, **k: calls.append(a))
    with pytest.raises(train.ConfigError):
        train.train_and_evaluate(tiny_config(global_batch=3), str(tmp_path / "wd"), enable_cache=True)
    assert calls == [] and not (tmp_path / "wd").exists()


# --------------------------------------------------------------------------------------------------------
# The non-finite guard checks the update and the new params, not only loss and gradients
# --------------------------------------------------------------------------------------------------------

def test_guard_rejects_a_finite_gradient_whose_update_overflows():
    params = {"w": jnp.ones((3,), jnp.float32)}
    tx = optax.sgd(1e30)  # finite gradients, but the update overflows float32 to -inf
    state = train_step.create_train_state(params, tx, jnp.zeros((2,), jnp.uint32))
    grads = {"w": jnp.full((3,), 1e10, jnp.float32)}
    new, metrics = train_step.apply_gradients(state, jnp.float32(1.0), {}, grads, tx, lambda s: 1e30)
    assert int(metrics["nonfinite"]) == 1
    np.testing.assert_array_equal(np.asarray(new["params"]["w"]), [1.0, 1.0, 1.0])
    assert int(new["step"]) == 0
    # the same with a small rate goes through
    tx = optax.sgd(1e-12)
    state = train_step.create_train_state(params, tx, jnp.zeros((2,), jnp.uint32))
    new, metrics = train_step.apply_gradients(state, jnp.float32(1.0), {}, grads, tx, lambda s: 1e-12)
    assert int(metrics["nonfinite"]) == 0 and int(new["step"]) == 1
    np.testing.assert_allclose(np.asarray(new["params"]["w"]), 1.0 - 1e-2, rtol=1e-6)


@pytest.mark.parametrize("clip", [0.0, 0.5])
def test_update_equals_adam_leaf_by_leaf(clip):
    """Two steps of apply_gradients give what optax's Adam gives applied to the parameter tree leaf by leaf (with
    and without clipping), in the state's own layout, and the norms it reports are numpy's."""
    rng = np.random.default_rng(0)
    tree = lambda: {"conv": {"kernel": rng.normal(size=(3, 3, 4, 5)), "bias": rng.normal(size=(5,))},
                    "head": {"kernel": rng.normal(size=(1, 1, 5, 2))}, "scale": rng.normal(size=()),
                    "big": rng.normal(size=(1025, 256))}
    f32 = lambda t: jax.tree.map(lambda x: jnp.asarray(x, jnp.float32), t)
    params = f32(tree())
    tx, schedule = train_step.make_optimizer(train_step.OptimizerConfig(lr=1e-2, clip_grad_norm=clip), 10)
    state = train_step.create_train_state(params, tx, jnp.zeros((2,), jnp.uint32))
    step = jax.jit(lambda s, g: train_step.apply_gradients(s, jnp.float32(1.0), {}, g, tx, schedule))
    ref_params, ref_opt = params, tx.init(params)
    for _ in range(2):
        grads = f32(tree())
        state, metrics = step(state, grads)
        updates, ref_opt = tx.update(grads, ref_opt, ref_params)
        ref_params = optax.apply_updates(ref_params, updates)
        assert int(metrics["nonfinite"]) == 0
        for got, want in ((state["params"], ref_params), (state["opt_state"], ref_opt)):
            assert jax.tree.structure(got) == jax.tree.structure(want)
            for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
                assert np.shape(a) == np.shape(b)
                np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=1e-6, atol=1e-7)
        norm = lambda t: np.sqrt(sum(np.sum(np.asarray(x, np.float64) ** 2) for x in jax.tree.leaves(t)))
        assert float(metrics["grad_norm"]) == pytest.approx(norm(grads), rel=1e-5)
        assert float(metrics["param_norm"]) == pytest.approx(norm(ref_params), rel=1e-5)
    assert int(state["step"]) == 2


# --------------------------------------------------------------------------------------------------------
# metrics.jsonl reads as one run after resumes
# --------------------------------------------------------------------------------------------------------

def test_truncate_metrics_drops_later_steps_and_torn_lines(tmp_path):
    path = tmp_path / "metrics.jsonl"
    lines = [json.dumps({"step": s, "kind": k}) for s, k in ((1, "train"), (2, "train"), (2, "val"), (3, "train"),
                                                             (4, "train"))]
    path.write_text("\n".join(lines) + "\n" + '{"step": 5, "ki')
    assert truncate_metrics(str(path), 2) == 3
    assert [(r["step"], r["kind"]) for r in _jsonl(path)] == [(1, "train"), (2, "train"), (2, "val")]
    assert truncate_metrics(str(path), 2) == 0


def test_resume_after_lost_steps_and_rerun_of_a_finished_run_do_not_repeat_records(tmp_path):
    wd = str(tmp_path / "wd")
    cfg = dict(num_train_steps=6, checkpoint_every=3, eval_every=0)
    first = train.train_and_evaluate(tiny_config(**cfg), wd)
    assert first["step"] == 6
    shutil.rmtree(os.path.join(wd, "checkpoints", "6"))  # as if killed after logging steps 4-6, before saving 6
    second = train.train_and_evaluate(tiny_config(**cfg), wd)
    assert second["start_step"] == 3 and second["step"] == 6
    third = train.train_and_evaluate(tiny_config(**cfg), wd)  # already finished: no new validation either
    assert third["start_step"] == 6 and third["validation"] == second["validation"]
    recs = _jsonl(os.path.join(wd, "metrics.jsonl"))
    assert [r["step"] for r in recs if r["kind"] == "train"] == [1, 2, 3, 4, 5, 6]
    assert [r["step"] for r in recs if r["kind"] == "val"] == [6]
    status = json.load(open(os.path.join(wd, STATUS_JSON)))
    assert status["status"] == "finished" and status["step"] == 6


# --------------------------------------------------------------------------------------------------------
# Signals
# --------------------------------------------------------------------------------------------------------

def test_first_signal_is_recorded_and_the_handlers_are_restored():
    # the handler before (Python's default_int_handler, or SIG_IGN when the tests run in a background job)
    before = signal.getsignal(signal.SIGINT)
    with train._StopSignals(announce=False) as stop:
        os.kill(os.getpid(), signal.SIGINT)
        assert stop.received == signal.SIGINT  # a second one exits at once: tests/test_reliability.py
    assert signal.getsignal(signal.SIGINT) == before  # restored on exit
    assert signal.set_wakeup_fd(-1) == -1  # and the wake-up pipe unset


def test_stop_request_skips_the_validation_of_that_step(tmp_path, monkeypatch):
    """A stop asked for during step 2 (validation due every step): step 1 is validated, step 2 is not, the run
    saves step 2, reports interrupted and writes status "interrupted"."""

    class StopDuringStep2(train._StopSignals):
        reads = 0

        def __enter__(self):
            return self

        @property
        def received(self):  # the loop reads it at the top of each step and once after it
            StopDuringStep2.reads += 1
            return signal.SIGTERM if StopDuringStep2.reads >= 4 else None

        @received.setter
        def received(self, value):
            pass

    monkeypatch.setattr(train, "_StopSignals", StopDuringStep2)
    wd = str(tmp_path / "wd")
    res = train.train_and_evaluate(tiny_config(num_train_steps=10, eval_every=1, checkpoint_every=100), wd)
    assert res["interrupted"] and res["step"] == 2
    recs = _jsonl(os.path.join(wd, "metrics.jsonl"))
    assert [r["step"] for r in recs if r["kind"] == "val"] == [1]
    assert sorted(os.listdir(os.path.join(wd, "checkpoints"))) == ["2"]
    assert json.load(open(os.path.join(wd, STATUS_JSON)))["status"] == "interrupted"


# --------------------------------------------------------------------------------------------------------
# The command line end to end: a config by name from outside the repo, quiet output, exit codes
# --------------------------------------------------------------------------------------------------------

def test_cli_by_name_from_another_directory_is_quiet_and_says_what_it_runs(tmp_path):
    wd = tmp_path / "wd"
    cmd = [sys.executable, "-m", "bridge_jax.train", "--config=default:local", f"--workdir={wd}",
           "--config.height=64", "--config.width=128", "--config.num_devices=2", "--config.global_batch=2",
           "--config.micro_batch=0", "--config.loop.num_train_steps=2", "--config.loop.checkpoint_every=1",
           "--config.loop.eval_every=-1", "--config.loop.image_every=-1", "--config.loop.progress_bar=False",
           "--config.data.synthetic_num=8", "--config.data.prefetch=0"]
    r = subprocess.run(cmd, cwd=tmp_path, env=subprocess_env(2), capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    noise = [line for line in r.stderr.splitlines() if line.startswith(("I", "W")) and len(line) > 5
             and line[1:5].isdigit()]  # absl's "I1201 13:00:00..." lines
    assert noise == [], noise[:5]
    start = [line for line in r.stdout.splitlines() if line.startswith("train: ")]
    assert len(start) == 1 and "config default:local" in start[0] and "data synthetic: 8 cycles" in start[0]
    assert "2 cpu devices" in start[0] and str(wd) in start[0]
    status = json.load(open(wd / STATUS_JSON))
    assert status["status"] == "finished"
    # one line before the first (compiling) step naming the cache, one after it with the time to that step
    assert f"compiling the train step for 64x128 (first run only: cached in {CACHE_DIR})" in r.stdout.splitlines()
    ready = [line for line in r.stdout.splitlines() if line.startswith("train step ready after ")]
    assert len(ready) == 1 and f"{status['first_step_s']:.1f} s" in ready[0]
    # the time to the first step counts from the start of the process: Python and JAX's import come first
    assert status["first_step_s"] > 1.0 and 0 < status["compile_s"] < status["first_step_s"]


# --------------------------------------------------------------------------------------------------------
# A broken newest checkpoint: resume from the newest good one, name the broken one, keep its bytes
# --------------------------------------------------------------------------------------------------------

def test_training_resumes_from_the_newest_good_checkpoint_and_keeps_the_broken_one(tmp_path):
    from bridge_jax import checkpointing
    wd = str(tmp_path / "wd")
    train.train_and_evaluate(tiny_config(num_train_steps=4, checkpoint_every=2), wd)
    step4 = os.path.join(wd, "checkpoints", "4", "state")
    biggest = max((os.path.join(dp, f) for dp, _, fs in os.walk(step4) for f in fs), key=os.path.getsize)
    with open(biggest, "r+b") as f:
        f.truncate(os.path.getsize(biggest) // 2)
    with pytest.warns(checkpointing.CheckpointFallbackWarning, match=r"checkpoints/4"):
        res = train.train_and_evaluate(tiny_config(num_train_steps=6, checkpoint_every=2), wd)
    assert res["start_step"] == 2 and res["step"] == 6
    names = os.listdir(os.path.join(wd, "checkpoints"))
    assert "4.broken-1" in names and "6" in names  # moved aside, not deleted
    assert os.path.getsize(os.path.join(wd, "checkpoints", "4.broken-1", os.path.relpath(biggest, os.path.dirname(
        step4)))) > 0
    steps = [r["step"] for r in _jsonl(os.path.join(wd, "metrics.jsonl")) if r["kind"] == "train"]
    assert steps == [1, 2, 3, 4, 5, 6]


def test_init_from_refuses_non_finite_params_naming_the_leaf_and_accepts_a_model_name(tmp_path):
    from bridge_jax import checkpointing, zoo
    cfg, params = zoo.load_params("demo")
    params = jax.tree.map(np.asarray, params)
    params["estimator_flow"]["kernel"] = params["estimator_flow"]["kernel"].copy()
    params["estimator_flow"]["kernel"][0, 0, 0, 0] = np.nan
    checkpointing.save_params(tmp_path / "nan", params, cfg)
    wd = tmp_path / "wd"
    with pytest.raises(train.ConfigError, match=r"config.init_from=.*nan.*: parameter estimator_flow/kernel has 1 "
                                                r"non-finite"):
        train.train_and_evaluate(tiny_config(init_from=str(tmp_path / "nan")), str(wd))
    assert not wd.exists()
    with pytest.raises(train.ConfigError, match=r"config.init_from='demo' holds a different architecture"):
        train.train_and_evaluate(tiny_config(init_from="demo"), str(wd))  # a name resolves; tiny resnet != pwc_lite
    with pytest.raises(train.ConfigError, match=r"'dmeo' is neither an existing path nor a model name"):
        train.train_and_evaluate(tiny_config(init_from="dmeo"), str(wd))


@pytest.mark.parametrize("error,match", [
    (OSError(28, "No space left on device", "/w/checkpoints/4"), "error: /w/checkpoints/4: No space left on device"),
    (RuntimeError("RESOURCE_EXHAUSTED: Error writing local file \"/w/checkpoints/4/state/d/0\"\nmore"),
     "error: --workdir=/w: the disk is full (RESOURCE_EXHAUSTED: Error writing local file"),
    (ValueError("config.data: 7 consecutive cycles unreadable\nfiles: a, b"), "error: config.data: 7 consecutive"),
])
def test_environment_errors_during_training_are_one_line_exit_2(monkeypatch, capsys, error, match):
    def fail(*a, **k):
        raise error
    monkeypatch.setattr(train, "train_and_evaluate", fail)
    assert train.main(["--config=demo", "--workdir=/w"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(match), err


def test_debug_flag_shows_the_traceback(monkeypatch, capsys):
    def fail(*a, **k):
        raise ValueError("config.data: broken")
    monkeypatch.setattr(train, "train_and_evaluate", fail)
    assert train.main(["--config=demo", "--workdir=/w", "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback" in err and err.strip().splitlines()[-1] == "error: config.data: broken"


def test_override_names_close_matches_for_every_caller():
    """The hint lives in configs.override, so bench's --set gets it as well as train's --config.KEY."""
    from bridge_jax import configs
    from bridge_jax.bench import cli as bench_cli
    with pytest.raises(ValueError, match=r"no field 'loss.two_wrap'; did you mean loss.two_warp\?$"):
        configs.override(configs.load("demo"), ["loss.two_wrap=full2"])
    with pytest.raises(bench_cli.BenchError, match=r"^--set 'loss.two_wrap=full2': .*did you mean loss.two_warp\?$"):
        bench_cli.load_config("demo", ["loss.two_wrap=full2"])
    with pytest.raises(ValueError, match=r"no field 'zzz'$"):  # nothing close: no hint
        configs.override(configs.load("demo"), ["zzz=1"])


def test_the_start_line_says_where_params_and_validation_come_from(tmp_path):
    """A fine-tune is "initialised from" its model, and training on other data without `data.val_dir` says that
    it validates on synthetic frames."""
    from bridge_jax import setup
    run = setup.parse(tiny_config(**{"init_from": "demo", "data.source": "folder", "data.data_dir": str(tmp_path)}),
                      devices=jax.devices()[:1])
    line = train._startup_line(run, "demo", 8, ("synthetic", [None] * 2), str(tmp_path), 0, 4)
    assert "initialised from demo" in line and "from scratch" not in line
    assert "synthetic frames, not your data" in line and "--config.data.val_dir" in line
    plain = setup.parse(tiny_config(), devices=jax.devices()[:1])
    line = train._startup_line(plain, "default", None, ("synthetic", [None] * 2), str(tmp_path), 0, 4)
    assert "from scratch" in line and "not your data" not in line
