"""Test-time iterative residual refinement (`inference.refine_maps`, `TestTime(refine=)`): the warp direction
and the composition rule on hand-built cases, and the predictor against a numpy pass built from its own
unrefined network calls."""

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import inference, models
from bridge_jax.inference import TestTime, WorkingSize
from tests.test_geometry import np_warp

H, W = 64, 128


def shift_matcher(max_shift: int = 4):
    """A stand-in network that is exact for a uniform integer translation: for each pair it tries every shift
    (dx, dy) in [-max_shift, max_shift]^2 and returns the one whose shifted b best matches a (interior pixels),
    as a constant map. It never sees the estimate: what it returns depends on the warped b alone."""
    shifts = [(dx, dy) for dy in range(-max_shift, max_shift + 1) for dx in range(-max_shift, max_shift + 1)]
    m = max_shift

    def estimate(pairs):
        a, b = pairs[..., :3], pairs[..., 3:]
        errors = []
        for dx, dy in shifts:  # b sampled at x + dx, y + dy
            moved = jnp.roll(b, shift=(-dy, -dx), axis=(1, 2))
            errors.append(jnp.mean(jnp.abs(a - moved)[:, 2 * m:-2 * m, 2 * m:-2 * m], axis=(1, 2, 3)))
        best = jnp.argmin(jnp.stack(errors, axis=-1), axis=-1)
        table = jnp.asarray(shifts, jnp.float32)[best]  # (N, 2)
        return jnp.broadcast_to(table[:, None, None, :], pairs.shape[:3] + (2,))

    return estimate


def test_refine_warps_b_by_the_estimate_and_adds_the_residual(rng):
    """b = a moved by (6, -5) px: a first estimate of (3, -1) leaves (3, -4) to find in b warped by it, which the
    matcher (range ±4) finds only if b, not a, is warped, and in the estimate's direction; one pass gives the
    true (6, -5), which the matcher alone (range ±4) cannot reach."""
    a = rng.uniform(size=(1, H + 40, W + 40, 3)).astype(np.float32)
    true = (6, -5)
    b = np.roll(a, shift=(true[1], true[0]), axis=(1, 2))  # b(x + 6, y - 5) = a(x, y)
    a, b = a[:, 20:-20, 20:-20], b[:, 20:-20, 20:-20]
    pairs = jnp.asarray(np.concatenate([a, b], -1))
    first = jnp.broadcast_to(jnp.asarray([3.0, -1.0]), (1, H, W, 2))
    out = np.asarray(inference.refine_maps(shift_matcher(), pairs, first, jnp.ones(1), passes=1))
    np.testing.assert_allclose(out[0, 10:-10, 10:-10], np.broadcast_to(true, (H - 20, W - 20, 2)), atol=1e-5)
    # a second pass finds nothing left to add
    out2 = np.asarray(inference.refine_maps(shift_matcher(), pairs, first, jnp.ones(1), passes=2))
    np.testing.assert_allclose(out2[0, 10:-10, 10:-10], out[0, 10:-10, 10:-10], atol=1e-5)


def test_composition_samples_the_estimate_at_the_residual_end_point(rng):
    """D'(x) = R(x) + D(x + R(x)): with D a ramp in x (D_x = 0.1 x, D_y = 0.05 y) and a constant residual
    R = (2, 1), D' = (2 + 0.1 (x + 2), 1 + 0.05 (y + 1)) in the interior (an additive rule would give
    (2 + 0.1 x, ...), a rule sampling at x - R (2 + 0.1 (x - 2), ...))."""
    ys, xs = np.mgrid[0:H, 0:W].astype(np.float32)
    first = np.stack([0.1 * xs, 0.05 * ys], -1)[None]
    residual = np.array([2.0, 1.0], np.float32)
    estimate = lambda pairs: jnp.broadcast_to(jnp.asarray(residual), pairs.shape[:3] + (2,))
    pairs = jnp.asarray(rng.uniform(size=(1, H, W, 6)).astype(np.float32))
    out = np.asarray(inference.refine_maps(estimate, pairs, jnp.asarray(first), jnp.ones(1), passes=1))[0]
    want = np.stack([2 + 0.1 * (xs + 2), 1 + 0.05 * (ys + 1)], -1)
    np.testing.assert_allclose(out[2:-4, 2:-4], want[2:-4, 2:-4], atol=1e-4)


