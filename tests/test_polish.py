"""Test-time photometric polish (`bridge_jax.polish`, `TestTime(polish=)`, `--polish`): the filters against
OpenCV, the local normalisation's invariances, the polish on sub-pixel translations of a smooth texture
(flow and stereo rows), matches near and beyond b's border, a textureless region, candidate selection and the
refinement on a hand-built bled motion boundary, the polish at the input size against the working size on a
hand-built whole-pixel motion, and the wiring into the predictor, the export, the cards and the command."""


import dataclasses

import cv2
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import export, inference, models, polish, zoo
from bridge_jax.inference import TestTime, WorkingSize
from bridge_jax.predict import ReducedImage
from tests.scenes import KnownMaps
from tests.test_symmetry import check_predict_option

H, W = 64, 96


def test_box_and_gaussian_filters_match_opencv(rng):
    x = rng.uniform(size=(2, 23, 31)).astype(np.float32)
    box = np.asarray(polish.box_filter(jnp.asarray(x), 3))
    gauss = np.asarray(polish.gaussian_filter(jnp.asarray(x), 1.5))
    for i in range(2):
        np.testing.assert_allclose(box[i], cv2.boxFilter(x[i], -1, (7, 7), borderType=cv2.BORDER_REFLECT_101),
                                   atol=1e-5)
        want = cv2.GaussianBlur(x[i], (7, 7), 1.5, borderType=cv2.BORDER_REFLECT_101)  # radius ceil(2 sigma) = 3
        np.testing.assert_allclose(gauss[i], want, atol=1e-5)


def test_gradients_of_a_ramp():
    """Central differences of 3x + 2y: (3, 2) inside; at the edges (replicated) half of that."""
    ys, xs = np.mgrid[:8, :10].astype(np.float32)
    gx, gy = (np.asarray(g[0]) for g in polish.gradients(jnp.asarray((3 * xs + 2 * ys)[None])))
    np.testing.assert_allclose(gx[:, 1:-1], 3.0, atol=1e-5)
    np.testing.assert_allclose(gy[1:-1], 2.0, atol=1e-5)
    np.testing.assert_allclose(gx[:, [0, -1]], 1.5, atol=1e-5)
    np.testing.assert_allclose(gy[[0, -1]], 1.0, atol=1e-5)


def test_local_normalisation_cancels_offset_and_gain(rng):
    """An offset cancels exactly; a gain cancels exactly without the contrast floor, and nearly with it on a
    textured image (the floor is small next to its contrast)."""
    g = jnp.asarray(rng.uniform(0.2, 0.6, size=(1, 30, 40)).astype(np.float32))
    n = polish.normalise_locally(g, floor=0.0)
    np.testing.assert_allclose(polish.normalise_locally(g + 0.25, floor=0.0), n, atol=1e-4)
    np.testing.assert_allclose(polish.normalise_locally(0.5 * g, floor=0.0), n, atol=1e-4)
    np.testing.assert_allclose(np.asarray(polish.normalise_locally(g + 0.25)), np.asarray(polish.normalise_locally(g)),
                               atol=1e-4)


def _texture(x, y):
    """A smooth grey texture in [0, 1] (sums of sinusoids of 9-23 px periods, no direction without texture)."""
    v = (np.sin(2 * np.pi * x / 17.0 + 0.3) + np.sin(2 * np.pi * y / 13.0 + 1.1)
         + 0.7 * np.sin(2 * np.pi * (x + y) / 23.0) + 0.5 * np.sin(2 * np.pi * (x - 2 * y) / 9.0 + 0.5))
    return 0.5 + v / 7.0


def _translated_pair(u: float, v: float) -> np.ndarray:
    """`(1, H, W, 6)` with b(x, y) = a(x - u, y - v): pixel (x, y) of a is found at (x + u, y + v) of b."""
    ys, xs = np.mgrid[:H, :W].astype(np.float64)
    a, b = _texture(xs, ys), _texture(xs - u, ys - v)
    return np.concatenate([np.repeat(a[..., None], 3, -1), np.repeat(b[..., None], 3, -1)], -1)[None].astype(
        np.float32)


