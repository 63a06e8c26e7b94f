"""Videos that end early: a truncated file and left/right files of different lengths are shortened with one note
on stderr naming the file(s), the frame counts and what is used (`bridge_jax.data.videos`)."""
import os

import cv2
import numpy as np

from bridge_jax.data import videos
from tests.test_data_videos import _write_video


def _frames(n):
    """`n` frames of noise: large JPEGs, so that a cut lands in the frame data, not in the AVI header."""
    rng = np.random.default_rng(n)
    return [rng.integers(0, 256, (32, 48, 3), dtype=np.uint8) for _ in range(n)]


def _truncated(path, num_frames, keep):
    """An MJPG AVI of `num_frames` frames cut to its first `keep` fraction of bytes: the header still states
    `num_frames` (the index at the end is gone), fewer decode. Returns how many decode."""
    _write_video(path, _frames(num_frames))
    data = path.read_bytes()
    path.write_bytes(data[:int(len(data) * keep)])
    cap = cv2.VideoCapture(str(path))
    stated, decoded = int(cap.get(cv2.CAP_PROP_FRAME_COUNT)), 0
    while cap.read()[0]:
        decoded += 1
    cap.release()
    assert stated == num_frames and 0 < decoded < num_frames  # the case under test
    return decoded


def _notes(capsys):
    return [line for line in capsys.readouterr().err.splitlines() if line.startswith("note:")]


def test_a_truncated_video_is_one_note_naming_the_file_and_both_counts(tmp_path, capsys):
    path = tmp_path / "cut.avi"
    n = _truncated(path, 10, keep=0.6)
    capsys.readouterr()
    assert len(list(videos.video_frames(str(path)))) == n
    assert _notes(capsys) == [f"note: video {path} has {n} decodable frames, its header states 10 (a truncated or "
                              f"damaged file?): using those {n}"]
    # a whole video, and one read only partly (--max-frames), are silent
    _write_video(tmp_path / "whole.avi", _frames(4))
    assert len(list(videos.video_frames(str(tmp_path / "whole.avi")))) == 4
    first = videos.video_frames(str(path))
    next(first)
    first.close()
    assert _notes(capsys) == []
    # bridge-frames of the side-by-side truncated video: the note, and the frames that decode
    out = tmp_path / "out"
    assert videos.main([str(path), "--side-by-side", "--out", str(out)]) == 0
    assert len(_notes(capsys)) == 1 and len(os.listdir(out / "left")) == n


def test_left_and_right_of_different_lengths_are_one_note_and_the_shorter_length(tmp_path, capsys):
    left, right = tmp_path / "left.avi", tmp_path / "right.avi"
    _write_video(left, _frames(6))
    _write_video(right, _frames(4))
    pairs = list(videos.stereo_frames([str(left), str(right)]))
    assert len(pairs) == 4
    np.testing.assert_array_equal(pairs[3][0], next(f for i, f in enumerate(videos.video_frames(str(left)))
                                                    if i == 3))
    assert _notes(capsys) == [f"note: {right} has 4 frames, {left} 6: using the first 4 of each"]
    # the other way round, through bridge-frames: 4 stereo frames written; the short file is now the left one
    out = tmp_path / "out"
    assert videos.main([str(right), str(left), "--out", str(out)]) == 0
    assert _notes(capsys) == [f"note: {right} has 4 frames, {left} 6: using the first 4 of each"]
    assert len(os.listdir(out / "left")) == len(os.listdir(out / "right")) == 4
    # equal lengths: no note
    assert len(list(videos.stereo_frames([str(right), str(right)]))) == 4
    assert _notes(capsys) == []


def test_a_truncated_right_video_says_so_in_the_one_note(tmp_path, capsys):
    left, right = tmp_path / "left.avi", tmp_path / "right.avi"
    _write_video(left, _frames(10))
    n = _truncated(right, 10, keep=0.6)
    capsys.readouterr()
    assert len(list(videos.stereo_frames([str(left), str(right)]))) == n
    assert _notes(capsys) == [f"note: {right} has {n} frames (its header states 10: a truncated or damaged file?), "
                              f"{left} 10: using the first {n} of each"]