def test_stereo_rows_refine_along_rows_only(rng):
    """A stereo row's vertical component is dropped before each warp and from the residual; a flow row in
    the same batch keeps its own."""
    residual = np.array([1.0, 2.0], np.float32)
    estimate = lambda pairs: jnp.broadcast_to(jnp.asarray(residual), pairs.shape[:3] + (2,))
    first = jnp.broadcast_to(jnp.asarray([-4.0, 3.0]), (2, H, W, 2))
    pairs = jnp.asarray(rng.uniform(size=(2, H, W, 6)).astype(np.float32))
    out = np.asarray(inference.refine_maps(estimate, pairs, first, jnp.asarray([0.0, 1.0]), passes=1))
    np.testing.assert_allclose(out[0, 8:-8, 8:-8], np.broadcast_to([-3.0, 0.0], (H - 16, W - 16, 2)), atol=1e-5)
    np.testing.assert_allclose(out[1, 8:-8, 8:-8], np.broadcast_to([-3.0, 5.0], (H - 16, W - 16, 2)), atol=1e-5)


@pytest.fixture(scope="module")
def network():
    return models.init(0, "pwc_lite")


def test_predictor_refine_matches_a_numpy_pass_over_its_own_calls(network, rng):
    """`TestTime(refine=1)` = the unrefined predictor on (a, b), then on (a, b warped by that map in numpy),
    composed in numpy: one compiled function per refine value, the same numbers as the pass done by hand."""
    cfg = models.model_config("pwc_lite")
    plain = inference.Predictor(*network, size=WorkingSize(H, W), model_cfg=cfg)
    refined = inference.Predictor(*network, size=WorkingSize(H, W), test_time=TestTime(refine=1), model_cfg=cfg)
    # a smooth image moved by a sub-pixel shift, so the untrained network's maps are smooth and non-zero
    base = rng.uniform(size=(H // 8, W // 8, 3)).astype(np.float32)
    big = cv2.resize(base, (W + 16, H + 16), interpolation=cv2.INTER_CUBIC)
    a, b = big[8:-8, 8:-8], big[9:-7, 6:-10]
    pairs = np.concatenate([a, b], -1)[None]
    d0 = plain.run_network(pairs)[0]
    d0 = d0 + np.array([1.5, -0.75], np.float32)  # a random network's map is tiny: move the warp well away from 0
    wb = np_warp(b, d0)
    r = plain.run_network(np.concatenate([a, wb], -1)[None])[0]
    want = r + np_warp(d0, r)
    got = np.asarray(inference.refine_maps(lambda x: plain.forward(x, ["flow"] * len(x)), jnp.asarray(pairs),
                                           jnp.asarray(d0[None]), jnp.ones(1), passes=1))[0]
    np.testing.assert_allclose(got, want, atol=2e-4)
    # the predictor's own refined call: its first estimate is its own d0
    d0 = plain.run_network(pairs)[0]
    r = plain.run_network(np.concatenate([a, np_warp(b, d0)], -1)[None])[0]
    np.testing.assert_allclose(refined.run_network(pairs)[0], r + np_warp(d0, r), atol=2e-4)
    n = refined.trace_count
    refined.run_network(pairs)
    assert refined.trace_count == n == 1
    refined.test_time = inference.TestTime(refine=2)  # another pass count: one more compile
    refined.run_network(pairs)
    assert refined.trace_count == 2


def test_predictor_refine_zero_is_the_plain_network(network, rng):
    cfg = models.model_config("pwc_lite")
    pairs = rng.uniform(size=(2, H, W, 6)).astype(np.float32)
    plain = inference.Predictor(*network, size=WorkingSize(H, W), model_cfg=cfg)
    np.testing.assert_array_equal(plain.run_network(pairs), inference.Predictor(
        *network, size=WorkingSize(H, W), test_time=TestTime(refine=0), model_cfg=cfg).run_network(pairs))


@pytest.mark.parametrize("bad", [-1, inference.MAX_REFINE + 1, 1.5, "2", True])
def test_refine_out_of_range_is_one_clear_error(network, bad):
    with pytest.raises(ValueError, match=r"refine .*expected a whole number of refinement passes from 0 to 8"):
        inference.Predictor(*network, size=WorkingSize(H, W), test_time=TestTime(refine=bad),
                            model_cfg=models.model_config("pwc_lite"))
