"""Inference: compile once per working size, resolution and unit conventions, bad input."""

import jax
import numpy as np
import pytest

from bridge_jax import checkpointing, inference, models

H, W = 128, 256  # small working size for tests (multiple of 64)


@pytest.fixture(scope="module")
def tiny():
    graphdef, params = models.init(0, "resnet_md_tiny")
    return graphdef, params


@pytest.fixture(scope="module")
def predictor(tiny):
    return inference.Predictor(*tiny, size=inference.WorkingSize(H, W), model_cfg=models.model_config("resnet_md_tiny"))


class ConstantPredictor(inference.Predictor):
    """Network replaced by a known working-resolution map, to test the resizing / unit conventions alone."""

    def __init__(self, field):
        self.size = inference.WorkingSize(*field.shape[:2])
        self.field = field
        self.separate = False
        self.seen = []

    def run_network(self, pairs, tasks="flow", polish=True):
        self.seen.append(pairs)
        return np.broadcast_to(self.field, (len(pairs),) + self.field.shape).astype(np.float32)


def test_compiled_once_per_working_size(predictor, rng):
    n0 = predictor.trace_count
    for h, w in [(100, 300), (375, 1242), (128, 256), (61, 77)]:
        a = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        b = rng.integers(0, 256, size=(h, w, 3), dtype=np.uint8)
        out = predictor.predict_pair(a, b)
        assert out.shape == (h, w, 2) and out.dtype == np.float32 and np.isfinite(out).all()
    assert predictor.trace_count - n0 <= 1  # at most the first call compiled
    assert predictor.trace_count >= 1


def test_u_v_scaling_constant_field():
    field = np.zeros((H, W, 2), np.float32)
    field[..., 0], field[..., 1] = 2.0, -3.0
    pred = ConstantPredictor(field)
    out = pred.predict_pair(np.zeros((375, 1242, 3), np.uint8), np.zeros((375, 1242, 3), np.uint8))
    np.testing.assert_allclose(out[..., 0], 2.0 * 1242 / W, rtol=1e-5)
    np.testing.assert_allclose(out[..., 1], -3.0 * 375 / H, rtol=1e-5)


def test_align_corners_resize_of_a_ramp():
    """u = x at the working resolution: with align_corners=True the input pixel X maps to x = X (W-1)/(w-1),
    then u is scaled by w/W."""
    field = np.zeros((H, W, 2), np.float32)
    field[..., 0] = np.arange(W)[None, :]
    field[..., 1] = np.arange(H)[:, None]
    h, w = 90, 700
    out = ConstantPredictor(field).predict_pair(np.zeros((h, w)), np.zeros((h, w)))
    X = np.arange(w)
    Y = np.arange(h)
    np.testing.assert_allclose(out[0, :, 0], X * (W - 1) / (w - 1) * w / W, rtol=1e-4, atol=1e-3)
    np.testing.assert_allclose(out[:, 5, 1], Y * (H - 1) / (h - 1) * h / H, rtol=1e-4, atol=1e-3)


def test_input_resize_is_antialiased_bilinear():
    """Downscaling by 2 with the PIL-style triangle filter (support 2) averages with weights 1/8, 3/8, 3/8, 1/8."""
    x = np.arange(16, dtype=np.float32)[None, :, None]  # (1, 16, 1) -> width 8
    out = inference.resize_images(np.repeat(x, 4, axis=0), 4, 8)
    inner = out[0, 1:-1, 0]
    expect = [(2 * j - 1) * 1 / 8 + 2 * j * 3 / 8 + (2 * j + 1) * 3 / 8 + (2 * j + 2) * 1 / 8 for j in range(1, 7)]
    np.testing.assert_allclose(inner, expect, rtol=1e-5)


def test_channels_and_dtypes():
    field = np.zeros((H, W, 2), np.float32)
    pred = ConstantPredictor(field)
    rgb = np.random.default_rng(0).integers(0, 256, size=(40, 60, 3), dtype=np.uint8)
    gray = rgb[..., 0]
    pred.predict_pair(gray, gray)
    g3 = pred.seen[-1]
    pred.predict_pair(np.repeat(gray[..., None], 3, axis=-1), np.repeat(gray[..., None], 3, axis=-1))
    np.testing.assert_array_equal(g3, pred.seen[-1])  # grayscale replicated to RGB
    rgba = np.concatenate([rgb, np.full((40, 60, 1), 7, np.uint8)], axis=-1)
    pred.predict_pair(rgba, rgba)
    a4 = pred.seen[-1]
    pred.predict_pair(rgb, rgb)
    np.testing.assert_array_equal(a4, pred.seen[-1])  # alpha dropped
    pred.predict_pair(rgb.astype(np.float32) / 255, rgb.astype(np.float32) / 255)
    np.testing.assert_allclose(pred.seen[-1], a4, atol=1e-6)  # uint8 == float / 255
    assert pred.seen[-1].shape == (1, H, W, 6) and pred.seen[-1].max() <= 1.0


