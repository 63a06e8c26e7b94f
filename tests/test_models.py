"""Networks: sizes, conventions (padding/stride, heads), PWC-Net ops, against numpy references."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from bridge_jax import models
from bridge_jax.models import layers, pwcnet, resnet_md

pytestmark = pytest.mark.usefixtures("release_after_each_test")  # see tests/conftest.py

# ---------------------------------------------------------------- numpy references (NHWC, float64)


def np_conv(x, k, b=None, stride=1, pad=None, dilation=1):
    """Direct PyTorch-style conv: x (N,H,W,Ci), k (kh,kw,Ci,Co) HWIO, symmetric zero padding."""
    kh = k.shape[0]
    pad = dilation * (kh // 2) if pad is None else pad
    xp = np.pad(x, ((0, 0), (pad, pad), (pad, pad), (0, 0)))
    n, hp, wp, _ = xp.shape
    ho = (hp - dilation * (kh - 1) - 1) // stride + 1
    wo = (wp - dilation * (k.shape[1] - 1) - 1) // stride + 1
    out = np.zeros((n, ho, wo, k.shape[3]))
    for i, j, patch in np_tap_views(xp, k.shape[:2], (ho, wo), stride, dilation):
        out += patch @ k[i, j]
    return out + (0 if b is None else b)


def np_tap_views(xp, kernel_hw, out_hw, stride, dilation):
    """(i, j, view) for each kernel tap of the padded input xp (N, Hp, Wp, C): view[n, o] = xp[n, s*o + d*(i, j)]."""
    (ho, wo) = out_hw
    for i in range(kernel_hw[0]):
        for j in range(kernel_hw[1]):
            yield i, j, xp[:, i * dilation:i * dilation + stride * (ho - 1) + 1:stride,
                           j * dilation:j * dilation + stride * (wo - 1) + 1:stride]


def np_elu(x):
    return np.where(x > 0, x, np.expm1(np.minimum(x, 0)))


def np_maxpool(x):
    xp = np.pad(x, ((0, 0), (1, 1), (1, 1), (0, 0)), constant_values=-np.inf)
    ho, wo = (x.shape[1] + 1) // 2, (x.shape[2] + 1) // 2
    return np.max([xp[:, i:i + 2 * ho:2, j:j + 2 * wo:2] for i in range(3) for j in range(3)], axis=0)


def f32(x):
    return jnp.asarray(x, jnp.float32)


# ---------------------------------------------------------------- sizes


def test_param_counts():
    _, p = models.abstract_init("resnet_md")
    assert models.param_count(p) == 58_461_416  # upstream MonodepthNet
    _, p = models.abstract_init("pwcnet")
    assert models.param_count(p) == 9_374_340  # upstream PWCDCNet (incl. its unused deconv2)


@pytest.mark.parametrize("name", models.NAMES)
def test_shapes_only_build_matches_a_traced_abstract_build(name):
    """abstract_init builds without tracing initializers (layers.shapes_only); the reference is flax's own
    nnx.eval_shape of a real build: the same GraphDef, the same parameter names, shapes and dtypes."""
    cfg = models.model_config(name)
    traced = nnx.eval_shape(lambda: models._module(cfg, nnx.Rngs(params=0)))
    g_ref, state = nnx.split(traced, nnx.Param)
    ref = nnx.to_pure_dict(state)
    g, params = models.abstract_init(name)
    assert g == g_ref
    assert jax.tree.structure(params) == jax.tree.structure(ref)
    for a, b in zip(jax.tree.leaves(params), jax.tree.leaves(ref)):
        assert isinstance(a, jax.ShapeDtypeStruct) and a.shape == b.shape and a.dtype == b.dtype
    # and outside the context, layers draw real values again
    conv = layers.Conv(3, 4, 3, rngs=nnx.Rngs(params=0))
    assert isinstance(conv.kernel[...], jax.Array) and float(jnp.abs(conv.kernel[...]).max()) > 0


@pytest.mark.parametrize("hw", [(256, 512), (128, 256)])
def test_full_size_output_shapes(hw):
    h, w = hw
    graphdef, params = models.abstract_init("resnet_md")
    out = jax.eval_shape(lambda p, x: models.apply(graphdef, p, x), params,
                         jax.ShapeDtypeStruct((2, h, w, 6), jnp.float32))
    for key in ("px", "frac"):
        assert [o.shape for o in out[key]] == [(2, h >> s, w >> s, 2) for s in range(4)]
        assert all(o.dtype == jnp.float32 for o in out[key])


@pytest.mark.slow
def test_full_size_forward_128x256_bounded():
    graphdef, params = models.init(jax.random.key(0), "resnet_md")
    x = np.random.default_rng(0).uniform(size=(1, 128, 256, 6)).astype(np.float32)
    out = jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x)
    for s in range(4):
        frac, px = np.asarray(out["frac"][s]), np.asarray(out["px"][s])
        assert frac.shape == (1, 128 >> s, 256 >> s, 2) and np.isfinite(frac).all()
        assert np.abs(frac).max() <= 0.3
        np.testing.assert_allclose(px, frac * [256 >> s, 128 >> s], rtol=1e-6)


def test_heads_bounded_and_pixel_scaling():
    """Saturated heads reach but never exceed +-0.3; px = frac * (W_s, H_s) with ch0 = x (width)."""
    graphdef, params = models.init(jax.random.key(1), "resnet_md_tiny")
    for name in ("get_disp1", "get_disp2", "get_disp3", "get_disp4"):
        params[name]["conv1"]["kernel"] = params[name]["conv1"]["kernel"] * 1e4
    x = np.random.default_rng(1).uniform(size=(2, 64, 128, 6)).astype(np.float32)
    out = jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x)
    for s in range(4):
        frac = np.asarray(out["frac"][s])
        assert np.abs(frac).max() <= 0.3 + 1e-7
        assert np.abs(frac).max() > 0.29  # the bound is reached, so it is 0.3 and not larger/smaller
        np.testing.assert_allclose(out["px"][s][..., 0], frac[..., 0] * (128 >> s), rtol=1e-6)
        np.testing.assert_allclose(out["px"][s][..., 1], frac[..., 1] * (64 >> s), rtol=1e-6)


def test_tiny_uses_same_code_path():
    g_full, _ = models.abstract_init("resnet_md")
    g_tiny, p_tiny = models.abstract_init("resnet_md_tiny")
    full = models.model_config("resnet_md")
    tiny = models.model_config("resnet_md_tiny")
    assert set(full) == set(tiny) and models.param_count(p_tiny) < 200_000
    assert type(nnx.merge(g_full, nnx.State(models.abstract_init("resnet_md")[1]))) is resnet_md.MonodepthResNet
    assert type(nnx.merge(g_tiny, nnx.State(p_tiny))) is resnet_md.MonodepthResNet


def test_bad_config_and_input():
    with pytest.raises(ValueError, match="unknown model name"):
        models.model_config("resnet101")
    with pytest.raises(ValueError, match="unknown resnet_md(_tiny)? config keys"):
        models.model_config("resnet_md", widht=2)
    graphdef, params = models.init(0, "resnet_md_tiny")
    with pytest.raises(ValueError, match="multiples of 64"):
        models.apply(graphdef, params, np.zeros((1, 64, 100, 6), np.float32))
    with pytest.raises(ValueError, match=r"\(N, H, W, 6\)"):
        models.apply(graphdef, params, np.zeros((1, 64, 128, 3), np.float32))


# ---------------------------------------------------------------- conventions of the building blocks


def test_stride2_padding_hand_case():
    """3x3/2 conv of ones with ones, PyTorch padding 1 on every side: corners see 2x2, edges 2x3, centre 3x3.
    (Flax 'SAME' would pad (0, 1) and give [[9, 6], [6, 4]].)"""
    x = jnp.ones((1, 4, 4, 1))
    k = jnp.ones((3, 3, 1, 1))
    out = layers.conv2d(x, k, stride=2)
    np.testing.assert_array_equal(np.asarray(out)[0, ..., 0], [[4, 6], [6, 9]])
    # 7x7/2 with padding 3 on an 8x8 input: output (0, 0) sees rows/cols 0..3 -> 16 ones.
    out7 = layers.conv2d(jnp.ones((1, 8, 8, 1)), jnp.ones((7, 7, 1, 1)), stride=2)
    assert out7.shape == (1, 4, 4, 1) and float(out7[0, 0, 0, 0]) == 16.0


@pytest.mark.parametrize("k,stride,dilation", [(7, 2, 1), (3, 2, 1), (3, 1, 1), (1, 1, 1), (1, 2, 1), (3, 1, 4)])
def test_conv_matches_numpy(rng, k, stride, dilation):
    x = rng.normal(size=(2, 10, 14, 5))
    w = rng.normal(size=(k, k, 5, 4))
    b = rng.normal(size=(4,))
    out = layers.conv2d(f32(x), f32(w), f32(b), stride=stride, dilation=dilation)
    np.testing.assert_allclose(out, np_conv(x, w, b, stride, dilation=dilation), rtol=1e-4, atol=1e-4)


def test_maxpool_upsample_and_subpixel_upconv(rng):
    x = rng.normal(size=(2, 7, 10, 3))
    np.testing.assert_allclose(layers.max_pool_3x3_s2(f32(x)), np_maxpool(x), rtol=1e-6)
    up = np.repeat(np.repeat(x, 2, axis=1), 2, axis=2)
    np.testing.assert_allclose(layers.upsample_nearest2x(f32(x)), up, rtol=1e-6)
    w = rng.normal(size=(3, 3, 3, 4))
    b = rng.normal(size=(4,))
    np.testing.assert_allclose(layers.upsample_nearest2x_conv3x3(f32(x), f32(w), f32(b)), np_conv(up, w, b),
                               rtol=1e-4, atol=1e-4)


def test_conv_transpose_matches_scatter_definition(rng):
    """PyTorch ConvTranspose2d(k=4, s=2, p=1): each input pixel scatters w * x to output (2i - 1 + a, 2j - 1 + b)."""
    x = rng.normal(size=(1, 3, 5, 2))
    w = rng.normal(size=(4, 4, 2, 3))  # (kh, kw, in, out) = torch (in, out, kh, kw) permuted (2, 3, 0, 1)
    full = np.zeros((1, 2 * 3 + 2, 2 * 5 + 2, 3))
    for i in range(3):
        for j in range(5):
            full[0, 2 * i:2 * i + 4, 2 * j:2 * j + 4] += np.einsum("c,abco->abo", x[0, i, j], w)
    ref = full[:, 1:-1, 1:-1]
    np.testing.assert_allclose(layers.conv_transpose2d(f32(x), f32(w)), ref, rtol=1e-4, atol=1e-5)


def test_torch_default_init_bounds():
    graphdef, params = models.init(0, "resnet_md_tiny")
    k = np.asarray(params["layer2"]["0"]["conv2"]["kernel"])  # 3x3, in 16*... -> fan_in = 9 * in
    bound = 1 / np.sqrt(9 * k.shape[2])
    assert np.abs(k).max() <= bound and np.abs(k).max() > 0.9 * bound


def test_encoder_first_stage_matches_numpy():
    """Tiny net, constant-ish weights: conv1 7x7/2 + ELU, max-pool, one stride-2 bottleneck with 1x1 shortcut."""
    cfg = models.model_config("resnet_md_tiny", blocks=[1, 1, 1, 1])
    graphdef, params = models.init(0, cfg)
    rng = np.random.default_rng(3)
    params = jax.tree.map(lambda p: f32(rng.normal(size=p.shape) * 0.2), params)
    x = rng.uniform(size=(1, 64, 128, 6))
    model = nnx.merge(graphdef, nnx.State(params))
    skip1, skip2, skip3 = (np.asarray(a) for a in model.encode(f32(x))[:3])
    P = jax.tree.map(np.asarray, params)

    def conv(x, p, stride=1):
        return np_conv(x, p["kernel"].astype(np.float64), p["bias"].astype(np.float64), stride)

    r1 = np_elu(conv(x, P["conv1"], 2))
    r2 = np_maxpool(r1)
    blk = P["layer1"]["0"]
    y = np_elu(conv(r2, blk["conv1"]))
    y = np_elu(conv(y, blk["conv2"], 2))  # the single (= last) block of the stage carries the stride
    r3 = np_elu(conv(y, blk["conv3"]) + conv(r2, blk["shortcut"], 2))
    assert skip1.shape == (1, 32, 64, 8) and skip2.shape == (1, 16, 32, 8) and skip3.shape == (1, 8, 16, 32)
    for got, ref in ((skip1, r1), (skip2, r2), (skip3, r3)):
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)


def test_bf16_compute_close_to_fp32():
    graphdef, params = models.init(0, "resnet_md_tiny")
    x = np.random.default_rng(0).uniform(size=(1, 64, 128, 6)).astype(np.float32)
    a = jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x)
    b = jax.jit(lambda p, x: models.apply(graphdef, p, x, dtype=jnp.bfloat16))(params, x)
    assert b["px"][0].dtype == jnp.float32
    assert jax.tree.leaves(params)[0].dtype == jnp.float32
    np.testing.assert_allclose(b["frac"][0], a["frac"][0], atol=2e-2)


# ---------------------------------------------------------------- PWC-Net


def np_correlation(f1, f2, d):
    n, h, w, c = f1.shape
    f2p = np.pad(f2, ((0, 0), (d, d), (d, d), (0, 0)))
    out = np.zeros((n, h, w, (2 * d + 1) ** 2))
    for y in range(h):
        for x in range(w):
            for dy in range(-d, d + 1):
                for dx in range(-d, d + 1):
                    out[:, y, x, (dy + d) * (2 * d + 1) + dx + d] = (
                        f1[:, y, x] * f2p[:, y + d + dy, x + d + dx]).sum(-1) / c
    return out


def test_correlation_matches_numpy(rng):
    f1 = rng.normal(size=(2, 6, 7, 5))
    f2 = rng.normal(size=(2, 6, 7, 5))
    np.testing.assert_allclose(pwcnet.correlation(f32(f1), f32(f2), 2), np_correlation(f1, f2, 2), rtol=1e-4,
                               atol=1e-5)


@pytest.mark.parametrize("width,d", [(37, 4), (16, 4), (3, 4), (33, 2)])
def test_correlation_blocks_match_numpy_at_any_width(rng, width, d):
    # Widths above pwcnet.CORRELATION_TILE run in column blocks with a zero-padded last block (37, 33), one
    # block (16), and a map narrower than the search window (3): each must give the plain definition.
    f1 = rng.normal(size=(2, 3, width, 4))
    f2 = rng.normal(size=(2, 3, width, 4))
    np.testing.assert_allclose(pwcnet.correlation(f32(f1), f32(f2), d), np_correlation(f1, f2, d), rtol=1e-4,
                               atol=1e-5)


def test_correlation_gradient_matches_numpy_at_block_width(rng):
    # d/df1[y, x, c] = sum_k cot[y, x, k] f2[y+dy, x+dx, c] / C, d/df2 the same scattered back (linear: exact).
    d, (h, w, c) = 2, (3, 37, 4)
    f1, f2 = rng.normal(size=(1, h, w, c)), rng.normal(size=(1, h, w, c))
    cot = rng.normal(size=(1, h, w, (2 * d + 1) ** 2))
    g1, g2 = jax.grad(lambda a, b: jnp.sum(pwcnet.correlation(a, b, d) * f32(cot)), argnums=(0, 1))(f32(f1), f32(f2))
    f2p = np.pad(f2, ((0, 0), (d, d), (d, d), (0, 0)))
    want1, want2p = np.zeros_like(f1), np.zeros_like(f2p)
    for y in range(h):
        for x in range(w):
            for dy in range(-d, d + 1):
                for dx in range(-d, d + 1):
                    g = cot[0, y, x, (dy + d) * (2 * d + 1) + dx + d] / c
                    want1[0, y, x] += g * f2p[0, y + d + dy, x + d + dx]
                    want2p[0, y + d + dy, x + d + dx] += g * f1[0, y, x]
    np.testing.assert_allclose(g1, want1, rtol=1e-4, atol=1e-5)
    np.testing.assert_allclose(g2, want2p[:, d:-d, d:-d], rtol=1e-4, atol=1e-5)


def test_correlation_gradient_matches_finite_difference(rng):
    f1 = f32(rng.normal(size=(1, 4, 5, 3)))
    f2 = f32(rng.normal(size=(1, 4, 5, 3)))
    cot = f32(rng.normal(size=(1, 4, 5, 9)))
    fn = lambda a, b: jnp.sum(pwcnet.correlation(a, b, 1) * cot)  # noqa: E731
    g1, g2 = jax.grad(fn, argnums=(0, 1))(f1, f2)
    # analytic: d/df1[y,x,c] = sum_k cot[y,x,k] f2[y+dy,x+dx,c] / C (linear, so exact)
    e = np.zeros(f1.shape, np.float32)
    e[0, 2, 3, 1] = 1.0
    fd = (fn(f1 + e, f2) - fn(f1, f2))
    np.testing.assert_allclose(float(fd), float(g1[0, 2, 3, 1]), rtol=1e-3)
    fd2 = (fn(f1, f2 + e) - fn(f1, f2))
    np.testing.assert_allclose(float(fd2), float(g2[0, 2, 3, 1]), rtol=1e-3)


def test_pwc_warp_and_resize_match_numpy(rng):
    x = rng.normal(size=(1, 5, 6, 2))
    flow = rng.uniform(-2, 2, size=(1, 5, 6, 2))
    out = np.asarray(pwcnet.warp_zero(f32(x), f32(flow)))
    for (y, xx) in [(0, 0), (2, 3), (4, 5), (1, 2)]:
        px, py = xx + flow[0, y, xx, 0], y + flow[0, y, xx, 1]
        x0, y0 = int(np.floor(px)), int(np.floor(py))
        if 0 <= x0 and x0 + 1 <= 5 and 0 <= y0 and y0 + 1 <= 4:
            ax, ay = px - x0, py - y0
            ref = ((1 - ay) * ((1 - ax) * x[0, y0, x0] + ax * x[0, y0, x0 + 1])
                   + ay * ((1 - ax) * x[0, y0 + 1, x0] + ax * x[0, y0 + 1, x0 + 1]))
        else:
            ref = np.zeros(2)  # footprint leaves the image: masked like upstream
        np.testing.assert_allclose(out[0, y, xx], ref, rtol=1e-4, atol=1e-5)
    # align_corners=True resize: corners preserved, a linear ramp stays linear
    ramp = np.arange(4, dtype=np.float64)[None, None, :, None] * np.ones((1, 3, 4, 1))
    up = np.asarray(pwcnet.resize_bilinear_align_corners(f32(ramp), (6, 10)))
    np.testing.assert_allclose(up[0, 0, :, 0], np.linspace(0, 3, 10), rtol=1e-5, atol=1e-6)


def test_pwcnet_shapes():
    cfg = models.model_config("pwcnet", md=1, pyramid=[4, 4, 8, 8, 8, 8], estimator=[8, 8, 8, 8, 8],
                              context=[8, 8, 8, 8, 8, 8])
    graphdef, params = models.init(0, cfg)
    x = np.random.default_rng(0).uniform(size=(1, 64, 128, 6)).astype(np.float32)
    out = jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x)
    for s in range(4):
        assert out["px"][s].shape == (1, 64 >> s, 128 >> s, 2)
        np.testing.assert_allclose(out["frac"][s] * np.array([128 >> s, 64 >> s]), out["px"][s], rtol=1e-5,
                                   atol=1e-6)


@pytest.mark.slow
def test_pwcnet_gradient_finite():
    cfg = models.model_config("pwcnet", md=1, pyramid=[4, 4, 8, 8, 8, 8], estimator=[8, 8, 8, 8, 8],
                              context=[8, 8, 8, 8, 8, 8])
    graphdef, params = models.init(0, cfg)
    x = np.random.default_rng(0).uniform(size=(1, 64, 128, 6)).astype(np.float32)

    def loss(p):
        m = models.apply(graphdef, p, x)
        return sum(jnp.mean(jnp.abs(v)) for v in m["px"])

    grads = jax.jit(jax.grad(loss))(params)
    leaves = jax.tree.leaves(grads)
    assert all(np.isfinite(np.asarray(g)).all() for g in leaves)
    assert float(np.abs(np.asarray(grads["conv1a"]["conv"]["kernel"])).max()) > 0  # flows to the pyramid


@pytest.mark.parametrize("warp", ["upstream", "pixels"])
def test_pwcnet_warp_modes_use_the_documented_flow(warp, monkeypatch):
    """Level l warps image_b's features by deconv(flow_{l+1}) * 20/2^l (upstream) or by the level-(l+1) flow
    upsampled 2x and doubled (pixels: the motion the loss trains, in level-l pixels). Recorded per level and
    compared with the formula, the upsampling done in numpy."""
    cfg = models.model_config("pwcnet", md=1, pyramid=[4, 4, 8, 8, 8, 8], estimator=[8, 8, 8, 8, 8],
                              context=[8, 8, 8, 8, 8, 8], warp=warp)
    model = nnx.merge(*models.init(0, cfg))
    # Non-zero flows at every level: random heads would already give them; add a bias to be sure.
    for lvl in range(2, 7):
        head = getattr(model, f"predict_flow{lvl}")
        head.bias[...] = jnp.array([0.7, -0.4]) * lvl
    flows, warps = {}, []
    estimate = model._estimate

    def record_estimate(lvl, x):
        x, flow = estimate(lvl, x)
        flows[lvl] = np.asarray(flow, np.float64)
        return x, flow

    real_warp = pwcnet.warp_zero
    monkeypatch.setattr(model, "_estimate", record_estimate)
    monkeypatch.setattr(pwcnet, "warp_zero", lambda x, f: (warps.append(np.asarray(f, np.float64)), real_warp(x, f))[1])
    pair = np.random.default_rng(3).uniform(size=(1, 64, 128, 6)).astype(np.float32)
    model(jnp.asarray(pair))
    assert len(warps) == 4  # levels 5, 4, 3, 2
    for lvl, got in zip(range(5, 1, -1), warps):
        coarse = flows[lvl + 1]
        if warp == "pixels":
            h, w = got.shape[1:3]
            hc, wc = coarse.shape[1:3]
            # align_corners bilinear upsampling in numpy
            ys = np.arange(h) * ((hc - 1) / (h - 1) if h > 1 else 0.0)
            xs = np.arange(w) * ((wc - 1) / (w - 1) if w > 1 else 0.0)
            y0 = np.minimum(np.floor(ys).astype(int), max(hc - 2, 0))
            x0 = np.minimum(np.floor(xs).astype(int), max(wc - 2, 0))
            y1 = np.minimum(y0 + 1, hc - 1)
            x1 = np.minimum(x0 + 1, wc - 1)
            wy = (ys - y0)[:, None, None]
            wx = (xs - x0)[None, :, None]
            c = coarse[0]
            up = ((1 - wy) * ((1 - wx) * c[y0][:, x0] + wx * c[y0][:, x1])
                  + wy * ((1 - wx) * c[y1][:, x0] + wx * c[y1][:, x1]))
            want = 2.0 * up[None]
        else:
            want = np.asarray(getattr(model, f"deconv{lvl + 1}")(jnp.asarray(coarse, jnp.float32))) * 20.0 / 2 ** lvl
        np.testing.assert_allclose(got, want, rtol=1e-4, atol=1e-5, err_msg=f"level {lvl}")
    assert np.abs(warps[-1]).max() > 0.1  # a real (non-zero) warp was compared


def test_pwcnet_rejects_unknown_warp():
    with pytest.raises(ValueError, match="warp"):
        models.model_config("pwcnet", warp="bilinear")


def test_pwcnet_full_size_shapes():
    graphdef, params = models.abstract_init("pwcnet")
    out = jax.eval_shape(lambda p, x: models.apply(graphdef, p, x), params,
                         jax.ShapeDtypeStruct((1, 256, 832, 6), jnp.float32))
    assert [o.shape for o in out["px"]] == [(1, 256 >> s, 832 >> s, 2) for s in range(4)]


def test_subpixel_upconv_same_maps():
    """The low-resolution (sub-pixel) decoder path gives the same maps as literal upsample-then-conv."""
    x = np.random.default_rng(2).uniform(size=(1, 64, 128, 6)).astype(np.float32)
    outs = []
    for sub in (True, False):
        graphdef, params = models.init(0, models.model_config("resnet_md_tiny", subpixel_upconv=sub))
        outs.append(jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x))
    for s in range(4):
        np.testing.assert_allclose(outs[0]["frac"][s], outs[1]["frac"][s], atol=1e-5)


# ---------------------------------------------------------------- head_init


@pytest.mark.parametrize("cfg", [
    {"name": "resnet_md_tiny"},
    pytest.param({"name": "pwcnet", "pyramid": [4, 4, 4, 4, 4, 4], "estimator": [4, 4, 4, 4, 4],
                  "context": [4, 4, 4, 4, 4, 4]}, marks=pytest.mark.slow),  # the same head rule, compiled for pwcnet
])
def test_head_init_zeros_starts_at_zero_motion(cfg):
    """head_init="zeros": only the output convs differ from the default draw, and every map is exactly 0
    (0.3 tanh(0) = 0 for resnet_md; 4 x resize(0) = 0 for PWC-Net) while the default init is not."""
    _, p_default = models.init(3, cfg)
    graphdef, p_zero = models.init(3, dict(cfg, head_init="zeros"))
    heads = resnet_md.HEAD_PREFIXES if cfg["name"].startswith("resnet_md") else pwcnet.HEAD_PREFIXES
    n_head = 0
    for name in p_default:
        a, b = jax.tree.leaves(p_default[name]), jax.tree.leaves(p_zero[name])
        if name.startswith(heads):
            n_head += 1
            assert all(float(jnp.abs(x).max()) == 0.0 for x in b), name
        else:
            assert all(np.array_equal(x, y) for x, y in zip(a, b)), name
    assert n_head == (4 if cfg["name"].startswith("resnet_md") else 6)
    x = jax.random.uniform(jax.random.key(0), (2, 64, 128, 6))
    maps = models.apply(graphdef, p_zero, x)
    assert all(float(jnp.abs(m).max()) == 0.0 for m in maps["px"] + maps["frac"])
    maps = models.apply(graphdef, p_default, x)
    assert float(jnp.abs(maps["px"][0]).max()) > 0.01
    # the zero heads still receive gradients, so training can move them
    g = jax.grad(lambda p: jnp.sum(models.apply(graphdef, p, x)["px"][0] * x[..., :2]))(p_zero)
    assert any(float(jnp.abs(v).max()) > 0 for k in p_zero if k.startswith(heads) for v in jax.tree.leaves(g[k]))


def test_head_init_rejects_unknown_value():
    with pytest.raises(ValueError, match="head_init"):
        models.model_config("resnet_md_tiny", head_init="xavier")
    with pytest.raises(ValueError, match="head_init"):
        models.model_config("pwcnet", head_init="torch")


def np_weight_grad(x, g, k_shape, stride, pad, dilation):
    """dW[i, j] = sum_{n, o} xpad[n, s*o + d*(i, j)]^T g[n, o], float64, padding ((top, bottom), (left, right))."""
    xp = np.pad(x, ((0, 0), pad[0], pad[1], (0, 0)))
    dk = np.zeros(k_shape)
    for i, j, patch in np_tap_views(xp, k_shape[:2], g.shape[1:3], stride, dilation):
        dk[i, j] = np.einsum("nhwc,nhwo->co", patch, g)
    return dk


@pytest.mark.parametrize("method", ["shift_dy", "shift_x", "xla_chunks"])
@pytest.mark.parametrize("kernel,stride,pad,dilation", [
    (3, 1, ((1, 1), (1, 1)), 1), (3, 2, ((1, 1), (1, 1)), 1), (3, 1, ((2, 2), (2, 2)), 2),
    (2, 1, ((1, 0), (0, 1)), 1),  # a sub-pixel phase: asymmetric padding
    (7, 2, ((3, 3), (3, 3)), 1), (3, 2, ((0, 2), (1, 0)), 1)])
def test_weight_grad_methods_match_the_float64_definition(rng, method, kernel, stride, pad, dilation):
    """Each weight-gradient formulation of `layers.conv_nhwc` gives the numpy float64 dW, and the forward and
    the input gradient stay XLA's (the same as method "xla")."""
    x = rng.standard_normal((3, 9, 11, 5))  # 3 rows: xla_chunks sums a chunk of 2 and one of 1
    k = rng.standard_normal((kernel, kernel, 5, 4))
    with layers.weight_grad_method("xla"):
        y = layers.conv_nhwc(f32(x), f32(k), stride, pad, dilation)
    g = rng.standard_normal(y.shape)

    def f(a, b):
        return jnp.sum(layers.conv_nhwc(a, b, stride, pad, dilation) * f32(g))

    with layers.weight_grad_method(method):
        jaxpr = str(jax.make_jaxpr(jax.grad(f, argnums=(0, 1)))(f32(x), f32(k)))
        dx, dk = jax.grad(f, argnums=(0, 1))(f32(x), f32(k))
    with layers.weight_grad_method("xla"):
        jaxpr_xla = str(jax.make_jaxpr(jax.grad(f, argnums=(0, 1)))(f32(x), f32(k)))
    # the method is really in use: matmuls, or one backward convolution per chunk, instead of XLA's one
    if method == "xla_chunks":
        assert jaxpr.count("conv_general_dilated") > jaxpr_xla.count("conv_general_dilated")
    else:
        assert "dot_general" in jaxpr and "dot_general" not in jaxpr_xla
    with layers.weight_grad_method("xla"):
        dx_xla, dk_xla = jax.grad(f, argnums=(0, 1))(f32(x), f32(k))
    dk_ref = np_weight_grad(x, g, k.shape, stride, pad, dilation)
    np.testing.assert_allclose(np.asarray(dk), dk_ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_allclose(np.asarray(dk_xla), dk_ref, rtol=1e-4, atol=1e-4)
    np.testing.assert_array_equal(np.asarray(dx), np.asarray(dx_xla))


def test_weight_grad_shift_dy_is_exact_in_float64(rng):
    """In float64 the shifted-dy matmuls equal the definition to rounding (1e-12), so the float32 differences
    to XLA are summation order only."""
    with jax.enable_x64(True):
        x = rng.standard_normal((2, 8, 10, 6))
        g = rng.standard_normal((2, 4, 5, 3))
        dk = layers.weight_grad_shift_dy(jnp.asarray(x), jnp.asarray(g), (3, 3, 6, 3), 2, ((1, 1), (1, 1)))
        assert dk.dtype == jnp.float64
        np.testing.assert_allclose(np.asarray(dk), np_weight_grad(x, g, (3, 3, 6, 3), 2, ((1, 1), (1, 1)), 1),
                                   rtol=1e-12, atol=1e-12)


def test_auto_weight_grad_uses_shift_dy_only_where_measured_faster(monkeypatch):
    """"auto" on CPU: shift_dy for stride-1 convs with >= SHIFT_DY_MIN_CHANNELS input channels, chunks of XLA's
    for the 7x7 stem on the image pair when the batch is larger than a chunk, else XLA's; on other backends
    always XLA's. Unknown names are refused."""
    r = layers.resolve_weight_grad
    n = layers.SHIFT_DY_MIN_CHANNELS
    monkeypatch.setattr(layers, "cpu_vector_isa", lambda: "AVX-512")
    with layers.weight_grad_method("auto"):
        assert r((2, 32, 64, n), (3, 3, n, 8), 1) == "shift_dy"
        assert r((2, 32, 64, n - 1), (3, 3, n - 1, 8), 1) == "xla"
        assert r((2, 32, 64, n), (3, 3, n, 8), 2) == "xla"
        assert r((16, 256, 512, 6), (7, 7, 6, 64), 2) == "xla_chunks"
        assert r((2, 256, 512, 6), (7, 7, 6, 64), 2) == "xla"  # one chunk: nothing to split
        assert r((16, 64, 128, 6), (3, 3, 6, 16), 1) == "xla"
        monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
        assert r((2, 32, 64, n), (3, 3, n, 8), 1) == "xla"
    assert r((2, 32, 64, 8), (3, 3, 8, 8), 2, "shift_x") == "shift_x"
    with pytest.raises(ValueError, match="conv_weight_grad must be one of"):
        with layers.weight_grad_method("fast"):
            pass


@pytest.mark.parametrize("isa", ["AVX2", "older"])
def test_auto_weight_grad_without_avx512_shifts_x_at_stride_2(monkeypatch, isa):
    """Without AVX-512, "auto" picks "shift_x" for strided convs from SHIFT_X_MIN_CHANNELS input channels and for
    the 7x7 stem at any batch (the AVX2 measurements); stride 1 and narrow strided convs keep the AVX-512 rule."""
    r = layers.resolve_weight_grad
    m = layers.SHIFT_X_MIN_CHANNELS
    monkeypatch.setattr(layers, "cpu_vector_isa", lambda: isa)
    with layers.weight_grad_method("auto"):
        assert r((16, 64, 128, 128), (3, 3, 128, 128), 2) == "shift_x"
        assert r((2, 32, 64, m), (3, 3, m, 8), 2) == "shift_x"
        assert r((2, 32, 64, m - 1), (3, 3, m - 1, 8), 2) == "xla"  # pwc_lite's narrow pyramid convs
        assert r((16, 256, 512, 6), (7, 7, 6, 64), 2) == "shift_x"
        assert r((2, 256, 512, 6), (7, 7, 6, 64), 2) == "shift_x"
        assert r((2, 32, 64, m), (3, 3, m, 8), 1) == "shift_dy"
        assert r((16, 256, 512, 18), (3, 3, 18, 16), 1) == "xla"
        monkeypatch.setattr(jax, "default_backend", lambda: "gpu")
        assert r((16, 64, 128, 128), (3, 3, 128, 128), 2) == "xla"
    monkeypatch.setattr(layers, "cpu_vector_isa", lambda: None)  # unknown CPU: the AVX-512 rule
    with layers.weight_grad_method("auto"):
        assert r((16, 64, 128, 128), (3, 3, 128, 128), 2) == "xla"


def test_cpu_vector_isa_reads_the_flags(monkeypatch, tmp_path):
    """AVX-512 when avx512f is listed, AVX2 with avx2 only, older without either; None without the file."""
    import builtins
    real_open = builtins.open
    for flags, want in (("fpu sse2 avx avx2 avx512f avx512bw", "AVX-512"), ("fpu sse2 avx avx2 fma", "AVX2"),
                        ("fpu sse2", "older"), (None, None)):
        path = tmp_path / "cpuinfo"
        if flags is None:
            path.unlink(missing_ok=True)
        else:
            path.write_text(f"processor\t: 0\nmodel name\t: Test CPU\nflags\t\t: {flags}\n")
        monkeypatch.setattr(builtins, "open", lambda f, *a, **k: real_open(path if f == "/proc/cpuinfo" else f,
                                                                            *a, **k))
        layers.cpu_vector_isa.cache_clear()
        try:
            assert layers.cpu_vector_isa() == want, flags
        finally:
            monkeypatch.setattr(builtins, "open", real_open)
            layers.cpu_vector_isa.cache_clear()


def test_im2col_conv_path_matches_numpy(rng, monkeypatch):
    """The small-map / many-channel im2col path of conv2d (forced here) equals the float64 definition."""
    monkeypatch.setattr(layers, "IM2COL_MIN_CHANNELS", 1)
    x = rng.standard_normal((2, 5, 7, 6))
    k = rng.standard_normal((3, 3, 6, 4))
    assert layers._use_im2col(x.shape, k.shape, 1, 1)
    np.testing.assert_allclose(np.asarray(layers.conv2d(f32(x), f32(k))), np_conv(x, k), atol=1e-4)


def test_working_size_check_names_the_option_and_a_size_that_fits():
    with pytest.raises(ValueError, match=r"^--height/--width 64x100: .* multiples of 64 for model "
                                         r"resnet_md \(try 64x128\)$"):
        models.check_working_size("resnet_md", 64, 100, "--height/--width")
    # nearest multiples, halves rounded up: 100/64 → 2·64, 200/64 → 3·64, 20/8 = 2.5 → 3·8
    with pytest.raises(ValueError, match=r"multiples of 64 for model resnet_md \(try 128x192\)"):
        models.check_working_size("resnet_md", 100, 200, "--working-size")
    with pytest.raises(ValueError, match=r"multiples of 8 for model pwc_lite \(try 48x104\)"):
        models.check_working_size("pwc_lite", 44, 100, "--working-size")
    # pwc_lite also needs 3 pyramid levels (at least 32x64): the suggestion is a size that works
    with pytest.raises(ValueError, match=r"multiples of 8 for model pwc_lite \(try 32x64\)"):
        models.check_working_size("pwc_lite", 12, 20, "--working-size")
    with pytest.raises(ValueError, match=r"^--working-size 16x24: working size 16x24 .* too small "
                                         r"for pwc_lite"):
        models.check_working_size("pwc_lite", 16, 24, "--working-size")
    models.check_working_size("resnet_md", 128, 192, "--working-size")      # fine: no error


def test_abstract_init_is_memoised_per_config():
    """The second call with an equal config (name or mapping) reuses the abstract build; another config does
    not; callers get their own dict (mutating it does not reach the memo)."""
    g1, p1 = models.abstract_init("pwc_lite")
    g2, p2 = models.abstract_init(models.model_config("pwc_lite"))
    assert g1 is g2 and p1 == p2 and p1 is not p2
    p2.clear()
    assert models.abstract_init("pwc_lite")[1] == p1
    narrow = dict(models.model_config("pwc_lite"), feature_width=16)
    g3, p3 = models.abstract_init(narrow)
    assert g3 is not g1 and p3 != p1
    assert any(a.shape[-1] == 16 for a in jax.tree.leaves(p3))
