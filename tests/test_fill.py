"""The polish's fill step (`confidence.left_right_fill`, `confidence.forward_backward_fill`,
`TestTime(polish="...+fill")`, `Predictor.fill_maps`): the left-right difference and the background fill on rows
derived by hand, the forward-backward difference and the guided fill of flow on a moving square built by hand, and
the predictor's fill against the same hand-derived answers with the network's maps injected."""

import numpy as np
import pytest

from bridge_jax import confidence, export, inference, testtime
from bridge_jax.eval.datasets import Frame
from bridge_jax.eval.methods import ModelMethod
from bridge_jax.testtime import TestTime
from tests.scenes import KnownMaps

H, W = 64, 128


def test_left_right_difference_by_hand():
    # right view's disparity 0, 10, 20, 30 along the row; the left disparities send columns 0..3 to 0, 0.5, 0.5, -2
    d_right = np.array([[0.0, 10.0, 20.0, 30.0]], np.float32)
    d_left = np.array([[0.0, 0.5, 1.5, 5.0]], np.float32)
    diff, out = confidence.left_right_difference(d_left, d_right)
    # column 1 and 2 read half way between 0 and 10 (5); column 3 lies left of the image, read at column 0
    np.testing.assert_allclose(diff, [[0.0, 4.5, 3.5, 5.0]])
    assert out.tolist() == [[False, False, False, True]]


def _bled_row():
    """One row, 16 px. Truth: background at disparity 2, a foreground block at left columns 9-12 at disparity 5,
    seen by the right camera at columns 4-7. The left view's background at columns 6-8 lands on 4-6 in the right
    view, behind the block: hidden there. The right view's disparity (truth): 5 at 4-7, 2 elsewhere (its own
    columns 8-10 are background the left view cannot see). The left map bleeds the block's disparity 2 px to the
    left (columns 7 and 8), as a network does."""
    d_right = np.full((1, 16), 2.0, np.float32)
    d_right[0, 4:8] = 5.0
    d_left = np.full((1, 16), 2.0, np.float32)
    d_left[0, 7:13] = 5.0
    return d_left, d_right


def test_the_fill_gives_a_bled_occlusion_its_background_by_hand():
    d_left, d_right = _bled_row()
    filled, failed = confidence.left_right_fill(d_left, d_right)
    # columns 0-1 match left of the right image; 6 (background behind the block: the right view says 5 at
    # column 4); 7-8 (5 lands on background 2 at columns 2-3). The run 6-8 lies between column 5 (2) and column
    # 9 (5): the farther, 2. The run 0-1 touches the row's start: its one end, column 2 (2).
    assert np.flatnonzero(failed[0]).tolist() == [0, 1, 6, 7, 8]
    expected = np.full(16, 2.0, np.float32)
    expected[9:13] = 5.0
    np.testing.assert_array_equal(filled[0], expected)


def test_the_fill_keeps_a_consistent_map_and_its_tolerance_is_three_quarters_of_a_pixel():
    assert testtime.FILL_MAX_DIFFERENCE_STEREO == 0.75
    d_left, d_right = _bled_row()
    d_left[0, 7:9] = 2.0  # the truth: nothing bled
    d_left[0, 3:6] += 0.7  # within the tolerance of the check (the right view says 2 at their matches, 0.3-2.3)
    filled, failed = confidence.left_right_fill(d_left, d_right)
    # the truly hidden columns 6-8 fail on their own (background 2 lands on the block's 5 in the right view)
    assert np.flatnonzero(failed[0]).tolist() == [0, 1, 6, 7, 8]
    np.testing.assert_array_equal(filled[0, 2:6], d_left[0, 2:6])
    np.testing.assert_allclose(filled[0, 6:9], 2.7)  # between column 5 (2.7) and 9 (5): the farther
    d_left[0, 4] += 0.2  # 0.9 px off: fails (SGBM's 1 px would pass it), takes the smaller of its ends (2.7, 2.7)
    filled, failed = confidence.left_right_fill(d_left, d_right)
    assert failed[0, 4] and filled[0, 4] == pytest.approx(2.7)
    assert not confidence.left_right_fill(d_left, d_right, max_difference=1.0)[1][0, 4]


