"""Broken checkpoints: the readers fall back to the newest step that reads completely, name what they skipped,
never delete it; load_params survives steps deleted under it by a live run; non-finite params are named.

Every broken checkpoint here is built by hand from a good one (truncated / garbled files, an empty step dir, a
NaN state), so each test fails if the fallback, the reason or the kept bytes are wrong.
"""

from __future__ import annotations

import collections
import hashlib
import json
import os
import re
import shutil
import warnings
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import checkpointing, models
from bridge_jax.checkpointing import CheckpointFallbackWarning

# ---------------------------------------------------------------------------------------------- small states


def _small_state(v: float) -> dict:
    """A train-state-like tree whose every value encodes `v` (so a restored step is recognised exactly)."""
    return {"params": {"encoder": {"conv1": {"kernel": jnp.full((3, 2), v, jnp.float32)}},
                       "head": {"bias": jnp.arange(4, dtype=jnp.float32) + v}},
            "opt_state": {"mu": jnp.full((3,), v / 10, jnp.float32)},
            "step": jnp.int32(int(v))}


_ABSTRACT = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), _small_state(0.0))


def _workdir(tmp_path: Path, steps=(40, 50), state_fn=_small_state, keep=5) -> Path:
    """`tmp_path/wd` with `checkpoints/<step>` for each step: state_fn(step), data state {"next_index": step}."""
    wd = tmp_path / "wd"
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=keep, async_save=False)
    for s in steps:
        assert ck.save(s, state_fn(float(s)), {"next_index": s}, force=True)
    ck.close()
    return wd


def _assert_is_step(state, data_state, v: int) -> None:
    want = _small_state(float(v))
    assert jax.tree.structure(state) == jax.tree.structure(want)
    for got, exp in zip(jax.tree.leaves(state), jax.tree.leaves(want)):
        np.testing.assert_array_equal(np.asarray(got), np.asarray(exp))
    assert data_state == {"next_index": v}


def _digest(d: Path) -> dict[str, str]:
    """{relative path: sha256} of every file under d: proves a broken dir is kept byte for byte."""
    return {str(p.relative_to(d)): hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(d.rglob("*"))
            if p.is_file()}


def _largest_file(d: Path) -> Path:
    return max((p for p in d.rglob("*") if p.is_file()), key=lambda p: p.stat().st_size)