@pytest.mark.parametrize("stereo", [False, True])
def test_polish_recovers_a_sub_pixel_translation(stereo):
    """From a zero map, a flow row finds (0.6, -0.3) and a stereo row the horizontal -1.4 with its vertical
    component kept at exactly 0. Away from the image border the mean error is a few hundredths of a pixel
    (bilinear resampling of the 9 px component biases the optimum by up to ~0.13 px), so a wrong sign, a
    swapped component or a missing step would show at once."""
    u, v = (-1.4, 0.0) if stereo else (0.6, -0.3)
    pairs = jnp.asarray(_translated_pair(u, v))
    flow_rows = jnp.asarray([0.0 if stereo else 1.0])
    out = np.asarray(polish.polish_maps(pairs, jnp.zeros((1, H, W, 2)), flow_rows))[0]
    err = np.abs(out[10:-10, 10:-10] - np.float32([u, v]))
    assert err.mean() < (0.01 if stereo else 0.04) and err.max() < (0.05 if stereo else 0.15), (err.mean(), err.max())
    if stereo:
        assert np.all(out[..., 1] == 0.0)


def test_cubic_sampling_removes_the_half_pixel_bias_of_bilinear():
    """At a half-pixel translation bilinear sampling blurs `b` the most (its weights are 1/2, 1/2), and a fit
    that compares a sharp window of `a` with that blurred one misreads the motion; cubic convolution keeps the
    detail (`PolishConfig.interpolation`). Measured on this texture: mean error 0.012 px bilinear, 0.005 cubic."""
    pairs = jnp.asarray(_translated_pair(0.5, 0.5))
    errors = {}
    for interpolation in polish.INTERPOLATIONS:
        out = np.asarray(polish.polish_maps(pairs, jnp.zeros((1, H, W, 2)), jnp.asarray([1.0]),
                                            polish.PolishConfig(interpolation=interpolation)))[0]
        errors[interpolation] = float(np.abs(out[10:-10, 10:-10] - np.float32([0.5, 0.5])).mean())
    assert errors["cubic"] < 0.008 and errors["cubic"] < 0.6 * errors["bilinear"], errors
    assert polish.DEFAULT_CONFIG.interpolation == "cubic"
    with pytest.raises(ValueError, match="interpolation"):
        polish.PolishConfig(interpolation="lanczos")


def _refine(pairs, maps, flow_rows=(1.0,)):
    grey_a, grey_b = pairs[..., :3].mean(-1), pairs[..., 3:].mean(-1)
    return np.asarray(polish.variational_fit(polish.normalise_locally(grey_a), grey_a, grey_b,
                                             jnp.asarray(maps), jnp.asarray(flow_rows)))[0]


def test_matches_near_and_beyond_the_border_of_b():
    """A translation of 8.4 px started from 8. Pixels whose match lies within 2-7 px of b's right border
    converge like the others: `b` is normalised after the warp, in `a`'s windows (normalised in its own frame,
    its windows there are reflected where `a`'s are not, and those pixels ended 0.21 px off). Pixels whose
    match lies outside b (the last 8 columns) have no data term and take their neighbours' motion; with border
    clamping as their data they would drift towards whatever the clamped column matches."""
    pairs = jnp.asarray(_translated_pair(8.4, 0.0))
    out = _refine(pairs, np.broadcast_to(np.float32([8.0, 0.0]), (1, H, W, 2)))
    near = np.abs(out[10:-10, W - 16:W - 11] - np.float32([8.4, 0.0]))  # matched at x + 8.4 in [W - 7.6, W - 2.6]
    assert near.mean() < 0.05, near.mean()
    beyond = np.abs(out[10:-10, W - 8:] - np.float32([8.4, 0.0]))  # matched at x + 8.4 > W - 1
    assert beyond.mean() < 0.05, beyond.mean()


def test_a_textureless_region_takes_its_neighbours_motion():
    """A flat disc (radius 14 px) in the textured image, the whole image translated by (2.3, -1.1). The map
    given is right outside the disc and (0, 0) inside: no window inside the disc sees texture and every
    candidate there costs the same, so no local step can move it, but the refinement's smoothness term carries
    the surrounding motion in (the disc's inside is flat, so no edge weight cuts it off)."""
    ys, xs = np.mgrid[:H, :W].astype(np.float64)
    u, v, cy, cx = 2.3, -1.1, 32.0, 48.0

    def image(x, y):
        return np.where((x - cx) ** 2 + (y - cy) ** 2 < 14 ** 2, 0.5, _texture(x, y))

    a, b = image(xs, ys), image(xs - u, ys - v)
    pairs = jnp.asarray(np.concatenate([np.repeat(a[..., None], 3, -1), np.repeat(b[..., None], 3, -1)], -1)[None],
                        jnp.float32)
    maps = np.broadcast_to(np.float32([u, v]), (1, H, W, 2)).copy()
    inner = (xs - cx) ** 2 + (ys - cy) ** 2 < 9 ** 2
    maps[0][(xs - cx) ** 2 + (ys - cy) ** 2 < 16 ** 2] = 0.0
    out = np.asarray(polish.polish_maps(pairs, jnp.asarray(maps), jnp.ones(1)))[0]
    err = np.linalg.norm(out - np.float32([u, v]), axis=-1)
    assert err[inner].mean() < 0.15, err[inner].mean()  # 0.05; 2.55 as given


