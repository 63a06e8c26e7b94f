"""The moving average of the params (`OptimizerConfig.ema_decay`): its arithmetic against a hand-written numpy
recurrence, the non-finite guard, that every reader of a checkpoint gets the average, that a resumed run
continues it exactly, and that switching it on or off on resume is refused."""

from __future__ import annotations

import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from bridge_jax import checkpointing, train, train_step
from tests.train_helpers import enable_compilation_cache, tiny_config


@pytest.fixture(scope="module", autouse=True)
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


def _numpy_average(params_after_each_step, decay):
    """The average by its definition, written out: sum_t decay^(T-t) p_t / sum_t decay^(T-t) over the params
    p_1 .. p_T after each update (the params before the first update get no weight)."""
    T = len(params_after_each_step)
    w = np.array([decay ** (T - t) for t in range(1, T + 1)])
    return np.tensordot(w / w.sum(), np.asarray(params_after_each_step, np.float64), axes=1)


def _sgd_state(w0, ema=True):
    tx = optax.sgd(1.0)  # new params = params - grads: the params after each step are known by hand
    state = train_step.create_train_state({"w": jnp.asarray(w0)}, tx, jnp.zeros((2,), jnp.uint32), ema=ema)
    return tx, state


def test_the_average_follows_the_warm_up_recurrence():
    w0 = np.array([1.0, -2.0, 4.0], np.float32)
    grads = [np.array(g, np.float32) for g in ([1, 0, 0], [0, 1, 0], [0, 0, -3], [2, 2, 2], [-1, 0.5, 0])]
    decay = 0.6
    tx, state = _sgd_state(w0)
    np.testing.assert_array_equal(state["ema_params"]["w"], w0)  # starts as a copy of the params
    schedule = optax.constant_schedule(1.0)
    w, after = w0.astype(np.float64), []
    for g in grads:
        state, metrics = train_step.apply_gradients(state, jnp.float32(0.5), {}, {"w": jnp.asarray(g)}, tx, schedule,
                                                    ema_decay=decay)
        w = w - g
        after.append(w.copy())
        assert int(metrics["nonfinite"]) == 0
    np.testing.assert_allclose(np.asarray(state["params"]["w"]), after[-1], rtol=0, atol=1e-6)
    np.testing.assert_allclose(np.asarray(state["ema_params"]["w"]), _numpy_average(after, decay), rtol=0,
                               atol=1e-6)
    # the rates themselves: 0 at the first update (the start gets no weight), d / (1 + d) at the second (two
    # params weighted d : 1), and the decay itself after many
    np.testing.assert_allclose([float(train_step.ema_rate(t, 0.6)) for t in (0, 1)], [0.0, 0.6 / 1.6], rtol=1e-6)
    assert float(train_step.ema_rate(5000, 0.99)) == pytest.approx(0.99, rel=1e-6)
    # the model is the average
    assert train_step.model_params(state) is state["ema_params"]


def test_a_skipped_step_leaves_the_average_where_it_was():
    tx, state = _sgd_state(np.array([1.0, 2.0], np.float32))
    schedule = optax.constant_schedule(1.0)
    state, _ = train_step.apply_gradients(state, jnp.float32(1.0), {}, {"w": jnp.asarray([1.0, 1.0])}, tx, schedule,
                                          ema_decay=0.9)
    before = jax.tree.map(np.asarray, state)
    state, metrics = train_step.apply_gradients(state, jnp.float32(1.0), {}, {"w": jnp.asarray([np.nan, 1.0])}, tx,
                                                schedule, ema_decay=0.9)
    assert int(metrics["nonfinite"]) == 1
    np.testing.assert_array_equal(np.asarray(state["ema_params"]["w"]), before["ema_params"]["w"])
    assert int(state["step"]) == int(before["step"])


def test_a_state_with_an_average_needs_a_decay():
    tx, state = _sgd_state(np.zeros(2, np.float32))
    with pytest.raises(ValueError, match="ema_decay"):
        train_step.apply_gradients(state, jnp.float32(1.0), {}, {"w": jnp.ones(2)}, tx, optax.constant_schedule(1.0))
    with pytest.raises(ValueError, match=r"ema_decay must be in \[0, 1\)"):
        train_step.OptimizerConfig(ema_decay=1.0)


def _close(a, b, tol=1e-6):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    return max(float(np.max(np.abs(np.asarray(x) - np.asarray(y)))) for x, y in
               zip(jax.tree.leaves(a), jax.tree.leaves(b))) <= tol