def test_the_fill_keeps_a_pixel_seen_through_a_nearer_surface():
    # the right view at 8 everywhere. Columns 0-7 match left of the right image (x - d < 0: out of view), and
    # column 2 claims 3, 5 px below its row (still out of view); column 10 (1) fails seen through a surface at 8 on both sides
    # (its match at 9 reads 8), column 12 (5) fails 3 px below it, column 14 (9.5) fails above it
    d_right = np.full((1, 18), 8.0, np.float32)
    d_left = np.full((1, 18), 8.0, np.float32)
    d_left[0, [2, 10, 12, 14]] = [3.0, 1.0, 5.0, 9.5]
    filled, failed = confidence.left_right_fill(d_left, d_right)
    assert np.flatnonzero(failed[0]).tolist() == [0, 1, 2, 3, 4, 5, 6, 7, 10, 12, 14]
    # column 10's background (8) is 7 px nearer than it (>= FILL_MAX_RAISE, 4): it keeps 1; column 12 is raised
    # 3 px to 8, column 14 lowered to 8; the out-of-view strip always takes its background (column 8's 8)
    assert testtime.FILL_MAX_RAISE == 4.0
    np.testing.assert_array_equal(filled[0], [8.0] * 10 + [1.0] + [8.0] * 7)
    # no limit on raising: the devkit's rule for a matcher's holes
    np.testing.assert_array_equal(confidence.left_right_fill(d_left, d_right, max_raise=np.inf)[0], 8.0)
    # a limit of 0: only lowering
    np.testing.assert_array_equal(confidence.left_right_fill(d_left, d_right, max_raise=0.0)[0][0, 10:13],
                                  [1.0, 8.0, 5.0])


def _ramped_row():
    """One row, 20 px. Truth: background at disparity 2, a nearer block at left columns 12-19 at disparity 8, seen
    by the right camera at columns 4-11; the left view's background at columns 6-11 lands on 4-9 in the right
    view, behind the block. The right view's map is the truth. The left map climbs to the block as a network's
    does: columns 4 and 5 at 2.4 and 2.7 (a ramp the check passes: their matches at 1.6 and 2.3 read 2), columns
    6-7 at 2 (hidden: their matches read the block's 8), columns 8-11 bled to 8 (their matches at 0-3 read 2)."""
    d_right = np.full((1, 20), 2.0, np.float32)
    d_right[0, 4:12] = 8.0
    d_left = np.full((1, 20), 2.0, np.float32)
    d_left[0, 4:6] = [2.4, 2.7]
    d_left[0, 8:] = 8.0
    return d_left, d_right


def test_an_occlusion_run_reaches_below_the_ramp_by_hand():
    d_left, d_right = _ramped_row()
    filled, failed = confidence.left_right_fill(d_left, d_right)
    # columns 0-1 match left of the right image; the run 6-11 lies between column 5 (2.7) and column 12 (8), more
    # than FILL_OCCLUSION_STEP (3 px) nearer on its right: an occlusion run, widened by FILL_OCCLUSION_REACH (3)
    # over columns 3-5, whose background is then column 2's 2 (not the ramp's 2.7): columns 3-11 take 2
    assert np.flatnonzero(failed[0]).tolist() == [0, 1, 6, 7, 8, 9, 10, 11]
    assert (testtime.FILL_OCCLUSION_STEP, testtime.FILL_OCCLUSION_REACH) == (3.0, 3)
    expected = np.full(20, 2.0, np.float32)
    expected[12:] = 8.0
    np.testing.assert_array_equal(filled[0], expected)
    # without the widening the run's background is the ramp's top, 2.7, and the ramp stays
    expected[4:12] = [2.4] + [2.7] * 7
    np.testing.assert_allclose(confidence.left_right_fill(d_left, d_right, occlusion_reach=0)[0][0], expected)


