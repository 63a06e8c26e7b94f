"""Metrics on hand-computed arrays (every expected number below is worked out by hand in the comments)."""

import math

import numpy as np
import pytest

from bridge_jax import metrics


def _flow_case():
    # 4 pixels in one row: (gt, pred) and the hand-computed end-point error / outlier status.
    gt = np.array([[[0, 0], [10, 0], [0, 100], [3, 4]]], np.float32)
    pred = np.array([[[1, 0], [14, 3], [3, 104], [3, 4]]], np.float32)
    # errors: 1, 5, 5, 0.   outliers (>3 px and >5 % |gt|): no, yes (5 > 0.5), no (5 is not > 5 % of 100), no.
    return pred, gt


def test_flow_metrics_hand_computed():
    pred, gt = _flow_case()
    valid = np.ones((1, 4), bool)
    noc = np.array([[True, True, False, True]])
    m = metrics.flow_metrics(pred, gt, valid, noc)
    assert m["epe_all"] == pytest.approx(11 / 4)
    assert m["fl_all"] == pytest.approx(25.0)
    assert m["epe_noc"] == pytest.approx(2.0)          # (1 + 5 + 0) / 3
    assert m["fl_noc"] == pytest.approx(100 / 3)
    assert m["epe_occ"] == pytest.approx(5.0)          # only pixel 2 is occluded
    assert m["fl_occ"] == pytest.approx(0.0)


def test_flow_invalid_pixels_ignored():
    pred, gt = _flow_case()
    valid = np.array([[True, False, True, True]])
    m = metrics.flow_metrics(pred, gt, valid)
    assert m["epe_all"] == pytest.approx(6 / 3)
    assert m["fl_all"] == 0.0
    assert "epe_noc" not in m


def test_outlier_strict_vs_inclusive():
    err = np.array([3.0, 3.0, 3.0001, 5.0])
    mag = np.array([10.0, 60.0, 60.0, 100.0])
    # strict: 3 !> 3; 3 !> 3; 3.0001 > 3 and > 0.05·60 = 3 → outlier; 5 > 3 but 5 !> 0.05·100 = 5
    np.testing.assert_array_equal(metrics.outliers(err, mag), [False, False, True, False])
    # inclusive (>=): every one of them reaches both thresholds
    np.testing.assert_array_equal(metrics.outliers(err, mag, inclusive=True), [True, True, True, True])


def test_disparity_metrics_hand_computed():
    gt = np.array([[10.0, 100.0, 60.0, 0.0]])
    pred = np.array([[13.0, 104.0, 63.0, 5.0]])
    # valid = gt > 0 → first 3 pixels, errors 3, 4, 3 → EPE 10/3.
    # strict: 3 !> 3; 4 > 3 but 4 !> 5; 3 !> 3 → D1 0 %.
    # paper (>=): 3>=3 & 3>=0.5 yes; 4>=3 but 4 < 5 no; 3>=3 & 3>=3 yes → 2/3.
    m = metrics.disparity_metrics(pred, gt)
    assert m["epe_all"] == pytest.approx(10 / 3)
    assert m["d1_all"] == 0.0
    assert m["d1_all_paper"] == pytest.approx(200 / 3)
    noc = np.array([[True, False, True, False]])
    m = metrics.disparity_metrics(pred, gt, noc=noc, prefix="d2")
    assert m["d2_epe_noc"] == pytest.approx(3.0)
    assert m["d2_epe_occ"] == pytest.approx(4.0)
    assert m["d2_all_paper"] == pytest.approx(200 / 3)
    assert m["d2_noc_paper"] == pytest.approx(100.0)    # pixels 0 and 2: 3 >= 3 and 3 >= 5 % of 10 / 60


def test_scene_flow_any_outlier():
    ones = np.ones((1, 5), bool)
    d1_gt, d2_gt = np.full((1, 5), 10.0), np.full((1, 5), 10.0)
    d1 = d1_gt + np.array([[5, 0, 0, 0, 0]])     # D1 wrong at pixel 0
    d2 = d2_gt + np.array([[0, 5, 0, 0, 0]])     # D2 wrong at pixel 1
    fl_gt = np.zeros((1, 5, 2))
    fl = fl_gt.copy()
    fl[0, 2] = (4, 0)                             # Fl wrong at pixel 2
    fl[0, 4] = (9, 9)                             # wrong but invalid flow GT at pixel 4
    fl_valid = ones.copy()
    fl_valid[0, 4] = False
    m = metrics.scene_flow_metrics((d1, d1_gt, ones), (d2, d2_gt, ones), (fl, fl_gt, fl_valid))
    assert m["sf_all"] == pytest.approx(75.0)   # 3 of the 4 pixels valid in all three


