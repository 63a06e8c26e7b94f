"""Evaluation: GT-resolution rescaling, KITTI-format round trips, baselines and an end-to-end run."""

import json
import os

import numpy as np
import pytest

from bridge_jax import evaluate, inference, metrics
from bridge_jax.data import kitti
from bridge_jax.eval import baselines, datasets, methods

# ----------------------------------------------------------------------------------------------------------------
# Rescaling to the ground-truth resolution (the paper's evaluation scripts)


def test_uniform_flow_maps_to_kitti_resolution():
    work = np.zeros((256, 512, 2), np.float32)
    work[..., 0], work[..., 1] = 4.0, -2.0                 # pixels of the 512×256 working image
    out = inference.flow_to_input_resolution(work, 375, 1242)
    assert out.shape == (375, 1242, 2)
    np.testing.assert_allclose(out[..., 0], 4.0 * 1242 / 512, rtol=1e-6)   # 9.703125 px
    np.testing.assert_allclose(out[..., 1], -2.0 * 375 / 256, rtol=1e-6)   # -2.9296875 px


def test_flow_resize_is_align_corners_bilinear():
    rng = np.random.default_rng(1)
    work = rng.normal(size=(4, 6, 2)).astype(np.float32)
    out = inference.flow_to_input_resolution(work, 7, 11)
    # independent reference: align_corners=True sample positions, separable linear interpolation with np.interp
    xs = np.arange(11) * (6 - 1) / (11 - 1)
    ys = np.arange(7) * (4 - 1) / (7 - 1)
    ref = np.empty((7, 11, 2))
    for c in range(2):
        rows = np.stack([np.interp(xs, np.arange(6), work[r, :, c]) for r in range(4)])       # (4, 11)
        ref[..., c] = np.stack([np.interp(ys, np.arange(4), rows[:, j]) for j in range(11)], 1)
    ref *= np.array([11 / 6, 7 / 4])
    np.testing.assert_allclose(out, ref, rtol=1e-4, atol=1e-5)
    # the corners are kept exactly (times the scale)
    np.testing.assert_allclose(out[-1, -1], work[-1, -1] * np.array([11 / 6, 7 / 4]), rtol=1e-6)


def test_disparity_rescale_fraction_times_width():
    work = np.full((256, 512), 10.0, np.float32)            # 10 px at 512 wide = 1.953 % of the width
    out = inference.disparity_to_input_resolution(work, 375, 1242)
    np.testing.assert_allclose(out, 10.0 / 512 * 1242, rtol=1e-6)
    # a ramp: OpenCV INTER_LINEAR uses half-pixel centres: x_src = (x + 0.5)·w/W − 0.5, clamped
    ramp = np.tile(np.arange(8, dtype=np.float32), (2, 1))
    out = inference.disparity_to_input_resolution(ramp, 2, 16)
    xs = np.clip((np.arange(16) + 0.5) * 8 / 16 - 0.5, 0, 7)
    np.testing.assert_allclose(out[0], xs / 8 * 16, rtol=1e-5, atol=1e-5)


def test_bring_to_frame_t():
    disp_t1 = np.tile(np.arange(10, dtype=np.float32), (3, 1))     # disparity = x at t+1
    flow = np.zeros((3, 10, 2), np.float32)
    flow[..., 0] = 2.0                                              # everything moves 2 px right
    out = methods.bring_to_frame_t(disp_t1, flow)
    np.testing.assert_allclose(out[:, :8], np.arange(2, 10)[None].repeat(3, 0))
    np.testing.assert_allclose(out[:, 8:], 9.0)                     # border clamp


def test_fill_invalid_disparity_like_devkit():
    disp = np.array([[0, 5, 0, 0, 3, 0], [0, 0, 0, 0, 0, 0]], np.float32)
    out = baselines.fill_invalid_disparity(disp, disp > 0)
    # a row without a valid pixel takes the filled row above it (the devkit's bottom extrapolation)
    np.testing.assert_array_equal(out, [[5, 5, 3, 3, 3, 3], [5, 5, 3, 3, 3, 3]])