def test_widen_occlusion_runs_by_hand():
    d = np.array([[5.0, 5.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 9.0, 9.0, 9.0, 4.0, 4.0, 4.0, 9.0, 9.0]], np.float32)
    failed = np.zeros_like(d, bool)
    failed[0, [0, 6, 7, 9, 12, 15]] = True
    widened = confidence.widen_occlusion_runs(failed, d, step=3.0, reach=3)
    # run 0 touches the row's start and run 15 its end: left alone. Run 6-7: 1 on its left, 9 on its right (8 px
    # nearer): widened over 3-5. Run 9: 9 and 9, no step. Run 12: 4 and 4, none
    assert np.flatnonzero(widened[0]).tolist() == [0, 3, 4, 5, 6, 7, 9, 12, 15]
    # a step of exactly 3 px is not more than 3: a run between 1 and 4 is not widened, between 1 and 4.5 it is, as
    # far as the row's start allows
    d2 = np.array([[1.0, 1.0, 0.0, 4.0]], np.float32)
    assert not confidence.widen_occlusion_runs(np.array([[False, False, True, False]]), d2, reach=3)[0, :2].any()
    d2[0, 3] = 4.5
    np.testing.assert_array_equal(
        confidence.widen_occlusion_runs(np.array([[False, False, True, False]]), d2, reach=3)[0],
        [True, True, True, False])


def test_forward_backward_difference_by_hand():
    # a 1 x 4 image: flow (1, 0) everywhere; the backward flow -1 at columns 0-2, +1 at column 3
    flow = np.zeros((1, 4, 2), np.float32)
    flow[..., 0] = [1.0, 1.0, 0.5, 1.0]
    backward = np.zeros((1, 4, 2), np.float32)
    backward[..., 0] = [-1.0, -1.0, -1.0, 1.0]
    diff, at_match, out = confidence.forward_backward_difference(flow, backward)
    # column 0 reads column 1 (-1): 0; column 1 reads column 2 (-1): 0; column 2 reads 2.5, half way between -1
    # and 1 (0): 0.5; column 3 matches right of the image (4 > 3), read at the clamped column 3 (+1): 2
    np.testing.assert_allclose(diff, [[0.0, 0.0, 0.5, 2.0]])
    np.testing.assert_allclose(at_match[..., 0], [[-1.0, -1.0, 0.0, 1.0]])
    assert out.tolist() == [[False, False, False, True]]
    with pytest.raises(ValueError, match=r"two \(H, W, 2\) flows of one shape"):
        confidence.forward_backward_difference(flow, backward[:, :3])


def _moving_square():
    """A 40 x 60 pair: grey background (0.3, slightly textured) at rest, a red square at rows 10-19, columns
    20-29 of `a` moving 6 px right (columns 26-35 of `b`). Truth: flow 6 on the square, 0 elsewhere; the
    background at columns 30-35 of the square's rows is hidden in `b` (occluded). Backward flow (b -> a, true):
    -6 on the square's place in `b`, 0 elsewhere. The forward flow as a network gives it: the square's motion
    bled 4 px into the hidden background (columns 30-33). Returns (image a, bled flow, backward, true flow)."""
    rng = np.random.default_rng(0)
    image = 0.3 + 0.02 * rng.standard_normal((40, 60, 3)).astype(np.float32)
    image[10:20, 20:30] = [0.9, 0.1, 0.1]
    truth = np.zeros((40, 60, 2), np.float32)
    truth[10:20, 20:30, 0] = 6.0
    bled = truth.copy()
    bled[10:20, 30:34, 0] = 6.0
    backward = np.zeros((40, 60, 2), np.float32)
    backward[10:20, 26:36, 0] = -6.0
    return image.clip(0, 1), bled, backward, truth


