"""File names that are not valid UTF-8 (Python hands them on as surrogate escapes, OpenCV's file functions crash
on them): images are read and written through `files.imread` / `files.imwrite`, predict runs on such a folder
end to end, and what OpenCV can only open by name (videos) is refused in one line."""

import json
import os

import cv2
import numpy as np
import pytest

from bridge_jax import files, predict
from bridge_jax.data import folders, videos

H, W = 64, 128
BAD = b"\xff\xfe"                    # not UTF-8 in any position
LONG = b"l" * 246                  # with ".png", a name of 250 bytes: near the 255-byte limit of a name


def _bytes_path(folder, name: bytes) -> str:
    """The str Python uses for `folder`/`name` (surrogate-escaped where `name` is not UTF-8)."""
    return os.path.join(str(folder), os.fsdecode(name))


def _write_png_by_bytes(path: bytes, bgr: np.ndarray) -> None:
    """A PNG written without bridge_jax: OpenCV encodes, os.open takes the name as bytes."""
    ok, buf = cv2.imencode(".png", bgr)
    assert ok
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o644)
    with os.fdopen(fd, "wb") as f:
        f.write(buf.tobytes())


def test_imwrite_and_imread_under_a_name_that_is_not_utf8(tmp_path):
    rng = np.random.default_rng(0)
    colour = rng.integers(0, 256, (5, 7, 3), dtype=np.uint8)
    deep = rng.integers(0, 65536, (5, 7), dtype=np.uint16)
    name = _bytes_path(tmp_path, BAD + b".png")
    assert files.imwrite(name, colour) == name
    # the file is there under the very bytes asked for, and holds exactly these pixels (decoded by OpenCV from
    # bytes read without bridge_jax)
    assert os.listdir(os.fsencode(tmp_path)) == [BAD + b".png"]
    with open(os.path.join(os.fsencode(tmp_path), BAD + b".png"), "rb") as f:
        raw = f.read()
    np.testing.assert_array_equal(cv2.imdecode(np.frombuffer(raw, np.uint8), cv2.IMREAD_UNCHANGED), colour)
    np.testing.assert_array_equal(files.imread(name), colour)
    # 16-bit single channel (the KITTI PNGs) keeps its depth with IMREAD_UNCHANGED
    other = _bytes_path(tmp_path, b"d" + BAD + b".png")
    files.imwrite(other, deep)
    got = files.imread(other, cv2.IMREAD_UNCHANGED)
    assert got.dtype == np.uint16
    np.testing.assert_array_equal(got, deep)
    # a file written by bytes name elsewhere reads back too
    third = os.path.join(os.fsencode(tmp_path), b"x" + BAD + b".png")
    _write_png_by_bytes(third, colour[::-1])
    np.testing.assert_array_equal(files.imread(os.fsdecode(third)), colour[::-1])


def test_imread_and_imwrite_report_what_they_cannot_do(tmp_path):
    (tmp_path / "empty.png").write_bytes(b"")
    (tmp_path / "text.png").write_bytes(b"not an image")
    assert files.imread(tmp_path / "empty.png") is None and files.imread(tmp_path / "text.png") is None
    with pytest.raises(OSError):
        files.imread(tmp_path / "missing.png")
    img = np.zeros((2, 2, 3), np.uint8)
    no_format = "no image format extension (.png, .jpg, ...)"
    for name, why in ((b"a.xyz", "OpenCV cannot encode a (2, 2, 3) uint8 array as .xyz"),
                      (b"no_extension", no_format),
                      (b"a." + BAD, no_format)):   # OpenCV would crash on this extension
        path = _bytes_path(tmp_path, name)
        with pytest.raises(ValueError) as e:
            files.imwrite(path, img)
        assert str(e.value) == f"cannot write image {files.shown_name(path)}: {why}"
    assert sorted(os.listdir(tmp_path)) == ["empty.png", "text.png"]   # nothing written, no temporary left


def test_names_opencv_can_open_and_how_any_name_prints():
    assert files.opencv_can_open("été/clip.mp4")
    assert not files.opencv_can_open(os.fsdecode(b"clip" + BAD + b".mp4"))
    assert files.shown_name(os.fsdecode(b"d/clip" + BAD + b".mp4")) == "d/clip\\xff\\xfe.mp4"
    assert files.shown_name("été") == "été"


def test_image_size_falls_back_to_opencv_under_any_name(tmp_path, monkeypatch):
    # a BMP has no PNG/JPEG header to read; with Pillow unable to read it too, OpenCV decodes the file
    import PIL.Image

    def no_pillow(*args, **kwargs):
        raise OSError("Pillow cannot read it")

    monkeypatch.setattr(PIL.Image, "open", no_pillow)
    ok, buf = cv2.imencode(".bmp", np.zeros((5, 7, 3), np.uint8))
    path = os.path.join(os.fsencode(tmp_path), BAD + b".bmp")
    with open(path, "wb") as f:
        f.write(buf.tobytes())
    assert folders.image_size(os.fsdecode(path)) == (5, 7)


