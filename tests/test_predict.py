"""predict: pair, cycle, folder, video (mono / side-by-side stereo), KITTI submission round trip, bad input."""

import json
import os

import cv2
import numpy as np
import pytest

from bridge_jax import inference, predict
from bridge_jax.eval import datasets, methods

H, W = 100, 200          # input resolution, deliberately not the working size (128×256)




@pytest.fixture(scope="module")
def predictor(tiny_checkpoint):
    return inference.load_predictor(tiny_checkpoint, height=128, width=256)


@pytest.fixture(scope="module")
def frames():
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 255, (H // 4, W // 4 + 8, 3), dtype=np.uint8), (W + 32, H),
                      interpolation=cv2.INTER_CUBIC)
    return [np.ascontiguousarray(base[:, 8 * i: 8 * i + W]) for i in range(4)]   # shifts of 8 px


def _disp(disp_valid):
    """A KITTI disparity PNG's (disparity, valid) as one map, 0 where invalid."""
    disp, valid = disp_valid
    return np.where(valid, disp, 0.0)


def _write(path, rgb):
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))
    return str(path)


def _decodable(path, shape=(H, W)):
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert img is not None, path
    assert img.shape[:2] == shape, (path, img.shape)
    return img


def _run(args):
    return predict.main([*args, "--no-progress"])


def test_pair(tiny_checkpoint, frames, tmp_path):
    a, b = _write(tmp_path / "a.png", frames[0]), _write(tmp_path / "b.jpg", frames[1])
    out = tmp_path / "out"
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(out), "--working-size", "128x256",
                 "--raw", "png,npy"]) == 0
    _decodable(out / "flow" / "000000.png")
    from bridge_jax.data import kitti
    flow, valid = kitti.read_flow_png(str(out / "flow_kitti" / "000000.png"))
    assert flow.shape == (H, W, 2) and valid.all()
    npy = np.load(out / "flow_npy" / "000000.npy")
    assert npy.shape == (H, W, 2) and npy.dtype == np.float32
    np.testing.assert_allclose(flow, npy, atol=1 / 64 + 1e-6)      # KITTI PNG quantises to 1/64 px
    _decodable(out / "legend_flow.png", (256, 256))
    desc = json.loads((out / "predict.json").read_text())
    assert desc["kind"] == "pair" and desc["outputs"] == {"flow": 1}


def test_stereo_pair_with_depth(predictor, frames, tmp_path):
    from bridge_jax.data import kitti
    a, b = _write(tmp_path / "a.png", frames[0]), _write(tmp_path / "b.png", frames[1])
    out2 = tmp_path / "out2"
    src = predict.open_inputs([a, b], pair_kind="stereo")
    predict.predict_source(predictor, src, str(out2), focal=100.0, baseline=0.5, progress=False, raw=("png",))
    _decodable(out2 / "disparity" / "000000.png")
    _decodable(out2 / "depth" / "000000.png")
    disp = _disp(kitti.read_disp_png(str(out2 / "disparity_kitti" / "000000.png")))
    assert disp.shape == (H, W)
    for leg in ("legend_disparity.png", "legend_depth.png"):
        assert (out2 / leg).is_file()


def test_cycle_folder_and_stereo_folder(predictor, frames, tmp_path):
    paths = [_write(tmp_path / f"{n}.png", frames[i]) for i, n in enumerate(("lt", "rt", "lt1", "rt1"))]
    src = predict.open_inputs(paths)
    assert src.kind == "cycle"
    out = tmp_path / "cycle"
    predict.predict_source(predictor, src, str(out), progress=False)
    for sub, n in (("disparity", 2), ("flow", 1), ("disparity_t1_in_t", 1)):
        assert sorted(os.listdir(out / sub)) == [f"{i:06d}.png" for i in range(n)]
        for f in os.listdir(out / sub):
            _decodable(out / sub / f)
    # mono folder: flow between consecutive frames
    folder = tmp_path / "mono"
    folder.mkdir()
    for i in range(3):
        _write(folder / f"f{i:02d}.png", frames[i])
    out = tmp_path / "mono_out"
    predict.predict_source(predictor, predict.open_inputs([str(folder)]), str(out), progress=False, batch=4)
    assert sorted(os.listdir(out / "flow")) == ["000000.png", "000001.png"]
    assert not (out / "disparity").exists()
    # stereo folder (left/ right/)
    st = tmp_path / "stereo"
    (st / "left").mkdir(parents=True)
    (st / "right").mkdir()
    for i in range(2):
        _write(st / "left" / f"{i}.png", frames[i])
        _write(st / "right" / f"{i}.png", frames[i + 1])
    out = tmp_path / "stereo_out"
    predict.predict_source(predictor, predict.open_inputs([str(st)]), str(out), progress=False)
    assert len(os.listdir(out / "disparity")) == 2 and len(os.listdir(out / "flow")) == 1


def _write_video(path, imgs, fps=5):
    h, w = imgs[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), fps, (w, h))
    assert vw.isOpened()
    for im in imgs:
        vw.write(np.ascontiguousarray(im[..., ::-1]))
    vw.release()
    return str(path)


def _count_video(path):
    cap = cv2.VideoCapture(str(path))
    n, shape = 0, None
    while True:
        ok, fr = cap.read()
        if not ok:
            break
        n, shape = n + 1, fr.shape
    cap.release()
    return n, shape


