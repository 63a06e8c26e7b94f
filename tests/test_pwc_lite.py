"""The correlation model `pwc_lite` and the coordinate channels, against numpy references and hand-built cases."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import models, recipe, setup
from bridge_jax.configs import demo
from bridge_jax.models import coordinates, pwc_lite

pytestmark = pytest.mark.usefixtures("release_after_each_test")  # see tests/conftest.py

TINY = {"name": "pwc_lite", "pyramid": [8, 16, 16, 16], "feature_width": 8, "estimator": [16, 16],
        "context": [16, 16], "dilations": [1, 2]}


def _np_normalize(f1, f2, eps=1e-6):
    both = np.stack([f1, f2], 1).astype(np.float64)
    mu = both.mean(axis=(1, 2, 3, 4), keepdims=True)
    sd = np.sqrt(((both - mu) ** 2).mean(axis=(1, 2, 3, 4), keepdims=True) + eps)
    out = (both - mu) / sd
    return out[:, 0], out[:, 1]


def _np_cost_volume(f1, f2, r):
    """Loop over displacements and pixels; f2 is 0 outside the image."""
    n, h, w, c = f1.shape
    out = np.zeros((n, h, w, (2 * r + 1) ** 2))
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            k = (dy + r) * (2 * r + 1) + (dx + r)
            for y in range(h):
                for x in range(w):
                    if 0 <= y + dy < h and 0 <= x + dx < w:
                        out[:, y, x, k] = (f1[:, y, x] * f2[:, y + dy, x + dx]).mean(-1)
    return out


def test_normalize_features_matches_numpy():
    rng = np.random.default_rng(0)
    f1 = rng.normal(3.0, 2.0, (2, 5, 6, 4)).astype(np.float32)
    f2 = rng.normal(-1.0, 0.5, (2, 5, 6, 4)).astype(np.float32)
    a, b = pwc_lite.normalize_features(jnp.asarray(f1), jnp.asarray(f2))
    ra, rb = _np_normalize(f1, f2)
    np.testing.assert_allclose(a, ra, atol=1e-5)
    np.testing.assert_allclose(b, rb, atol=1e-5)
    # per pair: zero mean and unit variance over both images together (not each image alone)
    both = np.stack([np.asarray(a), np.asarray(b)], 1)
    np.testing.assert_allclose(both.mean(axis=(1, 2, 3, 4)), 0, atol=1e-5)
    np.testing.assert_allclose(both.var(axis=(1, 2, 3, 4)), 1, atol=1e-4)
    assert abs(float(np.asarray(a)[0].mean())) > 0.5  # image a alone is not centred: the moments are shared


def test_cost_volume_matches_numpy_loop_with_zero_padding():
    rng = np.random.default_rng(1)
    f1 = rng.normal(size=(2, 6, 7, 3)).astype(np.float32)
    f2 = rng.normal(size=(2, 6, 7, 3)).astype(np.float32)
    got = np.asarray(pwc_lite.cost_volume(jnp.asarray(f1), jnp.asarray(f2), 2))
    want = _np_cost_volume(*_np_normalize(f1, f2), 2)
    np.testing.assert_allclose(got, want, atol=1e-5)
    # zero padding: at the top-left pixel every displacement with dy < 0 or dx < 0 reads outside -> exactly 0
    assert np.all(got[:, 0, 0, :2 * 5] == 0) and np.all(got[:, 0, 0, [10, 15, 20]] == 0)


def test_cost_volume_peaks_at_the_true_shift():
    rng = np.random.default_rng(2)
    f2 = rng.normal(size=(1, 12, 16, 64)).astype(np.float32)
    f1 = np.roll(f2, shift=(-1, 2), axis=(1, 2))  # f1[y, x] = f2[y + 1, x - 2]: displacement (dy, dx) = (1, -2)
    cv = np.asarray(pwc_lite.cost_volume(jnp.asarray(f1), jnp.asarray(f2), 3))
    k = (1 + 3) * 7 + (-2 + 3)
    assert np.all(np.argmax(cv[0, 3:-3, 3:-3], axis=-1) == k)


def test_coordinate_channels_corners_and_layout():
    c = np.asarray(coordinates.coordinate_channels(2, 4, 8))
    assert c.shape == (2, 4, 8, 2)
    np.testing.assert_allclose(c[0, 0, 0], [-1, -1])
    np.testing.assert_allclose(c[0, 0, -1], [1, -1])
    np.testing.assert_allclose(c[1, -1, 0], [-1, 1])
    np.testing.assert_allclose(c[1, -1, -1], [1, 1])
    np.testing.assert_allclose(c[0, 0, 1, 0], -1 + 2 / 7, atol=1e-6)  # x steps by 2 / (W - 1)
    x = jnp.ones((2, 4, 8, 3))
    out = np.asarray(coordinates.with_coordinates(x))
    assert out.shape == (2, 4, 8, 5)
    np.testing.assert_array_equal(out[..., :3], 1)
    np.testing.assert_array_equal(out[..., 3:], c)


FIRST_CONV = {"pwc_lite": "pyramid1_0", "resnet_md_tiny": "conv1", "pwcnet": "conv1a"}


@pytest.mark.parametrize("name, overrides", [("pwc_lite", TINY), ("resnet_md_tiny", {}), ("pwcnet", {
    "pyramid": [4, 4, 4, 4, 4, 4], "estimator": [4, 4, 4, 4, 4], "context": [4, 4, 4, 4, 4, 4]})])
def test_coordinate_switch_keeps_the_output_layout_and_feeds_position(name, overrides):
    base = dict(overrides, name=name, head_init="kaiming_normal" if name != "resnet_md_tiny" else "torch")
    x = jax.random.uniform(jax.random.key(3), (1, 64, 128, 6))
    g0, p0 = models.init(0, dict(base, coords=False))
    g1, p1 = models.init(0, dict(base, coords=True))
    out0, out1 = models.apply(g0, p0, x), models.apply(g1, p1, x)
    for key in ("px", "frac"):
        assert [m.shape for m in out1[key]] == [m.shape for m in out0[key]]
    conv = FIRST_CONV[name]
    k0, k1 = p0[conv]["conv"]["kernel"] if name != "resnet_md_tiny" else p0[conv]["kernel"], \
        p1[conv]["conv"]["kernel"] if name != "resnet_md_tiny" else p1[conv]["kernel"]
    assert k1.shape[2] == k0.shape[2] + 2  # the two coordinate channels come after the image channels
    # the coordinate inputs reach the output: zeroing their first-layer weights changes the maps
    p1z = jax.tree.map(lambda v: v, p1)
    node = p1z[conv]["conv"] if name != "resnet_md_tiny" else p1z[conv]
    node["kernel"] = node["kernel"].at[:, :, -2:].set(0.0)
    outz = models.apply(g1, p1z, x)
    assert float(jnp.abs(outz["px"][0] - out1["px"][0]).max()) > 1e-4


def test_pyramid_levels_follow_the_working_size():
    assert pwc_lite.pyramid_levels(64, 128, 6) == 4  # coarsest 4x8
    assert pwc_lite.pyramid_levels(256, 512, 6) == 6
    assert pwc_lite.pyramid_levels(256, 512, 4) == 4  # capped by the configured widths
    assert pwc_lite.pyramid_levels(32, 64, 6) == 3
    assert pwc_lite.pyramid_levels(96, 320, 6) == 4  # 96 = 2^5 * 3: level 5 would be 3 rows
    with pytest.raises(ValueError, match="too small for pwc_lite"):
        pwc_lite.pyramid_levels(24, 64, 6)


def test_too_small_working_size_is_one_config_error():
    c = recipe.single_run(demo.get_config("short"))
    c.height, c.width = 16, 32
    with pytest.raises(setup.ConfigError, match=r"config.height/config.width.*too small for pwc_lite"):
        setup.parse(c)
    with pytest.raises(ValueError, match="multiples of 8"):
        models.check_working_size("pwc_lite", 60, 128)


def test_unknown_model_keys_and_values_are_named():
    with pytest.raises(ValueError, match="unknown pwc_lite config keys"):
        models.model_config("pwc_lite", radus=3)
    with pytest.raises(ValueError, match="finest_level must be 1 or 2"):
        models.model_config("pwc_lite", finest_level=3)


def test_upsample_flow2x_is_bilinear_and_doubles_units():
    rng = np.random.default_rng(3)
    f = rng.normal(size=(2, 4, 6, 2)).astype(np.float32)
    got = np.asarray(pwc_lite.upsample_flow2x(jnp.asarray(f)))
    want = 2 * np.asarray(jax.image.resize(jnp.asarray(f), (2, 8, 12, 2), "linear"))
    np.testing.assert_allclose(got, want, atol=1e-5)
    const = np.asarray(pwc_lite.upsample_flow2x(jnp.full((1, 3, 3, 2), 1.5)))
    np.testing.assert_allclose(const, 3.0)  # 1.5 px of level l+1 = 3 px of level l


def test_outputs_four_scales_in_pixels_and_fractions_starting_at_zero():
    g, p = models.init(0, TINY)
    x = jax.random.uniform(jax.random.key(0), (2, 64, 128, 6))
    out = models.apply(g, p, x)
    assert [m.shape for m in out["px"]] == [(2, 64 >> s, 128 >> s, 2) for s in range(4)]
    for m in out["px"]:
        assert float(jnp.abs(m).max()) == 0.0  # zero heads: zero motion
    g, p = models.init(0, dict(TINY, head_init="kaiming_normal"))
    out = models.apply(g, p, x)
    for s in range(4):
        h, w = 64 >> s, 128 >> s
        np.testing.assert_allclose(out["frac"][s] * np.array([w, h]), out["px"][s], rtol=1e-5, atol=1e-6)
    # scales finer than the finest level are its refined flow upsampled: scale 1 = upsample(scale 2), in units
    np.testing.assert_allclose(out["px"][1], pwc_lite.upsample_flow2x(out["px"][2]), atol=1e-5)
    np.testing.assert_allclose(out["px"][0], pwc_lite.upsample_flow2x(out["px"][1]), atol=1e-5)


# ----------------------------------------------------------------------------------------- training with it
def _cycles(n, seed=0):
    from bridge_jax.data import synthetic
    return jnp.asarray(np.stack([synthetic.render_sample(synthetic.sample_seed(seed, i), 64, 128)["cycle"]
                                 for i in range(n)]).astype(np.float32) / 255.0)


@pytest.mark.slow
def test_pwc_lite_step_one_trace_per_shape_and_eight_devices_equal_one():
    from bridge_jax import train_step
    from tests.train_helpers import make_step
    state1, step1, _, _, kw1 = make_step(num_devices=1, model=TINY)
    state8, step8, _, _, kw8 = make_step(num_devices=8, model=TINY)
    before = train_step.TRACE_COUNTS["train_step"]
    for i in range(3):
        c = _cycles(8, seed=i)
        state1, m1 = step1(state1, jax.device_put(c, kw1["batch_sharding"]))
        state8, m8 = step8(state8, jax.device_put(c, kw8["batch_sharding"]))
        assert float(m1["loss"]) == pytest.approx(float(m8["loss"]), rel=1e-5)
    assert train_step.TRACE_COUNTS["train_step"] - before == 2  # one trace per mesh, none per step
    for a, b in zip(jax.tree.leaves(state1["params"]), jax.tree.leaves(state8["params"])):
        np.testing.assert_allclose(a, b, atol=2e-5)
    assert float(jnp.abs(state1["params"]["estimator_flow"]["bias"]).max()) > 0  # it trained


@pytest.mark.parametrize("same_image, bound", [(False, "<= 0.3"),
                                               pytest.param(True, ">= 0.8", marks=pytest.mark.slow)])
def test_pwc_lite_overfits_one_cycle_by_matching(same_image, bound):
    """Learning, not timing: 150 steps of the real training step (lr 3e-3) on ONE synthetic cycle bring the left
    flow to <= 0.3x the zero-motion EPE (measured 0.276; 300 steps at 1e-3 reach 0.25); with the flow pair's second
    frame replaced by its first there is nothing to match, and the same run stays near zero motion: the model
    matches, it does not guess flow from one image."""
    from experiments import flow_ceiling  # the diagnostic's own overfit loop (experiments/flow_ceiling.py)
    *_, (step, ratio, _) = flow_ceiling.overfit_cycle(dict(models.model_config("pwc_lite")), {}, steps=150, lr=3e-3,
                                                      same_image=same_image, eval_every=150)
    assert step == 150
    assert (ratio <= 0.3) if not same_image else (ratio >= 0.8), f"flow EPE ratio {ratio:.3f}, expected {bound}"
