"""The training switches beyond the paper (census, finest-scale loss, first-order smoothness, occlusion start
step, gradient clipping): each changes the loss exactly as defined, on hand-built cases and numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import configs, losses, recipe, setup, train_step
from tests.scenes import gt_maps, translating_cycle

pytestmark = pytest.mark.usefixtures("release_after_each_test")  # see tests/conftest.py

H, W = 64, 128
cycle_loss = jax.jit(losses.cycle_loss, static_argnums=2)


def np_census(img, patch=7):
    """Independent census transform: explicit loops over offsets and pixels, zero outside the image."""
    r = patch // 2
    g = 255.0 * (0.2989 * img[..., 0] + 0.5870 * img[..., 1] + 0.1140 * img[..., 2])
    h, w = g.shape
    out = np.zeros((h, w, patch * patch))
    for y in range(h):
        for x in range(w):
            k = 0
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    yy, xx = y + dy, x + dx
                    v = g[yy, xx] if 0 <= yy < h and 0 <= xx < w else 0.0
                    t = v - g[y, x]
                    out[y, x, k] = t / np.sqrt(0.81 + t * t)
                    k += 1
    return out


def test_census_transform_matches_numpy_on_a_hand_made_patch():
    img = np.zeros((6, 7, 3))
    img[2:4, 3:5] = [0.8, 0.2, 0.1]  # a bright square on black
    img[0, 0] = [0.1, 0.9, 0.5]
    got = np.asarray(losses.census_transform(jnp.asarray(img, jnp.float32)))
    np.testing.assert_allclose(got, np_census(img), atol=1e-5)
    # centre offset (k = 24) is always 0; a flat black pixel far from the square sees 0 in its whole patch
    assert np.all(got[..., 24] == 0)
    g_sq = 255 * (0.2989 * 0.8 + 0.587 * 0.2 + 0.114 * 0.1)
    assert got[5, 0, 24 - 7 * 2 + 3] == pytest.approx(g_sq / np.sqrt(0.81 + g_sq ** 2), abs=1e-6)  # (3, 3) from (5, 0)


def test_soft_hamming_and_robust_penalty():
    t1 = jnp.asarray([[[0.0, 1.0, -1.0]]])
    t2 = jnp.asarray([[[0.0, 0.0, 1.0]]])
    d = np.array([0.0, 1.0, -2.0])
    want = np.sum(d ** 2 / (0.1 + d ** 2))
    assert float(losses.soft_hamming_distance(t1, t2)[0, 0, 0]) == pytest.approx(want, rel=1e-6)
    assert float(losses.robust_penalty(jnp.asarray(0.0))) == pytest.approx(0.01 ** 0.4, rel=1e-6)
    assert float(losses.robust_penalty(jnp.asarray(-2.0))) == pytest.approx(2.01 ** 0.4, rel=1e-6)


def test_census_loss_masks_the_patch_border_and_sees_a_shift():
    rng = np.random.default_rng(0)
    img = rng.uniform(size=(20, 24, 3)).astype(np.float32)
    mask = np.ones((20, 24, 1), np.float32)
    same = losses.census_loss(jnp.asarray(img), jnp.asarray(img), jnp.asarray(mask)).census
    # identical images: distance 0 everywhere, penalty 0.01^0.4, normalised over the 14 x 18 interior
    assert float(same.num / same.den) == pytest.approx(0.01 ** 0.4, rel=1e-5)
    assert float(same.den) == pytest.approx(14 * 18 / (20 * 24), rel=1e-6)
    shifted = np.roll(img, 1, axis=1)
    c = losses.census_loss(jnp.asarray(shifted), jnp.asarray(img), jnp.asarray(mask)).census
    t1, t2 = np_census(shifted), np_census(img)
    dist = (np.sum((t1 - t2) ** 2 / (0.1 + (t1 - t2) ** 2), -1) + 0.01) ** 0.4
    want = dist[3:-3, 3:-3].mean()
    assert float(c.num / c.den) == pytest.approx(want, rel=1e-4)
    # brightness change: census is (nearly) invariant, L1 is not
    bright = np.clip(img * 0.8 + 0.1, 0, 1)
    cb = losses.census_loss(jnp.asarray(bright), jnp.asarray(img), jnp.asarray(mask)).census
    assert float(cb.num / cb.den) < 0.5 * want


def test_census_switch_at_the_true_shift_is_near_its_floor():
    cycle, gt = translating_cycle(H, W)
    maps = gt_maps(gt, H, W)
    cfg = losses.LossConfig(photometric="census")
    _, good = cycle_loss(maps, jnp.asarray(cycle), cfg)
    zero = jax.tree.map(jnp.zeros_like, maps)
    _, bad = cycle_loss(zero, jnp.asarray(cycle), cfg)
    assert "census_fwd/0" in good and "ssim_fwd/0" not in good
    assert float(good["photo_fwd/0"]) == pytest.approx(0.01 ** 0.4, rel=1e-3)  # exact warps: penalty of 0
    assert float(bad["photo_fwd/0"]) > 3 * float(good["photo_fwd/0"])


def _terms(cfg, step=None, maps=None):
    cycle, gt = translating_cycle(H, W)
    maps = maps if maps is not None else gt_maps(gt, H, W)
    noisy = {k: tuple(m + 0.5 * jnp.sin(jnp.arange(m.shape[2]) / 3.0)[None, None, :, None] for m in v)
             for k, v in maps.items()}  # not exact: occlusion masks and smoothness are not trivial
    return losses.cycle_loss(noisy, jnp.asarray(cycle), cfg, step=step)


def test_finest_only_equals_the_full_resolution_terms_of_the_paper_loss():
    total_all, t_all = _terms(losses.LossConfig())
    total_fin, t_fin = _terms(losses.LossConfig(scales="finest"))
    cfg = losses.LossConfig()
    want = (t_all["photo_fwd/0"] + t_all["photo_bwd/0"] + cfg.lambda_sm * (t_all["smooth_fwd/0"] + t_all["smooth_bwd/0"])
            + cfg.lambda_lr * (t_all["left_right_fwd/0"] + t_all["left_right_bwd/0"]))
    assert float(total_fin) == pytest.approx(float(want), rel=1e-6)
    assert "photo_fwd/1" not in t_fin and float(total_all) > float(total_fin)


def test_first_order_smoothness_on_a_ramp_and_its_own_weight():
    img = jnp.zeros((8, 10, 3))
    x = jnp.arange(10.0)[None, :, None]
    ramp = jnp.concatenate([jnp.broadcast_to(3.0 * x, (8, 10, 1)), jnp.zeros((8, 10, 1))], -1)
    # first differences of 3x (scaled by 1/20) on a flat image: 0.15 on channel 0 in x, 0 elsewhere
    got = float(losses.smoothness_loss(ramp, img, scale=1 / 20, order=1))
    assert got == pytest.approx((0.15 / 2 + 0.0) / 2, rel=1e-6)
    assert float(losses.smoothness_loss(ramp, img, order=2)) == pytest.approx(0.0, abs=1e-6)
    edge = img.at[:, 5:].set(1.0)  # an image edge (mean_c dI = 1) between x = 4 and 5: that step weighs exp(-beta)
    e = float(losses.smoothness_loss(ramp, edge, beta=10.0, scale=1 / 20, order=1))
    assert e == pytest.approx((0.15 * (8 + np.exp(-10.0)) / 9 / 2) / 2, rel=1e-5)
    # order 1 is weighted by lambda_sm1 in the total loss
    c1 = losses.LossConfig(smoothness_order=1, lambda_sm1=3.0, beta1=5.0)
    total, t = _terms(c1)
    rest = sum(t[f"photo_{d}"] for d in ("fwd", "bwd")) + c1.lambda_lr * t["left_right"]
    assert float(total) == pytest.approx(float(rest + 3.0 * (t["smooth_fwd"] + t["smooth_bwd"])), rel=1e-6)


def test_no_occlusion_mask_before_the_start_step():
    start = losses.LossConfig(occlusion_start_step=100)
    # before the start step the flow pairs are unmasked: the same as an occlusion check that never fires
    # (alpha1 huge, border band 0, floor 0) with the paper's other settings
    never = losses.LossConfig(occ_alpha1=1e9, border_ratio=0.0, mask_floor=0.0)
    _, before = _terms(start, step=jnp.int32(99))
    _, unmasked = _terms(never)
    _, after = _terms(start, step=jnp.int32(100))
    _, paper = _terms(losses.LossConfig())
    for k in ("photo_fwd", "photo_bwd"):
        assert float(before[k]) == pytest.approx(float(unmasked[k]), rel=1e-6)
        assert float(after[k]) == pytest.approx(float(paper[k]), rel=1e-6)
        assert abs(float(before[k]) - float(after[k])) > 1e-4




def test_stereo_occlusion_masks_the_stereo_pairs_like_the_flow_pairs():
    """`stereo_occlusion`: the stereo pairs' reconstruction term is the masked mean under the occlusion mask
    (here the border band alone: a check that never fires, a 25 % band, no floor), computed in numpy from the
    warped right views; the paper's stereo pairs (the default) take the plain mean. A check that passes
    everywhere (no band) gives the paper's numbers."""
    from bridge_jax import geometry
    from bridge_jax.cycle import PAIRS, STEREO_T, STEREO_T1
    cycle, gt = translating_cycle(H, W)
    maps = gt_maps(gt, H, W)
    noisy = {k: tuple(m + 0.5 * jnp.sin(jnp.arange(m.shape[2]) / 3.0)[None, None, :, None] for m in v)
             for k, v in maps.items()}
    band = dict(tasks="stereo_only", occ_alpha1=1e9, border_ratio=0.25, mask_floor=0.0)
    _, masked = losses.cycle_loss(noisy, jnp.asarray(cycle), losses.LossConfig(stereo_occlusion=True, **band))
    _, paper = losses.cycle_loss(noisy, jnp.asarray(cycle), losses.LossConfig(**band))
    _, open_ = losses.cycle_loss(noisy, jnp.asarray(cycle), losses.LossConfig(
        stereo_occlusion=True, **dict(band, border_ratio=0.0)))
    rows = (PAIRS[STEREO_T1], PAIRS[STEREO_T])  # the rows of tasks="stereo_only", in order
    px = np.asarray(noisy["px"][0])[[0, 3]]  # forward maps of the two stereo pairs at scale 0
    keep = np.zeros((H, W))
    keep[16:H - 16, 16:W - 16] = 1.0  # ceil(0.25 H) px off every side (the band's width comes from H, as upstream)
    l1_masked, l1_plain = [], []
    for pair, m in zip(rows, px):
        est = np.asarray(geometry.warp(jnp.asarray(cycle[pair.latter])[None], jnp.asarray(m)[None]))[0]
        err = np.abs(est - cycle[pair.former]).mean(-1)
        l1_masked.append((err * keep).sum() / keep.sum())
        l1_plain.append(err.mean())
    assert float(masked["l1_fwd/0"]) == pytest.approx(np.mean(l1_masked), rel=1e-4)
    assert float(paper["l1_fwd/0"]) == pytest.approx(np.mean(l1_plain), rel=1e-4)
    assert abs(np.mean(l1_masked) - np.mean(l1_plain)) > 1e-3  # the band matters here
    for k in ("photo_fwd", "photo_bwd"):
        assert float(open_[k]) == pytest.approx(float(paper[k]), rel=1e-6)