def _truncate_half(f: Path) -> None:
    os.truncate(f, f.stat().st_size // 2)


# Each way of breaking step 50, and how the reason must start.
def _break_truncate_largest(wd):
    _truncate_half(_largest_file(wd / "checkpoints" / "50" / "state"))


def _break_truncate_ocdbt_data(wd):
    # the OCDBT data file(s) the merged state reads its arrays from (state/d/<hash>)
    _truncate_half(_largest_file(wd / "checkpoints" / "50" / "state" / "d"))


def _break_garbage_data_json(wd):
    (wd / "checkpoints" / "50" / "data" / "process_0-of-1.json").write_text("{not json at all")


def _break_data_not_object(wd):
    (wd / "checkpoints" / "50" / "data" / "process_0-of-1.json").write_text("[1, 2]")


def _break_empty_dir(wd):
    shutil.rmtree(wd / "checkpoints" / "50")
    (wd / "checkpoints" / "50").mkdir()


def _break_no_data_item(wd):
    shutil.rmtree(wd / "checkpoints" / "50" / "data")


BREAKS = {
    "truncate_largest": (_break_truncate_largest, r"(/\S+/checkpoints/50/\S+: )?JSONDecodeError: "),
    "truncate_ocdbt_data": (_break_truncate_ocdbt_data, r"ValueError: OUT_OF_RANGE: .*checkpoints/50/state"),
    "garbage_data_json": (_break_garbage_data_json, r"/\S+/checkpoints/50/data/process_0-of-1\.json: JSONDecodeError: "
                                                    r"Expecting property name"),
    "data_not_object": (_break_data_not_object, r"ValueError: data iterator state is a JSON list, not an object$"),
    "empty_dir": (_break_empty_dir, r"empty directory$"),
    "no_data_item": (_break_no_data_item, r"incomplete: no data item$"),
}


# ---------------------------------------------------------------------------------------------- restore_latest


@pytest.mark.parametrize("how", list(BREAKS))
def test_restore_latest_falls_back_to_the_newest_good_step(tmp_path, how):
    wd = _workdir(tmp_path)
    breaker, reason = BREAKS[how]
    breaker(wd)
    broken_dir = wd / "checkpoints" / "50"
    before = _digest(broken_dir)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with pytest.warns(CheckpointFallbackWarning) as rec:
        r = ck.restore_latest(_ABSTRACT)
    assert r.step == 40
    _assert_is_step(r.state, r.data_state, 40)
    assert [s for s, _ in r.broken] == [50] and re.match(reason, r.broken[0][1]), r.broken
    msgs = [str(w.message) for w in rec if w.category is CheckpointFallbackWarning]
    assert len(msgs) == 1 and msgs[0].startswith(f"{broken_dir}: skipped a broken checkpoint ({r.broken[0][1]})")
    assert "resuming from step 40" in msgs[0]
    assert ck.latest_step() == 40  # the last good checkpoint, e.g. for the divergence message
    ck.close()
    assert broken_dir.is_dir() and _digest(broken_dir) == before  # reading changed nothing


def test_restore_latest_empty_newer_dir_beside_two_good_steps(tmp_path):
    wd = _workdir(tmp_path)
    (wd / "checkpoints" / "60").mkdir()
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with pytest.warns(CheckpointFallbackWarning, match=re.escape(f"{wd / 'checkpoints' / '60'}: skipped")):
        r = ck.restore_latest(_ABSTRACT)
    ck.close()
    assert (r.step, r.broken) == (50, [(60, "empty directory")])
    _assert_is_step(r.state, r.data_state, 50)


def test_restore_latest_treats_a_nan_state_as_broken(tmp_path):
    def state_fn(v):
        s = _small_state(v)
        if v == 50:  # a NaN that got saved (the non-finite guard failed): resuming into it is useless
            s["params"]["head"]["bias"] = jnp.array([1.0, jnp.nan, jnp.inf, 2.0], jnp.float32)
        return s

    wd = _workdir(tmp_path, state_fn=state_fn)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with pytest.warns(CheckpointFallbackWarning):
        r = ck.restore_latest(_ABSTRACT)
    ck.close()
    assert r.step == 40
    assert r.broken == [(50, "params not finite: head/bias has 2 non-finite values (NaN/Inf)")]


def test_restore_latest_nan_optimizer_state_is_broken_too(tmp_path):
    def state_fn(v):
        s = _small_state(v)
        if v == 50:
            s["opt_state"]["mu"] = jnp.array([0.0, 0.0, jnp.nan], jnp.float32)
        return s

    wd = _workdir(tmp_path, state_fn=state_fn)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with pytest.warns(CheckpointFallbackWarning):
        r = ck.restore_latest(_ABSTRACT)
    ck.close()
    assert r.broken == [(50, "opt_state not finite: mu has 1 non-finite values (NaN/Inf)")]


def test_restore_latest_none_without_steps_and_plain_when_all_good(tmp_path):
    ck = checkpointing.TrainCheckpointer(tmp_path / "fresh", save_every=10)
    assert ck.restore_latest(_ABSTRACT) is None
    ck.close()
    wd = _workdir(tmp_path)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointFallbackWarning)  # nothing broken: no warning
        r = ck.restore_latest(_ABSTRACT)
    ck.close()
    assert (r.step, r.broken) == (50, [])
    _assert_is_step(r.state, r.data_state, 50)


def test_restore_latest_all_broken_is_one_error_naming_the_dir_and_newest_problem(tmp_path):
    wd = _workdir(tmp_path)
    _break_garbage_data_json(wd)
    _truncate_half(_largest_file(wd / "checkpoints" / "40" / "state"))
    before = {s: _digest(wd / "checkpoints" / s) for s in ("40", "50")}
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with pytest.raises(ValueError) as e:
        ck.restore_latest(_ABSTRACT)
    ck.close()
    msg = str(e.value)
    assert msg.startswith(f"{wd / 'checkpoints'}: no usable checkpoint; the newest, step 50, is broken "
                          f"({wd / 'checkpoints' / '50' / 'data' / 'process_0-of-1.json'}: JSONDecodeError: Expecting "
                          "property name")
    assert "the 1 older step(s) are broken too" in msg and "\n" not in msg
    assert {s: _digest(wd / "checkpoints" / s) for s in ("40", "50")} == before  # nothing touched