def test_training_keeps_the_average_readers_get_it_and_a_resume_continues_it(tmp_path):
    cfg = lambda n: tiny_config(**{"num_train_steps": n, "checkpoint_every": 3, "lr": 1e-3, "ema_decay": 0.5})
    full = train.train_and_evaluate(cfg(6), str(tmp_path / "full"))
    state = full["state"]
    assert set(state) == {"params", "opt_state", "step", "rng", "ema_params"}
    # after 6 updates at lr 1e-3 the average lags the params: they differ, and readers get the average
    assert not _close(state["params"], state["ema_params"], 1e-7)
    _, read = checkpointing.read_params(str(tmp_path / "full"))
    assert _close(read, state["ema_params"], 0.0)
    step_dir = checkpointing.find_train_step_dir(str(tmp_path / "full"))
    assert _close(checkpointing.restore_train_params(step_dir), state["ema_params"], 0.0)
    raw = checkpointing._restore_tree(checkpointing.Path(step_dir) / checkpointing.STATE_ITEM, "params")
    assert _close(raw, state["params"], 0.0)
    # 3 + 3 steps with a restart in between: the same average as 6 in one go
    wd = str(tmp_path / "split")
    assert train.train_and_evaluate(cfg(3), wd)["step"] == 3
    second = train.train_and_evaluate(cfg(6), wd)
    assert second["start_step"] == 3
    assert _close(second["state"]["ema_params"], state["ema_params"])
    assert _close(second["state"]["params"], state["params"])


def test_switching_the_average_on_or_off_on_resume_is_refused(tmp_path):
    wd = str(tmp_path / "wd")
    train.train_and_evaluate(tiny_config(num_train_steps=2, checkpoint_every=2), wd)
    steps_before = sorted(os.listdir(os.path.join(wd, "checkpoints")))
    for allow in (False, True):
        with pytest.raises(train.ConfigError, match=r"config.ema_decay=0.9: .* was trained with ema_decay=0.0"):
            train.train_and_evaluate(tiny_config(**{"num_train_steps": 4, "checkpoint_every": 2, "ema_decay": 0.9}),
                                     wd, allow_config_change=allow)
    assert sorted(os.listdir(os.path.join(wd, "checkpoints"))) == steps_before  # nothing written
    on = str(tmp_path / "on")
    train.train_and_evaluate(tiny_config(**{"num_train_steps": 2, "checkpoint_every": 2, "ema_decay": 0.9}), on)
    with pytest.raises(train.ConfigError, match=r"config.ema_decay=0.0: .* hold a moving average"):
        train.train_and_evaluate(tiny_config(num_train_steps=4, checkpoint_every=2), on)


@pytest.mark.parametrize("micro_batch", [0, 4])
def test_both_training_steps_keep_the_average(micro_batch):
    """The plain jitted step and the micro-batched one (XLA:CPU's default) both update "ema_params": after three
    steps it is the numpy average of the params after each step."""
    from bridge_jax import losses, models, network
    from bridge_jax.micro_batch import MicroBatchedStep
    from tests.train_helpers import H, W

    graphdef, params = network.init_params(jax.random.key(0), models.model_config("resnet_md_tiny"), False)
    tx, schedule = train_step.make_optimizer(train_step.OptimizerConfig(lr=1e-3), 100)
    net, lcfg = network.Network(graphdef), losses.LossConfig()
    state = train_step.create_train_state(params, tx, jax.random.key_data(jax.random.key(2)), ema=True)
    if micro_batch:
        step = MicroBatchedStep(net, lcfg, tx, schedule, micro_batch=micro_batch, ema_decay=0.7)
    else:
        step = train_step.make_train_step(net, lcfg, tx, schedule, ema_decay=0.7)
    after = []
    for seed in range(3):
        cycles = jnp.asarray(np.random.default_rng(seed).random((1, 4, H, W, 3), dtype=np.float32))
        state, metrics = step(state, cycles)
        assert int(metrics["nonfinite"]) == 0
        after.append(jax.tree.map(np.asarray, state["params"]))
    want = jax.tree.map(lambda *ps: _numpy_average(list(ps), 0.7), *after)
    got = jax.tree.map(np.asarray, state["ema_params"])
    assert _close(got, want, 1e-6)
    assert not _close(got, after[-1], 1e-6)  # the average is not the last params
