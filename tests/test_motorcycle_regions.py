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
    n = mr.region_numbers(pred, gt, valid)
    assert n["occluded"]["epe"] == pytest.approx(8.0) and n["occluded"]["bias"] == pytest.approx(8.0)
    assert n["occluded"]["d1"] == pytest.approx(100.0) and n["out of view"]["epe"] == 0.0
    assert n["all"]["epe"] == pytest.approx(64 / 40)
    assert sum(n[k]["contribution"] for k in r) == pytest.approx(n["all"]["epe"])