# ----------------------------------------------------------------------------------------------------------------
# Metrics on predictions written in the KITTI formats by the project's writer


def test_kitti_png_roundtrip_metrics(tmp_path, rng):
    h, w = 20, 30
    gt_flow = np.round(rng.normal(0, 20, (h, w, 2)) * 64) / 64
    valid = rng.random((h, w)) > 0.3
    gt_disp = np.round(rng.uniform(1, 100, (h, w)) * 256) / 256
    kitti.write_flow_png(str(tmp_path / "gt_flow.png"), gt_flow, valid)
    kitti.write_disp_png(str(tmp_path / "gt_disp.png"), gt_disp, valid)
    for shift, epe in ((0.0, 0.0), (1.0, 1.0)):
        kitti.write_flow_png(str(tmp_path / "pred_flow.png"), gt_flow + [shift, 0.0], np.ones((h, w), bool))
        kitti.write_disp_png(str(tmp_path / "pred_disp.png"), gt_disp + shift, np.ones((h, w), bool))
        g, gv = kitti.read_flow_png(str(tmp_path / "gt_flow.png"))
        p, _ = kitti.read_flow_png(str(tmp_path / "pred_flow.png"))
        m = metrics.flow_metrics(p, g, gv)
        assert m["epe_all"] == pytest.approx(epe, abs=1e-6) and m["fl_all"] == 0.0
        gd = np.where(*reversed(kitti.read_disp_png(str(tmp_path / "gt_disp.png"))), 0.0)
        pd = np.where(*reversed(kitti.read_disp_png(str(tmp_path / "pred_disp.png"))), 0.0)
        m = metrics.disparity_metrics(pd, gd, gd > 0)
        assert m["epe_all"] == pytest.approx(epe, abs=1e-6) and m["d1_all"] == 0.0


# ----------------------------------------------------------------------------------------------------------------
# Datasets, baselines, end to end


@pytest.fixture(scope="module")
def synthetic_dir(tmp_path_factory):
    from bridge_jax.data import synthetic
    d = str(tmp_path_factory.mktemp("syn") / "val")
    synthetic.write_kitti_layout(d, 3, seed=5, height=128, width=256)
    return d




def test_baselines_beat_zero_motion(synthetic_dir):
    res = evaluate.evaluate(None, "synthetic", synthetic_dir, progress=False)
    zero, cv = res["methods"]["zero"], res["methods"]["opencv"]
    assert res["num_frames"] == 3
    for task, name in (("flow", "epe_all"), ("flow", "fl_all"), ("disparity", "epe_all"), ("disparity", "d1_all"),
                       ("depth", "abs_rel"), ("scene_flow", "sf_all")):
        for red in ("per_image_mean", "pooled"):
            assert cv[task][red][name] < zero[task][red][name], (task, name, red)
    # zero-motion flow EPE is the mean GT flow norm (independent check on the GT itself)
    norms = []
    for i in range(3):
        f, v = kitti.read_flow_png(os.path.join(synthetic_dir, "flow_occ", f"{i:06d}_10.png"))
        norms.append(np.linalg.norm(f[v.astype(bool)], axis=-1).mean())
    assert zero["flow"]["per_image_mean"]["epe_all"] == pytest.approx(np.mean(norms), rel=1e-5)
    assert "| zero motion | pooled |" in res["markdown"]


class _FakePredictor(inference.Predictor):
    """The predictor with its network replaced by the same working-size map for every pair; records call sizes."""

    def __init__(self, h=64, w=128):
        self.size, self.separate, self.calls = inference.WorkingSize(h, w), False, []

    def run_network(self, pairs, tasks="flow", polish=True):
        self.calls.append(len(pairs))
        out = np.zeros((len(pairs), self.height, self.width, 2), np.float32)
        out[..., 0] = -4.0                               # disparity 4 working px / flow u = −4 px
        return out


