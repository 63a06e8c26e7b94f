"""The cycle loss computes each equation once per scale on stacked rows (`losses.per_row`: both directions of
every pair and the 2-warp chains in one call). These tests rebuild every term the way the equations read, one
call per direction and per chain, from the public equation functions, and require the same numbers and the
same gradients: on random cycles for every loss switch, and on the upstream fixture's maps and pyramids.

Float32 sums over different groupings differ in the last bits, so the float32 checks allow 1e-6 (absolute, on
terms of order 0.01-1; 5e-5 relative on the fixture's 64x128 sums); under float64 the two must agree to 1e-12:
the stacking is exact algebra.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import cycle as cyc
from bridge_jax import geometry, losses
from bridge_jax.bench.measure import random_maps
from tests.fixture import fixture_file, reference_file
from tests.test_losses import two_warp_terms
from tests.test_losses_parity import fixture_maps, fixture_pyramids

CONFIGS = {
    "paper": {},
    "full1": dict(two_warp="full1"),
    "full2": dict(two_warp="full2"),
    "full3_image_target": dict(two_warp="full3", two_warp_target="image"),
    "census_full2": dict(photometric="census", two_warp="full2"),
    "stereo_only": dict(tasks="stereo_only"),
    "flow_only_order1": dict(tasks="flow_only", smoothness_order=1),
}


def per_call_scale_terms(px, frac, frames, cfg: losses.LossConfig) -> losses.ScaleTerms:
    """Every term of one cycle at one scale, one equation call per direction and per 2-warp chain."""
    pairs, p = cfg.pairs, len(cfg.pairs)
    former, latter = cyc.pair_images(frames, pairs)
    px_f, px_b, fr_f, fr_b = px[:p], px[p:], frac[:p], frac[p:]
    est_f, est_b = geometry.warp(latter, px_f), geometry.warp(former, px_b)
    px_b_w, px_f_w = geometry.warp(px_b, px_f), geometry.warp(px_f, px_b)
    fr_b_w, fr_f_w = geometry.warp(fr_b, px_f), geometry.warp(fr_f, px_b)
    m_f, m_b = geometry.occlusion_mask(px_f, px_b, px_b_w, px_f_w, alpha1=cfg.occ_alpha1, alpha2=cfg.occ_alpha2,
                                       warped_bw_norm=cfg.occlusion_norm == "warped",
                                       border_ratio=cfg.border_ratio, floor=cfg.mask_floor)
    stereo = jnp.array([cyc.PAIRS[k].task == "stereo" for k in pairs])[:, None, None, None]
    m_f = jax.lax.stop_gradient(jnp.where(stereo, 1.0, m_f))
    m_b = jax.lax.stop_gradient(jnp.where(stereo, 1.0, m_b))
    photometric = losses.PHOTOMETRIC_LOSSES[cfg.photometric]
    one = jnp.ones((), px.dtype)
    def smooth(d, im):
        return losses.Masked(losses.smoothness_loss(d, im, beta=cfg.smoothness_edge_constant(), scale=cfg.smooth_scale,
                                                    order=cfg.smoothness_order), one)
    st = np.array([i for i, k in enumerate(pairs) if cyc.PAIRS[k].task == "stereo"], int)
    lr_fwd = lr_bwd = None
    if st.size:
        lr_fwd = losses.Masked(losses.lr_consistency_loss(fr_f[st], fr_b_w[st]), one)
        lr_bwd = losses.Masked(losses.lr_consistency_loss(fr_b[st], fr_f_w[st]), one)
    two_warp = ()
    if cfg.two_warp != "none":
        chains = losses.two_warp_chains(cfg.two_warp, losses.PairMaps(former, latter, px_f, px_b, est_f, est_b,
                                                                      m_f, m_b), cfg.two_warp_target)
        for c in chains:  # eqs. 10-12 of each chain on its own
            mask = c.mask if c.mask_flow is None else geometry.warp(c.mask, c.mask_flow)
            two_warp += (photometric(geometry.warp(c.image, c.flow), c.target, mask),)
    return losses.ScaleTerms(photometric(est_f, former, m_f), photometric(est_b, latter, m_b),
                             smooth(px_f, former), smooth(px_b, latter), lr_fwd, lr_bwd, two_warp)


def all_terms(maps, cycles, cfg, pyramids, per_call: bool):
    """(B, ...) per-cycle ScaleTerms of every scale, stacked or per call."""
    per_cycle = cyc.unbatch_maps(maps, cycles.shape[0])

    def one(m, c, pyr):
        if not per_call:
            return losses.cycle_terms(m, c, cfg, pyr)
        return tuple(per_call_scale_terms(m["px"][s], m["frac"][s], pyr[s], cfg) for s in cfg.loss_scales)

    return jax.vmap(one)(per_cycle, cycles, pyramids)


def summed(terms):
    return sum(jnp.sum(x) for x in jax.tree.leaves(terms))


def assert_same_terms_and_grads(maps, cycles, pyramids, cfg, atol, rtol=0.0):
    def terms_and_grads(per_call):
        fn = lambda m: summed(all_terms(m, cycles, cfg, pyramids, per_call))
        return all_terms(maps, cycles, cfg, pyramids, per_call), jax.grad(fn)(maps)

    stacked, g_stacked = jax.jit(lambda: terms_and_grads(False))()
    reference, g_reference = jax.jit(lambda: terms_and_grads(True))()
    assert jax.tree.structure(stacked) == jax.tree.structure(reference)
    for got, want in zip(jax.tree.leaves(stacked), jax.tree.leaves(reference)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=rtol, atol=atol)
    for got, want in zip(jax.tree.leaves(g_stacked), jax.tree.leaves(g_reference)):
        np.testing.assert_allclose(np.asarray(got), np.asarray(want), rtol=rtol, atol=atol)
    # the reduced, weighted total as well
    total = lambda terms: losses.total_loss(losses.reduce_over_cycles(terms, cfg.reduction), cfg)[0]
    np.testing.assert_allclose(float(total(stacked)), float(total(reference)), rtol=max(rtol, 10 * atol))


def random_case(cfg, dtype, h=32, w=64, b=2):
    maps = random_maps(b * 2 * len(cfg.pairs), h, w, seed=7)
    maps = jax.tree.map(lambda m: jnp.asarray(m, dtype), maps)
    cycles = jnp.asarray(np.random.default_rng(11).random((b, 4, h, w, 3)), dtype)
    pyramids = jax.vmap(lambda c: geometry.image_pyramid(c, 4))(cycles)
    return maps, cycles, pyramids


FAST = ("stereo_only",)
"""The float32 cases of the default suite; the stacking does not depend on the photometric term (census has its
own numpy checks in test_loss_switches.py), and float64 `full2` below checks the 2-warp chains exactly."""


@pytest.mark.parametrize("name", [n if n in FAST else pytest.param(n, marks=pytest.mark.slow) for n in sorted(CONFIGS)])
def test_stacked_terms_equal_per_call_terms_float32(name):
    cfg = losses.LossConfig(**CONFIGS[name])
    assert_same_terms_and_grads(*random_case(cfg, jnp.float32), cfg, atol=1e-6)


@pytest.mark.parametrize("name", ["full2", "flow_only_order1", pytest.param("census_full2", marks=pytest.mark.slow)])
def test_stacked_terms_equal_per_call_terms_float64(name):
    with jax.enable_x64(True):
        cfg = losses.LossConfig(**CONFIGS[name])
        maps, cycles, pyramids = random_case(cfg, jnp.float64)
        assert maps["px"][0].dtype == jnp.float64
        assert_same_terms_and_grads(maps, cycles, pyramids, cfg, atol=1e-12)


FIXTURE_CASES = {
    "syn_upstream_full2": ("syn_", losses.LossConfig.upstream(two_warp="full2")),  # occluding maps, upstream loss
    "net_paper_full3": ("net_", losses.LossConfig(two_warp="full3")),  # the seeded upstream network's maps
}


@pytest.mark.parametrize("dtype", ["float32", pytest.param("float64", marks=pytest.mark.slow)])
@pytest.mark.parametrize("case", ["syn_upstream_full2", pytest.param("net_paper_full3", marks=pytest.mark.slow)])
def test_stacked_terms_equal_per_call_terms_on_the_upstream_fixture(case, dtype):
    """The fixture's 2 cycles (the shipped one; the network's maps: the full one): float32 (sums of 10^4-10^5
    pixels: 5e-5 relative) and float64 (exact)."""
    ref = dict(np.load(reference_file("in_repo") if case.startswith("syn_") else fixture_file("reference.npz")))
    prefix, cfg = FIXTURE_CASES[case]
    maps, pyramids = fixture_maps(ref, prefix), fixture_pyramids(ref)
    if dtype == "float32":
        assert_same_terms_and_grads(maps, pyramids[0], pyramids, cfg, atol=1e-6, rtol=5e-5)
        return
    with jax.enable_x64(True):
        f64 = lambda t: jax.tree.map(lambda x: jnp.asarray(x, jnp.float64), t)
        assert_same_terms_and_grads(f64(maps), f64(pyramids[0]), f64(pyramids), cfg, atol=1e-12)


def test_stacked_two_warp_rows_are_the_photometric_loss_of_each_chain():
    """Eq. 12 as training runs it (one per_row call over the rows of `two_warp_estimates`, a group_mean per chain)
    against eq. 12 applied to each chain alone."""
    cfg = losses.LossConfig(two_warp="full2")
    maps, cycles, pyramids = random_case(cfg, jnp.float32, b=1)
    px, frames = maps["px"][1], pyramids[1][0]
    former, latter = cyc.pair_images(frames)
    est_f, est_b = geometry.warp(latter, px[:4]), geometry.warp(former, px[4:])
    # a different mask on every pair and pixel, so that a chain given another chain's mask shows
    m_f, m_b = jnp.asarray(np.random.default_rng(5).uniform(0.2, 1.0, (2,) + former.shape[:-1] + (1,)), jnp.float32)
    chains = losses.two_warp_chains("full2", losses.PairMaps(former, latter, px[:4], px[4:], est_f, est_b, m_f, m_b))
    got = two_warp_terms(chains)
    for c, g in zip(chains, got):
        mask = geometry.warp(c.mask, c.mask_flow) if c.mask_flow is not None else c.mask
        want = losses.photometric_loss(geometry.warp(c.image, c.flow), c.target, mask)
        for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(want)):
            assert float(a) == pytest.approx(float(b), rel=1e-6, abs=1e-7)
