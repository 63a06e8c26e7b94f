"""Why training's validation and `evaluate` of the same checkpoint differ in the 5th digit, and the bound.

Validation scores frames rendered in memory with float ground truth; `evaluate` reads the same samples from the
KITTI-layout folder, whose ground truth is stored as 16-bit PNGs: flow rounded to 1/64 px per component,
disparity to 1/256 px. The images and therefore the predictions are bit-identical, and each evaluation is
deterministic, so the whole difference is that rounding: at most sqrt(2)/128 px of flow EPE and 1/512 px of
disparity EPE per pixel, hence of their means."""
import math

import numpy as np
import pytest

from bridge_jax import inference, train
from bridge_jax.data import synthetic
from bridge_jax.eval import datasets


def test_validation_and_evaluation_differ_only_by_the_png_rounding_of_the_ground_truth(tmp_path):
    predictor = inference.load_predictor("demo", size=(64, 128))  # any size shows it; a small one is cheap
    h, w, n, seed = predictor.height, predictor.width, 4, 1_000_003
    memory = datasets.synthetic_frames(n, seed, h, w)
    synthetic.write_kitti_layout(str(tmp_path / "val"), n, seed=seed, height=h, width=w)
    disk = [datasets.load_frame(s, "synthetic") for s in datasets.list_frames("synthetic", str(tmp_path / "val"))]
    for a, b in zip(memory, disk):
        for k in ("left_t", "right_t", "left_t1"):
            np.testing.assert_array_equal(a.images[k], b.images[k])
        valid = a.gt["flow_occ_valid"]
        assert np.abs(a.gt["flow_occ"] - b.gt["flow_occ"])[valid].max() <= 1 / 128 + 1e-6
        d = a.gt["disp_occ_0"] > 0
        assert np.abs(a.gt["disp_occ_0"] - b.gt["disp_occ_0"])[d].max() <= 1 / 512 + 1e-6

    first, _ = train.validate(predictor, predictor.params, memory, 2, picture=False)
    again, _ = train.validate(predictor, predictor.params, memory, 2, picture=False)
    assert first == again  # deterministic: same frames, same batch -> bitwise the same numbers
    from_disk, _ = train.validate(predictor, predictor.params, disk, 2, picture=False)
    assert abs(first["flow_epe_all"] - from_disk["flow_epe_all"]) <= math.sqrt(2) / 128
    assert abs(first["disp_epe_all"] - from_disk["disp_epe_all"]) <= 1 / 512
    assert first["flow_epe_all"] != pytest.approx(from_disk["flow_epe_all"], abs=1e-9)  # the rounding is visible