def test_a_wide_textureless_region_needs_the_fit_s_outer_iterations():
    """As above with a flat disc of radius 24 px in a 96x128 image: the surrounding motion has to travel about
    20 px in, and each outer iteration of the fit (`PolishConfig.variational_warps`) carries it only so far
    (its robust smoothness weights, computed from the map it starts from, still see the old edge of the wrong
    values). Measured at smoothness weight 2 (a stronger smoothness carries it further per iteration): mean error
    inside 0.17 px after 5 outer iterations, 0.085 after the default 20; the exact answer is the translation
    itself."""
    h, w = 96, 128
    ys, xs = np.mgrid[:h, :w].astype(np.float64)
    u, v, cy, cx, radius = 2.3, -1.1, 48.0, 64.0, 24

    def image(x, y):
        return np.where((x - cx) ** 2 + (y - cy) ** 2 < radius ** 2, 0.5, _texture(x, y))

    a, b = image(xs, ys), image(xs - u, ys - v)
    pairs = jnp.asarray(np.concatenate([np.repeat(a[..., None], 3, -1), np.repeat(b[..., None], 3, -1)], -1)[None],
                        jnp.float32)
    maps = np.broadcast_to(np.float32([u, v]), (1, h, w, 2)).copy()
    maps[0][(xs - cx) ** 2 + (ys - cy) ** 2 < (radius + 2) ** 2] = 0.0
    inner = (xs - cx) ** 2 + (ys - cy) ** 2 < (radius - 5) ** 2
    errors = {}
    for warps in (5, polish.DEFAULT_CONFIG.variational_warps):
        config = polish.PolishConfig(variational_warps=warps, smoothness_weight=2.0)
        out = np.asarray(polish.polish_maps(pairs, jnp.asarray(maps), jnp.ones(1), config))[0]
        errors[warps] = float(np.linalg.norm(out - np.float32([u, v]), axis=-1)[inner].mean())
    assert errors[polish.DEFAULT_CONFIG.variational_warps] < 0.12 < 0.15 < errors[5], errors


def test_stereo_rows_stop_after_their_own_outer_iterations(rng):
    """In one batch, a stereo row runs `variational_warps_stereo` outer iterations and a flow row
    `variational_warps`: each row equals the same row polished alone with both counts set to its own."""
    pairs = jnp.asarray(_translated_pair(-1.4, 0.0).repeat(2, 0))
    maps = jnp.asarray(rng.normal(0.0, 1.0, (2, H, W, 2)).astype(np.float32))
    rows = jnp.asarray([0.0, 1.0])
    config = polish.PolishConfig(variational_warps=12, variational_warps_stereo=3)
    both = np.asarray(polish.polish_maps(pairs, maps, rows, config))
    for i, warps in ((0, 3), (1, 12)):
        alone = polish.PolishConfig(variational_warps=warps, variational_warps_stereo=warps)
        want = np.asarray(polish.polish_maps(pairs[i:i + 1], maps[i:i + 1], rows[i:i + 1], alone))[0]
        np.testing.assert_allclose(both[i], want, atol=1e-5)
    # a batch of stereo rows only is compiled with the stereo count for both (`config_for_rows`)
    assert polish.config_for_rows(config, np.zeros(2)) == polish.PolishConfig(variational_warps=3,
                                                                              variational_warps_stereo=3)
    assert polish.config_for_rows(config, np.asarray(rows)) == config
    other = polish.PolishConfig(variational_warps=3, variational_warps_stereo=3)
    assert np.abs(both[1] - np.asarray(polish.polish_maps(pairs[1:], maps[1:], rows[1:], other))[0]).max() > 1e-3
    with pytest.raises(ValueError, match="counts"):
        polish.PolishConfig(variational_warps_stereo=-1)