def test_the_flow_fill_gives_hidden_background_its_own_motion_by_hand():
    image, bled, backward, truth = _moving_square()
    filled, failed = confidence.forward_backward_fill(bled, backward, image)
    # the bled columns 30-33 land on background in b (residual 6); the hidden columns 34-35 (flow 0) land on the
    # square in b (-6): both fail the check (36 > 0.01 * 36 + 1); nothing else does
    expected_failed = np.zeros((40, 60), bool)
    expected_failed[10:20, 30:36] = True
    np.testing.assert_array_equal(failed, expected_failed)
    # filled from the grey neighbours (flow 0): the red square next to them weighs exp(-0.51 / 0.0128) ~ 1e-17
    np.testing.assert_allclose(filled, truth, atol=1e-5)
    # the true flow fails the check just where the background is hidden (columns 30-35 land on the square in
    # b), and is kept: filled there with what it was
    kept, hidden = confidence.forward_backward_fill(truth, backward, image)
    np.testing.assert_array_equal(hidden, expected_failed)
    np.testing.assert_allclose(kept, truth, atol=1e-5)


def test_the_flow_fills_tolerance_grows_with_the_motion():
    # uniform vertical motion and a backward flow off by `off` px: the check compares off^2 with
    # 0.01 (motion^2 + (motion + off)^2) + 1 (a 3 px error fails a 3 px motion, passes a 30 px one)
    image = np.full((64, 8, 3), 0.5, np.float32)
    for motion, off, fails in ((3.0, 2.5, True), (30.0, 2.5, False), (0.0, 0.9, False), (0.0, 1.1, True)):
        flow = np.zeros((64, 8, 2), np.float32)
        flow[..., 1] = motion
        backward = np.zeros((64, 8, 2), np.float32)
        backward[..., 1] = -(motion + off)
        _, failed = confidence.forward_backward_fill(flow, backward, image)
        inside = 64 - 1 - int(motion)  # rows whose match lies inside the image
        assert failed[:inside].all() == fails and (not fails) == (~failed[:inside]).all(), (motion, off)
        assert failed[inside + 1:].all()  # matches below the image: out of view


def test_guided_fill_takes_the_look_alike_neighbours_and_the_nearest_beyond_its_reach():
    image = np.zeros((30, 80, 3), np.float32)
    image[:, 40:] = 1.0
    values = np.zeros((30, 80, 1), np.float32)
    values[:, 40:] = 5.0
    valid = np.ones((30, 80), bool)
    valid[10:20, 35:45] = False  # a hole across the boundary: each side takes its own look's value
    out = confidence.guided_fill(values, valid, image)
    np.testing.assert_allclose(out[..., 0], values[..., 0], atol=1e-5)
    # only the two end columns valid (1 on the left, 2 on the right): the rounds grow each 28 px inwards (4 rounds
    # of a 7 px window), the 20 columns between take the nearest grown pixel: columns 30-39 the left's, 40-49 the
    # right's
    values = np.zeros((30, 80, 1), np.float32)
    values[:, 0], values[:, 79] = 1.0, 2.0
    valid = np.zeros((30, 80), bool)
    valid[:, 0] = valid[:, 79] = True
    out = confidence.guided_fill(values, valid, np.zeros_like(image))
    assert (out[:, :40, 0] == 1.0).all() and (out[:, 40:, 0] == 2.0).all()


def test_nearest_fill_against_brute_force():
    rng = np.random.default_rng(1)
    values = rng.standard_normal((23, 31, 2)).astype(np.float32)
    valid = rng.uniform(size=(23, 31)) < 0.05
    out = confidence.nearest_fill(values, valid)
    ys, xs = np.nonzero(valid)
    for y in range(23):
        for x in range(31):
            d = np.hypot(ys - y, xs - x)
            # the value of a valid pixel within OpenCV's 5x5 distance approximation (< 2 %) of the nearest
            near = np.flatnonzero(d <= d.min() * 1.02 + 1e-6)
            chosen = [i for i in near if np.array_equal(values[ys[i], xs[i]], out[y, x])]
            assert chosen, (y, x)


def test_polish_modes_split_into_their_steps():
    assert TestTime().polish_steps == ()
    both = TestTime(polish="photometric+fill")
    assert both.polish_steps == ("photometric", "fill") and both.photometric and both.fill
    assert both.photometric_part == TestTime(polish="photometric")
    fill = TestTime(polish="fill")
    assert fill.fill and not fill.photometric and fill.photometric_part == TestTime()
    with pytest.raises(ValueError, match="polish 'fill\\+photometric'"):
        TestTime(polish="fill+photometric")
    with pytest.raises(ValueError, match="--polish 'sharpen'"):
        TestTime().with_given({"polish": "sharpen"}, testtime.OPTIONS)


