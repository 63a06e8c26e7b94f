"""OpenCV baselines: the KITTI devkit's background fill, SGBM in its standard form on a pair built by hand, the
stated disparity ranges of the real-image checks, and the optical flows (DIS medium, DIS fine, DeepFlow) on a
known shift."""

import cv2
import numpy as np
import pytest

from bridge_jax.eval import baselines, real_checks
from experiments import real_images


def _devkit_fill(disp, valid):
    """The KITTI devkit's `interpolateBackground`, pixel by pixel, as its C++ reads (rows, then the columns'
    top and bottom ends), plus rows between filled rows taking the smaller of their two nearest filled rows."""
    d = np.where(valid, disp, -1.0).astype(np.float64)
    h, w = d.shape
    for v in range(h):
        count = 0
        for u in range(w):
            if d[v, u] >= 0:
                if count and u - count > 0:
                    d[v, u - count:u] = min(d[v, u - count - 1], d[v, u])
                count = 0
            else:
                count += 1
        ok = np.flatnonzero(d[v] >= 0)
        if ok.size:
            d[v, :ok[0]] = d[v, ok[0]]
            d[v, ok[-1] + 1:] = d[v, ok[-1]]
    full = [v for v in range(h) if (d[v] >= 0).all()]
    if not full:
        return np.zeros((h, w), np.float32)
    for v in range(h):
        if v in full:
            continue
        above = [r for r in full if r < v]
        below = [r for r in full if r > v]
        ends = ([d[above[-1]]] if above else []) + ([d[below[0]]] if below else [])
        d[v] = np.min(ends, axis=0)
    return d.astype(np.float32)


def test_fill_hand_built_rows():
    nan = 0.0
    disp = np.array([[nan, 5, nan, nan, 3, nan],     # left end, a run between 5 and 3, right end
                     [9, nan, nan, nan, nan, 2],     # one long run: the smaller end
                     [4, 4, 4, 4, 4, 4],             # nothing to fill
                     [nan, nan, nan, 7, nan, nan]],  # one valid pixel: both ends take it
                    np.float32)
    out = baselines.fill_invalid_disparity(disp, disp > 0)
    np.testing.assert_array_equal(out, [[5, 5, 3, 3, 3, 3], [9, 2, 2, 2, 2, 2], [4] * 6, [7] * 6])
    assert out.dtype == np.float32


def test_fill_rows_without_a_valid_pixel():
    disp = np.array([[0, 0, 0], [1, 8, 1], [0, 0, 0], [6, 2, 6], [0, 0, 0]], np.float32)
    out = baselines.fill_invalid_disparity(disp, disp > 0)
    np.testing.assert_array_equal(out, [[1, 8, 1], [1, 8, 1], [1, 2, 1], [6, 2, 6], [6, 2, 6]])
    np.testing.assert_array_equal(baselines.fill_invalid_disparity(np.zeros((2, 3)), np.zeros((2, 3), bool)), 0)


@pytest.mark.parametrize("seed", range(6))
def test_fill_matches_the_devkit_loop(seed):
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 9)), int(rng.integers(1, 13))
    disp = rng.uniform(0, 50, (h, w)).astype(np.float32)
    valid = rng.random((h, w)) < rng.uniform(0.05, 0.9)
    valid[rng.random(h) < 0.3] = False  # whole rows without a valid pixel
    np.testing.assert_array_equal(baselines.fill_invalid_disparity(disp, valid), _devkit_fill(disp, valid))


def test_fill_rejects_mismatched_shapes():
    with pytest.raises(ValueError, match="same shape|one shape"):
        baselines.fill_invalid_disparity(np.zeros((3, 4)), np.zeros((3, 5), bool))


def test_sgbm_levels_cover_the_stated_maximum():
    assert baselines.sgbm_levels(741, 67.25) == 80       # searches 0..79 >= 67
    assert baselines.sgbm_levels(512, 47.0) == 48        # 0..47: exactly enough
    assert baselines.sgbm_levels(512, 48.0) == 64
    assert baselines.sgbm_levels(512, 0.0) == 16
    assert baselines.sgbm_levels(1242) == 192 and baselines.sgbm_levels(300) == 64  # no stated maximum
    for bad in (-1.0, float("nan"), "64"):
        with pytest.raises(ValueError, match="max_disparity"):
            baselines.sgbm_levels(512, bad)