def test_each_row_kind_has_its_own_data_window(rng):
    """In one batch, a flow row's data term is windowed by `variational_sigma` and a stereo row's by
    `variational_sigma_stereo`: each row equals the same row polished alone with both windows set to its own, and
    differs from it polished with the other row's window. A batch of one kind is compiled with its kind's window
    only (`config_for_rows`)."""
    pairs = jnp.asarray(_translated_pair(-1.4, 0.0).repeat(2, 0))
    maps = jnp.asarray(rng.normal(0.0, 1.0, (2, H, W, 2)).astype(np.float32))
    rows = jnp.asarray([0.0, 1.0])
    config = polish.PolishConfig(variational_warps=4, variational_warps_stereo=4, variational_sigma=3.0,
                                 variational_sigma_stereo=1.0)
    both = np.asarray(polish.polish_maps(pairs, maps, rows, config))
    for i, sigma, other in ((0, 1.0, 3.0), (1, 3.0, 1.0)):
        alone = dataclasses.replace(config, variational_sigma=sigma, variational_sigma_stereo=sigma)
        want = np.asarray(polish.polish_maps(pairs[i:i + 1], maps[i:i + 1], rows[i:i + 1], alone))[0]
        np.testing.assert_allclose(both[i], want, atol=1e-5)
        wrong = dataclasses.replace(config, variational_sigma=other, variational_sigma_stereo=other)
        assert np.abs(both[i] - np.asarray(polish.polish_maps(pairs[i:i + 1], maps[i:i + 1], rows[i:i + 1],
                                                               wrong))[0]).max() > 1e-3
    assert polish.config_for_rows(config, np.ones(2)).variational_sigma_stereo == 3.0
    assert polish.config_for_rows(config, np.zeros(2)).variational_sigma == 1.0
    assert polish.config_for_rows(config, np.asarray(rows)) == config
    with pytest.raises(ValueError, match="variational_sigma"):
        polish.PolishConfig(variational_sigma_stereo=0.0)


def test_flat_images_keep_a_constant_map():
    """Without texture every candidate costs the same: selection keeps any map as it is (no candidate is
    'clearly better'). The refinement then has only its smoothness term, which leaves a constant map exactly
    where it is and only smooths a noisy one."""
    flat = jnp.full((1, H, W, 6), 0.4)
    noisy = jnp.asarray(np.random.default_rng(0).normal(size=(1, H, W, 2)).astype(np.float32))
    grey = flat[..., :3].mean(-1)
    kept = polish.select_candidates(polish.normalise_locally(grey), grey, noisy, jnp.ones((1, 1, 1, 2)))
    np.testing.assert_array_equal(np.asarray(kept), np.asarray(noisy))
    constant = jnp.broadcast_to(jnp.float32([3.2, -1.5]), (1, H, W, 2))
    np.testing.assert_allclose(np.asarray(polish.polish_maps(flat, constant, jnp.ones(1))), np.asarray(constant),
                               atol=1e-6)
    smoothed = np.asarray(polish.polish_maps(flat, noisy, jnp.ones(1)))
    assert np.abs(np.diff(smoothed, axis=2)).mean() < 0.5 * np.abs(np.diff(np.asarray(noisy), axis=2)).mean()


def _bled_boundary(rng, size=96):
    """A square of a random texture moving by (-4, 2) over a background moving by (3, 0), both by whole
    pixels (bilinear warps are then exact); the true map with the square's motion bled 6 px outwards."""
    a = cv2.GaussianBlur(rng.uniform(size=(size, size)).astype(np.float32), (0, 0), 1.0)
    b = np.roll(a, 3, axis=1)  # background: a(x) at b(x + 3)
    y0, y1, x0, x1 = 40, 64, 36, 60  # the square in a
    b[y0 + 2:y1 + 2, x0 - 4:x1 - 4] = a[y0:y1, x0:x1]  # the square: a(x, y) at b(x - 4, y + 2)
    maps = np.broadcast_to(np.float32([3.0, 0.0]), (size, size, 2)).copy()
    maps[y0 - 6:y1 + 6, x0 - 6:x1 + 6] = (-4.0, 2.0)  # the square's motion, bled 6 px outwards
    return a, b, maps, (y0, y1, x0, x1)