# ---------------------------------------------------------------------------------------------- saving after it


def test_save_after_fallback_moves_the_broken_step_aside_and_keeps_it(tmp_path):
    wd = _workdir(tmp_path)
    _break_truncate_largest(wd)
    ckpts = wd / "checkpoints"
    before = _digest(ckpts / "50")
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5, async_save=False)
    with pytest.warns(CheckpointFallbackWarning):
        assert ck.restore_latest(_ABSTRACT).step == 40
    # the resumed run reaches step 50 again: its save must neither crash nor be skipped
    with pytest.warns(CheckpointFallbackWarning, match=re.escape(f"{ckpts / '50'}: broken checkpoint (")
                      + r"(\S+: )?JSONDecodeError"
                      + r".*moved aside to 50\.broken-1"):
        assert ck.save(50, _small_state(55.0), {"next_index": 55})
    ck.wait()
    assert sorted(os.listdir(ckpts)) == ["40", "50", "50.broken-1"]
    assert ck.all_steps() == [40, 50] and ck.latest_step() == 50
    assert _digest(ckpts / "50.broken-1") == before  # renamed, byte for byte
    state, data = ck.restore(50, _ABSTRACT)
    ck.close()
    np.testing.assert_array_equal(np.asarray(state["params"]["encoder"]["conv1"]["kernel"]), np.full((3, 2), 55.0))
    assert data == {"next_index": 55}

    # broken again later: the next free name, the first one kept as it is
    _break_garbage_data_json(wd)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5, async_save=False)
    with pytest.warns(CheckpointFallbackWarning):
        assert ck.restore_latest(_ABSTRACT).step == 40
    with pytest.warns(CheckpointFallbackWarning, match=r"moved aside to 50\.broken-2"):
        assert ck.save(42, _small_state(42.0), {"next_index": 42}, force=True)  # any save moves it, not only 50
    ck.close()
    assert sorted(os.listdir(ckpts)) == ["40", "42", "50.broken-1", "50.broken-2"]
    assert _digest(ckpts / "50.broken-1") == before
    # the loaders and the resume check ignore moved-aside dirs
    assert checkpointing.find_train_step_dir(wd).endswith(os.path.join("checkpoints", "42"))


def test_keep_k_clean_up_never_deletes_a_broken_step(tmp_path):
    """Left in place, orbax's keep-K would delete the broken step 50 after 3 resumed saves (observed)."""
    wd = _workdir(tmp_path)
    _break_empty_dir(wd)
    ck = checkpointing.TrainCheckpointer(wd, save_every=2, keep=3, async_save=False)
    with pytest.warns(CheckpointFallbackWarning):
        assert ck.restore_latest(_ABSTRACT).step == 40
    with pytest.warns(CheckpointFallbackWarning):
        for s in (42, 44, 46, 48):
            ck.save(s, _small_state(float(s)), {"next_index": s})
    ck.close()
    assert sorted(os.listdir(wd / "checkpoints")) == ["44", "46", "48", "50.broken-1"]


def test_save_without_a_fallback_still_skips_an_existing_good_step(tmp_path):
    wd = _workdir(tmp_path)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5, async_save=False)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointFallbackWarning)
        assert not ck.save(50, _small_state(99.0), {}, force=True)  # already there: kept, nothing moved
    ck.close()
    assert sorted(os.listdir(wd / "checkpoints")) == ["40", "50"]


# ---------------------------------------------------------------------------------------------- load_params


_CFG = models.model_config("resnet_md_tiny")


def _tiny_params(v: float) -> dict:
    """resnet_md_tiny params (right shapes, cheap: no init) whose every entry is `v`."""
    _, abstract = models.abstract_init(_CFG)
    return jax.tree.map(lambda s: np.full(s.shape, v, np.float32), abstract)


def _model_workdir(tmp_path: Path, steps=(40, 50), nan_at=None) -> Path:
    def state_fn(v):
        p = _tiny_params(v)
        if v == nan_at:
            p["up3"]["conv2"]["kernel"][0, 0, 0, :2] = np.nan
        return {"params": p, "step": np.int32(int(v))}

    wd = _workdir(tmp_path, steps, state_fn=state_fn)
    (wd / "model.json").write_text(json.dumps(_CFG))
    return wd


