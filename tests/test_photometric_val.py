"""Photometric validation on held-out frames without ground truth (bridge_jax.eval.photometric)."""
import math
import os

import cv2
import numpy as np
import pytest

from bridge_jax.data import kitti, pipeline
from bridge_jax.eval import photometric
from tests.test_data_fakes import write_stereo_sequence

H, W = 32, 48
D = 3                      # disparity of the hand-built stereo pair (inside the 4 px border band)
FLOW = (2, 1)              # (u, v) of the hand-built flow


def _cycle(seed=0):
    """left_t random texture; right_t = left_t shifted so that left(x) = right(x - D) (disparity D, map u = -D);
    left_t1 = left_t moved by FLOW (left_t(x, y) = left_t1(x + 2, y + 1)); right_t1 = right_t."""
    rng = np.random.default_rng(seed)
    left = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    right = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)  # the D columns that enter the view on the right
    right[:, :W - D] = left[:, D:]
    left1 = rng.uniform(0, 1, (H, W, 3)).astype(np.float32)
    u, v = FLOW
    left1[v:, u:] = left[:H - v, :W - u]
    return np.stack([left, right, left1, right])


class ShiftOracle:
    """A fake predictor: for every pair it finds the integer global shift (u, v) that maps a onto b exactly
    (brute force over |u|, |v| <= 4, compared inside the border band) and returns it as a constant map.
    `stereo=False` / `flow=False` make it return zeros for that task instead."""

    height, width = H, W

    def __init__(self, stereo=True, flow=True):
        self.use = {"stereo": stereo, "flow": flow}
        self.calls = []

    def stage_maps(self, jobs, batch=None):
        self.calls.append((len(jobs), batch))
        out = []
        for task, a, b in jobs:
            assert a.shape == (H, W, 3) and b.shape == (H, W, 3)   # fed at the working size
            best = (0, 0)
            if self.use[task]:
                errs = {(u, v): np.abs(b[8 + v:H - 8 + v, 8 + u:W - 8 + u] - a[8:H - 8, 8:W - 8]).mean()
                        for u in range(-4, 5) for v in range(-4, 5)}
                best = min(errs, key=errs.get)
            out.append(np.broadcast_to(np.array(best, np.float32), (H, W, 2)).copy())
        return out


def test_exact_maps_reconstruct_and_beat_zero_motion():
    cycles = np.stack([_cycle(0), _cycle(1), _cycle(2)])
    pred = ShiftOracle()
    m, panel = photometric.photometric_validation(pred, cycles, batch=2)
    assert pred.calls == [(9, 2)]                                   # 3 pairs per cycle, in batches of 2
    for task in ("stereo", "flow"):
        assert m[f"{task}_photo_l1"] < 1e-6 and m[f"{task}_photo_ssim_l1"] < 1e-5
        assert m[f"zero_{task}_photo_l1"] > 0.2                     # random texture: |a - b| ~ 1/3
        assert m[f"{task}_photo_l1_vs_zero"] < 1e-4 and m[f"{task}_photo_ssim_l1_vs_zero"] < 1e-4
    assert m["stereo_lr_consistency_px"] < 1e-5                     # -D + W(+D, -D) = 0
    assert m["disp_mean_px"] == pytest.approx(D, rel=1e-5)
    assert m["flow_mean_px"] == pytest.approx(math.hypot(*FLOW), rel=1e-5)
    assert m["num_cycles"] == 3
    assert panel.dtype == np.uint8 and panel.ndim == 3 and panel.shape[2] == 3
    assert panel.shape[0] > 2 * H and panel.shape[1] > 3 * W        # 3 x 2 tiles


def test_zero_motion_predictor_has_ratio_one_and_zero_baseline_by_hand():
    cycles = np.stack([_cycle(0), _cycle(5)])
    m, _ = photometric.photometric_validation(ShiftOracle(stereo=False, flow=False), cycles, batch=4,
                                              picture=False)
    for task in ("stereo", "flow"):
        assert m[f"{task}_photo_l1_vs_zero"] == pytest.approx(1.0, abs=1e-6)
        assert m[f"{task}_photo_ssim_l1_vs_zero"] == pytest.approx(1.0, abs=1e-6)
    # the zero-motion L1 by hand: mean |second - first| inside the border band, per cycle, then over cycles
    b = photometric.border_pixels(H)
    assert b == 4
    inner = (slice(b, H - b), slice(b, W - b))
    for task, k in (("stereo", 1), ("flow", 2)):
        want = np.mean([np.abs(c[k][inner] - c[0][inner]).mean() for c in cycles])
        assert m[f"zero_{task}_photo_l1"] == pytest.approx(want, rel=1e-5)
    assert m["disp_mean_px"] == 0 and m["stereo_lr_consistency_px"] == 0


def test_stereo_and_flow_are_scored_separately():
    cycles = _cycle(3)[None]
    m, _ = photometric.photometric_validation(ShiftOracle(stereo=True, flow=False), cycles, batch=3)
    assert m["stereo_photo_l1_vs_zero"] < 1e-4
    assert m["flow_photo_l1_vs_zero"] == pytest.approx(1.0, abs=1e-6)


def test_wrong_shift_is_penalised_and_mix_uses_alpha():
    cycles = _cycle(4)[None]

    class OffByOne(ShiftOracle):
        def stage_maps(self, jobs, batch=None):
            return [mp + np.array([1.0, 0.0], np.float32) for mp in super().stage_maps(jobs, batch)]

    m, _ = photometric.photometric_validation(OffByOne(), cycles, batch=3)
    assert m["stereo_photo_l1"] > 0.2 and m["flow_photo_l1"] > 0.2  # one pixel off on random texture
    assert m["stereo_lr_consistency_px"] == pytest.approx(2.0, abs=1e-5)   # (-D+1) + (D+1)
    m_l1, _ = photometric.photometric_validation(OffByOne(), cycles, batch=3, alpha=0.0)
    assert m_l1["stereo_photo_ssim_l1"] == pytest.approx(m["stereo_photo_l1"], rel=1e-6)   # alpha 0 = L1 only


