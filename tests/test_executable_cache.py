"""Compiled programs kept whole (`executable_cache.cached_compile`): a warm start loads the train step or the
predictor's network instead of tracing, lowering and compiling it.

Checked against the plain jitted function on the same arguments (same loss and new params; same maps), by the
trace counters (a hit traces nothing), and by the key (another config, other code or another environment gives
another entry)."""
from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.experimental.compilation_cache import compilation_cache as cc

from bridge_jax import compile_cache, executable_cache, inference, models, train, train_step
from tests.train_helpers import H, W, enable_compilation_cache, make_step, tiny_config

TINY = {"name": "pwc_lite", "pyramid": [8, 16, 16, 16], "feature_width": 8, "estimator": [16, 16],
        "context": [16, 16], "dilations": [1, 2]}


@pytest.fixture(scope="module")
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


@pytest.fixture(scope="module")
def plain(_cache):
    """(state, step, batch, the plain step's new state and metrics) of a tiny pwc_lite step on one device."""
    from bridge_jax.data import synthetic
    state, step, _, _, _ = make_step(model=TINY, lr=1e-2)
    batch = jnp.asarray(synthetic.render_sample(synthetic.sample_seed(0, 0), 64, 128)["cycle"][None]
                        .astype(np.float32) / 255.0)
    new_state, metrics = step(_copy(state), batch)
    return state, step, batch, jax.device_get(new_state), jax.device_get(metrics)


def _copy(state):
    return jax.tree.map(jnp.copy, state)  # the steps donate their state


@pytest.fixture
def fresh_compiles(_cache):
    """XLA compiles afresh inside the test: its persistent cache off and this process's compiled programs
    forgotten (`cached_compile` keeps only what it compiled itself)."""
    jax.config.update("jax_enable_compilation_cache", False)
    cc.reset_cache()  # JAX decides once per process whether the cache is on: make it decide again
    jax.clear_caches()
    yield
    jax.config.update("jax_enable_compilation_cache", True)
    cc.reset_cache()


def _assert_same_step(out, ref):
    (state, metrics), (ref_state, ref_metrics) = jax.device_get(out), ref
    assert float(metrics["loss"]) == pytest.approx(float(ref_metrics["loss"]), rel=1e-6)
    assert int(state["step"]) == int(ref_state["step"]) == 1
    moved = 0.0
    for a, b in zip(jax.tree.leaves(state["params"]), jax.tree.leaves(ref_state["params"])):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        moved = max(moved, float(np.abs(np.asarray(b)).max()))
    assert moved > 0


def test_a_written_entry_gives_the_plain_steps_result_and_a_hit_does_not_trace(plain, fresh_compiles, tmp_path):
    state, step, batch, ref_state, ref_metrics = plain
    stats = {}
    fn = executable_cache.cached_compile(step, (_copy(state), batch), config={"lr": 1e-2}, folder=str(tmp_path),
                                         stats=stats)
    assert stats["cache"] == "written", stats
    assert os.listdir(tmp_path) == [stats["cache_key"] + executable_cache.SUFFIX]
    _assert_same_step(fn(_copy(state), batch), (ref_state, ref_metrics))

    before = train_step.TRACE_COUNTS["train_step"]
    stats2 = {}
    fn2 = executable_cache.cached_compile(step, (_copy(state), batch), config={"lr": 1e-2}, folder=str(tmp_path),
                                          stats=stats2)
    out = fn2(_copy(state), batch)
    assert stats2 == {"cache": "hit", "cache_key": stats["cache_key"]}
    assert train_step.TRACE_COUNTS["train_step"] == before  # loaded, not traced
    _assert_same_step(out, (ref_state, ref_metrics))
    # and it keeps stepping: a second call from the first one's (donated) output
    s2, m2 = fn2(out[0], batch)
    assert int(s2["step"]) == 2 and np.isfinite(float(m2["loss"]))


