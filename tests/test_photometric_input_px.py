"""Validation on held-out frames in absolute units: distances in pixels of the input frames (not of the working
size) and the absolute photometric errors beside the ratios (`photometric.describe`)."""
import math

import cv2
import numpy as np
import pytest

from bridge_jax.eval import photometric
from tests.test_photometric_val import FLOW, D, H, W, ShiftOracle, _cycle

SY, SX = 2, 3            # the input frames are 2x taller and 3x wider than the working size
IN_H, IN_W = SY * H, SX * W


class OffBy(ShiftOracle):
    """The exact shifts plus `delta` (x, y) working pixels on every map: the left-right check is then off by
    2 * delta (D_lr + delta and D_rl + delta do not cancel)."""

    def __init__(self, delta):
        super().__init__()
        self.delta = np.array(delta, np.float32)

    def stage_maps(self, jobs, batch=None):
        return [m + self.delta for m in super().stage_maps(jobs, batch)]


def _write_upscaled_cycle(root, seed=0):
    """A val folder of one cycle (stems 0, 1) whose frames are `_cycle(seed)` (quantised to uint8) upscaled by
    pixel repetition to IN_H x IN_W; returns the working-size frames val_cycles should give back."""
    q = np.round(_cycle(seed) * 255).astype(np.uint8)          # (4, H, W, 3): left, right, left1, right1
    up = np.repeat(np.repeat(q, SY, axis=1), SX, axis=2)
    assert up.shape == (4, IN_H, IN_W, 3)
    for k, (side, stem) in enumerate((("left", "0"), ("right", "0"), ("left", "1"), ("right", "1"))):
        (root / side).mkdir(parents=True, exist_ok=True)
        assert cv2.imwrite(str(root / side / f"{stem}.png"), up[k][..., ::-1])
    return q.astype(np.float32) / 255


def test_val_cycles_record_the_input_size(tmp_path):
    want = _write_upscaled_cycle(tmp_path / "val")
    cycles = photometric.val_cycles(str(tmp_path / "val"), H, W, max_cycles=4)
    assert cycles.shape == (1, 4, H, W, 3)
    np.testing.assert_allclose(np.asarray(cycles[0]), want, atol=1e-6)  # INTER_AREA undoes the repetition
    assert cycles.input_sizes.tolist() == [[IN_H, IN_W]]
    assert cycles[:1].input_sizes.tolist() == [[IN_H, IN_W]]


def test_distances_are_in_input_pixels(tmp_path):
    """Right = left shifted by D working px = SX * D input px; flow (2, 1) working px = (2 SX, SY) input px."""
    _write_upscaled_cycle(tmp_path / "val")
    cycles = photometric.val_cycles(str(tmp_path / "val"), H, W, max_cycles=4)
    m, _ = photometric.photometric_validation(ShiftOracle(), cycles, batch=3, picture=False)
    assert m["disp_mean_px"] == pytest.approx(D, rel=1e-5)                    # unchanged: working pixels
    assert m["disp_mean_input_px"] == pytest.approx(SX * D, rel=1e-5)
    assert m["flow_mean_px"] == pytest.approx(math.hypot(*FLOW), rel=1e-5)
    assert m["flow_mean_input_px"] == pytest.approx(math.hypot(SX * FLOW[0], SY * FLOW[1]), rel=1e-5)
    assert m["stereo_lr_consistency_px"] < 1e-5 and m["stereo_lr_consistency_input_px"] < 1e-5
    # one working pixel off horizontally: 2 working px = 2 SX input px of inconsistency; vertically: 2 SY
    for delta, want in (((1.0, 0.0), 2 * SX), ((0.0, 1.0), 2 * SY)):
        m, _ = photometric.photometric_validation(OffBy(delta), cycles, batch=3, picture=False)
        assert m["stereo_lr_consistency_px"] == pytest.approx(2.0, abs=1e-5)
        assert m["stereo_lr_consistency_input_px"] == pytest.approx(want, abs=1e-5), delta
        assert m["disp_mean_input_px"] == pytest.approx(SX * (D - delta[0]), rel=1e-5)
        flow = (SX * (FLOW[0] + delta[0]), SY * (FLOW[1] + delta[1]))
        assert m["flow_mean_input_px"] == pytest.approx(math.hypot(*flow), rel=1e-5)


def test_each_cycle_is_scaled_by_its_own_size_and_plain_arrays_by_none():
    frames = np.stack([_cycle(0), _cycle(1)])
    cycles = photometric.HeldOutCycles(frames, [(IN_H, IN_W), (H, W)])  # the second one read at working size
    m, _ = photometric.photometric_validation(ShiftOracle(), cycles, batch=2, picture=False)
    assert m["disp_mean_input_px"] == pytest.approx((SX * D + D) / 2, rel=1e-5)
    assert cycles[[1]].input_sizes.tolist() == [[H, W]] and cycles[1:].input_sizes.tolist() == [[H, W]]
    assert cycles[0].input_sizes is None and (cycles * 1).input_sizes is None
    m, _ = photometric.photometric_validation(ShiftOracle(), frames, batch=2, picture=False)
    for key in ("disp_mean", "flow_mean", "stereo_lr_consistency"):
        assert m[f"{key}_input_px"] == pytest.approx(m[f"{key}_px"], rel=1e-6)


def test_describe_shows_ratios_absolute_errors_and_input_pixels():
    res = {"flow_photo_ssim_l1": 0.0425, "zero_flow_photo_ssim_l1": 0.05, "flow_photo_ssim_l1_vs_zero": 0.85,
           "stereo_photo_ssim_l1": 0.03, "zero_stereo_photo_ssim_l1": 0.12, "stereo_photo_ssim_l1_vs_zero": 0.25,
           "stereo_lr_consistency_px": 2.0, "stereo_lr_consistency_input_px": 6.0,
           "disp_mean_px": 3.0, "disp_mean_input_px": 9.0, "flow_mean_px": 2.24, "flow_mean_input_px": 6.3246}
    assert photometric.describe(res) == [
        "flow photometric error 0.85x zero motion (SSIM+L1 0.0425 vs 0.0500)",
        "stereo photometric error 0.25x zero motion (SSIM+L1 0.0300 vs 0.1200)",
        "left-right disparity inconsistency 2.00 px (6.00 px of the input frames)",
        "mean disparity 9.00 px, mean flow 6.32 px of the input frames"]
    # metrics recorded before the input-pixel keys existed: the old parts only
    old = {k: v for k, v in res.items() if "input" not in k and not k.endswith("_photo_ssim_l1")}
    assert photometric.describe(old) == ["flow photometric error 0.85x zero motion",
                                         "stereo photometric error 0.25x zero motion",
                                         "left-right disparity inconsistency 2.00 px"]
    assert photometric.describe({"flow_epe_all": 1.0}) == []  # synthetic validation: not photometric
