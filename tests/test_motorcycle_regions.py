"""The region split of experiments/motorcycle_regions.py on a row built by hand."""
import numpy as np
import pytest

from experiments import motorcycle_regions as mr


def test_regions_of_a_foreground_block_by_hand():
    """One row of 40 columns: background at 4 px, a nearer block at 12 px on columns 20-27. Columns 0-3 match
    x - 4 < 0 (out of view). The block lands on right columns 8-15, which the background columns 12-19 would
    have used (12 - 4 = 8 ... 19 - 4 = 15): those 8 background pixels are occluded. Everything else is visible;
    the depth edges are columns 19/20 and 27/28."""
    gt = np.full((1, 40), 4.0)
    gt[0, 20:28] = 12.0
    valid = gt > 0
    occ = mr.occluded_in_right(gt, valid)
    assert np.flatnonzero(occ[0]).tolist() == list(range(12, 20))
    r = mr.regions(gt, valid)
    assert np.flatnonzero(r["out of view"][0]).tolist() == [0, 1, 2, 3]
    assert not (r["out of view"] & r["occluded"]).any()
    total = sum(m.astype(int) for m in r.values())
    assert (total == valid).all()  # disjoint and covering every pixel with ground truth
    # a prediction that bleeds the block over the occluded background: error 8 px on those 8 pixels only
    pred = gt.copy()
    pred[0, 12:20] = 12.0
    n = mr.region_numbers(pred, gt, {"all": valid, **r})
    assert n["occluded"]["epe"] == pytest.approx(8.0) and n["occluded"]["bias"] == pytest.approx(8.0)
    assert n["occluded"]["d1"] == pytest.approx(100.0) and n["out of view"]["epe"] == 0.0
    assert n["all"]["epe"] == pytest.approx(64 / 40)
    assert sum(n[k]["contribution"] for k in r) == pytest.approx(n["all"]["epe"])


def test_left_right_flags_by_hand():
    """The block scene of the test above: a left map that bleeds the block (12 px) over the hidden background
    (columns 12-19) reads the right view's background (4 px) there and fails, (12 - 4)^2 = 64 > 0.01 (144 + 16)
    + 0.5; so do columns 0-3 (out of view). The same scene 36 px farther back (background 40 px, block 46 px):
    the bled columns differ by 6 px from what they read, and 36 < 0.01 (46^2 + 40^2) + 0.5 = 37.66, so the check
    passes them: its relative term lets a jump of about a tenth of the disparity through."""
    left = np.full((1, 40), 4.0)
    left[0, 12:28] = 12.0  # the block on 20-27, bled over 12-19
    right = np.full((1, 40), 4.0)
    right[0, 8:16] = 12.0  # the block where the right view shows it
    assert np.flatnonzero(mr.left_right_flags(left, right)[0]).tolist() == [0, 1, 2, 3] + list(range(12, 20))
    far_left = np.full((1, 100), 40.0)
    far_left[0, 64:80] = 46.0  # the block on 70-79, bled over the hidden 64-69
    far_right = np.full((1, 100), 40.0)
    far_right[0, 24:34] = 46.0
    assert np.flatnonzero(mr.left_right_flags(far_left, far_right)[0]).tolist() == list(range(40))