def test_bad_input(predictor):
    a = np.zeros((50, 60, 3), np.uint8)
    with pytest.raises(ValueError, match="same size"):
        predictor.predict_pair(a, np.zeros((50, 61, 3), np.uint8))
    with pytest.raises(ValueError, match="image_a.*shape"):
        predictor.predict_pair(np.zeros((50, 60, 2), np.uint8), a)
    with pytest.raises(ValueError, match=r"\[0, 1\]"):
        predictor.predict_pair(np.full((50, 60, 3), 255.0), a)
    with pytest.raises(ValueError, match="multiples of 64"):
        inference.Predictor(predictor.graphdef, predictor.params, size=inference.WorkingSize(100, 256))
    with pytest.raises(ValueError, match="dtype"):
        inference.Predictor(predictor.graphdef, predictor.params, size=inference.WorkingSize(H, W), dtype="float16")
    with pytest.raises(ValueError, match="task"):
        predictor.predict_pair(a, a, task="disparity")


def test_predict_cycle_consistent_with_pairs(predictor, rng):
    """predict_cycle = the pairs' working maps, flow brought to the input size by the flow rule and disparity by
    the disparity rule (what evaluate and predict write)."""
    imgs = [rng.integers(0, 256, size=(70, 150, 3), dtype=np.uint8) for _ in range(4)]
    out = predictor.predict_cycle(*imgs)
    assert out["disp_t"].shape == (70, 150) and out["flow"].shape == (70, 150, 2)
    work = [predictor.run_network(predictor.prepare([a], [b])[0], task)[0]
            for a, b, task in ((imgs[0], imgs[1], "stereo"), (imgs[2], imgs[3], "stereo"), (imgs[0], imgs[2], "flow"))]
    np.testing.assert_allclose(out["disp_t"], inference.disparity_to_input_resolution(-work[0][..., 0], 70, 150),
                               atol=1e-5)
    np.testing.assert_allclose(out["disp_t1"], inference.disparity_to_input_resolution(-work[1][..., 0], 70, 150),
                               atol=1e-5)
    np.testing.assert_allclose(out["flow"], predictor.predict_pair(imgs[0], imgs[2]), atol=1e-5)
    batch = predictor.predict_pairs(np.stack(imgs[:2]), np.stack(imgs[2:]))
    assert batch.shape == (2, 70, 150, 2)
    np.testing.assert_allclose(batch[1], predictor.predict_pair(imgs[1], imgs[3]), atol=1e-5)


def test_a_stereo_pair_gives_disparity_everywhere(predictor, rng):
    """One resize rule per task: predict_pair / predict_pairs of a stereo pair give the disparity that predict
    and predict_cycle give (the disparity rule), not a flow-rule map."""
    left, right = (rng.integers(0, 256, size=(70, 150, 3), dtype=np.uint8) for _ in range(2))
    disp = predictor.predict_pair(left, right, task="stereo")
    assert disp.shape == (70, 150)
    np.testing.assert_allclose(disp, predictor.predict([("stereo", left, right)])[0], atol=1e-5)
    np.testing.assert_allclose(predictor.predict_pairs([left, left], [right, right], task="stereo")[1], disp,
                               atol=1e-5)
    np.testing.assert_allclose(disp, predictor.predict_cycle(left, right, left, right)["disp_t"], atol=1e-5)


def test_network_output_matches_apply(predictor, tiny, rng):
    """The full path at the working size equals models.apply on the same pair (no resize when sizes match)."""
    graphdef, params = tiny
    a = rng.uniform(size=(H, W, 3)).astype(np.float32)
    b = rng.uniform(size=(H, W, 3)).astype(np.float32)
    ref = np.asarray(jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, np.concatenate([a, b], -1)[None])["px"][0][0])
    np.testing.assert_allclose(predictor.predict_pair(a, b), ref, rtol=1e-4, atol=1e-4)


