"""Own stereo-video folders (bridge_jax.data.folders): gaps split sequences, image sizes read from headers, the
pre-scan before training, and the skip report of the pipeline on such folders."""
import logging
import os
import re
import struct

import cv2
import numpy as np
import pytest

from bridge_jax.data import folders, kitti, pipeline
from tests.test_data_fakes import truncate_file, write_stereo_sequence

TEN = [f"{k:04d}" for k in range(10)]


def _frame_numbers(rec):
    """(number of left_t, number of left_t1) of a cycle record."""
    return tuple(int(os.path.splitext(os.path.basename(rec["paths"][k]))[0][-4:]) for k in (0, 2))


def _assert_cycles_consecutive(recs):
    for r in recs:
        a, b = _frame_numbers(r)
        assert b == a + 1, f"cycle {r['id']} pairs frames {a} and {b}"
        # left and right of one time step are the same frame
        for k in (0, 2):
            assert os.path.basename(r["paths"][k]) == os.path.basename(r["paths"][k + 1])


# ------------------------------------------------------------------------------------------------ gaps

def test_frame_missing_on_one_side_splits_the_sequence(tmp_path, caplog):
    files = write_stereo_sequence(str(tmp_path), TEN)
    os.remove(files["right/0007.png"])
    with caplog.at_level(logging.WARNING):
        recs = folders.folder_cycles(str(tmp_path))
    # 0-1 … 5-6 and 8-9; before the fix 6 and 8 formed one cycle
    assert [r["id"] for r in recs] == [f"{tmp_path.name}/{k:04d}" for k in (0, 1, 2, 3, 4, 5, 8)]
    _assert_cycles_consecutive(recs)
    assert not any(_frame_numbers(r) == (6, 8) for r in recs)
    assert "2 across 1 frame(s) present on one side only (right/ lacks 0007.png)" in caplog.text


def test_frames_missing_on_both_sides_of_different_frames(tmp_path, caplog):
    files = write_stereo_sequence(str(tmp_path), TEN)
    os.remove(files["left/0002.png"])
    os.remove(files["right/0003.png"])
    with caplog.at_level(logging.WARNING):
        recs = folders.folder_cycles(str(tmp_path))
    # 2 and 3 both dropped: cycles 0-1, 4-5 … 8-9; transitions 1-2, 2-3, 3-4 are lost
    assert [_frame_numbers(r) for r in recs] == [(0, 1), (4, 5), (5, 6), (6, 7), (7, 8), (8, 9)]
    assert "3 across 2 frame(s)" in caplog.text and "right/ lacks 0003.png" in caplog.text
    assert "left/ lacks 0002.png" in caplog.text


def test_jump_in_frame_numbers_splits_the_sequence(tmp_path, caplog):
    write_stereo_sequence(str(tmp_path), ["0", "1", "2", "5", "6"])
    with caplog.at_level(logging.WARNING):
        recs = folders.folder_cycles(str(tmp_path))
    assert [_frame_numbers(r) for r in recs] == [(0, 1), (1, 2), (5, 6)]           # no cycle (2, 5)
    assert "1 across jump(s) in the frame numbers (2 -> 5)" in caplog.text


def test_jump_when_left_and_right_are_named_differently(tmp_path):
    # Positional pairing (no common names): a jump on either side cuts the sequence.
    for side, prefix in (("left", "L_"), ("right", "R_")):
        os.makedirs(tmp_path / side)
        for k in (0, 1, 2, 3, 7, 8, 9):
            assert cv2.imwrite(str(tmp_path / side / f"{prefix}{k:03d}.png"), np.zeros((4, 6, 3), np.uint8))
    recs = folders.folder_cycles(str(tmp_path))
    pairs = [(os.path.basename(r["paths"][0]), os.path.basename(r["paths"][2])) for r in recs]
    assert ("L_003.png", "L_007.png") not in pairs and len(recs) == 5
    assert all(os.path.basename(r["paths"][1]) == "R_" + os.path.basename(r["paths"][0])[2:] for r in recs)