def test_gradient_clipping_by_global_norm():
    grads = {"a": jnp.asarray([3.0, 4.0]), "b": jnp.asarray([12.0])}  # global norm 13
    params = jax.tree.map(jnp.zeros_like, grads)
    opt = train_step.OptimizerConfig(lr=1.0, lr_milestones=(), clip_grad_norm=1.3, adam_eps=100.0)
    tx, _ = train_step.make_optimizer(opt, 10)
    updates, _ = tx.update(grads, tx.init(params), params)
    # first Adam step: -lr * m_hat / (sqrt(v_hat) + eps) with m_hat = g_c, v_hat = g_c^2, g_c = g * 1.3 / 13
    for k, g in grads.items():
        gc = np.asarray(g) * 0.1
        np.testing.assert_allclose(updates[k], -gc / (np.abs(gc) + 100.0), rtol=1e-5)
    off, _ = train_step.make_optimizer(train_step.OptimizerConfig(lr=1.0, lr_milestones=(), adam_eps=100.0), 10)
    u_off, _ = off.update(grads, off.init(params), params)
    np.testing.assert_allclose(u_off["b"], -12.0 / 112.0, rtol=1e-5)


@pytest.mark.parametrize("item, match", [
    ("loss.photometric=censsus", r"loss.photometric must be one of \('ssim_l1', 'census'\)"),
    ("loss.scales=coarse", r"loss.scales must be one of \('all', 'finest'\)"),
    ("loss.smoothness_order=3", r"loss.smoothness_order must be one of \(1, 2\)"),
    ("loss.occlusion_start_step=-5", r"loss.occlusion_start_step must be an integer >= 0"),
    ("clip_grad_norm=-1.0", r"config.clip_grad_norm=-1.0: must be a number >= 0"),
])
def test_unknown_switch_values_are_one_config_error(item, match):
    c = recipe.single_run(configs.load("demo:short"))
    configs.override(c, [item])
    with pytest.raises(setup.ConfigError, match=match):
        setup.parse(c)


