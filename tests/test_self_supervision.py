"""The self-supervision switch (`LossConfig.self_supervision`): the full-frame maps (teacher, gradient stopped,
where its forward-backward check passes and its match is inside the image) supervise the maps of cropped frames
(student). Hand-built cases against numpy, the mask, the stopped gradient, off by default, and a real training
step (plain and micro-batched) with a small pwc_lite."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import configs, cycle, losses, recipe, setup, train_step
from tests.scenes import gt_maps, translating_cycle

H, W = 32, 48
C = 4  # crop per side
ON = losses.LossConfig(self_supervision=0.3, self_supervision_crop=C)


def np_penalty(d):
    """(|d| + 0.01)^0.4 - 0.01^0.4 per channel, mean over the two channels, in float64."""
    d = np.asarray(d, np.float64)
    return np.mean((np.abs(d) + 0.01) ** 0.4 - 0.01 ** 0.4, axis=-1)


def shift_maps(dx, dy, rows=8, h=H, w=W):
    """Forward rows a constant (dx, dy), backward rows its negative: forward-backward consistent everywhere."""
    fwd = np.broadcast_to(np.array([dx, dy], np.float32), (rows // 2, h, w, 2))
    return np.concatenate([fwd, -fwd]).copy()


def window(x, offset, c=C):
    oy, ox = offset
    return x[:, oy:oy + x.shape[1] - 2 * c, ox:ox + x.shape[2] - 2 * c]


def term(teacher, student, offset, cfg=ON):
    m = losses.self_supervision_loss(jnp.asarray(teacher), jnp.asarray(student), jnp.asarray(offset, jnp.int32), cfg)
    return float(m.num / m.den)


# ----------------------------------------------------------------------------------------------- the term
def test_zero_for_the_cropped_teacher_and_the_penalty_of_a_constant_delta():
    # a constant shift well inside the image for most pixels, plus a gentle ramp so that the window position matters
    teacher = shift_maps(3.0, 1.0)
    teacher[..., 0] += 0.05 * np.arange(W)[None, None, :]
    offset = (2, 5)
    student = window(teacher, offset)
    assert term(teacher, student, offset) == pytest.approx(0.0, abs=1e-6)
    assert term(teacher, student, (2, 6)) > 1e-3  # the same student against another window is not the crop
    delta = np.array([0.7, -1.3], np.float32)
    got = term(teacher, student + delta, offset)
    assert got == pytest.approx(float(np_penalty(delta)), rel=1e-5)
    # the centre window, another delta
    delta = np.array([-0.25, 2.0], np.float32)
    assert term(teacher, window(teacher, (C, C)) + delta, (C, C)) == pytest.approx(float(np_penalty(delta)), rel=1e-5)


def np_mask():
    """The teacher of `test_the_mask...` and its confidence mask, by hand.

    Forward rows D = (+3, 0); backward rows D' = (-3, 0) except a block B = rows 10..13, cols 20..25 of the latter
    frame where D' = (+3, 0). Forward pixel (y, x) reads D'(y, x + 3): inconsistent (|3 + 3|^2 = 36 > 0.01 * 18 +
    0.5) iff (y, x + 3) is in B; its match is outside iff x + 3 > W - 1. Backward pixel in B reads D(y, x + 3) = 3:
    inconsistent; elsewhere consistent, and outside iff x - 3 < 0 (those in B: iff x + 3 > W - 1, never here).
    """
    teacher = shift_maps(3.0, 0.0)
    teacher[4:, 10:14, 20:26, 0] = 3.0
    ys, xs = np.mgrid[0:H, 0:W]
    block = (ys >= 10) & (ys < 14)
    fwd = (xs + 3 <= W - 1) & ~(block & (xs + 3 >= 20) & (xs + 3 < 26))
    in_b = block & (xs >= 20) & (xs < 26)
    bwd = ~in_b & (xs - 3 >= 0)
    mask = np.concatenate([np.broadcast_to(fwd, (4, H, W)), np.broadcast_to(bwd, (4, H, W))]).astype(np.float32)
    return teacher, mask[..., None]


def test_the_mask_drops_matches_outside_the_image_and_fwd_bwd_occlusions():
    teacher, want = np_mask()
    got = np.asarray(losses.self_supervision_mask(jnp.asarray(teacher), 4, ON))
    np.testing.assert_array_equal(got, want)
    assert 0 < want.mean() < 1 and want[:4, :, -3:].sum() == 0 and want[4:, :, :3].sum() == 0
    # a student that is wrong by 50 px on every untrusted pixel and by delta elsewhere: only delta counts. The
    # windows hold the left edge (backward matches outside), the right edge (forward matches outside), the block.
    delta = np.array([0.4, 0.9], np.float32)
    for offset in ((1, 0), (1, 8), (0, 4)):
        m = window(want, offset)
        assert (m == 0).any()
        student = window(teacher, offset) + np.where(m > 0, delta, 50.0).astype(np.float32)
        assert term(teacher, student, offset) == pytest.approx(float(np_penalty(delta)), rel=1e-5), offset
        # with the mask ignored it would be bigger: the test sees a mask that is not applied
        assert float(np.mean(np_penalty(student - window(teacher, offset)))) > 1.1 * float(np_penalty(delta))


def test_an_empty_mask_gives_zero_not_nan():
    teacher = shift_maps(100.0, 0.0)  # every match outside the image
    assert term(teacher, window(teacher, (C, C)) + 1.0, (C, C)) == 0.0


def test_gradient_is_stopped_at_the_teacher():
    teacher, _ = np_mask()
    offset = jnp.asarray((3, 2), jnp.int32)
    student = window(teacher, (3, 2)) + 0.5

    def f(t, s):
        m = losses.self_supervision_loss(t, s, offset, ON)
        return m.num / m.den

    gt, gs = jax.grad(f, argnums=(0, 1))(jnp.asarray(teacher), jnp.asarray(student))
    assert float(jnp.max(jnp.abs(gt))) == 0.0
    assert float(jnp.max(jnp.abs(gs))) > 0.0


def test_crop_offsets_and_cropped_cycles():
    c = np.random.default_rng(0).random((3, 4, H, W, 3), dtype=np.float32)
    centre = losses.self_supervision_offsets(3, C)
    np.testing.assert_array_equal(centre, np.full((3, 2), C))
    off = np.asarray(losses.self_supervision_offsets(64, C, jax.random.key(1)))
    assert off.min() == 0 and off.max() == 2 * C and len({tuple(o) for o in off}) > 10
    off = np.array([[0, 8], [5, 1], [8, 0]], np.int32)
    got = np.asarray(losses.crop_cycles(jnp.asarray(c), jnp.asarray(off), C))
    for b, (oy, ox) in enumerate(off):
        np.testing.assert_array_equal(got[b], c[b, :, oy:oy + H - 2 * C, ox:ox + W - 2 * C])


# --------------------------------------------------------------------------------------- in the cycle loss
def _cycle_case():
    cycle_, gt = translating_cycle(64, 128)
    maps = gt_maps(gt, 64, 128)
    # not exact (occlusion masks are not trivial); the same maps for both cycles, whose frames differ
    maps = {k: tuple(jnp.concatenate([m, m]) + 0.3 * jnp.sin(jnp.arange(m.shape[2]) / 3.0)[None, None, :, None]
                     for m in v) for k, v in maps.items()}
    cycles = jnp.asarray(np.stack([cycle_, cycle_[:, :, ::-1]]))
    px0 = np.asarray(maps["px"][0]).reshape(2, 8, 64, 128, 2)
    return maps, cycles, px0


def test_cycle_loss_adds_the_weighted_term_from_the_start_step_and_is_unchanged_when_off():
    maps, cycles, px0 = _cycle_case()
    # the finest scale only, to keep the test quick (the term does not depend on the other scales)
    cfg = losses.LossConfig(self_supervision=0.3, self_supervision_crop=8, self_supervision_start_step=10,
                            scales="finest")
    offsets = np.array([[8, 8], [3, 12]], np.int32)
    delta = np.array([0.5, -0.2], np.float32)
    student = np.concatenate([window(px0[b], offsets[b], 8) + delta for b in range(2)])
    s = losses.Student(jnp.asarray(student), jnp.asarray(offsets))
    off_total, off_terms = losses.cycle_loss(maps, cycles, losses.LossConfig(scales="finest"))
    assert "self_supervision" not in off_terms
    # the switch at weight 0 with other crop / start values changes nothing, bit for bit
    same_total, same_terms = losses.cycle_loss(maps, cycles, losses.LossConfig(
        scales="finest", self_supervision_crop=8, self_supervision_start_step=5))
    assert float(same_total) == float(off_total) and same_terms.keys() == off_terms.keys()
    before, tb = losses.cycle_loss(maps, cycles, cfg, step=jnp.int32(9), student=s)
    after, ta = losses.cycle_loss(maps, cycles, cfg, step=jnp.int32(10), student=s)
    assert float(tb["self_supervision"]) == 0.0 and float(before) == float(off_total)
    # per cycle: the penalty of delta where the teacher is trusted (both cycles share the maps, so their masks
    # differ only by the window); the mean of equal ratios
    want = float(np_penalty(delta))
    assert float(ta["self_supervision"]) == pytest.approx(want, rel=1e-5)
    assert float(after) == pytest.approx(float(off_total) + 0.3 * want, rel=1e-6)
    assert float(ta["total"]) == float(after)
    # no step (None) = after the start step
    none, _ = losses.cycle_loss(maps, cycles, cfg, student=s)
    assert float(none) == float(after)


def test_the_student_is_needed_exactly_when_the_switch_is_on():
    maps, cycles, px0 = _cycle_case()
    cfg = losses.LossConfig(self_supervision=0.3, self_supervision_crop=8)
    with pytest.raises(ValueError, match="needed exactly when loss.self_supervision > 0"):
        losses.cycle_loss(maps, cycles, cfg)
    s = losses.Student(jnp.zeros((16, 48, 112, 2)), jnp.full((2, 2), 8, jnp.int32))
    with pytest.raises(ValueError, match="needed exactly when loss.self_supervision > 0"):
        losses.cycle_loss(maps, cycles, losses.LossConfig(), student=s)
    bad = losses.Student(jnp.zeros((16, 40, 112, 2)), jnp.full((2, 2), 8, jnp.int32))
    with pytest.raises(ValueError, match="student maps must have shape"):
        losses.cycle_loss(maps, cycles, cfg, student=bad)


CROP_ERROR = "loss.self_supervision_crop must be a positive multiple of 4"


@pytest.mark.parametrize("kw, match", [
    (dict(self_supervision=0.3, self_supervision_crop=6), CROP_ERROR),
    (dict(self_supervision=0.3, self_supervision_crop=0), CROP_ERROR),
    (dict(self_supervision=-1.0), "loss.self_supervision must be a number >= 0"),
    (dict(self_supervision_start_step=-1), "loss.self_supervision_start_step must be an integer >= 0"),
])
def test_bad_values_are_one_error_naming_the_option(kw, match):
    with pytest.raises(ValueError, match=match):
        losses.LossConfig(**kw)


def test_a_crop_the_model_cannot_run_is_one_config_error():
    c = recipe.single_run(configs.load("demo:short"))  # pwc_lite at 64x128: the default crop 32 leaves 0x64
    configs.override(c, ["loss.self_supervision=0.3"])
    with pytest.raises(setup.ConfigError, match=r"config.loss.self_supervision_crop=32: .* 0x64, not a working size "
                                                r"of model pwc_lite.*e.g. 4"):
        setup.parse(c)
    configs.override(c, ["loss.self_supervision_crop=8"])
    assert setup.parse(c, devices=jax.devices()[:1]).loss.self_supervision_crop == 8


# ------------------------------------------------------------------------------------ a real training step
TINY = {"name": "pwc_lite", "pyramid": [8, 16, 16, 16], "feature_width": 8, "estimator": [16, 16],
        "context": [16, 16], "dilations": [1, 2]}  # test_pwc_lite's tiny pwc_lite


def _perturbed(state):
    """pwc_lite starts at zero motion (zero heads), where teacher and student agree trivially: perturb the
    params so that the maps depend on the images."""
    keys = iter(jax.random.split(jax.random.key(7), len(jax.tree.leaves(state["params"]))))
    params = jax.tree.map(lambda p: p + 0.05 * jax.random.normal(next(keys), p.shape), state["params"])
    return dict(state, params=params)


def _batch():
    from bridge_jax.data import synthetic
    return jnp.asarray(np.stack([synthetic.render_sample(synthetic.sample_seed(0, i), 64, 128)["cycle"]
                                 for i in range(2)]).astype(np.float32) / 255.0)


@pytest.fixture(scope="module")
def _cache():
    from tests.train_helpers import enable_compilation_cache
    restore = enable_compilation_cache()
    yield
    restore()


def test_one_training_step_with_the_switch_on_and_one_trace(_cache):
    from tests.train_helpers import make_step
    on = losses.LossConfig(self_supervision=0.3, self_supervision_crop=8, scales="finest")
    off = losses.LossConfig(scales="finest")
    state, step, net, _, _ = make_step(model=TINY, loss_cfg=on, lr=1e-30)  # params (nearly) unchanged
    state = _perturbed(state)
    cycles = _batch()
    before = train_step.TRACE_COUNTS["train_step"]
    s1, m1 = step(jax.tree.map(jnp.copy, state), cycles)
    s2, m2 = step(s1, cycles)
    assert train_step.TRACE_COUNTS["train_step"] - before == 1  # one trace for the shape, none per step
    assert int(m1["nonfinite"]) == 0 and np.isfinite(float(m1["loss"])) and int(s2["step"]) == 2
    ss = float(m1["loss/self_supervision"])
    assert ss > 0
    # the switch-off loss of the same params and batch (the loss alone: no gradient to compile)
    x = cycle.batch_pair_inputs(cycles)
    loss_off, t_off = jax.jit(lambda p: losses.cycle_loss(net(p, x), cycles, off))(state["params"])
    assert "self_supervision" not in t_off
    assert float(m1["loss"]) == pytest.approx(float(loss_off) + 0.3 * ss, rel=1e-5)
    assert abs(float(m1["loss"]) - float(loss_off)) > 1e-4
    # the crop window is drawn from the state's rng: step 2 (a new rng, near-equal params) sees another window
    assert float(m2["loss/self_supervision"]) != pytest.approx(ss, rel=1e-4)


@pytest.mark.slow
def test_micro_batched_step_equals_the_plain_step_with_the_switch_on(_cache):
    from tests.train_helpers import make_step
    on = losses.LossConfig(self_supervision=0.3, self_supervision_crop=8, scales="finest")
    state, micro, net, _, _ = make_step(model=TINY, loss_cfg=on, micro_batch=8)
    params = _perturbed(state)["params"]
    cycles = _batch()
    plain = jax.jit(lambda p, c: train_step.loss_and_grads(p, c, net=net, loss_cfg=on))  # centre crops
    (lp, tp), gp = plain(params, cycles)
    (lm, tm), gm = micro.loss_and_grads(params, cycles)
    assert float(tp["self_supervision"]) > 0
    for k in tp:
        assert float(tm[k]) == pytest.approx(float(tp[k]), rel=1e-5, abs=1e-6), k
    scale = max(float(jnp.max(jnp.abs(g))) for g in jax.tree.leaves(gp))
    for a, b in zip(jax.tree.leaves(gp), jax.tree.leaves(gm)):
        np.testing.assert_allclose(a, b, atol=1e-5 * max(1.0, scale))
