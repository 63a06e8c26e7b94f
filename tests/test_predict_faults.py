"""bridge-predict when things go wrong around the network: a full disk while writing the outputs is one line naming
the file (under the requested folder) with nothing left behind, and tiny inputs that are upscaled a lot to the
working size get one note per run naming the sizes and the option that avoids it."""
import errno
import os

import cv2
import numpy as np
import pytest

from bridge_jax import files, inference, predict



def full_disk(path, data):
    """A writer on a full disk: OSError ENOSPC as a write call raises it, naming no file."""
    raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))


def _frames(n, h, w):
    rng = np.random.default_rng(0)
    base = cv2.resize(rng.integers(0, 255, (h // 2, w // 2 + 4, 3), dtype=np.uint8), (w + 8, h))
    return [np.ascontiguousarray(base[:, 2 * i: 2 * i + w]) for i in range(n)]


def _write(path, rgb):
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]))
    return str(path)


def _run(args):
    return predict.main([*args, "--no-progress"])


def _leftovers(folder):
    return [f for f in os.listdir(folder) if f.startswith(".")]


# ---------------------------------------------------------------------------------------------- a full disk


def test_write_bytes_names_the_file_a_failed_write_was_for(tmp_path, monkeypatch):
    real_fdopen = os.fdopen

    class FullDisk:
        def __init__(self, fd, mode):
            self.f = real_fdopen(fd, mode)

        def __enter__(self):
            return self

        def __exit__(self, *exc):
            self.f.close()

        def write(self, data):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(files.os, "fdopen", FullDisk)
    with pytest.raises(OSError) as info:
        files.write_bytes(tmp_path / "a.png", b"data")
    assert info.value.errno == errno.ENOSPC and info.value.filename == str(tmp_path / "a.png")
    assert os.listdir(tmp_path) == []   # the temporary file is gone too


def test_staged_dir_names_the_file_under_the_requested_folder(tmp_path):
    out = tmp_path / "out"
    with pytest.raises(OSError) as info:
        with files.staged_dir(out) as tmp:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), os.path.join(tmp, "flow", "a.png"),
                          None, os.path.join(tmp, "flow"))
    assert info.value.filename == str(out / "flow" / "a.png") and info.value.filename2 == str(out / "flow")
    assert os.listdir(tmp_path) == []
    with pytest.raises(OSError) as info:   # a file elsewhere keeps its name
        with files.staged_dir(out):
            raise OSError(errno.EACCES, os.strerror(errno.EACCES), str(tmp_path / "input.png"))
    assert info.value.filename == str(tmp_path / "input.png") and os.listdir(tmp_path) == []


@pytest.mark.parametrize("overwrite", [False, True])
def test_a_full_disk_while_writing_is_one_line_naming_the_file(tiny_checkpoint, tmp_path, monkeypatch, capsys,
                                                                overwrite):
    a, b = (_write(tmp_path / f"f{i}.png", f) for i, f in enumerate(_frames(2, 64, 128)))
    out = tmp_path / "out"
    if overwrite:   # an earlier result stays as it was
        out.mkdir()
        (out / "keep.txt").write_text("x")

    monkeypatch.setattr(predict.visualize, "write_image", full_disk)
    rc = _run(["--checkpoint", tiny_checkpoint, a, b, "--out", str(out), "--working-size", "64x128", "--raw", "npy"]
              + (["--overwrite"] if overwrite else []))
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and err == [f"error: {out / 'flow' / 'f0.png'}: No space left on device"]
    assert _leftovers(tmp_path) == []
    assert os.listdir(out) == ["keep.txt"] if overwrite else not out.exists()


def test_opencv_failing_to_write_names_the_file(tmp_path):
    writer = predict.Writer(str(tmp_path), raw=(), max_flow=1.0, max_disp=None, focal=None, baseline=None,
                            video_fps=None)
    (tmp_path / "flow").mkdir()
    (tmp_path / "flow" / "000000.png").mkdir()   # a folder in the way of the image
    with pytest.raises(OSError) as info:
        writer.flow(0, np.zeros((8, 8, 2), np.float32))
    # the error names the output, not the temporary file it was written to first
    assert info.value.filename == str(tmp_path / "flow" / "000000.png") and info.value.filename2 is None
    assert info.value.strerror == "Is a directory" and ".tmp-" not in str(info.value)
    assert not [p for p in os.listdir(tmp_path / "flow") if ".tmp-" in p]