def _params_value(params) -> float:
    """The single value all leaves share (asserts that they do)."""
    vals = {float(v) for leaf in jax.tree.leaves(params) for v in np.unique(np.asarray(leaf))}
    assert len(vals) == 1, sorted(vals)[:5]
    return vals.pop()


@pytest.fixture
def no_settle(monkeypatch):
    monkeypatch.setattr(checkpointing, "_SETTLE_S", 0.0)


@pytest.mark.parametrize("how", ["truncate_largest", "truncate_ocdbt_data", "empty_dir"])
def test_load_params_workdir_falls_back(tmp_path, how, no_settle):
    wd = _model_workdir(tmp_path)
    BREAKS[how][0](wd)
    with pytest.warns(CheckpointFallbackWarning, match=re.escape(f"{wd / 'checkpoints' / '50'}: skipped a broken")
                      + r".*using the older step 40") as rec:
        cfg, params = checkpointing.read_params(wd)
    assert len([w for w in rec if w.category is CheckpointFallbackWarning]) == 1
    assert cfg["name"] == "resnet_md_tiny" and _params_value(params) == 40.0
    assert (wd / "checkpoints" / "50").is_dir()


def test_load_params_broken_step_dir_is_an_error_naming_it(tmp_path):
    wd = _model_workdir(tmp_path)
    _break_truncate_largest(wd)
    step_dir = wd / "checkpoints" / "50"
    with pytest.raises(ValueError, match=r"^" + re.escape(f"{step_dir}: cannot read {step_dir / 'state'} (")):
        checkpointing.read_params(step_dir)
    _break_empty_dir(wd)
    with pytest.raises(ValueError, match=r"^" + re.escape(f"{step_dir}: missing state/")):
        checkpointing.read_params(step_dir)
    assert _params_value(checkpointing.read_params(wd / "checkpoints" / "40")[1]) == 40.0


def test_load_params_all_steps_broken(tmp_path, no_settle):
    wd = _model_workdir(tmp_path)
    _break_empty_dir(wd)
    shutil.rmtree(wd / "checkpoints" / "40" / "state")
    with pytest.raises(ValueError, match=r"^" + re.escape(
            f"{wd / 'checkpoints'}: no readable checkpoint step; the newest, 50, is broken (missing state/")):
        checkpointing.read_params(wd)


def test_load_params_does_not_refuse_nan_unless_asked(tmp_path, no_settle):
    wd = _model_workdir(tmp_path, nan_at=50)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointFallbackWarning)
        _, params = checkpointing.read_params(wd)  # evaluating a diverged run is legitimate
    assert np.isnan(np.asarray(params["up3"]["conv2"]["kernel"])).sum() == 2
    with pytest.warns(CheckpointFallbackWarning, match=r"params not finite: up3/conv2/kernel has 2 non-finite"):
        _, params = checkpointing.read_params(wd, require_finite=True)
    assert _params_value(params) == 40.0
    with pytest.raises(ValueError, match=r"^" + re.escape(
            f"{wd / 'checkpoints' / '50'}: params not finite: up3/conv2/kernel has 2 non-finite values")):
        checkpointing.read_params(wd / "checkpoints" / "50", require_finite=True)


# ---------------------------------------------------------------------- load_params racing a live run's clean-up


def _patch_restore(monkeypatch, before_read):
    """Wraps checkpointing._restore_tree: `before_read(step_dir, call_index)` runs first (it may delete dirs,
    add steps or raise, as a training run's keep-K clean-up would between resolve and read)."""
    real, calls = checkpointing._restore_tree, []

    def patched(path, subtree=None):
        calls.append(Path(path).parent.name)
        before_read(Path(path).parent, len(calls) - 1)
        return real(path, subtree)

    monkeypatch.setattr(checkpointing, "_restore_tree", patched)
    return calls


