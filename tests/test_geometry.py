"""geometry.py against an independent float64 numpy sampler and hand-built cases."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import geometry
from bridge_jax.models import layers


def np_warp(img, disp):
    """Reference: bilinear sample of img (H, W, C) at (x + dx, y + dy); corner indices clamped, weights unclamped."""
    h, w, _ = img.shape
    ys, xs = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    px = xs + disp[..., 0]
    py = ys + disp[..., 1]
    x0 = np.floor(px).astype(int)
    y0 = np.floor(py).astype(int)
    ax = (px - x0)[..., None]
    ay = (py - y0)[..., None]
    cx0, cx1 = np.clip(x0, 0, w - 1), np.clip(x0 + 1, 0, w - 1)
    cy0, cy1 = np.clip(y0, 0, h - 1), np.clip(y0 + 1, 0, h - 1)
    return ((1 - ay) * ((1 - ax) * img[cy0, cx0] + ax * img[cy0, cx1])
            + ay * ((1 - ax) * img[cy1, cx0] + ax * img[cy1, cx1]))


@pytest.mark.parametrize("kind", ["subpixel", "integer", "out_of_image"])
def test_warp_matches_numpy_reference(rng, kind):
    h, w = 12, 20
    img = rng.uniform(size=(2, h, w, 3))
    if kind == "subpixel":
        disp = rng.uniform(-3, 3, size=(2, h, w, 2))
    elif kind == "integer":
        disp = rng.integers(-4, 5, size=(2, h, w, 2)).astype(np.float64)
    else:
        disp = rng.uniform(-3, 3, size=(2, h, w, 2)) + rng.choice([-2 * w, 0, 2 * w], size=(2, h, w, 1))
    out = geometry.warp(jnp.asarray(img, jnp.float32), jnp.asarray(disp, jnp.float32))
    ref = np.stack([np_warp(img[i], disp[i]) for i in range(2)])
    np.testing.assert_allclose(out, ref, atol=1e-5)


def test_warp_identity_and_integer_shift(rng):
    img = rng.uniform(size=(1, 16, 24, 3)).astype(np.float32)
    np.testing.assert_array_equal(geometry.warp(img, np.zeros((1, 16, 24, 2), np.float32)), img)
    shifted = np.roll(img, 3, axis=2)  # shifted(x) = img(x - 3)
    d = np.zeros((1, 16, 24, 2), np.float32)
    d[..., 0] = 3.0  # sample shifted at x + 3 -> img(x)
    out = np.asarray(geometry.warp(shifted, d))
    np.testing.assert_array_equal(out[:, :, :-3], img[:, :, :-3])
    # past the right border the last column is replicated
    np.testing.assert_array_equal(out[:, :, -3:], np.repeat(shifted[:, :, -1:], 3, axis=2))


def test_warp_gradient_finite_differences(rng):
    h, w = 8, 10
    img = rng.uniform(size=(1, h, w, 2))
    disp = rng.uniform(-2.5, 2.5, size=(1, h, w, 2))
    disp = np.where(np.abs(disp - np.round(disp)) < 0.05, disp + 0.1, disp)  # stay away from integers
    cot = rng.normal(size=(1, h, w, 2))
    with jax.enable_x64(True):
        f = lambda d: jnp.sum(geometry.warp(jnp.asarray(img), d) * cot)
        g = np.asarray(jax.grad(f)(jnp.asarray(disp)))
        eps = 1e-6
        for idx in [(0, 3, 4, 0), (0, 5, 2, 1), (0, 0, 0, 0), (0, 7, 9, 1)]:
            e = np.zeros_like(disp)
            e[idx] = eps
            fd = (f(jnp.asarray(disp + e)) - f(jnp.asarray(disp - e))) / (2 * eps)
            assert abs(float(fd) - g[idx]) < 1e-6 * max(1.0, abs(g[idx]))
    # float32 gradient finite everywhere, also far outside and exactly on integer positions
    d = np.concatenate([rng.uniform(-50, 50, (1, h, w // 2, 2)), np.round(rng.uniform(-3, 3, (1, h, w // 2, 2)))], 2)
    g32 = jax.grad(lambda d: jnp.sum(geometry.warp(jnp.asarray(img, jnp.float32), d)))(jnp.asarray(d, jnp.float32))
    assert np.isfinite(np.asarray(g32)).all()


def test_warp_bad_shapes():
    with pytest.raises(ValueError, match="disp_px"):
        geometry.warp(jnp.zeros((1, 8, 8, 3)), jnp.zeros((1, 8, 8, 3)))
    with pytest.raises(ValueError, match="spatial size"):
        geometry.warp(jnp.zeros((1, 8, 8, 3)), jnp.zeros((1, 8, 4, 2)))


def test_cubic_warp_matches_opencv_inter_cubic(rng):
    """With OpenCV's kernel parameter (a = -0.75) the cubic warp is cv2.remap(INTER_CUBIC, BORDER_REPLICATE), an
    independent implementation, at positions on OpenCV's 1/32 px interpolation grid (where its table is exact)
    and inside the image (outside it the two clamp differently: ours reads the border pixel itself)."""
    import cv2
    h, w = 23, 31
    img = rng.random((h, w, 3)).astype(np.float32)
    d = (rng.integers(-96, 97, (h, w, 2)) / 32.0).astype(np.float32)
    ys, xs = np.mgrid[:h, :w].astype(np.float32)
    mx, my = xs + d[..., 0], ys + d[..., 1]
    ref = cv2.remap(img, mx, my, cv2.INTER_CUBIC, borderMode=cv2.BORDER_REPLICATE)
    out = np.asarray(geometry.warp_cubic(jnp.asarray(img)[None], jnp.asarray(d)[None], a=-0.75))[0]
    inside = (mx >= 0) & (mx <= w - 1) & (my >= 0) & (my <= h - 1)
    assert inside.mean() > 0.7
    np.testing.assert_allclose(out[inside], ref[inside], atol=2e-5)


def test_cubic_warp_reproduces_quadratics_and_whole_pixel_shifts(rng):
    """Keys' kernel at a = -0.5 reproduces a quadratic exactly (derived by hand: its weights' first and second
    moments about the sample point are 0 and match a quadratic's Taylor terms), so an image q(x, y) sampled
    anywhere at least 1 px inside the border gives q there; a whole-pixel shift is a plain copy; a position
    outside the image reads the border pixel, as the bilinear warp does."""
    h, w = 20, 26
    ys, xs = np.mgrid[:h, :w].astype(np.float64)
    q = lambda x, y: 0.3 + 0.02 * x - 0.01 * y + 0.004 * x * x - 0.003 * x * y + 0.002 * y * y  # noqa: E731
    img = q(xs, ys).astype(np.float32)[..., None]
    d = rng.uniform(-2.0, 2.0, (h, w, 2)).astype(np.float32)
    out = np.asarray(geometry.warp_cubic(jnp.asarray(img)[None], jnp.asarray(d)[None]))[0, ..., 0]
    px, py = xs + d[..., 0], ys + d[..., 1]
    inner = (px >= 1) & (px <= w - 2) & (py >= 1) & (py <= h - 2)
    np.testing.assert_allclose(out[inner], q(px, py)[inner], atol=1e-5)
    # bilinear sampling does not: its error on the same quadratic is the curvature times t(1 - t) / 2
    lin = np.asarray(geometry.warp(jnp.asarray(img)[None], jnp.asarray(d)[None]))[0, ..., 0]
    assert np.abs(lin - q(px, py))[inner].max() > 1e-3

    shift = np.zeros((h, w, 2), np.float32)
    shift[..., 0], shift[..., 1] = 2.0, -1.0
    img3 = rng.random((h, w, 2)).astype(np.float32)
    out = np.asarray(geometry.warp_cubic(jnp.asarray(img3)[None], jnp.asarray(shift)[None]))[0]
    np.testing.assert_allclose(out[1:, :w - 2], img3[:h - 1, 2:], atol=1e-6)

    far = np.zeros((h, w, 2), np.float32)
    far[..., 0] = -40.0  # every match left of the image: column 0 of the same row
    out = np.asarray(geometry.warp_cubic(jnp.asarray(img3)[None], jnp.asarray(far)[None]))[0]
    np.testing.assert_allclose(out, np.broadcast_to(img3[:, :1], img3.shape), atol=1e-6)
    with pytest.raises(ValueError, match="disp_px"):
        geometry.warp_cubic(jnp.zeros((1, 4, 5, 1)), jnp.zeros((1, 4, 6, 2)))


def test_frac_px_conversion():
    frac = jnp.ones((2, 4, 8, 2)) * jnp.array([0.25, -0.5])
    px = geometry.frac_to_px(frac)
    np.testing.assert_allclose(px[0, 0, 0], [2.0, -2.0])  # 0.25 * W=8, -0.5 * H=4
    np.testing.assert_allclose(geometry.px_to_frac(px), frac)


def test_pyramid_and_upsample():
    x = jnp.arange(2 * 16 * 8 * 1, dtype=jnp.float32).reshape(2, 16, 8, 1)
    pyr = geometry.image_pyramid(x)
    assert [p.shape for p in pyr] == [(2, 16, 8, 1), (2, 8, 4, 1), (2, 4, 2, 1), (2, 2, 1, 1)]
    # x2 downscale of a horizontal ramp away from the border = the mean of the 4 central taps (1/8,3/8,3/8,1/8)
    # (a quadratic separates these Pillow-style taps from a 2x2 box average: 43 vs 42.5)
    sq = jnp.tile((jnp.arange(16, dtype=jnp.float32) ** 2)[None, :, None], (8, 1, 1))
    half = geometry.resize_bilinear(sq, (4, 8))
    np.testing.assert_allclose(half[0, 3, 0], (1 * 25 + 3 * 36 + 3 * 49 + 1 * 64) / 8, rtol=1e-6)
    up = layers.upsample_nearest2x(jnp.array([[[[1.0], [2.0]]]]))
    np.testing.assert_array_equal(up[0, :, :, 0], [[1, 1, 2, 2], [1, 1, 2, 2]])
    with pytest.raises(ValueError, match="divisible by 8"):
        geometry.image_pyramid(jnp.zeros((1, 12, 16, 3)))


def test_align_corners_resize_matches_numpy():
    rng = np.random.default_rng(1)
    x = rng.uniform(size=(5, 7, 2)).astype(np.float32)
    out = np.asarray(geometry.resize_bilinear_align_corners(jnp.asarray(x), (9, 13)))
    # independent: separable linear interpolation with numpy
    rows = np.stack([np.stack([np.interp(np.linspace(0, 6, 13), np.arange(7), x[i, :, c]) for c in range(2)], -1) for i in range(5)])
    ref = np.stack([np.stack([np.interp(np.linspace(0, 4, 9), np.arange(5), rows[:, j, c]) for c in range(2)], -1) for j in range(13)], 1)
    np.testing.assert_allclose(out, ref, atol=1e-5)
    np.testing.assert_allclose(out[0, 0], x[0, 0])
    np.testing.assert_allclose(out[-1, -1], x[-1, -1])


def test_border_mask_band():
    m = np.asarray(geometry.border_mask(32, 64))[..., 0]  # ceil(3.2) = 4 px on all four sides
    assert m[:4].sum() == 0 and m[-4:].sum() == 0 and m[:, :4].sum() == 0 and m[:, -4:].sum() == 0
    assert m[4:-4, 4:-4].all()


def test_occlusion_hand_built():
    """Forward map +3 px everywhere; the backward map agrees (-3) except in a block where the pixels of
    the second image do not map back (a region that disappeared): only that block's preimage is occluded."""
    h, w = 16, 32
    d_fw = np.zeros((1, h, w, 2), np.float32)
    d_fw[..., 0] = 3.0
    d_bw = np.zeros((1, h, w, 2), np.float32)
    d_bw[..., 0] = -3.0
    d_bw[:, 4:10, 14:20, 0] = 5.0  # inconsistent block in the second frame
    occ_fw, occ_bw = geometry.forward_backward_occlusion(d_fw, d_bw)
    occ_fw = np.asarray(occ_fw)[0, ..., 0]
    occ_bw = np.asarray(occ_bw)[0, ..., 0]
    # first-frame pixels x with x + 3 in [14, 20) land in the block: x in [11, 17)
    expected = np.zeros((h, w), bool)
    expected[4:10, 11:17] = True
    np.testing.assert_array_equal(occ_fw.astype(bool), expected)
    expect_bw = np.zeros((h, w), bool)
    expect_bw[4:10, 14:20] = True
    np.testing.assert_array_equal(occ_bw.astype(bool), expect_bw)
    # threshold: alpha1 * (9 + |W(D')|^2) + 0.5 -> a 0.7 px inconsistency passes, a 1 px one does not
    for err, occluded in ((0.7, False), (1.0, True)):
        occ, _ = geometry.forward_backward_occlusion(d_fw, -d_fw + np.array([err, 0.0], np.float32))
        assert bool(np.asarray(occ).all()) == occluded
    m_fw, _ = geometry.occlusion_mask(d_fw, d_bw)
    m_fw = np.asarray(m_fw)[0, ..., 0]
    np.testing.assert_allclose(m_fw[6, 12], 1e-3)  # occluded -> floor
    np.testing.assert_allclose(m_fw[6, 25], 1.001, rtol=1e-6)  # consistent interior
    np.testing.assert_allclose(m_fw[0, 25], 1e-3)  # border band


