"""losses.py and cycle.py against numpy references and exact translating scenes."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import cycle as cyc
from bridge_jax import geometry, losses
from tests.scenes import gt_maps, translating_cycle

H, W = 64, 128

# jitted once per config: eager op-by-op dispatch of the 4-scale loss is far slower than compiling it
cycle_loss = jax.jit(losses.cycle_loss, static_argnums=2)


def photometric_value(estimate, target, mask, alpha=0.85):
    """losses.photometric_loss of one cycle as a number (its parts normalised, then mixed)."""
    return float(losses.reduce_over_cycles(losses.photometric_loss(estimate, target, mask), "cycle").value(alpha))


def two_warp_terms(chains, photometric=losses.photometric_loss):
    """Eq. 12 of each chain as `losses.scale_terms` computes it: the photometric term on the stacked rows of
    `two_warp_estimates` (eqs. 10-11) in one `per_row` call, then one `group_mean` per chain."""
    rows = losses.per_row(photometric, *losses.two_warp_estimates(chains))
    return tuple(losses.group_mean(rows, i, i + 1) for i in range(len(chains)))


def two_warp_value(px, former, latter, mask_fwd, mask_bwd, cfg):
    """The weighted 2-warp loss of one cycle at one scale and its per-chain values, through the functions the
    training runs (`two_warp_chains`, then `two_warp_terms`) on the 1-warp reconstructions of the maps."""
    est_fwd = geometry.warp(latter, px[:4])
    est_bwd = geometry.warp(former, px[4:])
    p = losses.PairMaps(former, latter, px[:4], px[4:], est_fwd, est_bwd, mask_fwd, mask_bwd)
    chains = losses.two_warp_chains(cfg.two_warp, p, cfg.two_warp_target)
    photometric = losses.PHOTOMETRIC_LOSSES[cfg.photometric]
    terms = {c.name: float(losses.reduce_over_cycles(t, "cycle").value(cfg.alpha))
             for c, t in zip(chains, two_warp_terms(chains, photometric))}
    return cfg.two_warp_term_weight() * sum(terms.values()), terms


def np_ssim(x, y):
    """Independent SSIM map: explicit 3x3 window loops."""
    c1, c2 = 0.01**2, 0.03**2
    h, w = x.shape[:2]
    out = np.zeros((h - 2, w - 2) + x.shape[2:])
    for i in range(h - 2):
        for j in range(w - 2):
            a = x[i:i + 3, j:j + 3].reshape(9, -1)
            b = y[i:i + 3, j:j + 3].reshape(9, -1)
            ma, mb = a.mean(0), b.mean(0)
            va, vb = (a * a).mean(0) - ma**2, (b * b).mean(0) - mb**2
            cov = (a * b).mean(0) - ma * mb
            s = (2 * ma * mb + c1) * (2 * cov + c2) / ((ma**2 + mb**2 + c1) * (va + vb + c2))
            out[i, j] = np.clip((1 - s) / 2, 0, 1)
    return out


def test_ssim_matches_numpy(rng):
    x = rng.uniform(size=(10, 12, 3))
    y = np.clip(x + rng.normal(0, 0.1, size=x.shape), 0, 1)
    np.testing.assert_allclose(losses.ssim(jnp.asarray(x, jnp.float32), jnp.asarray(y, jnp.float32)), np_ssim(x, y), atol=2e-5)
    np.testing.assert_allclose(losses.ssim(jnp.asarray(x, jnp.float32), jnp.asarray(x, jnp.float32)), 0.0, atol=1e-6)


def test_ssim_gradient_matches_finite_differences(rng):
    # The 3x3 mean pooling inside SSIM has a hand-written backward pass (a "full" box filter of the cotangent):
    # central differences of the SSIM sum, in float64 numpy, check it at interior, edge and corner pixels.
    x = rng.uniform(0.2, 0.8, size=(7, 9, 2))
    y = np.clip(x + rng.normal(0, 0.1, size=x.shape), 0, 1)
    w = rng.uniform(size=(5, 7, 2))
    grad = np.asarray(jax.grad(lambda a: jnp.sum(losses.ssim(a, jnp.asarray(y, jnp.float32)) * w))(
        jnp.asarray(x, jnp.float32)))
    eps = 1e-4
    for idx in [(3, 4, 0), (0, 0, 1), (6, 8, 0), (0, 5, 1), (4, 0, 0)]:
        e = np.zeros_like(x)
        e[idx] = eps
        fd = (np.sum(np_ssim(x + e, y) * w) - np.sum(np_ssim(x - e, y) * w)) / (2 * eps)
        assert grad[idx] == pytest.approx(fd, rel=2e-3, abs=2e-4), idx


def test_photometric_loss_normalisation(rng):
    est = rng.uniform(size=(2, 8, 8, 3)).astype(np.float32)
    img = rng.uniform(size=(2, 8, 8, 3)).astype(np.float32)
    mask = (rng.uniform(size=(2, 8, 8, 1)) > 0.3).astype(np.float32)
    l1 = np.mean(np.abs(est - img) * mask) / np.mean(mask)
    ss = np.mean(np.stack([np_ssim(est[i] * mask[i], img[i] * mask[i]) for i in range(2)])) / np.mean(mask)
    np.testing.assert_allclose(photometric_value(est, img, mask), 0.85 * ss + 0.15 * l1, rtol=1e-5)
    assert photometric_value(img, img, mask) == pytest.approx(0.0, abs=1e-6)


def test_smoothness_ramp_kink_and_edges():
    ys, xs = np.meshgrid(np.arange(16.0), np.arange(24.0), indexing="ij")
    img = np.full((1, 16, 24, 3), 0.5, np.float32)
    ramp = np.stack([0.3 * xs - 0.2 * ys + 1, 0.1 * xs], -1)[None].astype(np.float32)
    assert float(losses.smoothness_loss(ramp, img)) == pytest.approx(0.0, abs=1e-6)
    kink = np.stack([np.abs(xs - 12.0), 0 * xs], -1)[None].astype(np.float32)
    flat = float(losses.smoothness_loss(kink, img))
    # hand value: |d2x| = 2 at x=12 only (16 rows of 22 second differences), scale 1/20, /2 for the mean of x,y
    assert flat == pytest.approx((2 / 20 * 16 / (16 * 22 * 2)) / 2, rel=1e-5)
    edge_img = img.copy()
    # an image edge at the kink lowers its weight to exp(-10 * 0.5). Upstream's [1:] alignment pairs the
    # second difference centred at x with the image step between x and x + 1.
    edge_img[..., 13:, :] = 1.0
    assert float(losses.smoothness_loss(kink, edge_img)) < 0.05 * flat


def test_lr_consistency_zero_for_consistent_maps():
    frac = np.full((2, 8, 16, 2), [-0.1, 0.0], np.float32)
    px = geometry.frac_to_px(frac)
    # the backward map brought into the first frame: W(D', D)
    assert float(losses.lr_consistency_loss(frac, geometry.warp(-frac, px))) == pytest.approx(0.0, abs=1e-7)
    assert float(losses.lr_consistency_loss(frac, geometry.warp(frac, px))) == pytest.approx(0.1, rel=1e-5)  # |-f - f| avg over 2 ch


def test_pair_layout_and_direction():
    cycle, gt = translating_cycle(H, W)
    x = np.asarray(cyc.pair_inputs(jnp.asarray(cycle)))
    assert x.shape == (8, H, W, 6)
    # row 3 = forward stereo_t = concat(left_t, right_t); row 7 = its backward concat(right_t, left_t)
    np.testing.assert_array_equal(x[3, ..., :3], cycle[0])
    np.testing.assert_array_equal(x[3, ..., 3:], cycle[1])
    np.testing.assert_array_equal(x[7, ..., :3], cycle[1])
    # batch layout is cycle-major
    xb = np.asarray(cyc.batch_pair_inputs(jnp.stack([cycle, cycle[::-1]])))
    np.testing.assert_array_equal(xb[:8], x)
    # the GT forward map of each pair reconstructs its former image from its latter image (interior)
    for k, p in enumerate(cyc.PAIRS):
        est = geometry.warp(cycle[p.latter][None], gt[p.name][None])[0]
        np.testing.assert_allclose(est[10:-10, 10:-10], cycle[p.former][10:-10, 10:-10], atol=1e-6)


def test_photometric_zero_for_exact_maps_and_larger_for_wrong_signs():
    cycle, gt = translating_cycle(H, W)
    maps = gt_maps(gt, H, W)
    cfg = losses.LossConfig()
    _, terms = cycle_loss(maps, jnp.asarray(cycle), cfg)
    # exact integer shifts at full resolution: the full-scale reconstruction is exact
    assert float(terms["photo_fwd/0"]) < 1e-5 and float(terms["photo_bwd/0"]) < 1e-5
    # coarse scales: only interpolation noise (the 1/8 scale aliases this texture most)
    assert float(terms["photo_fwd/1"]) < 2e-3 and float(terms["photo_bwd/1"]) < 2e-3
    # flipping the sign of every map (a direction mix-up) is clearly worse, as is swapping fwd/bwd rows
    flipped = {k: tuple(-m for m in v) for k, v in maps.items()}
    _, bad = cycle_loss(flipped, jnp.asarray(cycle), cfg)
    assert float(bad["photo_fwd/0"]) > 50 * max(float(terms["photo_fwd/0"]), 1e-4)
    assert float(bad["photo_fwd"]) > 10 * float(terms["photo_fwd"])
    swapped = {k: tuple(jnp.concatenate([m[4:], m[:4]]) for m in v) for k, v in maps.items()}
    _, bad2 = cycle_loss(swapped, jnp.asarray(cycle), cfg)
    assert float(bad2["photo_fwd"]) > 5 * float(terms["photo_fwd"])
    # the LR term is zero for exact maps
    assert float(terms["left_right"]) < 1e-6


@pytest.mark.parametrize("variant", ["full1", "full2", "full3"])
@pytest.mark.parametrize("target", ["reconstruction", "image"])
def test_two_warp_zero_for_gt_and_positive_when_perturbed(variant, target):
    cycle, gt = translating_cycle(H, W)
    c = jnp.asarray(cycle)
    cfg = losses.LossConfig(two_warp=variant, two_warp_target=target)
    s = 0
    maps = gt_maps(gt, H, W)
    px = jnp.asarray(maps["px"][s])
    former, latter = cyc.pair_images(c)
    ones = jnp.ones((4, H, W, 1), jnp.float32)
    good, terms = two_warp_value(px, former, latter, ones, ones, cfg)
    assert float(good) < 1e-5, terms
    # perturb one map used by every variant's chains: the left flow / stereo at t by a 1.5 px shift
    for pair in (cyc.FLOW_LEFT, cyc.STEREO_T, cyc.FLOW_RIGHT):
        bad_px = px.at[pair].add(jnp.array([1.5, 0.0])).at[4 + pair].add(jnp.array([-1.5, 0.0]))
        bad, _ = two_warp_value(bad_px, former, latter, ones, ones, cfg)
        used = {"full1": (cyc.FLOW_LEFT, cyc.STEREO_T), "full2": (cyc.FLOW_LEFT, cyc.STEREO_T, cyc.FLOW_RIGHT),
                "full3": (cyc.FLOW_LEFT, cyc.STEREO_T, cyc.FLOW_RIGHT)}[variant]
        if pair in used:
            assert float(bad) > 20 * max(float(good), 1e-4), (variant, pair)
    if target == "reconstruction":  # one compile per variant is enough
        # through the whole cycle loss: exact at full scale, interpolation noise at the coarser ones
        _, all_terms = cycle_loss(maps, c, cfg)
        assert float(all_terms["two_warp_a/0"]) + float(all_terms["two_warp_b/0"]) < 1e-4
        assert float(all_terms["two_warp_a/1"]) + float(all_terms["two_warp_b/1"]) < 5e-3


def test_two_warp_weighting():
    assert losses.LossConfig(two_warp="full2").two_warp_term_weight() == pytest.approx(0.2)
    assert losses.LossConfig(two_warp="full2", two_warp_weighting="upstream").two_warp_term_weight() == pytest.approx(0.1)
    with pytest.raises(ValueError, match="tasks='flow_stereo'"):
        losses.LossConfig(tasks="stereo_only", two_warp="full1")
    with pytest.raises(ValueError, match="unknown loss config"):
        losses.LossConfig.from_dict({"lamda_sm": 1})


def _random_maps(rng, rows, h, w, amp=2.0):
    px = tuple(jnp.asarray(rng.uniform(-amp, amp, (rows, h >> s, w >> s, 2)) / 2**s, jnp.float32) for s in range(4))
    frac = tuple(geometry.px_to_frac(p) for p in px)
    return {"px": px, "frac": frac}


@pytest.mark.parametrize("reduction,b", [("cycle", 1), ("cycle", 3), ("batch", 2)])
def test_batch_of_identical_cycles_equals_one_cycle(rng, reduction, b):
    cycle, _ = translating_cycle(H, W)
    maps = _random_maps(rng, 8, H, W)
    cfg = losses.LossConfig(two_warp="full2", reduction=reduction)
    one, t1 = cycle_loss(maps, jnp.asarray(cycle), cfg)
    cycles = jnp.asarray(np.stack([cycle] * b))
    bmaps = {k: tuple(jnp.concatenate([m] * b) for m in v) for k, v in maps.items()}
    total, terms = cycle_loss(bmaps, cycles, cfg)
    np.testing.assert_allclose(total, one, rtol=1e-5)
    np.testing.assert_allclose(terms["left_right"], t1["left_right"], rtol=1e-5)
    np.testing.assert_allclose(terms["two_warp"], t1["two_warp"], rtol=1e-5)


def test_reductions_differ_only_for_different_cycles(rng):
    """reduction='batch' divides batch means (upstream), 'cycle' averages per-cycle ratios: hand check on L1."""
    cycle, _ = translating_cycle(H, W)
    cycles = jnp.asarray(np.stack([cycle, cycle[:, :, ::-1]]))
    maps = _random_maps(rng, 16, H, W)
    t = {r: cycle_loss(maps, cycles, losses.LossConfig(reduction=r))[1] for r in ("cycle", "batch")}
    terms = jax.jit(jax.vmap(lambda m, c: losses.cycle_terms(m, c, losses.LossConfig())))(
        cyc.unbatch_maps(maps, 2), cycles)
    num, den = (np.asarray(x, np.float64) for x in terms[0].photo_fwd.l1)
    np.testing.assert_allclose(t["cycle"]["l1_fwd/0"], np.mean(num / den), rtol=1e-5)
    np.testing.assert_allclose(t["batch"]["l1_fwd/0"], num.mean() / den.mean(), rtol=1e-5)


def test_task_variants_use_their_pairs(rng):
    cycle, gt = translating_cycle(H, W)
    maps = _random_maps(rng, 8, H, W)
    c = jnp.asarray(cycle)
    st, st_terms = cycle_loss(maps, c, losses.LossConfig(tasks="stereo_only", lambda_lr=1.0))
    fl, fl_terms = cycle_loss(maps, c, losses.LossConfig(tasks="flow_only"))
    assert float(fl_terms["left_right"]) == 0.0 and float(st_terms["left_right"]) > 0
    # passing only the active pairs' rows gives the same value as passing all 8
    idx = np.array([0, 3, 4, 7])
    sub = {k: tuple(m[idx] for m in v) for k, v in maps.items()}
    st2, _ = cycle_loss(sub, c, losses.LossConfig(tasks="stereo_only", lambda_lr=1.0))
    np.testing.assert_allclose(st2, st, rtol=1e-6)


def test_jit_grad_compiles_once_no_nan_for_zero_maps():
    cycle, _ = translating_cycle(H, W)
    cycles = jnp.asarray(np.stack([cycle, cycle]))
    cfg = losses.LossConfig(two_warp="full1")
    traces = []

    def loss_fn(px):
        traces.append(1)
        maps = {"px": px, "frac": tuple(geometry.px_to_frac(p) for p in px)}
        return losses.cycle_loss(maps, cycles, cfg)[0]

    f = jax.jit(jax.value_and_grad(loss_fn))
    zeros = tuple(jnp.zeros((16, H >> s, W >> s, 2)) for s in range(4))
    v, g = f(zeros)
    assert np.isfinite(float(v)) and all(np.isfinite(np.asarray(x)).all() for x in g)
    v2, _ = f(tuple(z + 0.5 for z in zeros))
    assert np.isfinite(float(v2)) and len(traces) == 1


def test_bad_shapes_raise_value_error():
    cycle, gt = translating_cycle(H, W)
    maps = gt_maps(gt, H, W)
    cfg = losses.LossConfig()
    bad = {"px": maps["px"], "frac": tuple(m[..., :1] for m in maps["frac"])}
    with pytest.raises(ValueError, match=r"maps\['frac'\]\[0\]"):
        cycle_loss(bad, jnp.asarray(cycle), cfg)
    with pytest.raises(ValueError, match="divisible by 8"):
        cycle_loss(maps, jnp.zeros((4, 60, 128, 3)), cfg)
    with pytest.raises(ValueError, match="cycle must have shape"):
        cycle_loss(maps, jnp.zeros((3, 64, 128, 3)), cfg)
    with pytest.raises(ValueError, match="cycles must have shape"):
        cyc.batch_pair_inputs(jnp.zeros((4, 64, 128, 3)))
    with pytest.raises(ValueError, match="cycles must have shape"):
        cycle_loss(maps, jnp.zeros((1, 2, 4, 64, 128, 3)), cfg)


def test_two_warp_chains_match_numpy_reference(rng):
    """full-2 (eqs. 10-12) against a float64 numpy re-derivation: each chain warps a 1-warp reconstruction a
    second time, its occlusion map is carried across by the other time's stereo map, and the result is compared
    with the 1-warp reconstruction of the same frame under that mask."""
    from tests.test_geometry import np_warp
    h, w = 12, 20
    former = rng.uniform(size=(4, h, w, 3))
    latter = rng.uniform(size=(4, h, w, 3))
    px_f = rng.uniform(-3, 3, size=(4, h, w, 2))
    px_b = rng.uniform(-3, 3, size=(4, h, w, 2))
    m_f = rng.uniform(0.2, 1.0, size=(4, h, w, 1))
    m_b = rng.uniform(0.2, 1.0, size=(4, h, w, 1))
    est_f = np.stack([np_warp(latter[k], px_f[k]) for k in range(4)])
    est_b = np.stack([np_warp(former[k], px_b[k]) for k in range(4)])
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    p = losses.PairMaps(*(f32(x) for x in (former, latter, px_f, px_b, est_f, est_b, m_f, m_b)))
    chains = losses.two_warp_chains("full2", p, "reconstruction")
    assert [c.name for c in chains] == ["L_t1->L_t->R_t", "R_t1->R_t->L_t"]
    got = [float(losses.reduce_over_cycles(t, "cycle").value(0.85)) for t in two_warp_terms(chains)]
    S1, FL, FR, S0 = cyc.STEREO_T1, cyc.FLOW_LEFT, cyc.FLOW_RIGHT, cyc.STEREO_T
    # (image, its second map, target, mask, map that carries the mask)
    spec = [(est_f[FL], px_b[S0], est_f[FR], m_f[FL], px_b[S1]), (est_f[FR], px_f[S0], est_f[FL], m_f[FR], px_f[S1])]
    for (image, flow, target, mask, mask_flow), value in zip(spec, got):
        est2 = np_warp(image, flow)
        m = np_warp(np.repeat(mask, 3, -1), mask_flow)[..., :1]
        ssim_term = np.mean(np_ssim(est2 * m, target * m)) / np.mean(m)
        l1_term = np.mean(np.abs(est2 - target) * m) / np.mean(m)
        assert value == pytest.approx(0.85 * ssim_term + 0.15 * l1_term, rel=2e-4)