def test_numbering_breaks_usual_step():
    assert folders.numbering_breaks(["0", "1", "2", "5", "6"]) == {3: ("2", "5")}
    assert folders.numbering_breaks(["f0", "f2", "f4", "f8", "f10"]) == {3: ("f4", "f8")}   # step 2
    assert folders.numbering_breaks(["f0", "f2", "f4", "f5"]) == {}                         # smaller: fine
    # jittering timestamps (no difference is the most common one): 1.5 x the median difference
    ts = [str(1_000_000 + t) for t in (0, 50_003, 99_998, 150_001, 300_004, 350_000)]
    assert folders.numbering_breaks(ts) == {4: (ts[3], ts[4])}
    # different text before the number, or no number: never compared
    assert folders.numbering_breaks(["a1", "b7", "b8", "b9"]) == {}
    assert folders.numbering_breaks(["cat", "dog", "emu"]) == {}
    assert folders.numbering_breaks(["3", "9"]) == {}                 # one difference is its own step


# ------------------------------------------------------------------------------------------------ image headers

def _jpeg_with_app_segment(img, payload_len=70_000):
    """A JPEG with two APP segments (EXIF-like) before the frame header, which the scanner must skip."""
    ok, buf = cv2.imencode(".jpg", img)
    data = buf.tobytes()
    segs = b""
    for _ in range(2):
        body = b"Exif\x00\x00" + bytes(min(payload_len, 65_000))
        segs += b"\xff\xe1" + struct.pack(">H", len(body) + 2) + body
    return data[:2] + segs + data[2:]


def test_image_size_from_headers(tmp_path):
    img = np.random.default_rng(0).integers(0, 256, (37, 53, 3), dtype=np.uint8)
    cases = {"a.png": cv2.imencode(".png", img)[1].tobytes(),
             "b.jpg": cv2.imencode(".jpg", img)[1].tobytes(),
             "c.jpg": cv2.imencode(".jpg", img, [cv2.IMWRITE_JPEG_PROGRESSIVE, 1])[1].tobytes(),
             "d.jpeg": _jpeg_with_app_segment(img),
             "e.png": cv2.imencode(".bmp", img)[1].tobytes(),          # a BMP behind a .png name
             "g.png": cv2.imencode(".png", img[..., 0])[1].tobytes()}  # grayscale
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
        assert folders.image_size(str(tmp_path / name)) == (37, 53), name
        assert cv2.imread(str(tmp_path / name)).shape[:2] == (37, 53)  # the decoder agrees
    # a truncated body keeps its header: the size is known, decoding fails later (the pipeline skips it)
    truncate_file(str(tmp_path / "a.png"))
    assert folders.image_size(str(tmp_path / "a.png")) == (37, 53)
    bad = {"empty.png": (b"", "empty file"), "text.png": (b"not an image at all", "not a PNG or JPEG image"),
           "sof-less.jpg": (b"\xff\xd8\xff\xd9", "not a PNG or JPEG image")}
    for name, (data, why) in bad.items():
        (tmp_path / name).write_bytes(data)
        with pytest.raises(kitti.CorruptImageError, match=re.escape(f"unreadable image ({why})")) as e:
            folders.image_size(str(tmp_path / name))
        assert e.value.path == str(tmp_path / name)
    with pytest.raises(kitti.CorruptImageError, match="unreadable image"):
        folders.image_size(str(tmp_path / "missing.png"))


# ------------------------------------------------------------------------------------------------ pre-scan

def _folder_cfg(root, **kw):
    return pipeline.DataConfig(source="folder", data_dir=str(root), augment=False, **kw)


def test_left_right_sizes_differ_everywhere_is_one_error(tmp_path, caplog):
    seq = tmp_path / "seq"
    write_stereo_sequence(str(seq), TEN, sizes={f"right/{s}.png": (8, 10) for s in TEN})
    with caplog.at_level(logging.WARNING), pytest.raises(ValueError) as e:
        pipeline.make_train_dataset(_folder_cfg(tmp_path), global_batch=1, seed=0, height=8, width=12,
                                    process_index=0, process_count=1)
    msg = str(e.value)
    assert msg.startswith(f"left and right differ in size: {seq / 'left' / '0000.png'} is 8x12, "
                          f"{seq / 'right' / '0000.png'} is 8x10")
    assert "10 of 10 stereo frames of sequence 'seq'" in msg
    assert "skipping" not in caplog.text and "unreadable" not in msg   # not reported as corrupt data