def test_fixed_batch_shape_and_scaling(synthetic_dir):
    fake = _FakePredictor()
    res = evaluate.evaluate(fake, "synthetic", synthetic_dir, baselines=False, batch=2, progress=False)
    assert fake.calls == [6, 6]                           # 3 frames × 3 pairs, padded to 2 × 3 per call
    # the synthetic GT is 128×256, working 64×128: disparity 4 px → 4/128·256 = 8 px, flow u −4 → −8 px
    gd = np.where(*reversed(kitti.read_disp_png(os.path.join(synthetic_dir, "disp_occ_0", "000000_10.png"))), 0.0)
    expected = np.abs(8.0 - gd[gd > 0]).mean()
    frames = datasets.list_frames("synthetic", synthetic_dir)
    frame = datasets.load_frame(frames[0], "synthetic")
    pred = methods.ModelMethod(fake)([frame])[0]
    np.testing.assert_allclose(pred["disp_t"], 8.0, rtol=1e-6)
    np.testing.assert_allclose(pred["flow"][..., 0], -8.0, rtol=1e-6)
    m = metrics.disparity_metrics(pred["disp_t"], frame.gt["disp_occ_0"])
    assert m["epe_all"] == pytest.approx(expected, rel=1e-5)
    assert res["methods"]["model"]["disparity"]["num_images"]["epe_all"] == 3


def test_evaluate_end_to_end_tiny_checkpoint(synthetic_dir, tiny_checkpoint, tmp_path):
    out = tmp_path / "eval"
    rc = evaluate.main(["--checkpoint", tiny_checkpoint, "--dataset", "synthetic", "--data-dir", synthetic_dir,
                        "--working-size", "128x256", "--out", str(out), "--no-progress", "--max-frames", "2",
                        "--pictures", "1"])
    assert rc == 0
    res = json.loads((out / "results.json").read_text())
    assert res["num_frames"] == 2
    model = res["methods"]["model"]
    for task, name in (("flow", "epe_all"), ("flow", "fl_noc"), ("disparity", "d1_all"), ("disparity", "d1_all_paper"),
                       ("depth", "abs_rel"), ("scene_flow", "sf_all")):
        assert np.isfinite(model[task]["per_image_mean"][name]) and np.isfinite(model[task]["pooled"][name])
    assert "bridge_jax" in (out / "results.md").read_text()
    assert len(os.listdir(out / "pictures")) == 1
    assert res["timing"]["model_inference_s"] > 0
    # a second run into the same folder is refused, then allowed with --overwrite
    assert evaluate.main(["--dataset", "synthetic", "--data-dir", synthetic_dir, "--out", str(out),
                          "--no-progress", "--max-frames", "1"]) == 2
    assert evaluate.main(["--dataset", "synthetic", "--data-dir", synthetic_dir, "--out", str(out), "--overwrite",
                          "--no-progress", "--max-frames", "1"]) == 0
    assert "model" not in json.loads((out / "results.json").read_text())["methods"]