def test_a_program_xla_loaded_from_its_own_cache_is_used_not_kept(plain, tmp_path):
    """XLA:CPU cannot serialise an executable it deserialised (the copy fails when run): such a program runs
    this time, and no entry is written."""
    state, step, batch, ref_state, ref_metrics = plain
    jax.clear_caches()
    step(_copy(state), batch)  # compiled or loaded, and now in XLA's persistent cache (the module's `_cache`)
    jax.clear_caches()
    stats = {}
    fn = executable_cache.cached_compile(step, (_copy(state), batch), config={"lr": 1e-2}, folder=str(tmp_path),
                                         stats=stats)
    assert stats["cache"] == "off" and "XLA loaded" in stats["cache_error"] and os.listdir(tmp_path) == []
    _assert_same_step(fn(_copy(state), batch), (ref_state, ref_metrics))


def test_a_predictor_keeps_its_network_and_a_new_one_loads_it(fresh_compiles, tmp_path):
    """Two predictors of one model with the same folder: the first compiles and writes (static arguments:
    the rows' kinds and the refinement passes), the second traces nothing and gives the same maps, which are
    the maps of a predictor without the folder."""
    model = dict(TINY)
    graphdef, params = models.init(jax.random.key(0), model)
    rng = np.random.default_rng(0)
    # the output layer starts at zero: perturb every weight so that the maps (and the refinement) are not zero
    params = jax.tree.map(lambda p: p + 0.1 * rng.standard_normal(p.shape).astype(p.dtype), params)
    pairs = rng.random((2, 64, 128, 6), dtype=np.float32)

    def predictor(folder, refine=1):
        return inference.Predictor(graphdef, params, size=inference.WorkingSize(64, 128), model_cfg=model,
                                   test_time=inference.TestTime(refine=refine), executable_cache=folder)

    first = predictor(str(tmp_path))
    kept = first.run_network(pairs, ["stereo", "flow"])  # first: a program this process compiled before is not kept
    assert first.trace_count == 1 and len(os.listdir(tmp_path)) == 1
    ref = predictor(None).run_network(pairs, ["stereo", "flow"])
    np.testing.assert_allclose(kept, ref, rtol=1e-6, atol=1e-6)
    second = predictor(str(tmp_path))
    out = second.run_network(pairs, ["stereo", "flow"])
    assert second.trace_count == 0  # loaded whole: not traced
    np.testing.assert_allclose(out, ref, rtol=1e-6, atol=1e-6)
    assert np.abs(ref).max() > 0
    second.test_time = inference.TestTime(refine=0)  # another static argument: another program, compiled and kept
    kept = second.run_network(pairs, ["stereo", "flow"])
    unrefined = predictor(None, refine=0).run_network(pairs, ["stereo", "flow"])
    assert np.abs(unrefined - ref).max() > 1e-4  # the refinement pass changes the maps: the test can tell
    np.testing.assert_allclose(kept, unrefined, rtol=1e-6, atol=1e-6)
    assert second.trace_count == 1 and len(os.listdir(tmp_path)) == 2


def test_another_config_code_or_environment_is_another_entry(plain, monkeypatch):
    state, _, batch, _, _ = plain
    key = executable_cache.entry_key({"lr": 1e-2}, (state, batch))
    assert executable_cache.entry_key({"lr": 1e-2}, (state, batch)) == key
    assert executable_cache.entry_key({"lr": 2e-2}, (state, batch)) != key
    assert executable_cache.entry_key({"lr": 1e-2}, (state, batch[:, :, :32])) != key  # another shape
    # static arguments by value: the predictor's row kinds and refinement passes
    assert (executable_cache.entry_key({}, (batch, (True, False), 1))
            != executable_cache.entry_key({}, (batch, (True, True), 1))
            != executable_cache.entry_key({}, (batch, (True, True), 0)))
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    assert executable_cache.entry_key({"lr": 1e-2}, (state, batch)) != key
    monkeypatch.undo()
    monkeypatch.setattr(executable_cache, "cpu_signature", lambda: "another CPU model")
    assert executable_cache.entry_key({"lr": 1e-2}, (state, batch)) != key
    monkeypatch.undo()
    monkeypatch.setattr(executable_cache, "source_fingerprint", lambda: "other code")
    assert executable_cache.entry_key({"lr": 1e-2}, (state, batch)) != key


