"""Training: the whole train_and_evaluate on a tiny model, resume, sharding, guards, micro-batching, CLI.

Tiny ResNet-MD (`resnet_md_tiny`) at 64x128, 2 cycles per step, 8 fake CPU devices (conftest). All tests
that build the same step share one compiled executable through the persistent compilation cache.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time

import jax
import jax.numpy as jnp
import ml_collections
import numpy as np
import pytest

from bridge_jax import checkpointing, compile_cache, setup, train, train_step
from bridge_jax.configs import default as default_config
from bridge_jax.micro_batch import MicroBatchedStep
from bridge_jax.workdir import STATUS_JSON
from tests.train_helpers import (H, W, REPO, enable_compilation_cache, make_step, plain_loss_and_grads, subprocess_env,
                                 tiny_config, train_cli)


@pytest.fixture(scope="module", autouse=True)
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


@pytest.fixture(scope="module", autouse=True)
def _memoised_synthetic_data():
    """Renders each synthetic training sample once per module (the pipeline itself is tested elsewhere)."""
    from bridge_jax.data import pipeline
    orig = pipeline.SyntheticSource.load
    memo = {}

    def load(self, index):
        key = (repr(self.inner), int(index) % len(self))
        if key not in memo:
            memo[key] = orig(self, index)
        return memo[key]

    pipeline.SyntheticSource.load = load
    yield
    pipeline.SyntheticSource.load = orig


def _read_jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def _params_close(a, b, tol):
    la, lb = jax.tree.leaves(a), jax.tree.leaves(b)
    assert jax.tree.structure(a) == jax.tree.structure(b)
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in zip(la, lb)) <= tol


def _record_batches(monkeypatch):
    """Records a digest of every local batch the trainer places on devices."""
    seen = []
    orig = train._global_array

    def spy(sharding, local, global_shape):
        seen.append(np.asarray(local).copy())
        return orig(sharding, local, global_shape)

    monkeypatch.setattr(train, "_global_array", spy)
    return seen


# ------------------------------------------------------------------------------------------------------
# One whole run (shared by several tests)
# ------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def fixed_batch_run(tmp_path_factory):
    """6 steps on a fixed batch (2 cycles, no augmentation, lr 1e-3), validation and pictures at the end."""
    workdir = str(tmp_path_factory.mktemp("run") / "wd")
    cfg = tiny_config(**{"loop.num_train_steps": 6, "lr": 1e-3, "data.synthetic_num": 2, "data.augment": False,
                         "loop.eval_every": 0, "loop.image_every": 3})
    before = train_step.TRACE_COUNTS["train_step"]
    result = train.train_and_evaluate(cfg, workdir)
    return workdir, result, train_step.TRACE_COUNTS["train_step"] - before


def test_train_and_evaluate_end_to_end(fixed_batch_run):
    workdir, result, traces = fixed_batch_run
    assert result["step"] == 6 and not result["interrupted"]
    recs = _read_jsonl(os.path.join(workdir, "metrics.jsonl"))
    train_recs = [r for r in recs if r["kind"] == "train"]
    assert [r["step"] for r in train_recs] == [1, 2, 3, 4, 5, 6]
    loss = [r["loss"] for r in train_recs]
    assert all(np.isfinite(loss))
    assert loss[-1] < loss[0], loss  # same batch every step: the loss must go down
    for key in ("loss/photo_fwd", "loss/smooth_bwd", "loss/left_right", "grad_norm", "param_norm", "update_norm", "lr",
                "cycles_per_s"):
        assert key in train_recs[-1], key
    assert train_recs[-1]["lr"] == pytest.approx(1e-3)
    val = [r for r in recs if r["kind"] == "val"]
    assert val and np.isfinite(val[-1]["flow_epe_all"]) and np.isfinite(val[-1]["disp_epe_all"])
    assert val[-1]["zero_flow_epe_all"] > 0
    # checkpoints every 2 steps (keep 3) + final, model/config json, TensorBoard events, pictures
    assert sorted(int(s) for s in os.listdir(os.path.join(workdir, "checkpoints"))) == [2, 4, 6]
    with open(os.path.join(workdir, "model.json")) as f:
        assert json.load(f)["name"] == "resnet_md_tiny"
    assert json.load(open(os.path.join(workdir, "config.json")))["global_batch"] == 2
    assert any(n.startswith("events.out.tfevents") for n in os.listdir(os.path.join(workdir, "tensorboard")))
    assert len(os.listdir(os.path.join(workdir, "images"))) >= 2
    assert traces == 1  # one trace for the whole run
    # the checkpoint is readable by the params-only loader (evaluate/export path)
    cfg, params = checkpointing.read_params(workdir)
    assert cfg["name"] == "resnet_md_tiny"
    assert _params_close(params, result["state"]["params"], 0.0)


# ------------------------------------------------------------------------------------------------------
# Resume
# ------------------------------------------------------------------------------------------------------

def test_resume_gives_identical_params_and_batches(tmp_path, monkeypatch):
    seen = _record_batches(monkeypatch)
    full = train.train_and_evaluate(tiny_config(num_train_steps=6, checkpoint_every=3), str(tmp_path / "full"))
    batches_full = list(seen)
    seen.clear()
    wd = str(tmp_path / "split")
    first = train.train_and_evaluate(tiny_config(num_train_steps=3, checkpoint_every=3), wd)
    assert first["step"] == 3
    second = train.train_and_evaluate(tiny_config(num_train_steps=6, checkpoint_every=3), wd)
    assert second["start_step"] == 3 and second["step"] == 6
    assert len(seen) == len(batches_full) == 6
    for a, b in zip(seen, batches_full):
        np.testing.assert_array_equal(a, b)
    assert _params_close(full["state"]["params"], second["state"]["params"], 1e-6)
    assert _params_close(full["state"]["opt_state"], second["state"]["opt_state"], 1e-6)
    # metrics.jsonl continues (steps 1..6 once each)
    steps = [r["step"] for r in _read_jsonl(os.path.join(wd, "metrics.jsonl")) if r["kind"] == "train"]
    assert steps == [1, 2, 3, 4, 5, 6]


# ------------------------------------------------------------------------------------------------------
# Step level: sharding, trace counting, NaN guard, micro-batching
# ------------------------------------------------------------------------------------------------------

def _setup(num_devices=None, micro_batch=0, lr=1e-3, separate=False, model="resnet_md_tiny", loss_cfg=None):
    return make_step(num_devices=num_devices, micro_batch=micro_batch, lr=lr, separate=separate, model=model,
                     loss_cfg=loss_cfg)


def _cycles(batch, seed=0):
    return np.random.default_rng(seed).random((batch, 4, H, W, 3), dtype=np.float32)


def _put(x, kw):
    return jax.device_put(x, kw["batch_sharding"]) if kw else jnp.asarray(x)


@pytest.fixture(scope="module")
def two():
    """The plain step on a 2-device mesh, 2 cycles (the shape train_and_evaluate compiles in these tests)."""
    return _setup(num_devices=2)


def _fresh(state):
    return jax.tree.map(jnp.copy, state)


def test_eight_devices_equal_one_device():
    state8, step8, _, _, kw8 = _setup(num_devices=8)
    state1, step1, _, _, kw1 = _setup(num_devices=1)
    for i in range(2):
        c = _cycles(8, seed=i)
        state1, m1 = step1(state1, _put(c, kw1))
        state8, m8 = step8(state8, _put(c, kw8))
        assert float(m1["loss"]) == pytest.approx(float(m8["loss"]), abs=1e-5)
    assert _params_close(state1["params"], state8["params"], 1e-5)
    assert all(x.sharding.is_fully_replicated for x in jax.tree.leaves(state8["params"]))
    assert len(jax.tree.leaves(state8["params"])[0].sharding.device_set) == 8


def test_one_trace_per_shape(two):
    state, step, _, _, kw = two
    state = _fresh(state)
    before = train_step.TRACE_COUNTS["train_step"]
    for i in range(3):
        state, _ = step(state, _put(_cycles(2, seed=i), kw))
    after_same = train_step.TRACE_COUNTS["train_step"]
    assert after_same - before <= 1  # 0 if an earlier test already ran this shape
    state, _ = step(state, _put(_cycles(2, seed=5), kw))
    assert train_step.TRACE_COUNTS["train_step"] == after_same
    step.lower(state, _put(_cycles(4), kw))  # a new shape traces again (lowering is enough to see it)
    assert train_step.TRACE_COUNTS["train_step"] == after_same + 1


def test_nonfinite_step_is_skipped(two):
    state, step, _, _, kw = two
    state = _fresh(state)
    state, m = step(state, _put(_cycles(2), kw))
    assert int(m["nonfinite"]) == 0 and int(state["step"]) == 1
    before = jax.tree.map(np.asarray, state)
    bad = _cycles(2, seed=1)
    bad[1, 1, 5, 7, 0] = np.nan
    state, m = step(state, _put(bad, kw))
    assert int(m["nonfinite"]) == 1 and not np.isfinite(float(m["loss"]))
    after = jax.tree.map(np.asarray, state)
    for a, b in zip(jax.tree.leaves(before), jax.tree.leaves(after)):
        np.testing.assert_array_equal(a, b)
    state, m = step(state, _put(_cycles(2, seed=2), kw))
    assert int(m["nonfinite"]) == 0 and int(state["step"]) == 2


def test_micro_batched_step_equals_plain_step(two):
    """Maps-first micro-batching on the 2-device mesh: 2 micro-batches of 4 pair-forwards per device."""
    state, plain, net, lcfg, kw = two
    _, micro, _, _, _ = _setup(num_devices=2, micro_batch=4)
    c = _put(_cycles(2), kw)
    (l1, t1), g1 = plain_loss_and_grads(net, lcfg)(state["params"], c)
    (l2, t2), g2 = micro.loss_and_grads(state["params"], c)
    assert float(l1) == pytest.approx(float(l2), abs=1e-5)
    for k in t1:
        assert float(t1[k]) == pytest.approx(float(t2[k]), abs=1e-5), k
    scale = max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(g1))
    assert _params_close(g1, g2, 1e-5 * max(1.0, scale))
    # and the full update: same loss metric, same params
    s1, m1 = plain(jax.tree.map(jnp.copy, state), c)
    s2, m2 = micro(jax.tree.map(jnp.copy, state), c)
    assert float(m1["loss"]) == pytest.approx(float(m2["loss"]), abs=1e-5)
    # Adam's first update is ~lr * sign(g): gradients equal to 1e-5 can still flip the sign of near-zero
    # entries, so after the update only closeness to within the step size is meaningful.
    assert _params_close(s1["params"], s2["params"], 2.5e-3)
    bad = MicroBatchedStep(net, lcfg, *train_step.make_optimizer(train_step.OptimizerConfig(), 10), micro_batch=3,
                           num_devices=2)
    with pytest.raises(ValueError, match="micro_batch=3 must divide"):
        bad.loss_and_grads(state["params"], c)


# ------------------------------------------------------------------------------------------------------
# Guards in the loop: skipped and counted, N in a row stops with the last good checkpoint kept
# ------------------------------------------------------------------------------------------------------

def _inject_nan(monkeypatch, bad_calls):
    calls = {"n": 0}
    orig = train._global_array

    def poisoned(sharding, local, global_shape):
        i = calls["n"]
        calls["n"] += 1
        if i in bad_calls:
            local = np.array(local, copy=True)
            local[..., 0] = np.nan
        return orig(sharding, local, global_shape)

    monkeypatch.setattr(train, "_global_array", poisoned)


def test_nan_batches_skipped_then_stop(tmp_path, monkeypatch, capsys):
    _inject_nan(monkeypatch, {2})
    res = train.train_and_evaluate(tiny_config(num_train_steps=4), str(tmp_path / "a"))
    assert res["step"] == 4 and res["nonfinite_total"] == 1
    recs = _read_jsonl(str(tmp_path / "a" / "metrics.jsonl"))
    assert [r["nonfinite_total"] for r in recs if r["kind"] == "skip"] == [1]

    _inject_nan(monkeypatch, set(range(2, 100)))
    wd = tmp_path / "b"
    capsys.readouterr()
    with pytest.raises(train.TrainingDiverged, match="3 non-finite steps in a row.*checkpoints/2"):
        train.train_and_evaluate(tiny_config(num_train_steps=6, max_nonfinite_in_row=3), str(wd))
    assert sorted(os.listdir(wd / "checkpoints")) == ["2"]
    assert capsys.readouterr().err.count("update skipped") == 1  # one line for the row, then the error
    status = json.load(open(wd / "status.json"))
    assert status["status"] == "failed" and "non-finite steps in a row" in status["reason"]


# ------------------------------------------------------------------------------------------------------
# init_from: params only
# ------------------------------------------------------------------------------------------------------

def test_init_from_loads_params_not_optimizer(fixed_batch_run, tmp_path):
    src, src_result, _ = fixed_batch_run
    res = train.train_and_evaluate(tiny_config(num_train_steps=1, lr=1e-30, init_from=src), str(tmp_path / "wd"))
    assert res["step"] == 1  # a fresh run: step counter not taken from the source (6)
    # lr 1e-30 (0 is refused): params = source up to the ~1e-30 of one Adam step
    assert _params_close(res["state"]["params"], src_result["state"]["params"], 1e-20)
    counts = [np.asarray(x) for x in jax.tree.leaves(res["state"]["opt_state"]) if np.asarray(x).dtype == np.int32]
    assert counts and all(int(c) == 1 for c in counts)  # fresh Adam: one update counted, not 7

    other = str(tmp_path / "other")
    os.makedirs(other)
    with open(os.path.join(other, "sentinel"), "w") as f:
        f.write("x")
    with pytest.raises(train.ConfigError, match="different architecture"):
        train.train_and_evaluate(tiny_config(**{"init_from": src, "model.blocks": [1, 1, 1, 2]}), other)
    assert os.listdir(other) == ["sentinel"]


# ------------------------------------------------------------------------------------------------------
# Bad input: one clear error, nothing in the workdir touched
# ------------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("overrides,match", [
    ({"global_batch": 3}, "not divisible by the 2 devices"),
    ({"num_devices": 9}, "num_devices"),
    ({"height": 96}, "multiples of 64"),
    ({"micro_batch": 3}, "micro_batch"),
    ({"dtype": "float16"}, "config.dtype"),
    ({"loss.two_warp": "full9"}, "two_warp"),
    ({"data.source": "folder", "data.data_dir": "EMPTY"}, "config.data"),
    ({"init_from": "/nonexistent/ckpt"}, "init_from"),
])
def test_bad_input_is_one_clear_error(tmp_path, overrides, match):
    workdir = tmp_path / "wd"
    workdir.mkdir()
    (workdir / "config.json").write_text('{"keep": "me"}')
    empty = tmp_path / "empty"
    empty.mkdir()
    overrides = {k: (str(empty) if v == "EMPTY" else v) for k, v in overrides.items()}
    with pytest.raises(train.ConfigError, match=match):
        train.train_and_evaluate(tiny_config(**overrides), str(workdir))
    assert sorted(os.listdir(workdir)) == ["config.json"]
    assert (workdir / "config.json").read_text() == '{"keep": "me"}'


def test_cli_bad_input_exits_nonzero_with_one_line(tmp_path):
    env = subprocess_env(num_devices=2)
    r = subprocess.run(train_cli(str(tmp_path / "a"), "--config.no_such_field=1"), env=env, cwd=REPO,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode != 0 and "no_such_field" in r.stderr
    r = subprocess.run(train_cli(str(tmp_path / "b"), "--config.global_batch=3"), env=env, cwd=REPO,
                       capture_output=True, text=True, timeout=300)
    assert r.returncode == 2, r.stderr
    assert r.stderr.strip().splitlines()[-1].startswith("error: config.global_batch=3 is not divisible by the 2")
    assert "Traceback" not in r.stderr
    assert not os.path.exists(tmp_path / "b")


# ------------------------------------------------------------------------------------------------------
# Signals and crashes
# ------------------------------------------------------------------------------------------------------

def _wait_for(pred, proc, timeout):
    t0 = time.time()
    while time.time() - t0 < timeout:
        if pred():
            return True
        if proc.poll() is not None:
            return False
        time.sleep(0.5)
    return False


def _train_steps_logged(workdir):
    path = os.path.join(workdir, "metrics.jsonl")
    if not os.path.exists(path):
        return 0
    return sum(1 for r in _read_jsonl(path) if r.get("kind") == "train")


@pytest.mark.slow
def test_sigterm_saves_checkpoint_and_exits_75(tmp_path):
    wd = str(tmp_path / "wd")
    proc = subprocess.Popen(train_cli(wd, "--config.loop.num_train_steps=10000",
                                      "--config.loop.checkpoint_every=10000"),
                            env=subprocess_env(8), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: _train_steps_logged(wd) >= 2, proc, 400), proc.communicate()[1][-3000:]
        proc.send_signal(signal.SIGTERM)
        out, err = proc.communicate(timeout=200)
    finally:
        if proc.poll() is None:
            proc.kill()
    assert proc.returncode == train.EXIT_INTERRUPTED == 75, err[-3000:]  # distinct from "finished" (0)
    assert "interrupted; checkpoint saved" in out
    steps = [int(s) for s in os.listdir(os.path.join(wd, "checkpoints"))]
    assert len(steps) == 1 and steps[0] >= 2
    status = json.load(open(os.path.join(wd, STATUS_JSON)))
    assert status == {**status, "status": "interrupted", "step": steps[0], "signal": int(signal.SIGTERM)}


@pytest.mark.slow
def test_sigkill_then_restart_resumes(tmp_path):
    """Killed hard mid-run (async checkpoints in flight), restarted: same final params as an unbroken run."""
    wd = str(tmp_path / "wd")
    args = ("--config.loop.num_train_steps=8", "--config.loop.checkpoint_every=2")
    proc = subprocess.Popen(train_cli(wd, *args), env=subprocess_env(8), cwd=REPO, stdout=subprocess.DEVNULL,
                            stderr=subprocess.PIPE, text=True)
    try:
        assert _wait_for(lambda: _train_steps_logged(wd) >= 5, proc, 400)
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
    r = subprocess.run(train_cli(wd, *args), env=subprocess_env(8), cwd=REPO, capture_output=True, text=True,
                       timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    assert "Resuming from" in r.stdout
    ref = train.train_and_evaluate(tiny_config(num_train_steps=8), str(tmp_path / "ref"))
    _, params = checkpointing.read_params(wd)
    assert _params_close(params, ref["state"]["params"], 1e-6)


# ------------------------------------------------------------------------------------------------------
# Multi-host: 2 processes on loopback
# ------------------------------------------------------------------------------------------------------

@pytest.mark.slow
def test_two_process_distributed_run_matches_single_process(tmp_path):
    import socket
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    common = ("--config.loop.num_train_steps=2", "--config.data.augment=False", "--config.loop.checkpoint_every=2",
              "--config.distributed.enabled=True", f"--config.distributed.coordinator_address=127.0.0.1:{port}",
              "--config.distributed.num_processes=2", "--config.num_devices=-1")
    wd = str(tmp_path / "multi")
    procs = [subprocess.Popen(train_cli(wd, *common, f"--config.distributed.process_id={i}"),
                              env=subprocess_env(1), cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              text=True) for i in range(2)]
    outs = [p.communicate(timeout=550) for p in procs]
    for p, (out, err) in zip(procs, outs):
        assert p.returncode == 0, err[-3000:]
    # the same run in one process over 2 devices (= the same global batches: augmentation off)
    r = subprocess.run(train_cli(str(tmp_path / "single"), "--config.loop.num_train_steps=2",
                                 "--config.data.augment=False", "--config.loop.checkpoint_every=2"), env=subprocess_env(2), cwd=REPO,
                       capture_output=True, text=True, timeout=400)
    assert r.returncode == 0, r.stderr[-3000:]
    _, multi = checkpointing.read_params(wd)
    _, single = checkpointing.read_params(str(tmp_path / "single"))
    assert _params_close(multi, single, 1e-5)
    data_files = os.listdir(os.path.join(wd, "checkpoints", "2", "data"))
    assert "process_0-of-2.json" in data_files and "process_1-of-2.json" in data_files


def test_compilation_cache_folder_choice(tmp_path, monkeypatch):
    """The trainer's persistent compile cache: the per-user folder by default ("auto"), <workdir>/xla_cache with
    "workdir", off with "", a given folder, and the user's JAX_COMPILATION_CACHE_DIR wins. jax.config.update is
    recorded, not applied (process-global)."""
    calls = {}
    monkeypatch.setattr(compile_cache.jax.config, "update", lambda name, value: calls.__setitem__(name, value))
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "user_cache"))
    wd = str(tmp_path / "wd")
    cfg = default_config.get_config("local")
    assert cfg.compilation_cache_dir == "auto"
    assert compile_cache.enable(cfg.compilation_cache_dir, wd) == str(tmp_path / "user_cache")
    assert calls["jax_compilation_cache_dir"] == str(tmp_path / "user_cache") and not os.path.exists(wd)
    assert compile_cache.enable("workdir", wd) == os.path.join(wd, "xla_cache")
    assert calls["jax_compilation_cache_dir"] == os.path.join(wd, "xla_cache")
    calls.clear()
    assert compile_cache.enable("", wd) is None and not calls
    assert compile_cache.enable(str(tmp_path / "elsewhere"), wd) == str(tmp_path / "elsewhere")
    calls.clear()
    # a config file that sets a non-string is refused when the config is parsed, before anything runs
    bad = ml_collections.ConfigDict(dict(cfg.to_dict(), compilation_cache_dir=5))
    with pytest.raises(train.ConfigError, match="compilation_cache_dir"):
        setup.parse(bad)
    monkeypatch.setenv("JAX_COMPILATION_CACHE_DIR", "/env/cache")
    assert compile_cache.enable("auto", wd) == "/env/cache" and not calls