def _texture(rng, h, w, scale=2):
    """Random texture with structure at a few pixels (noise smoothed, then upsampled)."""
    small = rng.integers(0, 256, (h // scale + 2, w // scale + 2, 3)).astype(np.uint8)
    big = cv2.resize(small, ((w // scale + 2) * scale, (h // scale + 2) * scale), interpolation=cv2.INTER_CUBIC)
    return np.ascontiguousarray(cv2.GaussianBlur(big, (3, 3), 0.7)[:h, :w])


def test_sgbm_recovers_a_hand_built_two_layer_pair():
    """Background at disparity 6, a foreground square at 14: right(x) = left(x + d). Standard SGBM, searching
    0..20, plus the background fill gets all but 3 % of the pixels within 1 px; the background the square hides
    in the right image takes the background's disparity (6), not the square's (14)."""
    rng = np.random.default_rng(0)
    h, w, d_bg, d_fg = 96, 160, 6, 14
    bg, fg = _texture(rng, h, w + 32), _texture(rng, h, w + 32)
    y0, y1, x0, x1 = 30, 70, 70, 110
    left = bg[:, :w].copy()
    left[y0:y1, x0:x1] = fg[y0:y1, x0:x1]
    right = bg[:, d_bg:w + d_bg].copy()
    right[y0:y1, x0 - d_fg:x1 - d_fg] = fg[y0:y1, x0:x1]
    gt = np.full((h, w), float(d_bg))
    gt[y0:y1, x0:x1] = d_fg
    out = baselines.sgbm_disparity(left, right, max_disparity=20)
    err = np.abs(out - gt)
    assert np.median(err) < 0.25
    assert (err <= 1.0).mean() > 0.97
    hidden = (slice(y0 + 3, y1 - 3), slice(x0 - (d_fg - d_bg) + 1, x0 - 1))  # seen in left only
    assert np.abs(out[hidden] - d_bg).max() < 2.0 and np.median(np.abs(out[hidden] - d_bg)) <= 0.25


def test_sgbm_rejects_bad_input():
    img = np.zeros((20, 40, 3), np.uint8)
    with pytest.raises(ValueError, match="uint8 RGB"):
        baselines.sgbm_disparity(img.astype(np.float32), img)
    with pytest.raises(ValueError, match="differ in size"):
        baselines.sgbm_disparity(img, img[:, :30])


def _shifted_pair(dx, dy, h=96, w=128):
    rng = np.random.default_rng(4)
    src = _texture(rng, h + 40, w + 40, scale=3)
    a = src[20:20 + h, 20:20 + w]
    m = np.float32([[1, 0, 20 - dx], [0, 1, 20 - dy]])  # frame t+1 at x shows frame t at x - (dx, dy)
    b = cv2.warpAffine(src, m, (w, h), flags=cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP)
    return np.ascontiguousarray(a), np.ascontiguousarray(b)


@pytest.mark.parametrize("name", ["DIS medium", "DIS fine", "DeepFlow"])
def test_flows_recover_a_known_shift(name):
    if name == "DeepFlow" and not baselines.has_contrib():
        pytest.skip("DeepFlow needs OpenCV's contrib modules (opencv-contrib-python-headless)")
    a, b = _shifted_pair(2.5, -1.5)
    flow = baselines.FLOWS[name](a, b)
    assert flow.shape == (96, 128, 2) and flow.dtype == np.float32
    inner = flow[16:-16, 16:-16]
    np.testing.assert_allclose(np.median(inner.reshape(-1, 2), 0), [2.5, -1.5], atol=0.1)
    assert np.linalg.norm(inner - [2.5, -1.5], axis=-1).mean() < (0.3 if name == "DIS medium" else 0.2)


def test_deepflow_without_contrib_is_one_clear_line(monkeypatch):
    monkeypatch.setattr(baselines, "has_contrib", lambda: False)
    a, b = _shifted_pair(1, 0)
    with pytest.raises(RuntimeError, match="opencv-contrib-python-headless") as e:
        baselines.deepflow(a, b)
    assert "\n" not in str(e.value)


def test_stated_ranges_of_the_checks():
    assert real_checks.stated_max_disparity("motorcycle", 741) == pytest.approx(269 / 4, rel=1e-3)
    assert real_checks.stated_max_disparity("motorcycle", 512) == pytest.approx(46.47, abs=0.01)
    assert real_checks.stated_max_disparity("heldout_synthetic", 512) == real_checks.HELDOUT_SYNTHETIC_MAX_DISPARITY
    assert real_checks.stated_max_disparity("homography", 512) is None
    with pytest.raises(ValueError, match="unknown real-image check"):
        real_checks.stated_max_disparity("kitti", 512)
    cv = real_checks.OpenCV("DIS fine").for_check("motorcycle")
    assert (cv.flow, cv.check, cv._max_disparity(741)) == ("DIS fine", "motorcycle", pytest.approx(67.25))
    assert real_checks.OpenCV(max_disparity=30).for_check("motorcycle")._max_disparity(741) == 30
    with pytest.raises(ValueError, match="OpenCV flow"):
        real_checks.OpenCV("Farneback")


def test_the_heldout_frames_stay_within_the_stated_range():
    for frame in real_checks.heldout_synthetic(4):
        assert frame.gt["disp_occ_0"].max() <= real_checks.HELDOUT_SYNTHETIC_MAX_DISPARITY


def test_strongest_baseline_and_merged_model_rows():
    results = {"homography": {"zero motion": {"epe_all": 10.0}, "OpenCV SGBM / DIS medium": {"epe_all": 1.2},
                              "OpenCV SGBM / DeepFlow": {"epe_all": 1.1}, "long @ native": {"epe_all": 0.9}},
               "shifts": {"OpenCV SGBM / DIS medium": {"epe_horizontal": 0.1, "epe_vertical": 0.4},
                          "OpenCV SGBM / DIS fine": {"epe_horizontal": 0.2, "epe_vertical": 0.2}}}
    assert real_images.strongest_baseline(results, "homography") == "OpenCV SGBM / DeepFlow"  # a model is no baseline
    assert real_images.strongest_baseline(results, "shifts") == "OpenCV SGBM / DIS fine"      # mean of both
    assert real_images.strongest_baseline(results, "zooms") is None
    earlier = {"homography": {"zero motion": {"epe_all": 9.0}, "OpenCV (SGBM filled / DIS medium)": {"epe_all": 1.3},
                              "long @ native": {"epe_all": 0.8}}, "date": "then"}
    merged = real_images.merge_model_rows({"homography": {"zero motion": {"epe_all": 10.0}}, "seconds": {}}, earlier)
    assert list(merged["homography"]) == ["zero motion", "long @ native"]
    assert merged["homography"]["zero motion"] == {"epe_all": 10.0}
    text = real_images.markdown(results, "## head")
    assert "| **OpenCV DeepFlow** (strongest baseline) | 1.100 | – | – |" in text  # a flow check names the flow
    assert "Strongest baseline: OpenCV DIS fine (lowest epe_horizontal / epe_vertical)" in text
    same = {"epe_all": 1.6, "d1_all": 8.3}
    moto = {"motorcycle": {"OpenCV SGBM / DIS medium": same, "OpenCV SGBM / DeepFlow": same}}
    text = real_images.markdown(moto, "## head")
    assert text.count("OpenCV SGBM") == 2  # one row (the same SGBM under each flow) and the line naming it
    assert "| **OpenCV SGBM** (strongest baseline) | 1.600 | 8.3 |" in text


def test_the_cards_name_their_strongest_baselines():
    """The shipped cards' "opencv" numbers are each check's strongest baseline, and `bridge-zoo show` names it."""
    from bridge_jax import zoo
    for name in ("demo", "long"):
        card = zoo.info(name)
        assert set(card["real_images_opencv"]) == set(card["real_images"])
        lines = zoo.card_lines(name)
        for check, label in card["real_images_opencv"].items():
            assert label.startswith("OpenCV")
            assert any(ln.startswith(f"  {check} @ opencv ({label}, the strongest baseline):") for ln in lines)


def test_baselines_only_needs_the_models_rows(tmp_path, capsys):
    for argv, says in ((["--baselines-only"], "go together"),
                       (["--models-from", str(tmp_path / "none.json")], "go together"),
                       (["--baselines-only", "--models-from", str(tmp_path / "none.json")], "cannot read"),
                       (["--baselines-only", "--models-from", "x.json", "--card", "c.json"], "writes no --card")):
        with pytest.raises(SystemExit) as e:
            real_images.main(argv)
        assert e.value.code == 2
        assert says in capsys.readouterr().err
    (tmp_path / "empty.json").write_text("{}")
    with pytest.raises(SystemExit):
        real_images.main(["--baselines-only", "--models-from", str(tmp_path / "empty.json")])
    assert "no check results" in capsys.readouterr().err