def test_load_params_step_deleted_between_resolve_and_read(tmp_path, monkeypatch, no_settle):
    wd = _model_workdir(tmp_path)

    def delete_first(step_dir, i):
        if i == 0:
            shutil.rmtree(step_dir)  # keep-K removed it: orbax then fails on a missing file
            raise FileNotFoundError(2, "No such file or directory", str(step_dir / "state" / "_METADATA"))

    calls = _patch_restore(monkeypatch, delete_first)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointFallbackWarning)  # a deleted step is not a broken one
        _, params = checkpointing.read_params(wd)
    assert calls == ["50", "40"] and _params_value(params) == 40.0


def test_load_params_re_resolves_to_a_newer_step_not_an_older_one(tmp_path, monkeypatch, no_settle):
    """keep=1 in a live run: step 60 is saved and step 50 deleted while 50 is being read -> 60, not 40."""
    wd = _model_workdir(tmp_path, steps=(40, 50, 60))
    stash = tmp_path / "stash60"
    os.rename(wd / "checkpoints" / "60", stash)

    def swap_first(step_dir, i):
        if i == 0:
            os.rename(stash, wd / "checkpoints" / "60")
            shutil.rmtree(step_dir)
            raise FileNotFoundError(2, "No such file or directory", str(step_dir / "state"))

    calls = _patch_restore(monkeypatch, swap_first)
    _, params = checkpointing.read_params(wd)
    assert calls == ["50", "60"] and _params_value(params) == 60.0


def test_load_params_missing_file_that_stays_missing_is_broken(tmp_path, monkeypatch, no_settle):
    """A FileNotFoundError on a step that is still there: listed again once, then skipped as broken."""
    wd = _model_workdir(tmp_path)

    def fail_50(step_dir, i):
        if step_dir.name == "50":
            raise FileNotFoundError(2, "No such file or directory", str(step_dir / "state" / "x"))

    calls = _patch_restore(monkeypatch, fail_50)
    with pytest.warns(CheckpointFallbackWarning, match=r"checkpoints/50: skipped a broken checkpoint "
                      r"\(FileNotFoundError: \[Errno 2\] No such file or directory: "):
        _, params = checkpointing.read_params(wd)
    assert calls == ["50", "50", "40"] and _params_value(params) == 40.0


def test_load_params_gives_up_after_three_listings_that_keep_changing(tmp_path, monkeypatch, no_settle):
    wd = _model_workdir(tmp_path)

    def renumber(step_dir, i):  # every read: the step is replaced by a newer one
        os.rename(step_dir, step_dir.with_name(str(int(step_dir.name) + 1)))
        raise FileNotFoundError(2, "No such file or directory", str(step_dir))

    calls = _patch_restore(monkeypatch, renumber)
    with pytest.raises(ValueError, match=r"^" + re.escape(f"{wd / 'checkpoints'}: checkpoint steps kept changing "
                                                          "(deleted while being read) in 3 attempts")):
        checkpointing.read_params(wd)
    assert calls == ["50", "51", "52"]


# ---------------------------------------------------------------------------------------------- check_finite_params


def test_check_finite_params_names_the_first_bad_leaf_in_tree_order():
    params = {"zz": {"w": np.full(2, np.nan, np.float32)},  # bad too, but after "encoder" in tree order
              "encoder": {"conv1": {"kernel": np.array([[np.nan, 1.0], [np.inf, 0.0]], np.float32),
                                    "bias": np.zeros(2, np.float32)}},
              "decoder": {"b": jnp.ones(3)}}
    with pytest.raises(ValueError) as e:
        checkpointing.check_finite_params(params, "weights.pth")
    assert str(e.value).startswith("weights.pth: parameter encoder/conv1/kernel has 2 non-finite values (NaN/Inf); ")
    params["encoder"]["conv1"]["kernel"][:] = 1.0
    with pytest.raises(ValueError, match=r"^weights.pth: parameter zz/w has 2 non-finite values"):
        checkpointing.check_finite_params(params, "weights.pth")
    params["zz"]["w"][:] = 0.0
    assert checkpointing.check_finite_params(params, "weights.pth") is None


def test_check_finite_params_jax_bfloat16_sequences_and_non_float_leaves():
    Adam = collections.namedtuple("Adam", "count mu")
    tree = [{"rng": jax.random.key_data(jax.random.key(0)), "step": np.int32(3)},
            Adam(count=jnp.int32(1), mu={"w": jnp.array([1.0, -jnp.inf, 2.0], jnp.bfloat16)})]
    with pytest.raises(ValueError, match=r"^opt: parameter 1/mu/w has 1 non-finite values"):
        checkpointing.check_finite_params(tree, "opt")
    assert checkpointing.first_nonfinite(tree[0]) is None