def test_candidate_selection_repairs_a_bled_motion_boundary(rng):
    """Above the square, where the background stays visible in b, selection takes the background's (3, 0)
    back from the pixels further up, exactly, and leaves the square's inside alone."""
    a, b, maps, (y0, y1, x0, x1) = _bled_boundary(rng)
    mask = jnp.ones((1, 1, 1, 2))
    out = np.asarray(polish.select_candidates(polish.normalise_locally(jnp.asarray(a)[None]), jnp.asarray(b)[None],
                                              jnp.asarray(maps)[None], mask))[0]
    np.testing.assert_array_equal(out[y0 - 6:y0 - 2, x0 + 4:x1 - 4], np.broadcast_to([3.0, 0.0], (4, 16, 2)))
    np.testing.assert_array_equal(out[y0 + 6:y1 - 6, x0 + 6:x1 - 6], np.broadcast_to([-4.0, 2.0], (12, 12, 2)))
    assert polish.candidate_offsets().shape == (32, 2)


def test_soft_selection_is_the_softmin_of_the_candidates(rng):
    """`select_softness` = t: each pixel's value is sum w_i v_i / sum w_i over its own value, entered at its
    acceptance threshold (ratio x own cost - margin), and its 32 candidates, w_i = exp(-cost_i / t); here
    computed from the candidates' costs in numpy, in float64, all at once instead of the running rescaled sums."""
    a = cv2.GaussianBlur(rng.uniform(size=(40, 56)).astype(np.float32), (0, 0), 1.0)
    b = np.roll(a, 2, axis=1)
    maps = rng.normal(2.0, 3.0, size=(1, 40, 56, 2)).astype(np.float32)
    norm_a, grey_b, mask = polish.normalise_locally(jnp.asarray(a)[None]), jnp.asarray(b)[None], jnp.ones((1, 1, 1, 2))
    config = polish.PolishConfig(select_softness=0.05)
    own = np.asarray(polish.matching_cost(norm_a, grey_b, jnp.asarray(maps), config), np.float64)
    costs, values = [own * config.accept_ratio - config.accept_margin], [maps.astype(np.float64)]
    for dx, dy in polish.candidate_offsets(config.candidate_distances):
        rows, cols = np.clip(np.arange(40) + dy, 0, 39), np.clip(np.arange(56) + dx, 0, 55)
        cand = maps[:, rows][:, :, cols]
        costs.append(np.asarray(polish.matching_cost(norm_a, grey_b, jnp.asarray(cand), config), np.float64))
        values.append(cand.astype(np.float64))
    costs = np.stack(costs)
    w = np.exp(-(costs - costs.min(0)) / config.select_softness)
    expected = (w[..., None] * np.stack(values)).sum(0) / w.sum(0)[..., None]
    out = np.asarray(polish.select_candidates(norm_a, grey_b, jnp.asarray(maps), mask, config))
    np.testing.assert_allclose(out, expected, atol=2e-4)
    assert np.abs(out - maps).max() > 1.0  # the blend moved pixels: the check is not of an unchanged map


def test_soft_selection_keeps_clear_choices_and_is_continuous(rng):
    """On the bled boundary every choice is clear: a small softness repairs it as the hard choice does. A
    change of 1e-4 px in the input map then moves the softly selected map by a few 1e-4 px at most, where the
    hard choice is only piecewise constant in it (a near tie flips a pixel from one candidate to another)."""
    a, b, maps, (y0, y1, x0, x1) = _bled_boundary(rng)
    norm_a, grey_b, mask = polish.normalise_locally(jnp.asarray(a)[None]), jnp.asarray(b)[None], jnp.ones((1, 1, 1, 2))
    soft = polish.PolishConfig(select_softness=1e-3)
    hard = np.asarray(polish.select_candidates(norm_a, grey_b, jnp.asarray(maps)[None], mask))[0]
    out = np.asarray(polish.select_candidates(norm_a, grey_b, jnp.asarray(maps)[None], mask, soft))[0]
    np.testing.assert_allclose(out[y0 - 6:y0 - 2, x0 + 4:x1 - 4], hard[y0 - 6:y0 - 2, x0 + 4:x1 - 4], atol=1e-3)
    np.testing.assert_allclose(out[y0 + 6:y1 - 6, x0 + 6:x1 - 6], hard[y0 + 6:y1 - 6, x0 + 6:x1 - 6], atol=1e-3)
    nudged = maps + rng.normal(0, 1e-4, maps.shape).astype(np.float32)
    moved = np.asarray(polish.select_candidates(norm_a, grey_b, jnp.asarray(nudged)[None], mask,
                                                polish.PolishConfig(select_softness=0.05)))[0]
    base = np.asarray(polish.select_candidates(norm_a, grey_b, jnp.asarray(maps)[None], mask,
                                               polish.PolishConfig(select_softness=0.05)))[0]
    assert np.abs(moved - base).max() < 5e-3, np.abs(moved - base).max()
    with pytest.raises(ValueError, match="select_softness"):
        polish.PolishConfig(select_softness=-0.01)