def test_cycles_must_be_at_the_working_size():
    with pytest.raises(ValueError, match="working size is 32x48"):
        photometric.photometric_validation(ShiftOracle(), np.zeros((1, 4, 16, 24, 3), np.float32), batch=1)
    with pytest.raises(ValueError, match=r"\(N, 4, H, W, 3\)"):
        photometric.photometric_validation(ShiftOracle(), np.zeros((4, H, W, 3), np.float32), batch=1)


def test_with_params_is_used():
    class WithParams(ShiftOracle):
        def with_params(self, params):
            other = ShiftOracle(stereo=params, flow=params)
            return other

    cycles = _cycle(0)[None]
    m, _ = photometric.photometric_validation(WithParams(), cycles, batch=3, params=False)
    assert m["stereo_photo_l1_vs_zero"] == pytest.approx(1.0, abs=1e-6)


# ------------------------------------------------------------------------------------------------ val_cycles

def test_val_cycles_reads_and_resizes_like_the_pipeline(tmp_path):
    files = write_stereo_sequence(str(tmp_path / "val"), [f"{k:03d}" for k in range(6)], size=(16, 24))
    out = photometric.val_cycles(str(tmp_path / "val"), 8, 12, max_cycles=3)
    assert out.shape == (3, 4, 8, 12, 3) and out.dtype == np.float32
    # 5 cycles, 3 wanted: spread evenly, cycles 0, 2, 4
    for i, k in enumerate((0, 2, 4)):
        for j, rel in enumerate((f"left/{k:03d}.png", f"right/{k:03d}.png", f"left/{k + 1:03d}.png")):
            rgb = cv2.imread(files[rel])[..., ::-1]
            want = cv2.resize(rgb, (12, 8), interpolation=cv2.INTER_AREA).astype(np.float32) / 255
            np.testing.assert_allclose(out[i, j], want, atol=1e-6)
    big = photometric.val_cycles(pipeline.DataConfig(val_dir=str(tmp_path / "val")), 32, 48, max_cycles=10)
    assert big.shape == (5, 4, 32, 48, 3)
    rgb = kitti.read_image(files["right/004.png"])
    np.testing.assert_allclose(big[4, 1], cv2.resize(rgb, (48, 32), interpolation=cv2.INTER_LINEAR) / 255,
                               atol=1e-6)


def test_val_cycles_errors_name_the_option(tmp_path):
    with pytest.raises(ValueError, match=r"config\.data\.val_dir=.*nope.* does not exist"):
        photometric.val_cycles(str(tmp_path / "nope"), 8, 12, 4)
    (tmp_path / "empty").mkdir()
    with pytest.raises(ValueError, match=r"config\.data\.val_dir=.*empty.*no usable stereo cycles"):
        photometric.val_cycles(str(tmp_path / "empty"), 8, 12, 4)
    with pytest.raises(ValueError, match=r"config\.data\.val_dir is empty"):
        photometric.val_cycles(pipeline.DataConfig(), 8, 12, 4)
    files = write_stereo_sequence(str(tmp_path / "bad"), ["0", "1"])
    open(files["left/0.png"], "wb").close()
    with pytest.raises(ValueError, match=r"no usable cycles in config\.data\.val_dir=.*unreadable image"):
        photometric.val_cycles(str(tmp_path / "bad"), 8, 12, 4)


def test_val_cycles_leaves_out_unreadable_cycles(tmp_path):
    files = write_stereo_sequence(str(tmp_path), ["0", "1", "2", "3"], size=(8, 12))
    with open(files["right/3.png"], "wb") as fh:
        fh.write(b"\x89PNG\r\n\x1a\n" + b"\x00" * 8 + b"IHDR" + bytes(8))   # a PNG header saying 0x0
    out = photometric.val_cycles(str(tmp_path), 8, 12, 10)
    assert out.shape == (2, 4, 8, 12, 3)                              # cycle 2-3 left out
    np.testing.assert_allclose(out[1, 2], kitti.read_image(files["left/2.png"]) / 255, atol=1e-6)
    assert os.path.exists(files["right/3.png"])


def test_real_predictor_one_compiled_shape(tiny_checkpoint):
    """The real Predictor: pairs are fed at the working size (no resize), one compiled network shape serves
    every call, and the zero-motion terms do not depend on the model."""
    from bridge_jax import inference
    from bridge_jax.data import synthetic
    pred = inference.load_predictor(tiny_checkpoint, size=(64, 128))
    cycles = np.stack([synthetic.render_sample(s, 64, 128)["cycle"] for s in (1, 2)]).astype(np.float32) / 255
    m, panel = photometric.photometric_validation(pred, cycles, batch=4)
    assert pred.trace_count == 1                                    # 6 pairs in calls of 4 (last one padded)
    assert all(np.isfinite(v) for v in m.values()) and panel is not None
    b = photometric.border_pixels(64)
    inner = (slice(b, 64 - b), slice(b, 128 - b))
    want = np.mean([np.abs(c[2][inner] - c[0][inner]).mean() for c in cycles])
    assert m["zero_flow_photo_l1"] == pytest.approx(want, rel=1e-5)
    assert m["flow_photo_l1_vs_zero"] == pytest.approx(m["flow_photo_l1"] / want, rel=1e-5)
