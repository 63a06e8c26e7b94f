"""Every training variant config: builds (fast), runs one tiny step (slow); lr schedule; batch sizes; bf16."""

from __future__ import annotations

import glob
import importlib.util
import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import cycle, models, network, recipe, setup, train_step
from bridge_jax.micro_batch import MicroBatchedStep
from tests.train_helpers import H, W, REPO, enable_compilation_cache, plain_loss_and_grads

CONFIG_DIR = os.path.join(REPO, "bridge_jax", "configs")
VARIANTS = ["default", "stereo_only", "flow_only", "flow_stereo", "full1", "full2", "full3", "no_sharing", "pwcnet",
            "demo"]


def _load(name):
    spec = importlib.util.spec_from_file_location(f"cfg_{name}", os.path.join(CONFIG_DIR, f"{name}.py"))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


def test_all_variant_files_present():
    files = {os.path.basename(p)[:-3] for p in glob.glob(os.path.join(CONFIG_DIR, "*.py"))} - {"__init__"}
    assert set(VARIANTS) <= files


@pytest.mark.parametrize("name", VARIANTS)
def test_config_builds_and_documents_its_command_line(name):
    mod = _load(name)
    assert f"bridge_jax/configs/{name}.py" in mod.__doc__ or (name == "demo" and "bridge-demo" in mod.__doc__)
    cfg = mod.get_config()
    if recipe.is_recipe(cfg):  # the demo: every stage is a config of its own; the checks below use the first
        for stage in recipe.stage_names(cfg)[1:]:
            setup.parse(recipe.stage_config(cfg, stage), devices=jax.devices()[:1])
        cfg = recipe.single_run(cfg)
    run = setup.parse(cfg, devices=jax.devices()[:1])
    if cfg.global_batch % 2 == 0:
        setup.parse(cfg, devices=jax.devices()[:2])
    else:  # the demo's one cycle per step: one clear refusal on a 2-device mesh; the trainer's own choice runs it
        with pytest.raises(setup.ConfigError, match=r"config.global_batch=1 is not divisible by the 2 devices"):
            setup.parse(cfg, devices=jax.devices()[:2])
        assert setup.parse(cfg).num_devices == 1  # num_devices=-1 on this 8-device test session
    lcfg, mcfg = run.loss, run.model.config
    assert mcfg["name"] in models.NAMES
    expected = {"stereo_only": ("stereo_only", "none"), "flow_only": ("flow_only", "none"),
                "full1": ("flow_stereo", "full1"), "full2": ("flow_stereo", "full2"),
                "full3": ("flow_stereo", "full3")}.get(name, ("flow_stereo", "none"))
    assert (lcfg.tasks, lcfg.two_warp) == expected
    assert run.model.separate == (name == "no_sharing")
    assert (mcfg["name"] == "pwcnet") == (name == "pwcnet")
    if name not in ("demo",):
        # paper settings: 512x256, 2 cycles, Adam 1e-4 halved at epochs 4, 7, 10, 13, 80 epochs
        assert (run.height, run.width, run.global_batch, run.optimizer.lr, run.optimizer.lr_milestones,
                run.loop.num_epochs) == (256, 512, 2, 1e-4, (4, 7, 10, 13), 80)
        assert (lcfg.lambda_sm, lcfg.lambda_lr) == (10.0, 0.5)
        local = mod.get_config("local")
        setup.parse(local, devices=jax.devices()[:1])
        with pytest.raises(ValueError, match="unknown config argument"):
            mod.get_config("bogus")


def test_lr_schedule_matches_multisteplr():
    """Hand-derived: 1e-4 for epochs 0-3, then halved at the start of epochs 4, 7, 10, 13."""
    sched = train_step.lr_schedule(setup.parse(_load("default").get_config(), devices=jax.devices()[:1]).optimizer,
                                   steps_per_epoch=10)
    for step, lr in [(0, 1e-4), (39, 1e-4), (40, 5e-5), (69, 5e-5), (70, 2.5e-5), (100, 1.25e-5),
                     (129, 1.25e-5), (130, 6.25e-6), (10_000, 6.25e-6)]:
        assert float(sched(jnp.int32(step))) == pytest.approx(lr, rel=1e-6), step


def test_row_tasks_follow_pair_layout():
    pairs = (0, 1, 2, 3)
    assert cycle.row_tasks(pairs, 8) == ("stereo", "flow", "flow", "stereo") * 2
    assert cycle.row_tasks(pairs, 4, offset=6) == ("flow", "stereo", "stereo", "flow")
    assert cycle.row_tasks((1, 2), 4) == ("flow",) * 4
    assert cycle.row_tasks((0, 3), 4) == ("stereo",) * 4