def test_only_the_leftovers_of_a_failed_read_are_dropped():
    """The unraisable-hook filter installed after a failed read drops asyncio's closed-loop callbacks and
    orbax's per-array read errors, nothing else."""
    import asyncio
    import types

    loop = asyncio.new_event_loop()
    loop.close()
    with pytest.raises(RuntimeError) as closed:
        loop.call_soon_threadsafe(lambda: None)

    def args(e):
        return types.SimpleNamespace(exc_type=type(e), exc_value=e, exc_traceback=e.__traceback__, err_msg=None,
                                     object=None)

    assert checkpointing._is_failed_read_noise(args(closed.value))
    assert checkpointing._is_failed_read_noise(args(Exception("Encountered error while reading array index: (0,)")))
    try:
        raise RuntimeError("Event loop is closed")  # same text, not from asyncio: kept
    except RuntimeError as e:
        assert not checkpointing._is_failed_read_noise(args(e))
    assert not checkpointing._is_failed_read_noise(args(ValueError("anything else")))


def test_restore_latest_warn_false_is_silent_but_still_reports(tmp_path):
    wd = _workdir(tmp_path)
    _break_empty_dir(wd)
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with warnings.catch_warnings():
        warnings.simplefilter("error", CheckpointFallbackWarning)
        r = ck.restore_latest(_ABSTRACT, warn=False)  # e.g. the non-main processes of a multi-host run
    ck.close()
    assert (r.step, r.broken) == (40, [(50, "empty directory")])


def test_restore_latest_into_shardings_as_train_does(tmp_path):
    """The train loop's abstract state carries shardings (replicated over a data mesh); the finite check runs
    on those device arrays."""
    from jax.sharding import NamedSharding, PartitionSpec as P

    mesh = jax.make_mesh((2,), ("data",), axis_types=(jax.sharding.AxisType.Auto,), devices=jax.devices()[:2])
    rep = NamedSharding(mesh, P())
    wd = _workdir(tmp_path)
    _break_truncate_largest(wd)
    abstract = jax.tree.map(lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype, sharding=rep), _small_state(0.0))
    ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
    with pytest.warns(CheckpointFallbackWarning):
        r = ck.restore_latest(abstract)
    ck.close()
    assert r.step == 40
    _assert_is_step(r.state, r.data_state, 40)
    leaf = r.state["params"]["head"]["bias"]
    assert leaf.sharding.is_fully_replicated and len(leaf.sharding.device_set) == 2


def test_reason_is_the_first_line_and_unwraps_orbax_array_read_errors():
    try:
        try:
            raise ValueError('OUT_OF_RANGE: Error reading "params.w/0" in OCDBT database at local file "/x/"\nmore')
        except ValueError as inner:
            raise Exception("Encountered error while reading array index: (slice(0, 3, 1),). See full "
                            "TensorStore details: {...}") from inner
    except Exception as e:
        wrapped = e
    assert checkpointing._reason(wrapped) == ('ValueError: OUT_OF_RANGE: Error reading "params.w/0" in OCDBT '
                                              'database at local file "/x/"')
    assert checkpointing._reason(KeyError("k")) == "KeyError: 'k'"
    assert checkpointing._reason(ValueError("x" * 400)) == "ValueError: " + "x" * 285 + "..."  # 300 in all


def test_an_empty_step_dir_is_one_warning_without_orbax_log_lines(tmp_path, caplog):
    wd = _workdir(tmp_path)
    (wd / "checkpoints" / "60").mkdir()
    with caplog.at_level("WARNING"):
        ck = checkpointing.TrainCheckpointer(wd, save_every=10, keep=5)
        with pytest.warns(CheckpointFallbackWarning, match="60: skipped a broken checkpoint \\(empty directory\\)"):
            assert ck.restore_latest(_ABSTRACT).step == 50
        ck.close()
    assert [r.getMessage() for r in caplog.records if "Metadata file does not exist" in r.getMessage()] == []