def _scene():
    """Rows of `_bled_row`'s kind at the working size: background 2, a block at left columns 60-79 (disparity
    6) seen at 54-73 in the right view; the left map bleeds 6 over columns 55-59 (of which 56-59 are hidden
    behind the block in the right view). Returns (d_left (with the bleed), d_right, d_left filled by hand)."""
    d_right = np.full((H, W), 2.0, np.float32)
    d_right[20:40, 54:74] = 6.0
    d_left = np.full((H, W), 2.0, np.float32)
    d_left[20:40, 55:80] = 6.0
    expected = np.full((H, W), 2.0, np.float32)
    expected[20:40, 60:80] = 6.0
    # columns 0 and 1 match left of the right image: filled from column 2 (2), the value they had
    return d_left, d_right, expected


@pytest.fixture(scope="module")
def predictor(tiny_checkpoint):
    return inference.load_predictor(tiny_checkpoint, size=(H, W), executable_cache=None)


def _images():
    rng = np.random.default_rng(0)
    return [rng.integers(0, 255, (H, W, 3), dtype=np.uint8) for _ in range(4)]


def _flows():
    """A flow of 1.5 px down and right with a spurious block of 9 px at rows 10-19, columns 30-39, and its
    backward flow -1.5 everywhere: the block fails the forward-backward check (|9 - 1.5| against
    sqrt(0.01 (81 + 2.25) + 1) = 1.35 px), as do the last two rows and columns (matches beyond the image).
    Returns (flow, backward, the flow filled by hand: 1.5 everywhere, every neighbour's value)."""
    flow = np.full((H, W, 2), 1.5, np.float32)
    flow[10:20, 30:40] = 9.0
    return flow, np.full((H, W, 2), -1.5, np.float32), np.full((H, W, 2), 1.5, np.float32)


def _entries(left, right, flow_b):
    d_left, d_right, _ = _scene()
    zeros = np.zeros((H, W), np.float32)
    flow, backward, _ = _flows()
    return [("stereo", left, right, np.stack([-d_left, zeros], -1)),
            ("stereo", right[:, ::-1], left[:, ::-1], np.stack([-d_right[:, ::-1], zeros], -1)),
            ("flow", left, flow_b, flow), ("flow", flow_b, left, backward)]


def _filling(predictor, monkeypatch, left, right, later):
    """`predictor` with the hand-built maps of `_entries` injected and the polish's fill step on; the injected
    maps (their `calls`)."""
    known = KnownMaps(_entries(left, right, later))
    monkeypatch.setattr(predictor, "working_maps", known)
    monkeypatch.setattr(predictor, "test_time", TestTime(polish="fill"))
    return known


def test_the_predictor_fills_stereo_and_flow_maps(predictor, monkeypatch):
    left, right, later, _ = _images()
    d_left, _, expected = _scene()
    raw_flow, _, expected_flow = _flows()
    known = _filling(predictor, monkeypatch, left, right, later)
    disp, flow = predictor.predict([("stereo", left, right), ("flow", left, later)])
    np.testing.assert_array_equal(disp, expected)
    np.testing.assert_allclose(flow, expected_flow, atol=1e-6)
    assert known.calls == [4]  # the right view's pair and the backward flow's in the same call as the two jobs
    np.testing.assert_allclose(predictor.predict_pair(left, later), expected_flow, atol=1e-6)
    # the same through predict_pair (a batch of one stereo pair) and with confidence: the map is filled, the
    # occlusion is that of the check of the map before the fill: the bled columns 55-59 (6 lands on the right
    # view's background 2 at 49-53; score 4^2 / (0.01 (36 + 4) + 0.5) = 17.8, above the default check's 16)
    np.testing.assert_array_equal(predictor.predict_pair(left, right, "stereo"), expected)
    filled, occ = predictor.predict_pair(left, right, "stereo", occlusion=True)
    np.testing.assert_array_equal(filled, expected)
    assert occ[30, 55:60].all() and not occ[30, 60:80].any() and not occ[30, 2:50].any()
    # without the fill step the maps are the network's own
    monkeypatch.setattr(predictor, "test_time", TestTime())
    np.testing.assert_array_equal(predictor.predict([("stereo", left, right)])[0], d_left)
    np.testing.assert_array_equal(predictor.predict([("flow", left, later)])[0], raw_flow)