def test_error_panels_carry_the_error_colour_bar():
    import cv2
    from bridge_jax import visualize
    from bridge_jax.eval import report
    h, w = 32, 64
    flow_gt = np.zeros((h, w, 2), np.float32)
    disp_gt = np.full((h, w), 10.0, np.float32)
    frame = datasets.Frame("f", {"left_t": np.zeros((h, w, 3), np.uint8)},
                           {"flow_occ": flow_gt, "flow_occ_valid": np.ones((h, w), bool), "disp_occ_0": disp_gt})
    pred = {"flow": flow_gt + 1.0, "disp_t": disp_gt + 2.0}
    p = report.frame_panel(frame, pred)
    # 7 tiles (left, flow, flow GT, flow error, disparity, disparity GT, disparity error) in rows of 4 with 4 px
    # gaps: the grid is 2·32 + 4 = 68 rows by 4·64 + 3·4 = 268 columns; then a 4 px gap and the 80 px wide bar,
    # at least 96 rows tall
    assert p.shape == (96, 268 + 4 + 80, 3)
    bar = visualize.colorbar(0.0, 12.0, "jet", height=96, unit="px", label="error", log=True)
    np.testing.assert_array_equal(p[:, 272:], bar)
    assert (p[:, 268:272] == 255).all() and (p[68:, :268] == 255).all()
    # the bar's colours are the error map's: its top is jet's top (12 px and above), its bottom jet's 0
    def jet(i):
        return cv2.applyColorMap(np.array([[i]], np.uint8), cv2.COLORMAP_JET)[0, 0, ::-1].tolist()
    assert p[24, 282].tolist() == jet(255) and p[85, 282].tolist() == jet(0)
    # the flow error tile (row 0, column 3; below its caption) shows EPE √2 px: log1p(√2)/log1p(12) of the scale
    t = np.log1p(np.sqrt(2.0)) / np.log1p(12.0)
    assert p[h - 1, 3 * (w + 4) + w - 1].tolist() == jet(int(np.round(t * 255)))
    # without GT there is no error map, hence no bar: three tiles (left, flow, disparity) only
    bare = datasets.Frame("g", {"left_t": np.zeros((h, w, 3), np.uint8)}, {})
    assert report.frame_panel(bare, {"flow": flow_gt, "disp_t": disp_gt}).shape == (h, 3 * w + 8, 3)


def test_bad_inputs(synthetic_dir, tmp_path, capsys):
    assert evaluate.main(["--dataset", "synthetic", "--data-dir", str(tmp_path / "nope"), "--no-progress"]) == 2
    assert "nope" in capsys.readouterr().err
    # mismatched counts: one GT file missing
    import shutil
    broken = tmp_path / "broken"
    shutil.copytree(synthetic_dir, broken)
    os.remove(broken / "flow_occ" / "000001_10.png")
    with pytest.raises(datasets.EvaluationError, match="flow_occ"):
        datasets.list_frames("synthetic", str(broken))
    # an unreadable image
    (broken / "flow_occ" / "000001_10.png").write_bytes(b"")
    (broken / "image_2" / "000000_10.png").write_bytes(b"not a png")
    with pytest.raises(datasets.EvaluationError, match="000000_10.png"):
        evaluate.evaluate(None, "synthetic", str(broken), progress=False)
    # a checkpoint that is not one
    rc = evaluate.main(["--checkpoint", str(tmp_path), "--dataset", "synthetic", "--data-dir", synthetic_dir,
                        "--no-progress"])
    assert rc == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(tmp_path) in err[0]


def test_working_size_error_names_the_option(synthetic_dir, tiny_checkpoint, tmp_path, capsys):
    rc = evaluate.main(["--checkpoint", tiny_checkpoint, "--dataset", "synthetic", "--data-dir", synthetic_dir,
                        "--working-size", "100x200", "--out", str(tmp_path / "o"), "--no-progress"])
    assert rc == 2 and not (tmp_path / "o").exists()
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: --working-size 100x200: height and width must be multiples of 64 for model resnet_md_tiny "
        "(try 128x192)"]
    assert evaluate.main(["--dataset", "synthetic", "--data-dir", synthetic_dir, "--max-frames", "0"]) == 2
    assert "--max-frames" in capsys.readouterr().err


def test_help_teaches():
    parser = evaluate.build_parser()
    assert [a.option_strings for a in parser._actions if not a.help] == []
    text = parser.format_help()
    assert "bridge-evaluate --checkpoint" in text and "pictures/<frame id>.png" in text
    assert "shipped model name such as demo" in text and "--debug" in text
    # the flags parse as documented
    args = parser.parse_args(["--dataset", "synthetic", "--data-dir", "d"])
    assert (args.no_baselines, args.no_garg_crop, args.no_progress) == (False, False, False)
    args = parser.parse_args(["--dataset", "synthetic", "--data-dir", "d", "--no-baselines", "--no-progress"])
    assert args.no_baselines and args.no_progress
    assert not parser.parse_args(["--dataset", "folder", "--data-dir", "d", "--no-baselines", "--baselines"]).no_baselines


