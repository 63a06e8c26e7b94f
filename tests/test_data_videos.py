"""Stereo video files → the training folder layout (`bridge_jax.data.videos`)."""
import json
import os

import cv2
import numpy as np
import pytest

from bridge_jax.data import folders, videos


def _write_video(path, frames):
    h, w = frames[0].shape[:2]
    vw = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (w, h))
    assert vw.isOpened()
    for f in frames:
        vw.write(np.ascontiguousarray(f[..., ::-1]))
    vw.release()


def _flat(h, w, rgb):
    return np.broadcast_to(np.array(rgb, np.uint8), (h, w, 3)).copy()


def test_side_by_side_video_is_split_into_left_and_right_frames(tmp_path):
    # left half dark red, right half bright blue; brightness grows with the frame index
    frames = [np.concatenate([_flat(32, 48, (60 + 20 * i, 0, 0)), _flat(32, 48, (0, 0, 120 + 20 * i))], axis=1)
              for i in range(6)]
    _write_video(tmp_path / "sbs.avi", frames)
    out = tmp_path / "video"
    desc = videos.extract_stereo_video([str(tmp_path / "sbs.avi")], str(out), side_by_side=True, every=2)
    assert desc["frames"] == 3 and (desc["height"], desc["width"]) == (32, 48)
    assert sorted(os.listdir(out / "left")) == ["000000.png", "000001.png", "000002.png"]
    for k, i in enumerate((0, 2, 4)):  # every 2nd frame of the video
        left = cv2.imread(str(out / "left" / f"{k:06d}.png"))[..., ::-1].astype(int)
        right = cv2.imread(str(out / "right" / f"{k:06d}.png"))[..., ::-1].astype(int)
        assert np.abs(left[8:-8, 8:-8].mean((0, 1)) - (60 + 20 * i, 0, 0)).max() < 8
        assert np.abs(right[8:-8, 8:-8].mean((0, 1)) - (0, 0, 120 + 20 * i)).max() < 8
    assert json.load(open(out / "video.json"))["every"] == 2
    assert len(folders.folder_cycles(str(out))) == 2  # the trainer's folder source reads it: 3 frames, 2 cycles


def test_two_videos_of_different_sizes_and_bad_inputs_are_one_error_and_nothing_written(tmp_path):
    _write_video(tmp_path / "l.avi", [_flat(32, 48, (100, 100, 100))] * 3)
    _write_video(tmp_path / "r.avi", [_flat(32, 40, (100, 100, 100))] * 3)
    out = tmp_path / "video"
    with pytest.raises(videos.VideoError, match=r"frame 0: .*l.avi is 32x48 but .*r.avi is 32x40"):
        videos.extract_stereo_video([str(tmp_path / "l.avi"), str(tmp_path / "r.avi")], str(out))
    assert not out.exists() and [p for p in os.listdir(tmp_path) if p.startswith(".video")] == []
    with pytest.raises(videos.VideoError, match="does not exist"):
        videos.extract_stereo_video([str(tmp_path / "nope.mp4")], str(out), side_by_side=True)
    (tmp_path / "text.avi").write_text("not a video")
    with pytest.raises(videos.VideoError, match="text.avi"):
        videos.extract_stereo_video([str(tmp_path / "text.avi")], str(out), side_by_side=True)
    with pytest.raises(videos.VideoError, match="without --side-by-side"):
        videos.extract_stereo_video([str(tmp_path / "l.avi")], str(out))
    with pytest.raises(videos.VideoError, match="odd.avi has odd width 47"):  # (encoders round odd widths)
        videos.split_side_by_side(_flat(32, 47, (1, 2, 3)), "odd.avi")
    assert not out.exists()


def test_cli_is_one_line_on_error(tmp_path, capsys):
    assert videos.main([str(tmp_path / "missing.mp4"), "--side-by-side", "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "missing.mp4 does not exist" in err[0]
