"""predict: pair, cycle, folder, video (mono / side-by-side stereo), output names and predict.json's mapping,
raw .flo / .pfm outputs, KITTI submission round trip, bad input, --help."""

import json
import os
import struct

import cv2
import numpy as np
import pytest

from bridge_jax import flowio, inference, predict, resizing
from bridge_jax.eval import datasets, methods

H, W = 100, 200          # input resolution, deliberately not the working size (128×256)



@pytest.fixture(scope="module")
def predictor(tiny_checkpoint):
    return inference.load_predictor(tiny_checkpoint, size=(128, 256))


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
    a, b = _write(tmp_path / "frame0.png", frames[0]), _write(tmp_path / "frame1.jpg", frames[1])
    out = tmp_path / "out"
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(out), "--working-size", "128x256",
                 "--raw", "png,npy,flo"]) == 0
    # outputs keep the stem of the frame-t image
    assert sorted(os.listdir(out / "flow")) == ["frame0.png"]
    _decodable(out / "flow" / "frame0.png")
    from bridge_jax.data import kitti
    flow, valid = kitti.read_flow_png(str(out / "flow_kitti" / "frame0.png"))
    assert flow.shape == (H, W, 2) and valid.all()
    npy = np.load(out / "flow_npy" / "frame0.npy")
    assert npy.shape == (H, W, 2) and npy.dtype == np.float32
    np.testing.assert_allclose(flow, npy, atol=1 / 64 + 1e-6)      # KITTI PNG quantises to 1/64 px
    # the .flo is exactly the float32 values: magic, width, height, then u, v interleaved, top row first
    data = (out / "flow_flo" / "frame0.flo").read_bytes()
    assert data[:12] == b"PIEH" + struct.pack("<ii", W, H) and len(data) == 12 + H * W * 8
    assert data[12:] == npy.astype("<f4").tobytes()
    _decodable(out / "legend_flow.png", (256, 256))
    desc = json.loads((out / "predict.json").read_text())
    assert desc["kind"] == "pair" and desc["outputs"] == {"flow": 1}
    assert desc["raw"] == ["flo", "npy", "png"]
    assert desc["mapping"] == [{"index": 0, "stem": "frame0", "inputs": {"image": a}, "flow_to": {"image": b}}]


def test_stereo_pair_with_depth(predictor, frames, tmp_path):
    from bridge_jax.data import kitti
    a, b = _write(tmp_path / "a.png", frames[0]), _write(tmp_path / "b.png", frames[1])
    out2 = tmp_path / "out2"
    src = predict.open_inputs([a, b], task="stereo")
    desc = predict.predict_source(predictor, src, str(out2), focal=100.0, baseline=0.5, progress=False,
                                  raw=("png", "npy", "pfm", "flo"))
    _decodable(out2 / "disparity" / "a.png")
    _decodable(out2 / "depth" / "a.png")
    disp = _disp(kitti.read_disp_png(str(out2 / "disparity_kitti" / "a.png")))
    assert disp.shape == (H, W)
    for leg in ("legend_disparity.png", "legend_depth.png"):
        assert (out2 / leg).is_file()
    # .pfm: "Pf", width height, scale -1.0 (little-endian), then the rows from the bottom up
    npy = np.load(out2 / "disparity_npy" / "a.npy")
    header = f"Pf\n{W} {H}\n-1.0\n".encode()
    data = (out2 / "disparity_pfm" / "a.pfm").read_bytes()
    assert data == header + npy[::-1].astype("<f4").tobytes()
    depth = flowio.read_pfm(out2 / "depth_pfm" / "a.pfm")
    np.testing.assert_array_equal(depth, np.load(out2 / "depth_npy" / "a.npy"))
    ok = npy > 1.0                                           # depth = f·B/d = 100·0.5/d (unclamped there)
    np.testing.assert_allclose(depth[ok], 50.0 / npy[ok], rtol=1e-5)
    assert not (out2 / "flow_flo").exists()                  # a stereo pair has no flow, hence no .flo
    assert desc["mapping"] == [{"index": 0, "stem": "a", "inputs": {"left": a, "right": b}}]


