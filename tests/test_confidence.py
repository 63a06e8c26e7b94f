"""Confidence and occlusion maps (`bridge_jax.confidence`, `Predictor.predict(..., confidence=True)`,
`bridge-predict --confidence`): hand-built scenes whose occluded pixels are derived by hand (a stereo occluder,
a moving square), a known mismatch through a real model, and the sparsification metric on a hand-computed case."""

import json

import cv2
import numpy as np
import pytest

from bridge_jax import confidence, inference, metrics, predict
from tests.scenes import KnownMaps

H, W = 128, 256


def _texture(seed):
    rng = np.random.default_rng(seed)
    return cv2.resize(rng.integers(0, 255, (H // 4, W // 4, 3), dtype=np.uint8), (W, H), interpolation=cv2.INTER_CUBIC)


def _stereo_scene():
    """Background at disparity 2, a square (rows 40-79, left columns 100-129) at disparity 6: in the right view the
    square lies at columns 94-123. Returns (d_left, d_right) (H, W) px, each in its own view's frame."""
    d_left = np.full((H, W), 2.0, np.float32)
    d_left[40:80, 100:130] = 6.0
    d_right = np.full((H, W), 2.0, np.float32)
    d_right[40:80, 94:124] = 6.0
    return d_left, d_right


def _stereo_expected_occlusion():
    """By hand: a background pixel x of the left view (disparity 2) is seen at x - 2 in the right view; it is
    hidden there when x - 2 falls on the square (94..123) and x itself is background: x in 96..99, rows 40-79.
    Columns 0 and 1 match left of the right image (out of view)."""
    occ = np.zeros((H, W), bool)
    occ[40:80, 96:100] = True
    occ[:, :2] = True
    return occ


def _flow_scene():
    """A static background and a square (rows 40-59, columns 100-109 of image a) moving 4 px right: it covers
    columns 104-113 of image b. Returns (forward a -> b, backward b -> a) (H, W, 2) px."""
    fw = np.zeros((H, W, 2), np.float32)
    fw[40:60, 100:110, 0] = 4.0
    bw = np.zeros((H, W, 2), np.float32)
    bw[40:60, 104:114, 0] = -4.0
    return fw, bw


def test_consistency_score_of_a_moving_square_by_hand():
    fw, bw = _flow_scene()
    score, out_of_view = (np.asarray(x[0]) for x in confidence.consistency_score(fw[None], bw[None]))
    # background of a at columns 110-113 (rows 40-59) lands on the square in b, whose backward map says -4:
    # |0 + (-4)|^2 / (0.01 * (0 + 16) + 0.5) = 16 / 0.66
    expected = np.zeros((H, W), np.float32)
    expected[40:60, 110:114] = 16.0 / 0.66
    np.testing.assert_allclose(score, expected, rtol=1e-5, atol=1e-6)
    assert not out_of_view.any()
    occ = confidence.occlusion_from_score(score, out_of_view)
    assert np.array_equal(occ, expected > 0)
    conf = confidence.confidence_from_score(score, out_of_view)
    np.testing.assert_allclose(conf[~occ], 1.0)
    np.testing.assert_allclose(conf[occ], 2.0 ** (-16.0 / 0.66), rtol=1e-4)


def test_out_of_view_matches_are_occluded_and_halve_the_confidence():
    d = np.zeros((1, 8, 16, 2), np.float32)
    d[..., 0] = 3.0           # every pixel 3 px right: columns 13-15 land beyond the last column (15)
    back = -d
    score, oov = confidence.consistency_score(d, back)
    expected = np.zeros((8, 16), bool)
    expected[:, 13:] = True
    assert np.array_equal(np.asarray(oov[0]), expected)
    conf = confidence.confidence_from_score(np.asarray(score[0]), np.asarray(oov[0]))
    # inside: consistent (score 0) -> 1; out of view: the clamped warp reads -3 at column 15, so
    # x = 13 gives |3 - 3| = 0 but counts half: 0.5
    assert conf[0, 0] == 1.0 and conf[0, 13] == pytest.approx(0.5)


def test_a_backward_map_of_the_working_size_is_brought_to_the_forward_map_s():
    """A map polished at the input size is checked against a backward map of the working size (check mode
    "network"): everything moves 4 input px right, the backward map says -2 px at half the size, i.e. -4 input px.
    Brought up and scaled, the two agree: only the 4 columns whose match leaves b fail. Left at working
    pixels they would disagree by 2 px (score 4 / 0.7) everywhere."""
    fw = np.zeros((H, W, 2), np.float32)
    fw[..., 0] = 4.0
    bw = np.zeros((H // 2, W // 2, 2), np.float32)
    bw[..., 0] = -2.0
    value, conf, occ = confidence.checked_map("flow", fw, bw, H, W, confidence.OCCLUSION_THRESHOLD["network"])
    np.testing.assert_array_equal(value, fw)
    assert occ[:, -4:].all() and not occ[:, :-4].any()
    np.testing.assert_allclose(conf[:, :-4], 1.0, atol=1e-6)


def test_to_input_resolution_resizes_the_score_not_the_confidence():
    score = np.zeros((4, 8), np.float32)
    score[:, 4:] = 2.0
    oov = np.zeros((4, 8), bool)
    conf, occ = confidence.to_input_resolution(score, oov, 4, 15)   # columns 0..14 sample 0..7 every half px
    # align_corners: output column j reads input position j / 2; column 7 is half way between 3 (score 0) and 4 (2)
    assert conf.shape == (4, 15) and occ.shape == (4, 15)
    assert conf[0, 7] == pytest.approx(2.0 ** -1.0)
    assert conf[0, 6] == 1.0 and conf[0, 8] == pytest.approx(0.25)
    assert not occ[0, 7] and occ[0, 8]


@pytest.fixture(scope="module")
def predictor(tiny_checkpoint):
    return inference.load_predictor(tiny_checkpoint, size=(H, W), executable_cache=None)


def _stereo_entries(left, right):
    d_left, d_right = _stereo_scene()
    zeros = np.zeros((H, W), np.float32)
    # the network's map of a left -> right pair is (-d, 0); the reverse job is the pair flipped left-right,
    # whose left view is the flipped right image: its disparity is d_right flipped
    return [("stereo", left, right, np.stack([-d_left, zeros], -1)),
            ("stereo", right[:, ::-1], left[:, ::-1], np.stack([-d_right[:, ::-1], zeros], -1))]


def test_left_right_check_through_the_predictor_finds_the_hand_derived_occlusion(predictor, monkeypatch):
    left, right = _texture(1), _texture(2)
    monkeypatch.setattr(predictor, "working_maps", KnownMaps(_stereo_entries(left, right)))
    disp, conf, occ = predictor.predict_pair(left, right, "stereo", confidence=True, occlusion=True)
    d_left, _ = _stereo_scene()
    np.testing.assert_allclose(disp, d_left)
    expected = _stereo_expected_occlusion()
    assert np.array_equal(occ, expected)
    assert conf.dtype == np.float32 and occ.dtype == bool
    r = confidence.EDGE_RADIUS
    # away from the square (more than EDGE_RADIUS px from a change of the map) and consistent: 1
    far = np.ones((H, W), bool)
    far[40 - r:80 + r, 100 - r:130 + r] = False
    np.testing.assert_allclose(conf[far & ~expected], 1.0)
    # (60, 129 + r) is background, consistent (x - 2 is background in the right view too), but its window reaches
    # column 129 of the square: u ranges over -6..-2, edge = 4^2 / (0.01 * 2^2 + 0.5)
    assert conf[60, 129 + r] == pytest.approx(2.0 ** (-confidence.EDGE_WEIGHT * 16.0 / 0.54), rel=1e-4)
    assert conf[60, 130 + r] == 1.0
    # background 2 px against the square's 6 in the right view: |-2 + 6|^2 / (0.01 * (4 + 36) + 0.5), at the
    # occluded columns more than r px from the square (none when r >= 4), plus the edge term at the others
    occluded = conf[40:80, 96:100]
    score = 16.0 / 0.9
    clear_of_edge = [c for c in range(96, 100) if c < 100 - r]
    for c in range(96, 100):
        expected_conf = 2.0 ** -(score + (0.0 if c in clear_of_edge else confidence.EDGE_WEIGHT * 16.0 / 0.54))
        np.testing.assert_allclose(occluded[r:40 - r, c - 96], expected_conf, rtol=1e-4)
    assert (conf[:, :2] <= 0.5).all()
    # forward and backward maps in one call (the check runs the prediction's own stages)
    assert predictor.working_maps.calls == [2]


def test_forward_backward_check_of_a_cycle(predictor, monkeypatch):
    lt, rt, lt1, rt1 = (_texture(s) for s in (3, 4, 5, 6))
    fw, bw = _flow_scene()
    entries = _stereo_entries(lt, rt) + _stereo_entries(lt1, rt1)
    entries += [("flow", lt, lt1, fw), ("flow", lt1, lt, bw)]
    monkeypatch.setattr(predictor, "working_maps", KnownMaps(entries))
    out = predictor.predict_cycle(lt, rt, lt1, rt1, confidence=True, occlusion=True)
    assert sorted(out) == sorted(["disp_t", "disp_t1", "flow", "conf_disp_t", "conf_disp_t1", "conf_flow",
                                  "occ_disp_t", "occ_disp_t1", "occ_flow"])
    expected_flow = np.zeros((H, W), bool)
    expected_flow[40:60, 110:114] = True
    assert np.array_equal(out["occ_flow"], expected_flow)
    assert np.array_equal(out["occ_disp_t"], _stereo_expected_occlusion())
    assert np.array_equal(out["occ_disp_t1"], _stereo_expected_occlusion())
    np.testing.assert_allclose(out["conf_flow"][:30], 1.0)   # rows far from the square
    only_conf = predictor.predict_cycle(lt, rt, lt1, rt1, confidence=True)
    assert "occ_flow" not in only_conf and np.array_equal(only_conf["conf_flow"], out["conf_flow"])


def test_a_check_with_its_own_stages_runs_the_reverse_pairs_apart(predictor, monkeypatch):
    left, right = _texture(7), _texture(8)
    fake = KnownMaps(_stereo_entries(left, right))
    seen = []

    def record(jobs, batch=None):
        seen.append(predictor.test_time)
        return fake(jobs, batch)

    monkeypatch.setattr(predictor, "working_maps", record)
    monkeypatch.setattr(predictor, "check", inference.TestTime(symmetry="flips"))
    _, occ = predictor.predict_pair(left, right, "stereo", occlusion=True)
    assert seen == [inference.TestTime(), inference.TestTime(symmetry="flips")]
    assert predictor.test_time == inference.TestTime()   # put back after the backward maps
    assert np.array_equal(occ, _stereo_expected_occlusion())


def test_edge_score_by_hand():
    d = np.zeros((1, 9, 9, 2), np.float32)
    d[0, 4, 4] = (3.0, -4.0)   # one pixel moves (3, -4): every pixel within 2 px of it sees a range of length 5
    e = np.asarray(confidence.edge_score(d, radius=2)[0])
    expected = np.zeros((9, 9), np.float32)
    expected[2:7, 2:7] = 25.0 / 0.5
    expected[4, 4] = 25.0 / (0.01 * 25.0 + 0.5)
    np.testing.assert_allclose(e, expected, rtol=1e-6)


def test_the_check_mode_sets_the_occlusion_threshold(predictor, monkeypatch):
    """A square moving 2 px: background of a covered in b fails the check by |0 - 2|^2 / (0.01 * 4 + 0.5) = 7.4,
    between the thresholds of the two modes (2 for maps of the same stages, 16 for a plain backward map)."""
    a, b = _texture(10), _texture(11)
    fw = np.zeros((H, W, 2), np.float32)
    fw[40:60, 100:110, 0] = 2.0
    bw = np.zeros((H, W, 2), np.float32)
    bw[40:60, 102:112, 0] = -2.0
    monkeypatch.setattr(predictor, "working_maps", KnownMaps([("flow", a, b, fw), ("flow", b, a, bw)]))
    covered = np.zeros((H, W), bool)
    covered[40:60, 110:112] = True
    _, occ = predictor.predict_pair(a, b, occlusion=True)                  # plain stages both ways: "same"
    assert np.array_equal(occ, covered)
    monkeypatch.setattr(predictor, "test_time", inference.TestTime(refine=1))   # the check stays plain: "network"
    assert confidence.check_mode(confidence.default_check(predictor.test_time), predictor.test_time) == "network"
    _, occ = predictor.predict_pair(a, b, occlusion=True)
    assert not occ.any()
    monkeypatch.setattr(predictor, "check", confidence.check_record("same", predictor.test_time))
    _, occ = predictor.predict_pair(a, b, occlusion=True)
    assert np.array_equal(occ, covered)
    with pytest.raises(ValueError, match="--confidence-check 'fast': expected one of network, same"):
        confidence.check_record("fast", predictor.test_time, "--confidence-check")


def test_a_known_mismatch_through_a_trained_model():
    """The shipped demo model on a photograph and its copy moved 4 px left, a 60 x 60 patch replaced by noise
    in the second image: there is no match for the patch, and the check says so. The default check (a plain
    backward map) ranks it: its confidence is low there; its occlusion mask, at the wider threshold, flags part of
    it; the check of the same stages flags most of it."""
    from skimage import data as skdata
    img = skdata.astronaut()[::2, ::2]
    a = np.ascontiguousarray(img[20:212, 10:234])
    b = np.ascontiguousarray(img[20:212, 14:238])
    b[60:120, 80:140] = np.random.default_rng(0).integers(0, 255, (60, 60, 3))
    pred = inference.load_predictor("demo", executable_cache=None)
    patch = (slice(60, 120), slice(80, 140))
    clear = (slice(0, 50), slice(10, 214))
    flow, conf, occ = pred.predict_pair(a, b, confidence=True, occlusion=True)
    assert np.median(flow[..., 0]) == pytest.approx(-4.0, abs=0.3)
    assert conf[patch].mean() < 0.2 and conf[clear].mean() > 0.85
    assert occ[patch].mean() > 0.15 and occ[clear].mean() < 0.05
    assert occ[:, :3].all()            # columns 0-2 are found left of image b's first column
    disp, conf_d, occ_d = pred.predict_pair(a, b, "stereo", confidence=True, occlusion=True)
    assert np.median(disp) == pytest.approx(4.0, abs=0.3)
    assert conf_d[patch].mean() < 0.2 and conf_d[clear].mean() > 0.85
    assert occ_d[:, :3].all() and occ_d[clear].mean() < 0.05
    pred.check = confidence.check_record("same", pred.test_time)
    for task in ("flow", "stereo"):
        _, occ = pred.predict_pair(a, b, task, occlusion=True)
        assert occ[patch].mean() > 0.6 and occ[clear].mean() < 0.05, task


def test_sparsification_by_hand():
    errors = np.array([1.0, 2.0, 3.0, 4.0])
    conf = np.array([1.0, 0.0, 0.5, 0.2])   # most trusted first: errors 1, 3, 4, 2
    s = metrics.sparsification(errors, conf, fractions=(0.0, 0.25, 0.5, 0.75))
    np.testing.assert_allclose(s["curve"], [2.5, 8 / 3, 2.0, 1.0])
    np.testing.assert_allclose(s["oracle"], [2.5, 2.0, 1.5, 1.0])
    # gaps 0, 2/3, 1/2, 0 -> trapezoids of width 1/4: (1/3 + 7/12 + 1/4) / 4
    assert s["ause"] == pytest.approx(14 / 48)
    assert s["ause_relative"] == pytest.approx(14 / 48 / 2.5)
    assert s["top_half_ratio"] == pytest.approx(2.0 / 2.5)
    perfect = metrics.sparsification(errors, -errors, fractions=(0.0, 0.25, 0.5, 0.75))
    assert perfect["ause"] == 0.0 and perfect["curve"] == perfect["oracle"]
    masked = metrics.sparsification(errors, conf, mask=np.array([True, True, False, False]))
    assert masked["mean"] == 1.5


def test_mask_scores_by_hand():
    s = metrics.mask_scores(np.array([1, 1, 0, 0, 1], bool), np.array([1, 0, 1, 0, 1], bool),
                            valid=np.array([1, 1, 1, 1, 0], bool))
    assert s == {"precision": 0.5, "recall": 0.5, "f1": 0.5}


def test_predict_cli_writes_confidence_and_occlusion(tiny_checkpoint, tmp_path):
    a, b = _texture(9), np.ascontiguousarray(np.roll(_texture(9), -3, axis=1))
    pa, pb = tmp_path / "f0.png", tmp_path / "f1.png"
    cv2.imwrite(str(pa), a[..., ::-1])
    cv2.imwrite(str(pb), b[..., ::-1])
    out = tmp_path / "out"
    assert predict.main(["--checkpoint", tiny_checkpoint, str(pa), str(pb), "--out", str(out), "--working-size",
                         f"{H}x{W}", "--raw", "npy", "--confidence", "--no-progress"]) == 0
    conf = np.load(out / "flow_confidence_npy" / "f0.npy")
    occ = np.load(out / "flow_occlusion_npy" / "f0.npy")
    assert conf.shape == (H, W) and conf.dtype == np.float32 and 0.0 <= conf.min() and conf.max() <= 1.0
    assert occ.dtype == bool
    png = cv2.imread(str(out / "flow_occlusion" / "f0.png"), cv2.IMREAD_UNCHANGED)
    assert np.array_equal(png, np.where(occ, 255, 0).astype(np.uint8))   # the picture is the mask
    picture = cv2.imread(str(out / "flow_confidence" / "f0.png"))
    assert picture.shape == (H, W, 3)
    assert cv2.imread(str(out / "legend_confidence.png")) is not None
    # the files hold what the library gives for the same images
    pred = inference.load_predictor(tiny_checkpoint, size=(H, W), executable_cache=None)
    flow, lib_conf, lib_occ = pred.predict_pair(cv2.imread(str(pa))[..., ::-1], cv2.imread(str(pb))[..., ::-1],
                                                confidence=True, occlusion=True)
    np.testing.assert_allclose(conf, lib_conf, atol=1e-5)
    assert np.array_equal(occ, lib_occ)
    desc = json.loads((out / "predict.json").read_text())
    assert desc["outputs"] == {"flow": 1, "flow_confidence": 1, "flow_occlusion": 1}


def test_confidence_with_kitti_submission_is_refused(tmp_path, capsys):
    rc = predict.main(["--checkpoint", "demo", "--kitti-submission", "--data-dir", str(tmp_path), "--confidence",
                       "--out", str(tmp_path / "sub")])
    assert rc == 2
    assert "--confidence does not apply to --kitti-submission" in capsys.readouterr().err