def _velodyne_points_for(calib_dir, pixels, depths):
    """Velodyne points (N, 4) that project onto the given (col, row) pixels at camera depth z (inverting
    P_rect_02 · R_rect_00 · [R|T]; +1 on the pixel because the projection subtracts 1, MATLAB style)."""
    c2c = kitti.read_calib_file(os.path.join(calib_dir, "calib_cam_to_cam.txt"))
    v2c = kitti.read_calib_file(os.path.join(calib_dir, "calib_velo_to_cam.txt"))
    p2 = c2c["P_rect_02"].reshape(3, 4)
    rrect = c2c["R_rect_00"].reshape(3, 3)
    r, t = v2c["R"].reshape(3, 3), v2c["T"]
    pts = []
    for (c, row), z in zip(pixels, depths):
        u, v = c + 1.0, row + 1.0
        zz = z - p2[2, 3]
        x = (u * z - p2[0, 2] * zz - p2[0, 3]) / p2[0, 0]
        y = (v * z - p2[1, 2] * zz - p2[1, 3]) / p2[1, 1]
        cam0 = rrect.T @ np.array([x, y, zz])
        pts.append(np.append(r.T @ (cam0 - t), 1.0))
    return np.array(pts, np.float32)


def test_eigen_velodyne_smoke(tmp_path):
    from tests.test_data_fakes import make_fake_raw
    root = str(tmp_path / "raw")
    make_fake_raw(root, {"2011_09_26_drive_0001": 3}, height=16, width=32)
    calib = os.path.join(root, "2011_09_26")
    rng = np.random.default_rng(0)
    pixels = [(int(c), int(r)) for c, r in zip(rng.integers(0, 32, 40), rng.integers(0, 16, 40))]
    depths = rng.uniform(2, 90, 40)                      # some beyond the 80 m cap
    velo_dir = os.path.join(root, "2011_09_26", "2011_09_26_drive_0001_sync", "velodyne_points", "data")
    os.makedirs(velo_dir)
    velo = os.path.join(velo_dir, "0000000001.bin")
    _velodyne_points_for(calib, pixels, depths).tofile(velo)
    split = tmp_path / "list.txt"
    split.write_text("2011_09_26_drive_0001 1\n")
    gt = kitti.velodyne_depth_map(calib, velo, (16, 32)).astype(np.float64)
    assert (gt > 0).sum() >= 30
    for crop in (True, False):
        res = evaluate.evaluate(None, "eigen", root, split=str(split), garg_crop=crop, progress=False)
        mask = (gt > 1e-3) & (gt < 80)
        if crop:   # rows int(0.408·16)=6 .. int(0.992·16)=15, cols int(0.036·32)=1 .. int(0.964·32)=30
            box = np.zeros_like(mask)
            box[6:15, 1:30] = True
            mask &= box
        # zero disparity: the Eigen script turns its infinite depth into 0, then clamps it to 1e-3 m
        expected = np.mean(np.abs(gt[mask] - 1e-3) / gt[mask])
        zero = res["methods"]["zero"]["depth"]
        assert zero["per_image_mean"]["abs_rel"] == pytest.approx(expected, rel=1e-5)
        assert zero["num_images"]["abs_rel"] == 1
        assert np.isfinite(res["methods"]["opencv"]["depth"]["pooled"]["rmse"])
        assert "flow" not in res["methods"]["zero"]