def test_the_polish_keeps_a_repaired_motion_boundary_sharp(rng):
    """The whole polish on the bled boundary: above the square the background's motion comes back and stays
    within a few hundredths of a pixel of it up to 2 px from the square's edge, where the robust smoothness
    weight lets the map jump. With a quadratic smoothness term (a huge epsilon) the two motions are averaged
    across the edge instead."""
    a, b, maps, (y0, y1, x0, x1) = _bled_boundary(rng)
    pairs = jnp.asarray(np.concatenate([np.repeat(a[..., None], 3, -1), np.repeat(b[..., None], 3, -1)], -1)[None])
    band = (slice(y0 - 6, y0 - 2), slice(x0 + 4, x1 - 4))

    def err_above(config=polish.PolishConfig()):
        out = np.asarray(polish.polish_maps(pairs, jnp.asarray(maps)[None], jnp.ones(1), config))[0]
        return np.abs(out[band] - np.float32([3.0, 0.0])).mean()

    robust = err_above()
    assert robust < 0.05, robust
    assert err_above(polish.PolishConfig(smooth_eps=1e3)) > 4 * robust


def test_unknown_polish_is_one_clear_error():
    graphdef, params = models.init(0, "pwc_lite")
    with pytest.raises(ValueError, match=r"polish 'sharpen': expected one of none, photometric"):
        inference.Predictor(graphdef, params, size=WorkingSize(H, 128), model_cfg=models.model_config("pwc_lite"),
                            test_time=TestTime(polish="sharpen"))


PWC = {**models.model_config("pwc_lite"), "head_init": "kaiming_normal"}  # non-zero maps from a random network


def _agree(got, want, mean: float) -> None:
    """The same polish computed two ways (fused into the predictor's program or on its own, or exported): 200 SOR
    sweeps with robust weights on random images carry float reassociation to a few hundredths of a pixel on a
    handful of pixels (which ones depends on how XLA compiled each side), so all but 0.1 % of the pixels agree to
    5e-3 px, none by more than 0.1 px, and the mean difference is float rounding."""
    diff = np.abs(np.asarray(got) - np.asarray(want))
    assert np.quantile(diff, 0.999) < 5e-3 and diff.max() < 0.1 and diff.mean() < mean, (
        np.quantile(diff, 0.999), diff.max(), diff.mean())


CONFIG = polish.PolishConfig(variational_warps=4, variational_warps_stereo=2)


def test_predictor_polishes_its_final_maps_and_the_export_follows(rng, tmp_path):
    """`TestTime(polish="photometric")` = `polish_maps` on the plain predictor's (refined) maps, for a flow
    and a stereo row in one batch, one trace of the network, in either compile mode; the exported artifact
    computes the same. With few outer iterations of the fit (`CONFIG`): run for long on random images, a robust fit
    carries float reassociation further than this wiring needs."""
    pwc = models.init(0, PWC)
    pairs = rng.uniform(size=(2, 64, 128, 6)).astype(np.float32)
    size = WorkingSize(64, 128)
    plain = inference.Predictor(*pwc, size=size, test_time=TestTime(refine=1), model_cfg=PWC)
    polished = inference.Predictor(*pwc, size=size, test_time=TestTime(refine=1, polish="photometric"), model_cfg=PWC,
                                   polish_config=CONFIG)
    rows = ["flow", "stereo"]
    want = polish.polish_maps(jnp.asarray(pairs), jnp.asarray(plain.run_network(pairs, rows)), jnp.asarray([1.0, 0.0]),
                              CONFIG)
    got = polished.run_network(pairs, rows)
    _agree(got, want, mean=1e-5)
    assert np.abs(got - plain.run_network(pairs, rows)).max() > 1e-3  # the polish changed the maps
    assert np.all(got[1, ..., 1] == 0.0)  # the stereo row stays horizontal
    polished.run_network(pairs, rows)
    assert polished.trace_count == 1
    # the polish's config keys its program: another config, another polish, the same network program
    polished.polish_config = polish.PolishConfig(smooth_eps=1e3)
    assert np.abs(polished.run_network(pairs, rows) - got).max() > 1e-3 and polished.trace_count == 1
    # "fast" compiles the network at optimisation level 0 and the polish, a program of its own, in full
    fast = inference.Predictor(*pwc, size=size, test_time=TestTime(refine=1, polish="photometric"), model_cfg=PWC,
                               compile_mode="fast", polish_config=CONFIG)
    plain_fast = inference.Predictor(*pwc, size=size, test_time=TestTime(refine=1), model_cfg=PWC, compile_mode="fast")
    want_fast = polish.polish_maps(jnp.asarray(pairs), jnp.asarray(plain_fast.run_network(pairs, rows)),
                                   jnp.asarray([1.0, 0.0]), CONFIG)
    _agree(fast.run_network(pairs, rows), want_fast, mean=5e-5)  # random maps of up to 30 px here
    one = inference.Predictor(*pwc, size=size, test_time=TestTime(polish="photometric"), model_cfg=PWC,
                              polish_config=CONFIG)
    loaded = export.load_exported(export.serialize_to_file(export.export_network(one, batch=1), tmp_path / "p.hlo"))
    px, _ = loaded.call(pairs[:1])
    _agree(px, one.run_network(pairs[:1]), mean=1e-5)


