"""Options that change how the gradient is computed but not what it is.

Rematerialisation (`config.remat`, `network.REMAT_POLICIES`) recomputes activations in the gradient, and
`config.conv_weight_grad` (`layers.WEIGHT_GRAD_METHODS`) computes the convolutions' weight gradients as matmuls
instead of XLA's backward-filter convolution. The loss and every gradient must stay what the plain network gives
(to 1e-6 for remat, to float32 summation order for the weight gradients), for both architectures the demo and
the paper use, and a name outside either list is one config error."""

import jax
import numpy as np
import pytest

from bridge_jax import network, setup
from bridge_jax.configs import default as default_config


def _loss_and_grads(model: str, remat: str, height: int = 64, width: int = 128, conv_weight_grad: str = "auto"):
    """A scalar of every output of the network (a fixed random weighting of the maps at all 4 scales) and its
    gradient. Both options act inside the network only, so its own gradient is what they could change; the
    cycle loss on top of it would only multiply the compile time of this test."""
    c = default_config.get_config()
    c.model = default_config.model_section(model)
    c.height, c.width, c.global_batch, c.remat = height, width, 1, remat
    c.conv_weight_grad = conv_weight_grad
    run = setup.parse(c, devices=jax.devices()[:1], num_processes=1)
    graphdef, params = network.init_params(jax.random.key(0), run.model.config)
    params = jax.tree.map(lambda p: p + 0.01 * np.random.default_rng(1).standard_normal(p.shape).astype(p.dtype),
                          params)  # zero heads would give zero maps; move every weight off its init
    net = run.model.network(graphdef)
    assert net.remat == remat and net.conv_weight_grad == conv_weight_grad
    gen = np.random.default_rng(2)
    pairs = gen.random((8, height, width, 6), dtype=np.float32)  # the 8 pairs of one training cycle
    weights = [gen.standard_normal((8, height >> s, width >> s, 2)).astype(np.float32) for s in range(4)]

    def scalar(p):
        maps = net(p, pairs)["frac"]
        assert [m.shape for m in maps] == [w.shape for w in weights]
        return sum(jax.numpy.sum(m * w) for m, w in zip(maps, weights))

    loss, grads = jax.jit(jax.value_and_grad(scalar))(params)
    return float(loss), grads


@pytest.mark.parametrize("model,size", [("resnet_md_tiny", (64, 128)),
                                        pytest.param("pwc_lite", (32, 64), marks=pytest.mark.slow)])
def test_remat_policies_change_no_gradient(model, size):
    loss0, g0 = _loss_and_grads(model, "none", *size)
    scale = max(float(np.max(np.abs(x))) for x in jax.tree.leaves(g0))
    assert scale > 1e-4  # the comparison below is not between zeros
    for policy in ("conv_outputs", "nothing"):
        loss, g = _loss_and_grads(model, policy, *size)
        assert loss == pytest.approx(loss0, rel=1e-6)
        for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g0)):
            np.testing.assert_allclose(np.asarray(a), np.asarray(b), rtol=0, atol=1e-6 * max(scale, 1.0))


@pytest.mark.parametrize("model,size", [("resnet_md_tiny", (64, 128)),
                                        pytest.param("pwc_lite", (32, 64), marks=pytest.mark.slow)])
def test_conv_weight_grad_methods_change_no_gradient(model, size):
    """Every convolution's weight gradient by shifted-dy or shifted-x matmuls, or by XLA's in batch chunks
    (forced for all layers here; "auto" picks per layer) gives XLA's gradients to float32 summation order."""
    loss0, g0 = _loss_and_grads(model, "none", *size, conv_weight_grad="xla")
    scale = max(float(np.max(np.abs(x))) for x in jax.tree.leaves(g0))
    assert scale > 1e-4
    for method in ("shift_dy", "shift_x", "xla_chunks"):
        loss, g = _loss_and_grads(model, "none", *size, conv_weight_grad=method)
        assert loss == loss0  # the forward pass is XLA's in every method
        worst = max(float(np.max(np.abs(np.asarray(a) - np.asarray(b))))
                    for a, b in zip(jax.tree.leaves(g), jax.tree.leaves(g0)))
        assert 0 < worst <= 2e-6 * scale, (method, worst, scale)  # > 0: the other formulation really ran


@pytest.mark.parametrize("key,bad,allowed", [
    ("remat", "everything", r"\['conv_outputs', 'none', 'nothing'\]"),
    ("conv_weight_grad", "fast", r"\['auto', 'xla', 'shift_dy', 'shift_x', 'xla_chunks'\]")])
def test_option_names_are_checked(key, bad, allowed):
    """A name outside the list is one config error naming the key and the allowed names, and `Network`
    refuses it too."""
    c = default_config.get_config()
    c[key] = bad
    with pytest.raises(setup.ConfigError, match=rf"config.{key} must be one of {allowed}, got '{bad}'"):
        setup.parse(c, devices=jax.devices()[:1], num_processes=1)
    with pytest.raises(ValueError, match=f"{key} must be one of"):
        network.Network(None, **{key: bad})