def test_a_few_odd_pairs_are_excluded_with_their_cause(tmp_path):
    files = write_stereo_sequence(str(tmp_path), TEN, sizes={"right/0003.png": (8, 10)})
    recs = folders.folder_cycles(str(tmp_path))
    kept, excluded = folders.check_cycles(recs, where=str(tmp_path))
    assert [_frame_numbers(r) for r in kept] == [(k, k + 1) for k in (0, 1, 4, 5, 6, 7, 8)]
    assert [e["id"] for e in excluded] == [f"{tmp_path.name}/0002", f"{tmp_path.name}/0003"]
    want = (f"left and right differ in size: {files['left/0003.png']} is 8x12, "
            f"{files['right/0003.png']} is 8x10")
    assert all(e["path"] == files["right/0003.png"] and e["cause"] == want for e in excluded)


def test_size_change_mid_sequence_excludes_the_spanning_cycle(tmp_path):
    big = {f"{side}/{s}.png": (10, 14) for side in ("left", "right") for s in TEN[6:]}
    files = write_stereo_sequence(str(tmp_path), TEN, sizes=big)
    kept, excluded = folders.check_cycles(folders.folder_cycles(str(tmp_path)))
    assert len(kept) == 8 and [e["id"] for e in excluded] == [f"{tmp_path.name}/0005"]
    # frames 0-5 are the usual size (8x12), so frame 6 is the odd one
    assert excluded[0]["path"] == files["left/0006.png"]
    assert excluded[0]["cause"] == (f"frame size changes within the sequence: {files['left/0005.png']} is 8x12, "
                                    f"{files['left/0006.png']} is 10x14")


def test_unreadable_images_are_excluded_and_named(tmp_path):
    files = write_stereo_sequence(str(tmp_path), TEN)
    open(files["left/0004.png"], "wb").close()                        # empty
    with open(files["right/0008.png"], "wb") as fh:
        fh.write(b"<html>not found</html>")
    kept, excluded = folders.check_cycles(folders.folder_cycles(str(tmp_path)))
    assert [_frame_numbers(r) for r in kept] == [(0, 1), (1, 2), (2, 3), (5, 6), (6, 7)]
    causes = {e["id"].split("/")[1]: (e["path"], e["cause"]) for e in excluded}
    assert causes == {"0003": (files["left/0004.png"], "unreadable image (empty file)"),
                      "0004": (files["left/0004.png"], "unreadable image (empty file)"),
                      "0007": (files["right/0008.png"], "unreadable image (not a PNG or JPEG image)"),
                      "0008": (files["right/0008.png"], "unreadable image (not a PNG or JPEG image)")}


def test_every_cycle_excluded_is_one_error(tmp_path):
    files = write_stereo_sequence(str(tmp_path), ["0", "1"])
    open(files["right/1.png"], "wb").close()
    with pytest.raises(ValueError, match=re.escape(f"no usable cycles in {tmp_path}: all 1 cycles")):
        pipeline.make_source(_folder_cfg(tmp_path))


def test_decode_time_size_mismatch_names_the_odd_frame(tmp_path):
    # Without the pre-scan, the decoder finds the mismatch and names the frame whose size differs.
    files = write_stereo_sequence(str(tmp_path), ["0", "1", "2"], sizes={"left/1.png": (10, 14)})
    src = pipeline.make_source(_folder_cfg(tmp_path, prescan=False))
    assert len(src) == 2 and src.excluded == []
    with pytest.raises(kitti.CorruptImageError) as e:
        src.load(0)
    assert e.value.path == files["left/1.png"]
    assert e.value.reason == (f"the frames of the cycle differ in size: {files['left/1.png']} is 10x14 but "
                              f"{files['left/0.png']} is 8x12")
    with pytest.raises(kitti.CorruptImageError) as e:
        src.load(1)                                                   # odd frame first in this cycle
    assert e.value.path == files["left/1.png"]