def test_video_mono_and_side_by_side(predictor, frames, tmp_path):
    video = _write_video(tmp_path / "v.avi", frames[:3])
    out = tmp_path / "vout"
    desc = predict.predict_source(predictor, predict.open_inputs([video]), str(out), progress=False)
    assert desc["frames"] == 3
    assert sorted(os.listdir(out / "flow")) == ["000000.png", "000001.png"]
    n, shape = _count_video(out / "video.mp4")
    assert n == 3 and shape[0] == H and shape[1] > 2 * W        # panel: input | flow
    sbs = _write_video(tmp_path / "sbs.avi", [np.concatenate([f, g], 1) for f, g in zip(frames[:2], frames[1:3])])
    out = tmp_path / "sbs_out"
    predict.predict_source(predictor, predict.open_inputs([sbs], stereo_video="sbs"), str(out), progress=False)
    assert len(os.listdir(out / "disparity")) == 2 and len(os.listdir(out / "flow")) == 1
    for f in os.listdir(out / "disparity"):
        _decodable(out / "disparity" / f)
    n, shape = _count_video(out / "video.mp4")
    assert n == 2 and shape[1] > 3 * W                           # input | flow | disparity


def test_kitti_submission_roundtrip(predictor, tmp_path):
    from bridge_jax.data import kitti, synthetic
    data = tmp_path / "kitti15"
    synthetic.write_kitti_layout(str(data), 2, seed=3, height=128, width=256)
    out = tmp_path / "sub"
    desc = predict.kitti_submission(predictor, str(data), str(out), progress=False)
    assert desc["kitti_year"] == 2015
    specs = datasets.list_frames("folder", str(data))
    frames = [datasets.load_frame(s, "folder") for s in specs]
    preds = methods.ModelMethod(predictor)(frames)
    # flow agrees with the inference module's own input-resolution path (align_corners + u·w/W, v·h/H)
    np.testing.assert_allclose(preds[0]["flow"], predictor.predict_pair(frames[0].images["left_t"],
                                                                        frames[0].images["left_t1"]), atol=1e-4)
    for frame, pred in zip(frames, preds):
        name = f"{frame.frame_id}_10.png"
        d0 = _disp(kitti.read_disp_png(str(out / "disp_0" / name)))
        d1 = _disp(kitti.read_disp_png(str(out / "disp_1" / name)))
        fl, valid = kitti.read_flow_png(str(out / "flow" / name))
        assert d0.shape == d1.shape == (128, 256) and valid.all()
        np.testing.assert_allclose(d0, np.clip(pred["disp_t"], 1 / 256, 255), atol=1 / 256 + 1e-6)
        np.testing.assert_allclose(d1, np.clip(pred["disp_1"], 1 / 256, 255), atol=1 / 256 + 1e-6)
        np.testing.assert_allclose(fl, pred["flow"], atol=1 / 64 + 1e-6)
    # KITTI 2012 layout (grayscale image_0 / image_1): stereo/ and flow/
    k12 = tmp_path / "kitti12" / "testing"
    for src, dst in (("image_2", "image_0"), ("image_3", "image_1")):
        (k12 / dst).mkdir(parents=True)
        for f in os.listdir(data / src):
            g = cv2.imread(str(data / src / f), cv2.IMREAD_GRAYSCALE)
            cv2.imwrite(str(k12 / dst / f), g)
    out12 = tmp_path / "sub12"
    desc = predict.kitti_submission(predictor, str(tmp_path / "kitti12"), str(out12), progress=False)
    assert desc["kitti_year"] == 2012 and desc["split"] == "testing"
    assert sorted(os.listdir(out12 / "stereo")) == sorted(os.listdir(out12 / "flow")) == ["000000_10.png",
                                                                                        "000001_10.png"]
    assert kitti.read_flow_png(str(out12 / "flow" / "000001_10.png"))[0].shape == (128, 256, 2)


def test_bad_inputs(tiny_checkpoint, frames, tmp_path, capsys):
    a, b = _write(tmp_path / "a.png", frames[0]), _write(tmp_path / "b.png", frames[1])
    out = tmp_path / "taken"
    out.mkdir()
    (out / "keep.txt").write_text("x")
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "taken" in err[0] and "--overwrite" in err[0]
    assert os.listdir(out) == ["keep.txt"]
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"junk")
    assert _run(["--checkpoint", tiny_checkpoint, a, str(bad), "--out", str(tmp_path / "o1"),
                 "--working-size", "128x256"]) == 2
    assert "bad.png" in capsys.readouterr().err
    vid = tmp_path / "broken.mp4"
    vid.write_bytes(b"\x00" * 100)
    assert _run(["--checkpoint", tiny_checkpoint, str(vid), "--out", str(tmp_path / "o2")]) == 2
    assert "broken.mp4" in capsys.readouterr().err
    assert _run(["--checkpoint", str(tmp_path / "missing_ckpt"), a, b, "--out", str(tmp_path / "o3")]) == 2
    assert "missing_ckpt" in capsys.readouterr().err
    # nothing half-written next to the requested outputs
    leftovers = [f for f in os.listdir(tmp_path) if f.startswith(".")]
    assert leftovers == [] and not (tmp_path / "o1").exists() and not (tmp_path / "o2").exists()