def _whole_pixel_pair(h=80, w=150, u=3, v=2):
    """(a, b) `(h, w, 3)` float32 with b(x, y) = a(x - u, y - v) exactly: crops of one blurred-noise image (detail
    down to 2-3 px, which resampling to another size changes at every sub-pixel phase)."""
    rng = np.random.default_rng(0)
    big = cv2.GaussianBlur(rng.uniform(size=(h + 20, w + 20)).astype(np.float32), (0, 0), 1.2)
    big = (big - big.min()) / (big.max() - big.min())
    a, b = big[10:10 + h, 10:10 + w], big[10 - v:10 - v + h, 10 - u:10 - u + w]
    return np.repeat(a[..., None], 3, -1), np.repeat(b[..., None], 3, -1)


def test_the_predictor_polishes_at_the_input_size(monkeypatch):
    """A whole-pixel motion (3, 2) of an 80x150 pair, whose working size is 64x128, from a network map that is
    off by (0.4, -0.3) working px. Polished on the images as given (`PolishConfig.resolution="input"`, the
    default) the exact motion minimises the energy: mean error 0.001 px. Polished on the images resized to the
    working size (the polish until 2026-12-07, computed here by hand), the resampling leaves 0.027 px. The
    predictor's answer is `polish_maps` on the map brought to the input size, for `predict` and `predict_pairs`
    alike, and for images read at a reduced size; `polish_size` says where it runs, and `max_pixels` sends larger
    inputs back to the working size."""
    h, w, size = 80, 150, WorkingSize(64, 128)
    a, b = _whole_pixel_pair(h, w)
    known = np.zeros((64, 128, 2), np.float32)
    known[..., 0], known[..., 1] = 3 * 128 / w + 0.4, 2 * 64 / h - 0.3
    pred = inference.Predictor(*models.init(0, PWC), size=size, test_time=TestTime(polish="photometric"),
                               model_cfg=PWC, polish_config=CONFIG)
    monkeypatch.setattr(pred, "working_maps", KnownMaps([("flow", a, b, known)]))
    assert pred.polish_size(a) == (h, w)
    got = pred.predict([("flow", a, b)])[0]
    np.testing.assert_array_equal(pred.predict_pairs([a], [b])[0], got)
    pairs = np.concatenate([a, b], -1)[None]
    up = inference.flow_to_input_resolution(known[None], h, w)
    want = np.asarray(polish.polish_maps(jnp.asarray(pairs), jnp.asarray(up), jnp.asarray([1.0]), CONFIG))[0]
    _agree(got, want, mean=1e-5)
    # read at half the file's size (`predict.ReducedImage`): polished at the size it was read at, then brought to
    # the file's size as every map is
    ra, rb = (ReducedImage.of(x, (2 * h, 2 * w)) for x in (a, b))
    monkeypatch.setattr(pred, "working_maps", KnownMaps([("flow", ra, rb, known)]))
    assert pred.polish_size(ra) == (h, w)
    np.testing.assert_allclose(pred.predict([("flow", ra, rb)])[0],
                               inference.flow_to_input_resolution(got[None], 2 * h, 2 * w)[0], atol=1e-5)
    truth, inner = np.float32([3, 2]), np.s_[10:-10, 10:-10]
    at_input = np.abs(got[inner] - truth).mean()
    small = inference.resize_images(pairs, 64, 128)
    at_working = polish.polish_maps(jnp.asarray(small), jnp.asarray(known[None]), jnp.asarray([1.0]), CONFIG)
    at_working = inference.flow_to_input_resolution(np.asarray(at_working), h, w)[0]
    assert at_input < 0.005 and 5 * at_input < np.abs(at_working[inner] - truth).mean(), at_input
    pred.polish_config = dataclasses.replace(CONFIG, resolution="working")
    assert pred.polish_size(a) == (64, 128)
    pred.polish_config = dataclasses.replace(CONFIG, max_pixels=h * w - 1)
    assert pred.polish_size(a) == (64, 128)
    pred.test_time = TestTime()
    assert pred.polish_size(a) == (64, 128)  # no photometric polish: nothing moves
    for bad in ({"resolution": "full"}, {"max_pixels": 0}):
        with pytest.raises(ValueError, match=next(iter(bad))):
            polish.PolishConfig(**bad)