def test_depth_metrics_hand_computed():
    gt = np.array([[10.0, 20.0, 7.0]])
    pred = np.array([[8.0, 25.0, 1.0]])
    mask = np.array([[True, True, False]])
    m = metrics.depth_metrics(pred, gt, mask)
    assert m["abs_rel"] == pytest.approx((2 / 10 + 5 / 20) / 2)
    assert m["sq_rel"] == pytest.approx((4 / 10 + 25 / 20) / 2)
    assert m["rmse"] == pytest.approx(math.sqrt((4 + 25) / 2))
    assert m["rmse_log"] == pytest.approx(math.sqrt((math.log(10 / 8) ** 2 + math.log(20 / 25) ** 2) / 2))
    # both ratios are exactly 1.25: δ < 1.25 is strict → 0, δ < 1.25² → 1
    assert m["a1"] == 0.0 and m["a2"] == 1.0 and m["a3"] == 1.0


def test_disparity_to_depth_and_clamp():
    f, b = 721.5377, 0.54
    d = np.array([[f * b / 10.0, 0.0, -1.0, 1e9]])
    depth = metrics.disparity_to_depth(d, f, b)
    # d = 0 → inf → 80 m; d = −1 → negative depth → 1e-3 m; huge d → 1e-3 m
    np.testing.assert_allclose(depth, [[10.0, 80.0, 1e-3, 1e-3]])
    raw = metrics.disparity_to_depth(d, f, b, clamp=False)
    assert np.isinf(raw[0, 1]) and raw[0, 2] == pytest.approx(-f * b)
    eigen = metrics.disparity_to_depth(d, f, b, zero_disparity_depth=0.0)   # Eigen script: inf → 0 → 1e-3
    np.testing.assert_allclose(eigen, [[10.0, 1e-3, 1e-3, 1e-3]])


def test_accumulator_mean_vs_pooled():
    acc = metrics.MetricAccumulator()
    # image A: 1 pixel with EPE 10; image B: 3 pixels with EPE 0 and 0 and 2 (sum 2)
    acc.add({"epe_all": (10.0, 1), "rmse": (16.0, 1)})
    acc.add({"epe_all": (2.0, 3), "rmse": (12.0, 3)})
    acc.add({"epe_all": (0.0, 0)})                      # an image with no valid pixel: skipped by the mean
    mean, pooled = acc.per_image_mean(), acc.pooled()
    assert mean["epe_all"] == pytest.approx((10 + 2 / 3) / 2)
    assert pooled["epe_all"] == pytest.approx(12 / 4)
    assert mean["rmse"] == pytest.approx((4 + 2) / 2)   # sqrt(16/1)=4, sqrt(12/3)=2
    assert pooled["rmse"] == pytest.approx(math.sqrt(28 / 4))
    assert acc.summary()["num_images"]["epe_all"] == 2


def test_accumulator_matches_independent_numpy(rng):
    acc = metrics.MetricAccumulator()
    per_image, all_err = [], []
    for _ in range(3):
        h, w = rng.integers(3, 8, size=2)
        gt = rng.normal(0, 20, (h, w, 2))
        pred = gt + rng.normal(0, 3, (h, w, 2))
        valid = rng.random((h, w)) > 0.3
        acc.add(metrics.flow_sums(pred, gt, valid))
        err = np.linalg.norm(pred - gt, axis=-1)[valid]
        mag = np.linalg.norm(gt, axis=-1)[valid]
        bad = (err > 3) & (err / mag > 0.05)
        per_image.append((err.mean(), 100 * bad.mean()))
        all_err.append((err, bad))
    s = acc.summary()
    assert s["per_image_mean"]["epe_all"] == pytest.approx(np.mean([p[0] for p in per_image]))
    assert s["per_image_mean"]["fl_all"] == pytest.approx(np.mean([p[1] for p in per_image]))
    assert s["pooled"]["epe_all"] == pytest.approx(np.concatenate([e for e, _ in all_err]).mean())
    assert s["pooled"]["fl_all"] == pytest.approx(100 * np.concatenate([b for _, b in all_err]).mean())


def test_garg_crop():
    m = metrics.garg_crop_mask(370, 1224)
    rows, cols = np.nonzero(m.any(1))[0], np.nonzero(m.any(0))[0]
    # 0.40810811·370 = 151.0000007, 0.99189189·370 = 366.9999993 (→ 366, as upstream's int32 cast),
    # 0.03594771·1224 = 43.9999970 (→ 43), 0.96405229·1224 = 1180.0000030 (→ 1180)
    assert (rows[0], rows[-1] + 1, cols[0], cols[-1] + 1) == (151, 366, 43, 1180)