def test_cycle_folder_and_stereo_folder(predictor, frames, tmp_path):
    paths = [_write(tmp_path / f"{n}.png", frames[i]) for i, n in enumerate(("lt", "rt", "lt1", "rt1"))]
    src = predict.open_inputs(paths)
    assert src.kind == "cycle"
    out = tmp_path / "cycle"
    desc = predict.predict_source(predictor, src, str(out), progress=False)
    # frame t is named after left_t ("lt"), frame t+1 after left_t1 ("lt1")
    for sub, names in (("disparity", ["lt.png", "lt1.png"]), ("flow", ["lt.png"]),
                       ("disparity_t1_in_t", ["lt.png"]), ("disparity_kitti", ["lt.png", "lt1.png"])):
        assert sorted(os.listdir(out / sub)) == names
        for f in os.listdir(out / sub):
            _decodable(out / sub / f)
    assert desc["mapping"] == [
        {"index": 0, "stem": "lt", "inputs": {"left": paths[0], "right": paths[1]},
         "flow_to": {"left": paths[2], "right": paths[3]}},
        {"index": 1, "stem": "lt1", "inputs": {"left": paths[2], "right": paths[3]}}]
    assert json.loads((out / "predict.json").read_text())["mapping"] == desc["mapping"]
    # mono folder: flow between consecutive frames
    folder = tmp_path / "mono"
    folder.mkdir()
    for i in range(3):
        _write(folder / f"f{i:02d}.png", frames[i])
    out = tmp_path / "mono_out"
    predict.predict_source(predictor, predict.open_inputs([str(folder)]), str(out), progress=False, batch=4)
    assert sorted(os.listdir(out / "flow")) == ["f00.png", "f01.png"]
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
    assert sorted(os.listdir(out / "disparity")) == ["0.png", "1.png"] and os.listdir(out / "flow") == ["0.png"]


def test_unique_stems():
    assert predict.unique_stems(["a/frame.png", "b/frame.png", "c/x.jpg"]) == ["frame", "frame_2", "x"]
    # a suffix never takes a name that another input has; compared case-insensitively
    assert predict.unique_stems(["a/f.png", "b/f.png", "f_2.png"]) == ["f", "f_3", "f_2"]
    assert predict.unique_stems(["a/F.png", "b/f.png"]) == ["F", "f_2"]


def test_shared_stems_stay_apart(predictor, frames, tmp_path):
    # a cycle whose t and t+1 left images have the same file name, in different folders
    for d in ("t", "t1"):
        (tmp_path / d).mkdir()
    paths = [_write(tmp_path / "t" / "left.png", frames[0]), _write(tmp_path / "t" / "right.png", frames[1]),
             _write(tmp_path / "t1" / "left.png", frames[1]), _write(tmp_path / "t1" / "right.png", frames[2])]
    out = tmp_path / "out"
    desc = predict.predict_source(predictor, predict.open_inputs(paths), str(out), progress=False, raw=("npy",))
    assert sorted(os.listdir(out / "disparity")) == ["left.png", "left_2.png"]
    assert sorted(os.listdir(out / "disparity_npy")) == ["left.npy", "left_2.npy"]
    assert [(m["stem"], m["inputs"]["left"]) for m in desc["mapping"]] == [("left", paths[0]),
                                                                           ("left_2", paths[2])]
    # the two disparities really are the two frames' (frame t+1 is its own prediction, not frame t's again)
    d0, d1 = predictor.predict([("stereo", frames[0], frames[1]), ("stereo", frames[1], frames[2])])
    assert np.abs(d0 - d1).max() > 0.1
    np.testing.assert_allclose(np.load(out / "disparity_npy" / "left.npy"), d0, rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(np.load(out / "disparity_npy" / "left_2.npy"), d1, rtol=1e-5, atol=1e-4)


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
    assert sorted(os.listdir(out / "flow")) == ["000000.png", "000001.png"]   # video: frame index numbering
    assert desc["mapping"][1] == {"index": 1, "stem": "000001", "inputs": {"video": video, "frame": 1},
                                  "flow_to": {"video": video, "frame": 2}}
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
    # a working size that is not a multiple of the model's 64: the option is blamed, with a size to try
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(tmp_path / "o4"),
                 "--working-size", "100x200"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --working-size 100x200: height and width must be multiples of 64 for model "
                   "resnet_md_tiny (try 128x192)"]
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(tmp_path / "o5"), "--raw", "png,tiff"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--raw png,tiff" in err[0] and "tiff" in err[0] and "flo" in err[0]
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(tmp_path / "o6"), "--refine", "9"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --refine 9: expected a whole number of refinement passes from 0 to 8"]
    # nothing half-written next to the requested outputs
    leftovers = [f for f in os.listdir(tmp_path) if f.startswith(".")]
    assert leftovers == [] and not any((tmp_path / f"o{i}").exists() for i in range(1, 7))