def test_evaluation_runs_the_fill_too(predictor, monkeypatch):
    left, right, later, _ = _images()
    _, _, expected = _scene()
    known = _filling(predictor, monkeypatch, left, right, later)
    frame = Frame("hand", {"left_t": left, "right_t": right, "left_t1": later}, {})
    pred = ModelMethod(predictor)([frame])[0]
    np.testing.assert_array_equal(pred["disp_t"], expected)
    np.testing.assert_allclose(pred["flow"], _flows()[2], atol=1e-6)
    assert known.calls == [2, 2]  # the frame's two pairs, then the right view's and the backward flow's


def test_export_drops_a_cards_fill_and_refuses_a_given_one():
    card = TestTime(refine=1, polish="photometric+fill")
    assert export.without_fill(card, None) == TestTime(refine=1, polish="photometric")
    with pytest.raises(ValueError, match="--polish fill: .*cannot be exported; use --polish none"):
        export.without_fill(TestTime(polish="fill"), "fill")


def test_predict_cli_fills_a_stereo_pair_as_the_library_composes_it(tiny_checkpoint, tmp_path):
    """`bridge-predict --task stereo --polish fill`: the written disparity is the plain prediction filled against
    the plain prediction of the swapped, mirrored pair (flipped back): the wiring of which view is which."""
    import cv2
    from bridge_jax import predict
    rng = np.random.default_rng(3)
    left = cv2.resize(rng.integers(0, 255, (H // 4, W // 4, 3), dtype=np.uint8), (W, H), interpolation=cv2.INTER_CUBIC)
    right = np.ascontiguousarray(np.roll(left, -4, axis=1))
    pl, pr = tmp_path / "l.png", tmp_path / "r.png"
    cv2.imwrite(str(pl), left[..., ::-1])
    cv2.imwrite(str(pr), right[..., ::-1])
    out = tmp_path / "out"
    assert predict.main(["--checkpoint", tiny_checkpoint, str(pl), str(pr), "--task", "stereo", "--out", str(out),
                         "--working-size", f"{H}x{W}", "--refine", "0", "--symmetry", "none", "--polish", "fill",
                         "--raw", "npy", "--no-progress"]) == 0
    written = np.load(out / "disparity_npy" / "l.npy")
    plain = inference.load_predictor(tiny_checkpoint, size=(H, W), executable_cache=None)
    d_left = plain.predict_pair(left, right, "stereo")
    d_right = plain.predict_pair(right[:, ::-1], left[:, ::-1], "stereo")[:, ::-1]
    expected, failed = confidence.left_right_fill(d_left, d_right)
    assert failed.any() and not failed.all()  # an untrained network: the check fails somewhere, not everywhere
    np.testing.assert_allclose(written, expected, atol=1e-5)
    assert not np.allclose(written, d_left)


def test_a_filled_batch_of_stereo_pairs_and_its_bad_inputs(predictor, monkeypatch):
    left, right, later, _ = _images()
    _, _, expected = _scene()
    known = _filling(predictor, monkeypatch, left, right, later)
    both = predictor.predict_pairs([left, left], [right, right], "stereo")
    np.testing.assert_array_equal(both, np.stack([expected, expected]))
    # one call of the two pairs and their right views, run two pairs at a time (one compiled shape)
    assert known.calls == [4] and known.batches == [2]
    with pytest.raises(ValueError, match="non-zero number"):
        predictor.predict_pairs([], [], "stereo")
    with pytest.raises(ValueError, match="same, non-zero number of first and second images, got 2 and 1"):
        predictor.predict_pairs([left, left], [right], "stereo")