def test_shape_mismatch_is_an_error():
    with pytest.raises(ValueError, match="shape"):
        metrics.flow_metrics(np.zeros((2, 3, 2)), np.zeros((3, 2, 2)), np.ones((3, 2), bool))


def test_out_of_view_strip_by_hand():
    """Disparity 10 px on columns 0-19 and 30 px on 20-39 of an 8x40 left image: columns 0-9 match x - 10 < 0 and
    columns 20-29 match x - 30 < 0, beyond the right image's left border; column 10 matches column 0 exactly
    (inside). A prediction of 0 there errs by the true disparity on every strip pixel, all outliers; one that
    is right on columns 0-9 and 5 px short on 20-29 has half its strip pixels off by 5 (outliers: 5 > 3 px and
    > 5 % of 30)."""
    gt = np.zeros((8, 40))
    gt[:, :20], gt[:, 20:] = 10.0, 30.0
    strip = metrics.out_of_view_mask(gt)
    assert strip.sum() == 8 * 20 and strip[:, :10].all() and strip[:, 20:30].all()
    assert not strip[:, 10:20].any() and not strip[:, 30:].any()
    m = metrics.disparity_out_of_view_metrics(np.zeros_like(gt), gt)
    assert m["epe_outview"] == pytest.approx((10 * 10 + 10 * 30) / 20) and m["d1_outview"] == pytest.approx(100.0)
    pred = gt.copy()
    pred[:, 20:30] = 25.0
    m = metrics.disparity_out_of_view_metrics(pred, gt)
    assert m["epe_outview"] == pytest.approx(2.5) and m["d1_outview"] == pytest.approx(50.0)
    # pixels without ground truth are never in the strip; an image whose matches all lie inside has none
    holed = gt.copy()
    holed[:, :5] = 0.0
    assert metrics.out_of_view_mask(holed).sum() == 8 * 15
    # a match half a pixel beyond the border is out of view too: only column 0 of a 0.5 px disparity
    assert metrics.out_of_view_mask(np.full((4, 40), 0.5)).sum(axis=0).tolist() == [4] + [0] * 39
    inside = np.zeros((4, 40))
    inside[:, 10:] = 5.0
    assert math.isnan(metrics.disparity_out_of_view_metrics(inside, inside)["d1_outview"])


def test_depth_edge_band_and_fattening_by_hand():
    """A fronto-parallel step from 10 px (background, columns 0-19) to 30 px (foreground, 20-39): the edge pixels
    are columns 19 and 20, the band of radius 2 columns 17-22 on every row. A prediction whose foreground bled
    3 px onto the background (columns 17-19 read 30) has 3 wrong pixels of the band's 6 per row, each 20 px
    off and too large."""
    gt = np.zeros((8, 40))
    gt[:, :20], gt[:, 20:] = 10.0, 30.0
    band = metrics.depth_edge_band(gt, radius=2)
    assert band.sum() == 8 * 6 and band[:, 17:23].all()
    pred = gt.copy()
    pred[:, 17:20] = 30.0
    m = metrics.disparity_edge_metrics(pred, gt, radius=2)
    assert m["epe_edge"] == pytest.approx(3 * 20.0 / 6) and m["d1_edge"] == pytest.approx(50.0)
    assert m["fat_edge"] == pytest.approx(50.0)
    # the same error the other way (background eaten into the foreground) is wrong but not fattening
    thin = gt.copy()
    thin[:, 20:23] = 10.0
    m = metrics.disparity_edge_metrics(thin, gt, radius=2)
    assert m["d1_edge"] == pytest.approx(50.0) and m["fat_edge"] == 0.0
    # a slanted surface (1 px per column) and the border of a hole make no edge
    slant = np.tile(np.arange(1.0, 41.0), (8, 1))
    slant[:, 30:] = 0.0
    assert not metrics.depth_edge_band(slant).any()
    assert math.isnan(metrics.disparity_edge_metrics(slant, slant)["d1_edge"])
    # a pixel without ground truth is neither an edge nor in the band; row 3 then has no edge pixel of its own,
    # so its columns 17 and 22 lie sqrt(2^2 + 1) > 2 px from the nearest ones (rows 2 and 4, columns 19 and 20)
    holed = gt.copy()
    holed[3, 20] = 0.0
    band = metrics.depth_edge_band(holed, radius=2)
    assert not band[3, 20] and band[3, 19] and band[3, 21] and not band[3, 17] and not band[3, 22]
    assert band.sum() == 8 * 6 - 3