def test_load_predictor_and_bf16(tiny, tmp_path, rng):
    graphdef, params = tiny
    checkpointing.save_params(tmp_path / "ck", params, models.model_config("resnet_md_tiny"))
    p32 = inference.load_predictor(tmp_path / "ck", size=(H, W))
    p16 = inference.load_predictor(tmp_path / "ck", size=(H, W), dtype="bfloat16")
    a = rng.integers(0, 256, size=(64, 100, 3), dtype=np.uint8)
    b = rng.integers(0, 256, size=(64, 100, 3), dtype=np.uint8)
    o32, o16 = p32.predict_pair(a, b), p16.predict_pair(a, b)
    assert o16.dtype == np.float32
    np.testing.assert_allclose(o16, o32, atol=0.05 * max(1.0, np.abs(o32).max()))
    with pytest.raises(ValueError, match="does not exist"):
        inference.load_predictor(tmp_path / "missing")


def test_default_working_size_is_the_trained_size(tiny_checkpoint, tmp_path):
    """A checkpoint with a training config.json beside its model.json runs at the size it was trained at;
    without one, at the paper's 256x512; an explicit size always wins."""
    import json
    import shutil
    assert inference.trained_working_size(tiny_checkpoint) is None
    assert (inference.load_predictor(tiny_checkpoint).height, inference.load_predictor(tiny_checkpoint).width) \
        == (256, 512)
    d = tmp_path / "trained"
    shutil.copytree(tiny_checkpoint, d)
    (d / "config.json").write_text(json.dumps({"height": 64, "width": 192, "variant": "demo"}))
    assert inference.trained_working_size(d) == (64, 192)
    p = inference.load_predictor(d)
    assert (p.height, p.width) == (64, 192)
    p = inference.load_predictor(d, size=(128, 256))
    assert (p.height, p.width) == (128, 256)


@pytest.mark.parametrize("model, size, expected", [
    ("pwc_lite", (500, 741), (448, 704)),      # Middlebury Motorcycle: rounded down to multiples of 64
    ("pwc_lite", (375, 1242), (320, 1216)),    # KITTI
    ("pwc_lite", (64, 128), (64, 128)),        # already a multiple: unchanged
    ("pwc_lite", (127, 129), (64, 128)),       # just under the next multiple: down
    ("pwc_lite", (20, 30), (64, 64)),          # below one multiple: the minimum (upsampled)
    ("pwc_lite", (8000, 8000), (832, 832)),    # capped at 1024*768 pixels, same aspect: 886 -> 832
    ("resnet_md", (300, 1000), (256, 960)),
])
def test_native_working_size_rule(model, size, expected):
    assert inference.native_working_size(model, *size) == expected


def test_native_predictor_runs_each_input_at_its_own_size(rng):
    """A pwc_lite net built for 64x128 predicts at another input's native size (its pyramid follows the input),
    and the maps come back in pixels of the input."""
    cfg = models.model_config("pwc_lite", head_init="kaiming_normal")
    graphdef, params = models.init(0, cfg)
    pred = inference.Predictor(graphdef, params, size=inference.WorkingSize(64, 128, native=True), model_cfg=cfg)
    assert pred.working_size(150, 200) == (128, 192)
    a = rng.integers(0, 256, size=(150, 200, 3), dtype=np.uint8)
    b = rng.integers(0, 256, size=(150, 200, 3), dtype=np.uint8)
    flow = pred.predict_pair(a, b)
    assert flow.shape == (150, 200, 2) and np.isfinite(flow).all()
    # the same numbers as running the network on the input resized to 128x192 by hand
    pairs = inference.resize_images(np.concatenate([a, b], -1).astype(np.float32)[None] / 255.0, 128, 192)
    raw = np.asarray(models.apply(graphdef, params, pairs)["px"][0])[0]
    np.testing.assert_allclose(flow, inference.flow_to_input_resolution(raw, 150, 200), rtol=1e-4, atol=1e-4)
    fixed = inference.Predictor(graphdef, params, size=inference.WorkingSize(64, 128), model_cfg=cfg)
    assert fixed.working_size(150, 200) == (64, 128)


def test_resize_notice_names_the_native_size():
    pred = ConstantPredictor(np.zeros((64, 128, 2), np.float32))
    pred.model_name = "pwc_lite"
    note = inference.resize_notice(pred, 500, 741)
    assert note == ("note: the 500x741 input runs at 64x128 (7.8x smaller per side); --working-size native runs it "
                    "at 448x704")
    assert inference.resize_notice(pred, 100, 200) is None  # 1.6x: no notice


def test_working_size_option(tiny_checkpoint):
    assert inference.load_predictor(tiny_checkpoint, size="native").native
    p = inference.load_predictor(tiny_checkpoint, size=(128, 192))
    assert (p.height, p.width, p.native) == (128, 192, False)
    with pytest.raises(ValueError, match="--working-size 'huge'"):
        inference.load_predictor(tiny_checkpoint, size="huge", size_option="--working-size")