def test_a_write_error_without_a_reason_says_so_and_whether_the_disk_is_full(tmp_path, monkeypatch):
    path = str(tmp_path / "a.npy")

    def numpy_on_a_full_disk(p, data):   # what np.save raises when the disk fills up mid-file: no errno
        raise OSError("262144 requested and 35808 written")

    def free_bytes(n):
        monkeypatch.setattr(predict.shutil, "disk_usage", lambda p: predict.shutil._ntuple_diskusage(10 ** 9, 0, n))

    free_bytes(10 ** 9)
    with pytest.raises(OSError) as info:
        predict.save_file(path, numpy_on_a_full_disk, None)
    assert (info.value.filename, info.value.strerror) == (path, "cannot write it (262144 requested and 35808 "
                                                                "written)")
    free_bytes(0)
    with pytest.raises(OSError) as info:
        predict.save_file(path, numpy_on_a_full_disk, None)
    assert info.value.strerror == "cannot write it (262144 requested and 35808 written); the disk is full"
    with pytest.raises(OSError) as info:   # a reason of its own is kept, the file named
        predict.save_file(path, full_disk, None)
    assert (info.value.errno, info.value.strerror, info.value.filename) == (errno.ENOSPC, os.strerror(errno.ENOSPC),
                                                                            path)


# ---------------------------------------------------------------------------------------------- tiny inputs


class _Sized:
    """What `resize_notice` reads of a predictor: a fixed (or native) working size."""

    def __init__(self, size, model_name="resnet_md_tiny"):
        self.size, self.model_name, self.max_pixels = size, model_name, inference.NATIVE_MAX_PIXELS

    def working_size(self, h, w):
        return self.size or inference.native_working_size(self.model_name, h, w, self.max_pixels)


def test_resize_notice_names_an_upscaled_input():
    # 24x40 at 128x256: 128 / 24 = 5.3 and 256 / 40 = 6.4 times larger; native: 64x64 (one multiple of 64 per side)
    assert inference.resize_notice(_Sized((128, 256)), 24, 40) == (
        "note: the 24x40 input runs at 128x256 (6.4x larger per side: upscaled, each pair costs a 128x256 network "
        "call); --working-size native runs it at 64x64")
    assert inference.resize_notice(_Sized((128, 256)), 64, 128) is None   # exactly 2x: no note
    assert inference.resize_notice(_Sized((128, 256)), 60, 200) is not None   # one side is enough
    # already at the native size (the model's smallest): said, without an option that would not help
    assert inference.resize_notice(_Sized(None), 24, 40) == (
        "note: the 24x40 input runs at 64x64 (2.7x larger per side: upscaled, each pair costs a 64x64 network call)")
    # shrinking keeps its own wording
    assert inference.resize_notice(_Sized((64, 128)), 500, 741).startswith(
        "note: the 500x741 input runs at 64x128 (7.8x smaller per side); --working-size native runs it at ")


def test_a_folder_of_tiny_frames_is_one_note_per_run(tiny_checkpoint, tmp_path, capsys):
    folder = tmp_path / "frames"
    folder.mkdir()
    for i, f in enumerate(_frames(4, 24, 40)):
        _write(folder / f"{i:03d}.png", f)
    out = tmp_path / "out"
    assert _run(["--checkpoint", tiny_checkpoint, str(folder), "--out", str(out), "--working-size", "128x256",
                 "--raw", "none"]) == 0
    notes = [line for line in capsys.readouterr().err.splitlines() if line.startswith("note:")]
    assert notes == ["note: the 24x40 input runs at 128x256 (6.4x larger per side: upscaled, each pair costs a "
                     "128x256 network call); --working-size native runs it at 64x64"]
    assert sorted(os.listdir(out / "flow")) == ["000.png", "001.png", "002.png"]