def test_frames_differ_message_two_plus_two():
    paths = ("l0", "r0", "l1", "r1")
    assert folders.frames_differ_message(paths, [(4, 6), (4, 6), (5, 6), (5, 6)])[0] == "l1"
    assert folders.frames_differ_message(paths, [(4, 6), (5, 6), (4, 6), (5, 6)])[0] == "r0"
    assert folders.frames_differ_message(paths, [(5, 6), (4, 6), (4, 6), (4, 6)])[0] == "l0"


def test_kitti_raw_source_is_prescanned(tmp_path):
    from tests.test_data_fakes import make_fake_raw
    root = make_fake_raw(str(tmp_path), {"2011_09_26_drive_0001": 5}, height=8, width=12)
    bad = os.path.join(root, "2011_09_26", "2011_09_26_drive_0001_sync", "image_03", "data", "0000000004.png")
    open(bad, "wb").close()
    src = pipeline.make_source(pipeline.DataConfig(source="kitti_raw", data_dir=root, split="all"))
    assert len(src) == 3 and src.excluded == [{"id": "2011_09_26_drive_0001/0000000003", "path": bad,
                                               "cause": "unreadable image (empty file)"}]


def test_layout_help_documents_the_layouts():
    for part in ("ROOT/left/", "ROOT/right/", "ROOT/<sequence>/left/", "image_02/data", "same size"):
        assert part in folders.LAYOUT_HELP
    assert "left/" in folders.__doc__ and "KITTI raw" in folders.__doc__


# ------------------------------------------------------------------------------------------------ skip report

def _bad_folder(root):
    """8 frames: right/0002.png truncated (decode fails: cycles 1, 2), left/0005.png of another size (pre-scan:
    cycles 4, 5). Returns (truncated path, odd-size path)."""
    files = write_stereo_sequence(str(root), TEN[:8], sizes={"left/0005.png": (10, 14)})
    truncate_file(files["right/0002.png"])
    return files["right/0002.png"], files["left/0005.png"]


def _check_report_after_three_epochs(tmp_path, num_workers):
    truncated, odd = _bad_folder(tmp_path)
    cfg = _folder_cfg(tmp_path, num_epochs=3, num_workers=num_workers)
    ds = pipeline.make_train_dataset(cfg, global_batch=1, seed=0, height=8, width=12, process_index=0,
                                     process_count=1)
    assert ds.skips.prescan_report() == {
        "cycles": 2, "files": [odd],
        "causes": {odd: f"left and right differ in size: {odd} is 10x14, {odd.replace('left', 'right')} is 8x12"}}
    batches = list(ds)
    assert len(batches) == 3 * 5 and all(set(b) == {"cycle"} for b in batches)   # 5 kept cycles, 3 epochs
    rep = ds.skips.report()
    assert rep["cycles"] == 4 and rep["files"] == sorted([truncated, odd])
    assert rep["causes"][truncated] == "truncated PNG (no IEND chunk at the end)"
    assert rep["causes"][odd].startswith("left and right differ in size: ")


def test_a_second_dataset_in_the_process_reports_only_its_own_skips(tmp_path):
    """The skip log belongs to the dataset: a second run in one process does not report the first run's skips."""
    _bad_folder(tmp_path / "bad")
    first = pipeline.make_train_dataset(_folder_cfg(tmp_path / "bad", num_epochs=1), global_batch=1, seed=0,
                                        height=8, width=12, process_index=0, process_count=1)
    list(first)
    assert first.skips.report()["cycles"] == 4
    write_stereo_sequence(str(tmp_path / "good"), TEN[:4])
    second = pipeline.make_train_dataset(_folder_cfg(tmp_path / "good", num_epochs=1), global_batch=1, seed=0,
                                         height=8, width=12, process_index=0, process_count=1)
    list(second)
    assert second.skips.report() == {"cycles": 0, "files": [], "causes": {}}
    assert first.skips.report()["cycles"] == 4


def test_skip_report_counts_each_cycle_once_over_epochs(tmp_path, caplog):
    with caplog.at_level(logging.WARNING):
        _check_report_after_three_epochs(tmp_path, num_workers=0)
    # each distinct bad cycle is logged once, not once per epoch
    assert caplog.text.count("skipping unreadable cycle") == 2


@pytest.mark.slow
def test_skip_report_sees_worker_process_failures(tmp_path):
    _check_report_after_three_epochs(tmp_path, num_workers=1)