def test_default_polish_comes_from_a_shipped_card_only(tmp_path):
    for name in ("long", "demo"):
        want = zoo.info(name).get("default_polish", "none")
        assert zoo.card_test_time(name).polish == want
        assert inference.load_predictor(name).polish == want
    assert inference.load_predictor("long", test_time={"polish": "none"}).polish == "none"
    for name in ("long", "demo"):  # `bridge-zoo show` says so, for both shipped cards (both recommend it)
        assert any(line.startswith("  default polish: photometric") for line in zoo.card_lines(name)), name
    assert zoo.card_test_time(str(tmp_path)).polish == zoo.card_test_time("no-such-name").polish == "none"


def test_where_the_polish_runs_comes_from_the_card(monkeypatch):
    """A card may say where its polish runs (`default_polish_resolution`) and set other fields of its
    `PolishConfig` (`default_polish_settings`), each chosen by its real-image checks: `demo` polishes at the
    working size, `long` where `PolishConfig` says by default (the input size) with a wider data window on flow
    maps; a `polish_config` given to `load_predictor` is used as it is; a card naming a field `PolishConfig` does
    not have is refused, naming the card."""
    assert zoo.card_polish_resolution("demo") == "working" and zoo.card_polish_resolution("long") is None
    assert zoo.card_polish_settings("demo") == {"resolution": "working"}
    assert zoo.card_polish_settings("long") == {"variational_sigma": 4.5}
    assert inference.load_predictor("demo").polish_config == dataclasses.replace(polish.DEFAULT_CONFIG,
                                                                                 resolution="working")
    assert inference.load_predictor("long").polish_config == dataclasses.replace(polish.DEFAULT_CONFIG,
                                                                                 variational_sigma=4.5)
    assert polish.DEFAULT_CONFIG.resolution == "input" and polish.DEFAULT_CONFIG.variational_sigma == 1.5
    assert inference.load_predictor("demo", polish_config=CONFIG).polish_config is CONFIG
    assert any("polish runs at the working size" in line for line in zoo.card_lines("demo"))
    assert any(line.startswith("  polish settings: variational_sigma 4.5") for line in zoo.card_lines("long"))
    monkeypatch.setattr(zoo, "_card", lambda spec: {"default_polish_settings": {"window": 3.0}})
    with pytest.raises(ValueError, match=r"default_polish_settings names \['window'\]"):
        zoo.card_polish_settings("long")


def test_predict_polish_option(tiny_checkpoint, tmp_path, capsys):
    """`bridge-predict --polish photometric` writes the polished flow and says so in predict.json; an unknown
    mode is one argparse error (exit 2) and writes nothing; evaluate refuses it without a checkpoint."""
    from bridge_jax import evaluate
    # the network compiled as the command compiles it for one pair: candidate selection is an argmin, so the
    # rounding of another optimisation level can flip near-ties (by whole candidate values)
    check_predict_option(tiny_checkpoint, tmp_path, capsys, "polish", "photometric", "sharpen",
                         compile_mode=inference.compile_mode_for("auto", 1))
    assert evaluate.main(["--dataset", "synthetic", "--data-dir", str(tmp_path), "--polish", "photometric",
                          "--no-progress"]) == 2