def test_separate_networks_route_each_row_by_its_task():
    """With separate networks, a "stereo" row goes through params["stereo"] and a "flow" row through
    params["flow"], in the batch's order; a wrong count or an unknown task is one error naming `tasks`."""
    cfg = models.model_config("resnet_md_tiny", head_init="torch")  # non-zero maps from a random network
    graphdef, params = network.init_params(jax.random.key(0), cfg, separate=True)
    x = jnp.asarray(np.random.default_rng(0).random((2, 64, 128, 6), dtype=np.float32))
    both = network.Network(graphdef, separate=True)(params, x, ("flow", "stereo"))["px"][0]
    one = network.Network(graphdef)
    np.testing.assert_allclose(both[0], one(params["flow"], x[:1])["px"][0][0], atol=1e-5)
    np.testing.assert_allclose(both[1], one(params["stereo"], x[1:])["px"][0][0], atol=1e-5)
    assert np.abs(np.asarray(both[0]) - np.asarray(one(params["stereo"], x[:1])["px"][0][0])).max() > 1e-3
    with pytest.raises(ValueError, match="tasks has 1 entries for 2 rows"):
        network.Network(graphdef, separate=True)(params, x, ("flow",))
    with pytest.raises(ValueError, match=r"tasks must be one of \('flow', 'stereo'\), got 'disp'"):
        network.Network(graphdef, separate=True)(params, x, ("flow", "disp"))


# ------------------------------------------------------------------------------------------------------
# One tiny step per variant (compiles a step per variant: slow)
# ------------------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


def _one_step(cfg, batch=1, micro_batch=0, seed=0):
    cfg.global_batch, cfg.micro_batch = batch, micro_batch
    run = setup.parse(cfg, devices=jax.devices()[:1])
    graphdef, params = network.init_params(jax.random.key(0), run.model.config, run.model.separate)
    tx, schedule = train_step.make_optimizer(run.optimizer, 100)
    state = train_step.create_train_state(params, tx, jax.random.key_data(jax.random.key(2)))
    before = jax.tree.map(np.asarray, state["params"])
    step = setup.build_step(run, run.model.network(graphdef), tx, schedule)
    cycles = jnp.asarray(np.random.default_rng(seed).random((batch, 4, cfg.height, cfg.width, 3), dtype=np.float32))
    state, metrics = step(state, cycles)
    return before, state, metrics


def _tiny(name):
    cfg = _load(name).get_config("local") if name != "demo" else recipe.single_run(_load(name).get_config("short"))
    if cfg.model.name != "pwcnet":
        cfg.model = models.model_config("resnet_md_tiny")
    cfg.height, cfg.width = H, W
    return cfg


@pytest.mark.slow
@pytest.mark.parametrize("name", VARIANTS)
def test_variant_runs_one_tiny_step(name, _cache):
    cfg = _tiny(name)
    before, state, m = _one_step(cfg)
    assert np.isfinite(float(m["loss"])) and int(m["nonfinite"]) == 0
    changed = [not np.array_equal(a, np.asarray(b)) for a, b in
               zip(jax.tree.leaves(before), jax.tree.leaves(state["params"]))]
    assert any(changed)
    if name == "no_sharing":  # both networks are trained
        for part in ("stereo", "flow"):
            assert any(not np.array_equal(a, np.asarray(b)) for a, b in
                       zip(jax.tree.leaves(before[part]), jax.tree.leaves(state["params"][part])))
    if name.startswith("full"):
        assert float(m["loss/two_warp"]) > 0


@pytest.mark.slow
@pytest.mark.parametrize("batch", [1, 2, 3])
def test_batches_of_1_2_3_cycles(batch, _cache):
    cfg = _tiny("flow_stereo")
    _, state, m = _one_step(cfg, batch=batch)
    assert np.isfinite(float(m["loss"])) and int(state["step"]) == 1


@pytest.mark.slow
def test_bfloat16_compute_keeps_float32_params(_cache):
    cfg = _tiny("flow_stereo")
    cfg.dtype = "bfloat16"
    _, state, m = _one_step(cfg)
    assert np.isfinite(float(m["loss"]))
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(state["params"]))
    assert all(x.dtype == jnp.float32 for x in jax.tree.leaves(state["opt_state"]) if jnp.issubdtype(x.dtype, jnp.floating))


@pytest.mark.slow
def test_no_sharing_micro_batched_equals_plain(_cache):
    """Separate stereo/flow networks with micro-batches that mix stereo and flow rows."""
    run = setup.parse(_tiny("no_sharing"), devices=jax.devices()[:1])
    graphdef, params = network.init_params(jax.random.key(0), run.model.config, separate=True)
    net = run.model.network(graphdef)
    lcfg = run.loss
    tx, schedule = train_step.make_optimizer(run.optimizer, 100)
    cycles = jnp.asarray(np.random.default_rng(0).random((1, 4, H, W, 3), dtype=np.float32))
    (l1, _), g1 = plain_loss_and_grads(net, lcfg)(params, cycles)
    micro = MicroBatchedStep(net, lcfg, tx, schedule, micro_batch=2)
    (l2, _), g2 = micro.loss_and_grads(params, cycles)
    assert float(l1) == pytest.approx(float(l2), abs=1e-5)
    for a, b in zip(jax.tree.leaves(g1), jax.tree.leaves(g2)):
        np.testing.assert_allclose(np.asarray(a), np.asarray(b), atol=1e-5)