def test_refine_option_runs_the_refined_network_and_says_so(tiny_checkpoint, frames, tmp_path):
    """`--refine 1`: the written flow is the refined predictor's (not the plain one's), and predict.json says
    how many passes ran; without the option a checkpoint path runs unrefined."""
    from bridge_jax import inference
    a, b = _write(tmp_path / "a.png", frames[0]), _write(tmp_path / "b.png", frames[1])
    outs = {}
    for k in (0, 1):
        out = tmp_path / f"r{k}"
        args = ["--checkpoint", tiny_checkpoint, a, b, "--out", str(out), "--working-size", "128x256", "--raw", "npy"]
        assert _run(args + (["--refine", str(k)] if k else [])) == 0
        assert json.loads((out / "predict.json").read_text())["refine"] == k
        outs[k] = np.load(out / "flow_npy" / "a.npy")
    want = inference.load_predictor(tiny_checkpoint, size=(128, 256), test_time={"refine": 1}).predict_pair(
        cv2.imread(a)[..., ::-1], cv2.imread(b)[..., ::-1])
    np.testing.assert_allclose(outs[1], want, rtol=1e-5, atol=1e-5)
    assert np.abs(outs[1] - outs[0]).max() > 1e-4  # the pass changed the map


def _help_lines(parser):
    """(option strings, help) of every option of `parser` but -h."""
    return [(a.option_strings or [a.dest], a.help) for a in parser._actions if a.dest != "help"]


def test_help_teaches():
    parser = predict.build_parser()
    missing = [opts for opts, text in _help_lines(parser) if not text]
    assert missing == []
    text = parser.format_help()
    assert "bridge-predict --checkpoint" in text            # the docstring's examples are the epilog
    assert "flow_flo/<stem>.flo" in text and "mapping" in text
    assert "shipped model name such as demo" in text and "--debug" in text


# ---------------------------------------------------------------------------------- large and tiny inputs


def test_a_large_input_is_decoded_at_a_reduced_size_and_written_at_its_own(tiny_checkpoint, tmp_path, capsys):
    rng = np.random.default_rng(1)
    big = cv2.resize(rng.integers(0, 255, (60, 80, 3), dtype=np.uint8), (1280, 960), interpolation=cv2.INTER_CUBIC)
    a, b = _write(tmp_path / "a.png", big), _write(tmp_path / "b.png", np.roll(big, 8, axis=1))
    p = inference.load_predictor(tiny_checkpoint, size=(64, 64))
    img = predict.read_image(a, p.working_size)
    # 960x1280 at a 64x64 working size: 1/4 keeps >= 2x the working size per side (1/8 would be 120x160 < 128)
    assert img.shape == (240, 320, 3) and inference.input_size(img) == (960, 1280)
    np.testing.assert_array_equal(predict.read_image(a), big)  # without a working size: the full image
    out = tmp_path / "out"
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(out), "--working-size", "64x64",
                 "--raw", "png,npy"]) == 0
    assert np.load(out / "flow_npy" / "a.npy").shape == (960, 1280, 2)
    _decodable(out / "flow" / "a.png", (960, 1280))
    flow, valid = predict.kitti.read_flow_png(str(out / "flow_kitti" / "a.png"))
    assert flow.shape == (960, 1280, 2) and valid.all()
    err = capsys.readouterr().err
    assert "the 960x1280 input runs at 64x64" in err and "decoded at a reduced size" in err


def test_block_wise_writing_matches_whole_maps(monkeypatch):
    rng = np.random.default_rng(2)
    flow = rng.normal(0, 5, (37, 23, 2)).astype(np.float32)
    whole = predict.visualize.flow_to_color(flow, max_flow=7.0)
    monkeypatch.setattr(resizing, "ROW_BLOCK_PIXELS", 50)  # blocks of 2 rows
    np.testing.assert_array_equal(predict._by_rows(lambda f: predict.visualize.flow_to_color(f, max_flow=7.0),
                                                   flow), whole)
    small = rng.normal(0, 3, (5, 7, 2)).astype(np.float32)
    np.testing.assert_allclose(inference.flow_to_input_resolution(small, 37, 23),
                               resizing._resize(small, inference.resize_weights_align_corners(5, 37),
                                                 inference.resize_weights_align_corners(7, 23))
                               * np.array([23 / 7, 37 / 5], np.float32), rtol=1e-6)


def test_an_input_below_the_models_minimum_is_one_line(tiny_checkpoint, tmp_path, capsys):
    a = _write(tmp_path / "dot0.png", np.zeros((1, 1, 3), np.uint8))
    b = _write(tmp_path / "dot1.png", np.zeros((1, 1, 3), np.uint8))
    assert _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(tmp_path / "out")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {a}: a 1x1 input is smaller than model resnet_md_tiny accepts (at least 16x16 pixels, "
                   "height x width)"]
    assert not (tmp_path / "out").exists()