def test_predict_on_a_folder_with_names_that_are_not_utf8(tiny_checkpoint, tmp_path, capsys):
    # a stereo folder (itself named in Latin-1) whose frames a, LONG and BAD (in left/ and right/) hold the same
    # pixels: the outputs named after LONG and BAD must equal those named after a
    rng = np.random.default_rng(1)
    base = cv2.resize(rng.integers(0, 255, (H // 4, W // 4 + 4, 3), dtype=np.uint8), (W + 16, H),
                      interpolation=cv2.INTER_CUBIC)
    left, right = base[:, 8:8 + W], base[:, :W]
    root = os.path.join(os.fsencode(tmp_path), b"s\xe9quence")
    for side, img in ((b"left", left), (b"right", right)):
        os.makedirs(os.path.join(root, side))
        for name in (b"a.png", LONG + b".png", BAD + b".png"):
            _write_png_by_bytes(os.path.join(root, side, name), np.ascontiguousarray(img[..., ::-1]))
    out = os.path.join(os.fsencode(tmp_path), b"out" + BAD)
    code = predict.main(["--checkpoint", tiny_checkpoint, os.fsdecode(root), "--out", os.fsdecode(out),
                         "--working-size", "64x128", "--raw", "png,npy", "--no-progress"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    assert captured.out.splitlines()[-1] == "wrote " + files.shown_name(os.fsdecode(out))
    stem = os.fsdecode(BAD)
    for sub, ext in ((b"disparity", b".png"), (b"disparity_kitti", b".png"), (b"disparity_npy", b".npy")):
        assert sorted(os.listdir(os.path.join(out, sub))) == [b"a" + ext, LONG + ext, BAD + ext], sub
    assert sorted(os.listdir(os.path.join(out, b"flow"))) == [b"a.png", LONG + b".png"]
    for sub in (b"disparity", b"disparity_kitti"):
        first = files.imread(os.fsdecode(os.path.join(out, sub, b"a.png")), cv2.IMREAD_UNCHANGED)
        assert first.shape[:2] == (H, W)
        for name in (LONG, BAD):
            np.testing.assert_array_equal(
                files.imread(os.fsdecode(os.path.join(out, sub, name + b".png")), cv2.IMREAD_UNCHANGED), first)
    for name in (LONG, BAD):
        np.testing.assert_array_equal(np.load(os.path.join(out, b"disparity_npy", name + b".npy")),
                                      np.load(os.path.join(out, b"disparity_npy", b"a.npy")))
    with open(os.path.join(out, b"predict.json"), "rb") as f:
        desc = json.load(f)
    last_left = os.fsdecode(os.path.join(root, b"left", BAD + b".png"))
    assert desc["mapping"][2]["stem"] == stem and desc["mapping"][2]["inputs"]["left"] == last_left
    # only the output folder is there beside the inputs: no staging folder left
    assert sorted(os.listdir(os.fsencode(tmp_path))) == [b"out" + BAD, b"s\xe9quence"]


def test_a_video_whose_name_opencv_cannot_take_is_one_line(tiny_checkpoint, tmp_path, capsys):
    video = os.path.join(os.fsencode(tmp_path), b"clip" + BAD + b".mp4")
    with open(video, "wb") as f:
        f.write(b"\0" * 64)   # refused by name, before its contents matter
    code = predict.main(["--checkpoint", tiny_checkpoint, os.fsdecode(video), "--out", str(tmp_path / "out"),
                         "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2
    assert err == (f"error: video {tmp_path}/clip\\xff\\xfe.mp4: OpenCV cannot open a file whose name is not valid "
                   "UTF-8 (rename it)\n")
    assert sorted(os.listdir(tmp_path)) == ["clip\udcff\udcfe.mp4"]
    with pytest.raises(videos.VideoError, match="not valid UTF-8"):
        videos.video_info(os.fsdecode(video))


def test_a_video_into_a_folder_opencv_cannot_take_is_refused_before_anything(tmp_path):
    out = _bytes_path(tmp_path, b"out" + BAD)
    source = predict.Source("video", False, iter([]), 2)
    with pytest.raises(predict.PredictError) as e:
        predict.predict_source(object(), source, out, progress=False)
    assert str(e.value) == (f"output folder {tmp_path}/out\\xff\\xfe: OpenCV cannot write video.mp4 into a folder "
                            "whose path is not valid UTF-8 (rename it, or --no-video)")
    assert os.listdir(tmp_path) == []
