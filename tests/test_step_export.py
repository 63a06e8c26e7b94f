"""The train step kept as a lowered program (`step_export.cached_step`): a warm start loads it instead of tracing.

Checked against the plain jitted step on the same state and batch (same loss, same new params), by the trace
counter (a hit does not trace the step), and by the key (another config, other code or another environment
gives another entry)."""
from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import compile_cache, step_export, train, train_step
from tests.train_helpers import enable_compilation_cache, make_step, tiny_config

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


def _assert_same_step(out, ref):
    (state, metrics), (ref_state, ref_metrics) = jax.device_get(out), ref
    assert float(metrics["loss"]) == pytest.approx(float(ref_metrics["loss"]), rel=1e-6)
    assert int(state["step"]) == int(ref_state["step"]) == 1
    moved = 0.0
    for a, b in zip(jax.tree.leaves(state["params"]), jax.tree.leaves(ref_state["params"])):
        np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
        moved = max(moved, float(np.abs(np.asarray(b)).max()))
    assert moved > 0


def test_a_written_entry_gives_the_plain_steps_result_and_a_hit_does_not_trace(plain, tmp_path):
    state, step, batch, ref_state, ref_metrics = plain
    stats = {}
    fn = step_export.cached_step(step, _copy(state), batch, config={"lr": 1e-2}, folder=str(tmp_path), stats=stats)
    assert stats["step_cache"] == "written"
    assert os.listdir(tmp_path) == [stats["step_cache_key"] + step_export.SUFFIX]
    _assert_same_step(fn(_copy(state), batch), (ref_state, ref_metrics))

    before = train_step.TRACE_COUNTS["train_step"]
    stats2 = {}
    fn2 = step_export.cached_step(step, _copy(state), batch, config={"lr": 1e-2}, folder=str(tmp_path), stats=stats2)
    out = fn2(_copy(state), batch)
    assert stats2 == {"step_cache": "hit", "step_cache_key": stats["step_cache_key"]}
    assert train_step.TRACE_COUNTS["train_step"] == before  # loaded, not traced
    _assert_same_step(out, (ref_state, ref_metrics))
    # and it keeps stepping: a second call from the first one's (donated) output
    s2, m2 = fn2(out[0], batch)
    assert int(s2["step"]) == 2 and np.isfinite(float(m2["loss"]))


def test_another_config_code_or_environment_is_another_entry(plain, monkeypatch):
    state, _, batch, _, _ = plain
    key = step_export.step_key({"lr": 1e-2}, state, batch)
    assert step_export.step_key({"lr": 1e-2}, state, batch) == key
    assert step_export.step_key({"lr": 2e-2}, state, batch) != key
    assert step_export.step_key({"lr": 1e-2}, state, batch[:, :, :32]) != key  # another shape
    monkeypatch.setenv("XLA_FLAGS", os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_fast_math=false")
    assert step_export.step_key({"lr": 1e-2}, state, batch) != key
    monkeypatch.undo()
    monkeypatch.setattr(step_export, "source_fingerprint", lambda: "other code")
    assert step_export.step_key({"lr": 1e-2}, state, batch) != key


def test_the_fingerprint_changes_with_any_module_of_the_package(tmp_path, monkeypatch):
    pkg = tmp_path / "pkg"
    (pkg / "sub").mkdir(parents=True)
    (pkg / "a.py").write_text("x = 1\n")
    (pkg / "sub" / "b.py").write_text("y = 2\n")
    monkeypatch.setattr(step_export, "__file__", str(pkg / "a.py"))
    step_export.source_fingerprint.cache_clear()
    try:
        first = step_export.source_fingerprint()
        step_export.source_fingerprint.cache_clear()
        (pkg / "sub" / "b.py").write_text("y = 3\n")
        assert step_export.source_fingerprint() != first
    finally:
        step_export.source_fingerprint.cache_clear()


def test_a_damaged_entry_warns_and_is_made_again(plain, tmp_path):
    state, step, batch, ref_state, ref_metrics = plain
    key = step_export.step_key({"lr": 1e-2}, state, batch)
    (tmp_path / (key + step_export.SUFFIX)).write_bytes(b"not a pickle")
    stats = {}
    with pytest.warns(UserWarning, match="unreadable train-step cache entry"):
        fn = step_export.cached_step(step, _copy(state), batch, config={"lr": 1e-2}, folder=str(tmp_path),
                                     stats=stats)
    assert stats["step_cache"] == "written"
    _assert_same_step(fn(_copy(state), batch), (ref_state, ref_metrics))


def test_off_without_a_folder_and_for_a_state_on_several_devices(plain, tmp_path):
    state, step, batch, _, _ = plain
    stats = {}
    assert step_export.cached_step(step, state, batch, config={}, folder=None, stats=stats) is step
    assert stats["step_cache"] == "off"
    state2, step2, _, _, kw = make_step(model=TINY, num_devices=2)
    batch2 = jax.device_put(jnp.concatenate([batch, batch]), kw["batch_sharding"])
    assert step_export.cached_step(step2, state2, batch2, config={}, folder=str(tmp_path), stats=stats) is step2
    assert stats["step_cache"] == "off" and os.listdir(tmp_path) == []


def test_a_step_export_cannot_lower_is_traced_as_before(plain, tmp_path):
    state, step, batch, _, _ = plain

    @jax.jit
    def with_callback(state, batch):  # a host callback: jax.export refuses to serialise it
        jax.debug.callback(lambda x: None, batch.sum())
        return step(state, batch)

    stats = {}
    assert step_export.cached_step(with_callback, state, batch, config={}, folder=str(tmp_path),
                                   stats=stats) is with_callback
    assert stats["step_cache"] == "off" and "step_cache_error" in stats and os.listdir(tmp_path) == []


def test_a_second_training_run_loads_the_step_and_trains_the_same(_cache, tmp_path, monkeypatch):
    """Two one-device runs of one config: the first writes the entry, the second loads it (status.json
    "step_cache"), traces no step, and logs the same losses."""
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
            assert json.load(f)["step_cache"] == ("written" if run == "a" else "hit")
        with open(tmp_path / run / "metrics.jsonl") as f:
            losses.append([r["loss"] for r in map(json.loads, f) if r.get("kind") == "train"])
    assert traces == [1, 0]
    assert len(losses[0]) == 2 and losses[1] == pytest.approx(losses[0], rel=1e-6)