def test_train_step_reads_the_step_for_the_occlusion_switch():
    """The plain step passes state["step"] to the loss: with a start step of 1, step 0 and step 1 of the same
    params and batch give the unmasked and the masked loss."""
    from tests.train_helpers import make_step
    cycle, _ = translating_cycle(H, W)
    cycles = jnp.asarray(cycle)[None]
    cfg = losses.LossConfig(occlusion_start_step=1)
    state, _, net, _, _ = make_step(loss_cfg=cfg, lr=1e-30)
    maps = jax.jit(lambda p: net(p, jax.numpy.asarray(losses.cyc.batch_pair_inputs(cycles))))(state["params"])
    loss_at = lambda s: float(cycle_loss(maps, cycles, cfg, None, jnp.int32(s))[0])
    step = train_step.make_train_step(net, cfg, *train_step.make_optimizer(train_step.OptimizerConfig(lr=1e-30), 100))
    s0 = jax.tree.map(jnp.copy, state)
    _, m0 = step(s0, cycles)
    s1 = dict(jax.tree.map(jnp.copy, state), step=jnp.int32(1))
    _, m1 = step(s1, cycles)
    assert float(m0["loss"]) == pytest.approx(loss_at(0), rel=1e-5)
    assert float(m1["loss"]) == pytest.approx(loss_at(1), rel=1e-5)
    assert float(m0["loss"]) != pytest.approx(float(m1["loss"]), rel=1e-4)