def test_kitti2012_layout(synthetic_dir, tmp_path):
    """KITTI 2012 layout: grayscale image_0/image_1 (replicated to RGB), GT folders without the _0 suffix."""
    import shutil
    import cv2
    root = tmp_path / "kitti2012" / "training"
    for src, dst in (("image_2", "image_0"), ("image_3", "image_1")):
        (root / dst).mkdir(parents=True)
        for f in os.listdir(os.path.join(synthetic_dir, src)):
            gray = cv2.imread(os.path.join(synthetic_dir, src, f), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(root / dst / f), gray)
    for src, dst in (("flow_occ", "flow_occ"), ("flow_noc", "flow_noc"), ("disp_occ_0", "disp_occ"),
                     ("disp_noc_0", "disp_noc")):
        shutil.copytree(os.path.join(synthetic_dir, src), root / dst)
    spec = datasets.list_frames("kitti2012", str(tmp_path / "kitti2012"))[0]
    frame = datasets.load_frame(spec, "kitti2012")
    img = frame.images["left_t"]
    assert (img[..., 0] == img[..., 1]).all() and (img[..., 1] == img[..., 2]).all()
    res = evaluate.evaluate(None, "kitti2012", str(tmp_path / "kitti2012"), progress=False)
    zero = res["methods"]["zero"]
    assert set(zero) == {"flow", "disparity"}            # no t+1 disparity GT, no calibration → no SF, no depth
    assert res["methods"]["opencv"]["flow"]["pooled"]["epe_noc"] < zero["flow"]["pooled"]["epe_noc"]


def test_2015_layout_from_synthetic_writer(tmp_path):
    from bridge_jax.data import synthetic
    out = synthetic.write_kitti_layout(str(tmp_path / "syn"), num=2, seed=3, height=48, width=96)
    specs = datasets.list_frames("kitti2015", out)
    assert [s.frame_id for s in specs] == ["000000", "000001"]
    frame = datasets.load_frame(specs[1], "kitti2015")
    ref = synthetic.render_sample(synthetic.sample_seed(3, 1), 48, 96)
    cycle = np.stack([frame.images[k] for k in ("left_t", "right_t", "left_t1", "right_t1")])
    np.testing.assert_array_equal(cycle, ref["cycle"])
    disp = frame.gt["disp_noc_0"]
    np.testing.assert_array_equal(disp > 0, ref["noc_disp_t"])
    assert np.abs(disp - ref["disp_t"])[ref["noc_disp_t"]].max() <= 0.5 / 256 + 1e-5
    np.testing.assert_array_equal(frame.gt["flow_occ_valid"], ref["valid_flow"])
    assert np.abs(frame.gt["flow_occ"] - ref["flow"])[ref["valid_flow"]].max() <= 0.5 / 64 + 1e-5
    assert frame.focal == pytest.approx(ref["focal"]) and frame.baseline == pytest.approx(0.54)
    # the in-memory frames (training's validation) are the same samples, without the 16-bit PNG rounding
    mem = datasets.synthetic_frames(2, 3, 48, 96)[1]
    for k, img in frame.images.items():
        np.testing.assert_array_equal(mem.images[k], img)
    np.testing.assert_array_equal(mem.gt["disp_noc_0"], np.where(ref["noc_disp_t"], ref["disp_t"], 0.0))
    np.testing.assert_array_equal(mem.gt["flow_noc_valid"], ref["noc_flow"])


def test_2012_grayscale_layout_with_calibration(tmp_path):
    import cv2
    t = tmp_path / "training"
    for d in ("image_0", "image_1", "disp_occ", "calib"):
        (t / d).mkdir(parents=True)
    rng = np.random.default_rng(1)
    for d in ("image_0", "image_1"):
        for s in ("10", "11"):
            cv2.imwrite(str(t / d / f"000000_{s}.png"), rng.integers(0, 256, (6, 10), dtype=np.uint8))
    kitti.write_disp_png(str(t / "disp_occ" / "000000_10.png"), np.full((6, 10), 3.0), None)
    (t / "calib" / "000000.txt").write_text("P0: 700 0 300 0 0 700 90 0 0 0 1 0\n"
                                            "P1: 700 0 300 -378 0 700 90 0 0 0 1 0\n")
    (spec,) = datasets.list_frames("kitti2012", str(tmp_path))
    frame = datasets.load_frame(spec, "kitti2012")
    c = np.stack(list(frame.images.values()))
    assert c.shape == (4, 6, 10, 3) and (c[..., 0] == c[..., 1]).all() and (c[..., 1] == c[..., 2]).all()
    assert frame.focal == 700 and frame.baseline == pytest.approx(0.54)
    np.testing.assert_allclose(frame.gt["disp_occ_0"], 3.0)