def test_occlusion_warped_vs_unwarped_norm():
    """The variants differ only in which |D'|^2 enters the threshold; a case that separates them.

    D = +2 everywhere, D' = -2.8 (a 0.8 px inconsistency, 0.64 px^2) except a large D' = 40 in columns 0..2.
    Pixel x=1 reads D' at x=3 (normal). Warped (paper): thr = 0.01 (4 + 2.8^2) + 0.5 = 0.618 < 0.64 ->
    occluded. Unwarped (upstream): thr = 0.01 (4 + 40^2) + 0.5 = 16.5 -> not occluded.
    """
    h, w = 8, 16
    d_fw = np.zeros((1, h, w, 2), np.float32)
    d_fw[..., 0] = 2.0
    d_bw = np.zeros((1, h, w, 2), np.float32)
    d_bw[..., 0] = -2.8
    d_bw[:, :, :3, 0] = 40.0
    occ_w = np.asarray(geometry.forward_backward_occlusion(d_fw, d_bw, warped_bw_norm=True)[0])[0, :, :, 0]
    occ_u = np.asarray(geometry.forward_backward_occlusion(d_fw, d_bw, warped_bw_norm=False)[0])[0, :, :, 0]
    assert occ_w[3, 1] == 1 and occ_u[3, 1] == 0
    assert occ_w[3, 8] == 1 and occ_u[3, 8] == 1  # both thresholds 0.618 away from the large block