@pytest.mark.slow
def test_micro_batched_step_reads_the_step_like_the_plain_step():
    from tests.train_helpers import make_step
    cycle, _ = translating_cycle(H, W)
    cycles = jnp.asarray(np.stack([cycle, cycle]))
    cfg = losses.LossConfig(occlusion_start_step=5)
    state, micro, net, _, _ = make_step(micro_batch=4, loss_cfg=cfg)
    plain = jax.jit(lambda p, c, s: train_step.loss_and_grads(p, c, net=net, loss_cfg=cfg, step=s))
    got = {}
    for s in (None, 0, 7):  # None = after the start step, as losses.cycle_loss reads it
        (lm, _), _ = micro.loss_and_grads(state["params"], cycles, s)
        (lp, _), _ = plain(state["params"], cycles, None if s is None else jnp.int32(s))
        assert float(lm) == pytest.approx(float(lp), rel=1e-5)
        got[s] = float(lm)
    assert got[None] == pytest.approx(got[7], rel=1e-6) and got[0] != pytest.approx(got[7], rel=1e-4)


def _block_scene_maps(bleed: bool):
    """Stereo maps of a 40-px-wide scene by hand (rows: forward left->right, u = -d; backward right->left,
    u = +d), 8 rows high: background at 4 px, a nearer block at 12 px on left columns 20-27, which the right view
    shows on columns 8-15. Left columns 0-3 match beyond the right image (x - 4 < 0); left columns 12-19 are
    background the block hides in the right view; right columns 16-23 are background the block hides in the
    left view, and right columns 36-39 match beyond the left image. `bleed`: the left map gives the hidden
    left columns 12-19 the block's disparity (what the photometric term rewards), else the background's."""
    u_f = np.full((8, 40), -4.0)
    u_f[:, 20:28] = -12.0
    if bleed:
        u_f[:, 12:20] = -12.0
    u_b = np.full((8, 40), 4.0)
    u_b[:, 8:16] = 12.0
    px = np.zeros((4, 8, 40, 2), np.float32)  # tasks="stereo_only": forward t1, t; backward t1, t
    px[:2, ..., 0], px[2:, ..., 0] = u_f, u_b
    return jnp.asarray(px)


