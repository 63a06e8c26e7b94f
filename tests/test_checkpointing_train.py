"""Training checkpoints (checkpointing.TrainCheckpointer): state + data-iterator state, keep-K, async, readers."""

from __future__ import annotations

import json
import logging
import os

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import checkpointing, models


def _state(seed=0):
    _, params = models.init(jax.random.key(seed), models.model_config("resnet_md_tiny"))
    tx = optax.adam(1e-3)
    opt = tx.init(params)
    # make the optimizer state non-trivial
    grads = jax.tree.map(lambda p: jnp.full_like(p, 0.5), params)
    _, opt = tx.update(grads, opt, params)
    return {"params": params, "opt_state": opt, "step": jnp.int32(7), "rng": jax.random.key_data(jax.random.key(3))}


def _abstract(state):
    return jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=x.sharding), state)


def _assert_tree_equal(a, b):
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        np.testing.assert_array_equal(np.asarray(x), np.asarray(y))


def test_roundtrip_state_and_data_state(tmp_path):
    state = _state()
    ck = checkpointing.TrainCheckpointer(str(tmp_path), save_every=2, keep=2)
    assert ck.latest_step() is None
    assert not ck.save(3, state, {"next_index": 3})  # not due (3 % 2 != 0)
    assert ck.save(4, state, {"next_index": 4, "nested": {"a": [1, 2]}})
    assert not ck.save(4, state, {"next_index": 4})  # already there
    ck.wait()
    restored, data = ck.restore(4, _abstract(state))
    _assert_tree_equal(restored, state)
    assert type(restored["opt_state"][0]) is type(state["opt_state"][0])  # optax named tuples survive
    assert data == {"next_index": 4, "nested": {"a": [1, 2]}}
    ck.close()
    # per-process grain file next to the state
    assert "process_0-of-1.json" in os.listdir(tmp_path / "checkpoints" / "4" / "data")


def test_data_state_is_frozen_at_save_time(tmp_path):
    """The iterator state saved is the one passed to save(), even if the caller mutates its dict afterwards."""
    state = _state()
    ck = checkpointing.TrainCheckpointer(str(tmp_path), save_every=1, keep=3, async_save=True)
    live = {"next_index": 10}
    ck.save(1, state, live)
    live["next_index"] = 999
    ck.wait()
    _, data = ck.restore(1, _abstract(state))
    assert data == {"next_index": 10}
    ck.close()


def test_keeps_last_k_and_forced_saves(tmp_path):
    state = _state()
    ck = checkpointing.TrainCheckpointer(str(tmp_path), save_every=10, keep=2)
    for step in (10, 20, 25, 30):
        ck.save(step, state, {"s": step}, force=(step == 25))
    ck.wait()
    assert ck.all_steps() == [25, 30]
    ck.close()
    assert checkpointing.find_train_step_dir(str(tmp_path)).endswith(os.path.join("checkpoints", "30"))
    assert checkpointing.find_train_step_dir(str(tmp_path / "checkpoints" / "25")).endswith("25")
    assert checkpointing.find_train_step_dir(str(tmp_path / "nothing")) is None


def test_restore_with_sharding_on_eight_devices(tmp_path):
    mesh = jax.make_mesh((8,), ("data",), axis_types=(jax.sharding.AxisType.Auto,))
    rep = NamedSharding(mesh, P())
    state = jax.device_put(_state(), rep)
    ck = checkpointing.TrainCheckpointer(str(tmp_path), save_every=1, keep=1)
    ck.save(1, state, {})
    ck.wait()
    restored, data = ck.restore(1, _abstract(state))
    ck.close()
    _assert_tree_equal(restored, state)
    leaf = jax.tree.leaves(restored["params"])[0]
    assert leaf.sharding.is_fully_replicated and len(leaf.sharding.device_set) == 8
    assert data == {}


def test_params_readers_accept_training_workdir(tmp_path, caplog):
    state = _state(seed=1)
    ck = checkpointing.TrainCheckpointer(str(tmp_path), save_every=1, keep=1)
    ck.save(5, state, {})
    ck.close()
    with open(tmp_path / "model.json", "w") as f:
        json.dump(models.model_config("resnet_md_tiny"), f)
    params = checkpointing.restore_train_params(checkpointing.find_train_step_dir(str(tmp_path)))
    _assert_tree_equal(params, state["params"])
    with caplog.at_level(logging.WARNING):
        cfg, params2 = checkpointing.read_params(str(tmp_path))  # the params-only loader (evaluate / export)
    # orbax's "Metadata file does not exist" for the item dir checkpoints/5/state is silenced (file is one up)
    assert not [r for r in caplog.records if "Metadata file" in r.getMessage()], caplog.text
    assert cfg["name"] == "resnet_md_tiny"
    _assert_tree_equal(params2, state["params"])
    with pytest.raises(ValueError):
        checkpointing.read_params(str(tmp_path / "missing"))