def test_the_fingerprint_changes_with_any_module_of_the_package(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "a.py").write_text("x = 1\n")
    (pkg / "sub" / "b.py").write_text("y = 2\n")
    monkeypatch.setattr(executable_cache, "__file__", str(pkg / "a.py"))
    executable_cache.source_fingerprint.cache_clear()
    try:
        first = executable_cache.source_fingerprint()
        executable_cache.source_fingerprint.cache_clear()
        (pkg / "sub" / "b.py").write_text("y = 3\n")
        assert executable_cache.source_fingerprint() != first
    finally:
        executable_cache.source_fingerprint.cache_clear()


@pytest.mark.slow
def test_a_damaged_train_step_entry_is_removed_and_made_again(plain, fresh_compiles, tmp_path):
    """Bytes flipped inside the kept executable (where a damaged entry once loaded and silently changed the
    train state, or crashed the process) are caught by the seal before XLA sees them: one warning, the entry
    removed and written again, and the step's result is the plain step's."""
    state, step, batch, ref_state, ref_metrics = plain
    kw = dict(config={"lr": 1e-2}, folder=str(tmp_path))
    stats = {}
    executable_cache.cached_compile(step, (_copy(state), batch), stats=stats, **kw)
    path = tmp_path / (stats["cache_key"] + executable_cache.SUFFIX)
    good = path.read_bytes()
    for offset in (len(good) // 2, len(good) - 5):  # inside the executable's bytes
        damaged = bytearray(good)
        for i in range(4):
            damaged[offset + i] ^= 0x5A
        path.write_bytes(bytes(damaged))
        jax.clear_caches()
        stats = {}
        with pytest.warns(compile_cache.CacheWarning, match="checksum does not match.*removed, compiling instead"):
            fn = executable_cache.cached_compile(step, (_copy(state), batch), stats=stats, **kw)
        assert stats["cache"] == "written"
        compile_cache.unseal(stats["cache_key"], path.read_bytes())  # a sound entry again
        _assert_same_step(fn(_copy(state), batch), (ref_state, ref_metrics))


def test_off_without_a_folder_and_for_a_state_on_several_devices(plain, tmp_path):
    state, step, batch, _, _ = plain
    stats = {}
    assert executable_cache.cached_compile(step, (state, batch), config={}, folder=None, stats=stats) is step
    assert stats["cache"] == "off"
    state2, step2, _, _, kw = make_step(model=TINY, num_devices=2)
    batch2 = jax.device_put(jnp.concatenate([batch, batch]), kw["batch_sharding"])
    assert executable_cache.cached_compile(step2, (state2, batch2), config={}, folder=str(tmp_path),
                                           stats=stats) is step2
    assert stats["cache"] == "off" and os.listdir(tmp_path) == []


def test_a_program_with_a_host_callback_is_not_kept(fresh_compiles, tmp_path):
    batch = jnp.ones((2, 16, 32, 12))

    @jax.jit
    def with_callback(batch):  # a host callback: its executable points into this process
        jax.debug.callback(lambda x: None, batch.sum())
        return jnp.tanh(batch) * 2.0

    stats = {}
    assert executable_cache.cached_compile(with_callback, (batch,), config={}, folder=str(tmp_path),
                                           stats=stats) is with_callback
    assert stats["cache"] == "off" and "host callbacks" in stats["cache_error"] and os.listdir(tmp_path) == []


def test_a_second_training_run_loads_the_step_and_trains_the_same(fresh_compiles, tmp_path, monkeypatch, capsys):
    """Two one-device runs of one config: the first writes the entry, the second loads it (status.json
    "step_cache", the console's line before the step, the load counted in "compile_s"), traces no step, and
    logs the same losses."""
    monkeypatch.setattr(compile_cache, "active_dir", lambda: str(tmp_path / "cache"))
    os.makedirs(tmp_path / "cache")
    cfg = dict(num_devices=1, global_batch=1, **{"loop.num_train_steps": 2, "data.synthetic_num": 2,
                                                 "data.augment": False, "loop.checkpoint_every": 3})
    losses, traces = [], []
    for run in ("a", "b"):
        before = train_step.TRACE_COUNTS["train_step"]
        train.train_and_evaluate(tiny_config(**cfg), str(tmp_path / run))
        traces.append(train_step.TRACE_COUNTS["train_step"] - before)
        with open(tmp_path / run / "status.json") as f:
            status = json.load(f)
        assert status["step_cache"] == ("written" if run == "a" else "hit"), status.get("step_cache_error")
        assert 0 < status["compile_s"] <= status["first_step_s"]
        out = capsys.readouterr().out
        line = "compiling the train step" if run == "a" else "loading the compiled train step"
        assert f"{line} for {H}x{W} (" in out, out
        with open(tmp_path / run / "metrics.jsonl") as f:
            losses.append([r["loss"] for r in map(json.loads, f) if r.get("kind") == "train"])
    assert traces == [1, 0]
    assert len(losses[0]) == 2 and losses[1] == pytest.approx(losses[0], rel=1e-6)


def test_the_predict_command_finds_its_kept_network_in_a_new_process(tmp_path):
    """The key has nothing process-specific in it: a second `bridge_jax.predict` process looks up the very
    entries the first one wrote (shown by damaging them in between: the second run reports each entry by name
    and removes it) and writes the same maps."""
    import subprocess
    import sys

    from bridge_jax.bench.first import write_photo_pair
    from tests.train_helpers import subprocess_env
    a, b = write_photo_pair(str(tmp_path), 64, 128)
    cache = tmp_path / "cache"
    env = subprocess_env(1)
    env.pop("JAX_COMPILATION_CACHE_DIR")
    env["BRIDGE_JAX_CACHE_DIR"] = str(cache)

    def predict(out):
        r = subprocess.run([sys.executable, "-m", "bridge_jax.predict", "--checkpoint", "demo", "--task",
                            "flow", a, b, "--out", str(tmp_path / out), "--working-size", "64x128", "--refine", "0",
                            "--raw", "npy"], env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, r.stderr[-2000:]
        return r.stderr, np.load(tmp_path / out / "flow_npy" / "a.npy")

    _, first = predict("one")
    entries = [p for p in cache.iterdir() if p.name.endswith(executable_cache.SUFFIX)]
    # two programs: the network, and the demo card's polish (`Predictor._polish_program`)
    assert len(entries) == 2 and np.abs(first).max() > 0
    for entry in entries:
        entry.write_bytes(b"damaged")
    stderr, second = predict("two")
    for entry in entries:
        assert f"compilation cache entry {entry.name}: not a sealed bridge_jax cache entry" in stderr
        assert "removed, compiling instead" in stderr
        assert not entry.exists()  # removed: XLA's cache answers the compile now, so it is not written again
    np.testing.assert_array_equal(second, first)


_LIBRARY_CHILD = """
import sys, numpy as np
from bridge_jax import compile_cache, inference
pred = inference.load_predictor(sys.argv[1], size=(64, 128),
                                test_time={"refine": 0, "symmetry": "none", "polish": "none"})
a = np.random.default_rng(0).random((64, 128, 3), dtype=np.float32)
flow = pred.predict_pair(a, a[:, ::-1])
print("FOLDER", compile_cache.active_dir())
print("TRACES", pred.trace_count)
print("FLOW", float(np.abs(flow).sum()))
"""


def test_the_library_uses_the_commands_cache_by_default(tiny_checkpoint, tmp_path):
    """`load_predictor` with no cache argument, in two fresh Python processes: the first compiles and keeps the
    network in the per-user folder (here $BRIDGE_JAX_CACHE_DIR), the second loads it without tracing and gives
    the same flow."""
    import subprocess
    import sys
    from tests.train_helpers import REPO
    env = dict(os.environ, BRIDGE_JAX_CACHE_DIR=str(tmp_path / "user_cache"), PYTHONPATH=REPO)
    env.pop("JAX_COMPILATION_CACHE_DIR", None)

    def run():
        done = subprocess.run([sys.executable, "-c", _LIBRARY_CHILD, tiny_checkpoint], env=env, capture_output=True,
                              text=True, timeout=600, cwd=REPO)
        assert done.returncode == 0, done.stderr[-3000:]
        return dict(line.split(" ", 1) for line in done.stdout.splitlines() if line[:1].isupper())

    first, second = run(), run()
    assert first["FOLDER"] == second["FOLDER"] == str(tmp_path / "user_cache")
    assert int(first["TRACES"]) >= 1 and int(second["TRACES"]) == 0
    assert first["FLOW"] == second["FLOW"]
    assert any(name.endswith(executable_cache.SUFFIX) for name in os.listdir(tmp_path / "user_cache"))