def test_occlusion_fill_targets_the_background_by_hand():
    """Untrusted pixels (the forward-backward check fails, or the match is outside the other image) take the
    horizontal component of the farther of their row's nearest trusted pixels (`_block_scene_maps`)."""
    cfg = losses.LossConfig(tasks="stereo_only", occlusion_fill=1.0)
    target, mask = losses.occlusion_fill_targets(_block_scene_maps(bleed=True), 2, cfg)
    target, mask = np.asarray(target), np.asarray(mask)
    fwd_untrusted = [0, 1, 2, 3] + list(range(12, 20))  # beyond the right image; bled over by the block
    bwd_untrusted = list(range(16, 24)) + [36, 37, 38, 39]  # hidden in the left view; beyond the left image
    for row, cols, fill in ((0, fwd_untrusted, -4.0), (1, fwd_untrusted, -4.0), (2, bwd_untrusted, 4.0),
                            (3, bwd_untrusted, 4.0)):
        assert np.flatnonzero(mask[row, 3]).tolist() == cols, row
        assert (mask[row] == mask[row, :1]).all()  # every image row alike
        np.testing.assert_array_equal(target[row][:, cols], fill)


def test_occlusion_fill_loss_by_hand_and_in_the_cycle_loss():
    """The bled pixels (left columns 12-19: -12 against the background's -4) cost rho(8) each, everything else
    nothing: L = 2 rows * 8 * 8 px * rho(8) / (4 rows * 8 * 40 px) = rho(8) / 10, rho(x) = (x^2 + 0.01^2)^0.2 -
    0.01^0.4. Without the bleed the term is 0. In `cycle_loss` it is added to the total at its weight, and its
    gradient moves only the bled pixels' horizontal component, towards the background."""
    cfg = losses.LossConfig(tasks="stereo_only", occlusion_fill=1.0)
    rho8 = (64.0 + 0.01 ** 2) ** 0.2 - 0.01 ** 0.4
    bled = losses.occlusion_fill_loss(_block_scene_maps(bleed=True), cfg)
    assert float(bled.num / bled.den) == pytest.approx(rho8 / 10, rel=1e-5)
    clean = losses.occlusion_fill_loss(_block_scene_maps(bleed=False), cfg)
    assert float(clean.num) == 0.0
    grad = np.asarray(jax.grad(lambda p: losses.occlusion_fill_loss(p, cfg).num)(_block_scene_maps(bleed=True)))
    moved = np.argwhere(grad != 0)
    assert set(moved[:, 0]) == {0, 1} and set(moved[:, 2]) == set(range(12, 20)) and set(moved[:, 3]) == {0}
    assert (grad[:2, :, 12:20, 0] < 0).all()  # descending raises u from -12 towards -4

    cycle, _ = translating_cycle(8, 40)
    px = _block_scene_maps(bleed=True)
    maps = {"px": tuple(px[:, ::2 ** s, ::2 ** s] / 2 ** s for s in range(4)),
            "frac": tuple(px[:, ::2 ** s, ::2 ** s] * 0 for s in range(4))}
    off_cfg = losses.LossConfig(tasks="stereo_only", num_scales=1)
    on_cfg = losses.LossConfig(tasks="stereo_only", num_scales=1, occlusion_fill=2.0)
    total_off, _ = losses.cycle_loss(maps, jnp.asarray(cycle), off_cfg)
    total_on, terms = losses.cycle_loss(maps, jnp.asarray(cycle), on_cfg)
    assert float(terms["occlusion_fill"]) == pytest.approx(rho8 / 10, rel=1e-5)
    assert float(total_on) == pytest.approx(float(total_off) + 2.0 * rho8 / 10, rel=1e-5)


@pytest.mark.parametrize("overrides, match", [
    (dict(occlusion_fill=-1.0), r"loss.occlusion_fill must be a number >= 0"),
    (dict(occlusion_fill=0.5, tasks="flow_only"), r"loss.occlusion_fill fills the stereo maps"),
])
def test_occlusion_fill_config_errors(overrides, match):
    with pytest.raises(ValueError, match=match):
        losses.LossConfig(**overrides)
