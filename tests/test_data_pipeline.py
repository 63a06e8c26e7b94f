"""grain pipeline (bridge_jax.data.pipeline) and own-folder source (bridge_jax.data.folders)."""
import logging
import os

import numpy as np
import pytest

from bridge_jax.data import folders, kitti, pipeline, synthetic
from tests.test_data_fakes import bilinear, make_fake_raw, truncate_file


class _IdSource:
    """Cheap fake source: cycle i is a constant image with value i (so batches reveal which cycles they hold)."""

    def __init__(self, n, size=(4, 6)):
        self.n, self.size = n, size
        self.root = "<ids>"

    def __len__(self):
        return self.n

    def load(self, i):
        return {"cycle": np.full((4,) + self.size + (3,), i, np.uint8), "id": str(i)}


def _ids(batch):
    return [int(round(v * 255)) for v in batch["cycle"][:, 0, 0, 0, 0]]


# ------------------------------------------------------------------------------------------------ augmentation

def test_photometric_lut_on_unit_range_hand_values():
    p = pipeline.AugmentParams(flip=False, gamma=1.2, brightness=1.5, colour=(1.1, 0.9, 1.0))
    cyc = np.zeros((4, 1, 2, 3), np.uint8)
    cyc[:, 0, 0] = 128
    cyc[:, 0, 1] = 255
    out = pipeline.apply_augment(cyc, p)
    x = (128 / 255) ** 1.2 * 1.5
    np.testing.assert_allclose(out[0, 0, 0], [min(x * 1.1, 1), x * 0.9, x], rtol=1e-6)
    # gamma on [0,1] keeps white white; brightness clips at 1 before the colour factor (upstream order).
    np.testing.assert_allclose(out[:, 0, 1], np.tile([1.0, 0.9, 1.0], (4, 1)), rtol=1e-6)
    g = pipeline.apply_augment(cyc, pipeline.AugmentParams(gamma=0.8))
    np.testing.assert_allclose(g[0, 0, 1], 1.0)
    np.testing.assert_allclose(g[0, 0, 0], (128 / 255) ** 0.8, rtol=1e-6)


def test_uint8_training_path_matches_float_augmentation():
    cyc = np.random.default_rng(1).integers(0, 256, (4, 5, 7, 3), dtype=np.uint8)
    for seed in range(6):
        p = pipeline.draw_augment(np.random.default_rng(seed))
        exact = pipeline.apply_augment(cyc, p)
        fast = pipeline.apply_augment_uint8(cyc, p).astype(np.float32) / 255
        assert np.abs(exact - fast).max() <= 0.5 / 255 + 1e-6


def test_augmentation_same_draw_for_the_four_frames():
    base = np.random.default_rng(0).integers(0, 256, (8, 10, 3), dtype=np.uint8)
    cyc = np.stack([base] * 4)
    outs = []
    for seed in range(12):
        params = pipeline.draw_augment(np.random.default_rng(seed))
        out = pipeline.apply_augment(cyc, params)
        for k in range(1, 4):
            np.testing.assert_array_equal(out[k], out[0])
        outs.append(out[0])
    assert len({o.tobytes() for o in outs}) > 8                      # but the draws differ between cycles
    # Through the grain pipeline as well (random_map, seeded per element).
    ds = pipeline.make_train_dataset(pipeline.DataConfig(augment=True), global_batch=4, seed=3, height=8, width=10,
                                     process_index=0, process_count=1, source=_ConstSource(cyc))
    b = next(iter(ds))["cycle"]
    for k in range(1, 4):
        np.testing.assert_array_equal(b[:, k], b[:, 0])
    assert not np.array_equal(b[0, 0], b[1, 0]) or not np.array_equal(b[1, 0], b[2, 0])


class _ConstSource:
    def __init__(self, cyc):
        self.cyc, self.root = cyc, "<const>"

    def __len__(self):
        return 16

    def load(self, i):
        return {"cycle": self.cyc, "id": str(i)}


def test_flip_keeps_stereo_valid():
    h, w = 64, 128
    s = synthetic.render_sample(21, h, w)
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    f = pipeline.apply_augment(s["cycle"], pipeline.AugmentParams(flip=True))
    # New right = mirrored old left, whose disparity is the mirrored old disparity; its match in the new left
    # (= mirrored old right) is at x + d.
    d, m = s["disp_t"][:, ::-1], s["noc_disp_t"][:, ::-1]
    good = np.abs(bilinear(f[0], xs + d, ys) - f[1]).mean(-1)[m].mean()
    assert good < 0.006
    # A flip without the swap breaks the stereo geometry: new left at x - d no longer reproduces.
    noswap = s["cycle"][:, :, ::-1].astype(np.float64) / 255
    bad = np.abs(bilinear(noswap[1], xs - d, ys) - noswap[0]).mean(-1)[m].mean()
    assert bad > 3 * good
    # Flow direction: the new left_t1 is mirrored right_t1, frames order is kept (t before t+1).
    np.testing.assert_array_equal(f[2], s["cycle"][3, :, ::-1] / np.float32(255))


def test_resize_frames_area_and_linear():
    x = np.arange(16, dtype=np.float32).reshape(1, 4, 4, 1).repeat(3, -1)
    small = pipeline.resize_frames(x, 2, 2)
    np.testing.assert_allclose(small[0, ..., 0], [[2.5, 4.5], [10.5, 12.5]])   # 2x2 block means
    assert pipeline.resize_frames(x, 8, 8).shape == (1, 8, 8, 3)


# ------------------------------------------------------------------------------------------------ the dataset

def test_synthetic_dataset_batches():
    ds = pipeline.make_train_dataset(pipeline.DataConfig(source="synthetic", synthetic_num=8), global_batch=2, seed=0,
                                     height=32, width=64, process_index=0, process_count=1)
    b = next(iter(ds))
    assert set(b) == {"cycle"} and b["cycle"].shape == (2, 4, 32, 64, 3) and b["cycle"].dtype == np.float32
    assert 0.0 <= b["cycle"].min() and b["cycle"].max() <= 1.0


def test_iterator_resume_returns_same_next_batch():
    ds = pipeline.make_train_dataset(pipeline.DataConfig(augment=True), global_batch=3, seed=5, height=4, width=6,
                                     process_index=0, process_count=1, source=_IdSource(10))
    it = iter(ds)
    for _ in range(4):                      # crosses an epoch boundary (10 cycles / 3 per batch)
        next(it)
    state = it.get_state()
    expect = [next(it) for _ in range(3)]
    it2 = iter(ds)
    it2.set_state(state)
    for e in expect:
        np.testing.assert_array_equal(next(it2)["cycle"], e["cycle"])


@pytest.mark.slow
def test_iterator_resume_with_worker_process():
    cfg = pipeline.DataConfig(augment=True, num_workers=1)
    ds = pipeline.make_train_dataset(cfg, global_batch=2, seed=1, height=4, width=6, process_index=0,
                                     process_count=1, source=_IdSource(9))
    it = iter(ds)
    for _ in range(3):
        next(it)
    state = it.get_state()
    expect = next(it)
    it.close()
    it2 = iter(ds)
    it2.set_state(state)
    np.testing.assert_array_equal(next(it2)["cycle"], expect["cycle"])
    it2.close()


def test_two_process_shards_disjoint_and_complete():
    n = 12
    seen = []
    for p in range(2):
        ds = pipeline.make_train_dataset(pipeline.DataConfig(augment=False, num_epochs=1), global_batch=2, seed=9,
                                         height=4, width=6, process_index=p, process_count=2, source=_IdSource(n))
        ids = [i for b in ds for i in _ids(b)]
        assert len(ids) == n // 2
        seen.append(ids)
    assert not set(seen[0]) & set(seen[1])
    assert sorted(seen[0] + seen[1]) == list(range(n))
    # Second epoch: reshuffled, still disjoint and complete.
    both = []
    for p in range(2):
        ds = pipeline.make_train_dataset(pipeline.DataConfig(augment=False, num_epochs=2), global_batch=2, seed=9,
                                         height=4, width=6, process_index=p, process_count=2, source=_IdSource(n))
        ids = [i for b in ds for i in _ids(b)]
        both.append(ids[n // 2:])
        assert ids[: n // 2] == seen[p]
    assert sorted(both[0] + both[1]) == list(range(n)) and both[0] != seen[0]


def test_bad_batch_and_process_arguments():
    with pytest.raises(ValueError, match="multiple of the process count"):
        pipeline.make_train_dataset(pipeline.DataConfig(), global_batch=3, seed=0, process_index=0, process_count=2,
                                    source=_IdSource(4))


# ------------------------------------------------------------------------------------------------ corrupt data

def test_corrupt_and_missing_images_skipped_counted_logged(tmp_path, caplog):
    root = make_fake_raw(str(tmp_path), {"2011_09_26_drive_0001": 6}, height=8, width=12)
    data = os.path.join(root, "2011_09_26", "2011_09_26_drive_0001_sync")
    bad = os.path.join(data, "image_03", "data", "0000000002.png")
    truncate_file(bad)                                             # breaks cycles 1 and 2
    os.remove(os.path.join(data, "image_02", "data", "0000000004.png"))   # removes frame 4 from the listing
    src = pipeline.make_source(pipeline.DataConfig(source="kitti_raw", data_dir=root, split="all"))
    assert len(src) == 3                                           # cycles 0, 1, 2 (3 and 4 need frame 4)
    loader = pipeline.LoadCycle(src)
    with caplog.at_level(logging.WARNING):
        got = [loader(i)["id"] for i in range(3)]
    assert got == ["2011_09_26_drive_0001/0000000000"] * 3          # 1 and 2 replaced by the next valid (0)
    rep = loader.skips.report()
    assert rep["cycles"] == 2 and rep["files"] == [bad] and "truncated PNG" in rep["causes"][bad]  # each once
    assert [loader(i)["id"] for i in (1, 2)] == ["2011_09_26_drive_0001/0000000000"] * 2
    assert loader.skips.report()["cycles"] == 2                   # met again: not counted again
    assert bad in caplog.text
    # A missing file that is listed (deleted after listing) is skipped the same way.
    os.remove(os.path.join(data, "image_02", "data", "0000000000.png"))
    with pytest.raises(RuntimeError, match="unreadable"):
        loader(0)
    # Through the dataset: no crash, every batch holds the valid cycle, and the skips are counted.
    ds = pipeline.make_train_dataset(pipeline.DataConfig(augment=False), global_batch=1, seed=0, height=8, width=12,
                                     process_index=0, process_count=1,
                                     source=pipeline.FileCycleSource(_valid_plus_corrupt(root), root))
    it = iter(ds)
    out = [next(it)["cycle"] for _ in range(4)]
    assert all(o.shape == (1, 4, 8, 12, 3) and np.allclose(o, 7 / 255) for o in out)
    rep = ds.skips.report()
    assert rep["cycles"] == 1 and rep["files"] == [os.path.join(root, "bad.png")]   # met twice, counted once


def _valid_plus_corrupt(root):
    good = os.path.join(root, "good.png")
    kitti.write_image(good, np.full((8, 12, 3), 7, np.uint8))
    bad = os.path.join(root, "bad.png")
    with open(bad, "wb") as fh:
        fh.write(b"not an image")
    return [{"id": "bad", "paths": (bad,) * 4, "calib": None}, {"id": "good", "paths": (good,) * 4, "calib": None}]


def test_folder_without_cycles_gives_one_clear_error(tmp_path):
    (tmp_path / "left").mkdir()
    (tmp_path / "right").mkdir()
    with pytest.raises(ValueError, match=r"left/\*\.png"):
        folders.folder_cycles(str(tmp_path))
    with pytest.raises(ValueError, match="does not exist"):
        folders.folder_cycles(str(tmp_path / "nope"))
    with pytest.raises(ValueError, match=str(tmp_path / "left")):
        pipeline.make_source(pipeline.DataConfig(source="folder", data_dir=str(tmp_path / "left")))


def test_folder_source_png_and_jpeg(tmp_path):
    rng = np.random.default_rng(0)
    for side in ("left", "right"):
        (tmp_path / "seq" / side).mkdir(parents=True)
        for k in range(4):
            ext = ".jpg" if k % 2 else ".png"
            kitti.write_image(str(tmp_path / "seq" / side / f"frame{k}{ext}"),
                              rng.integers(0, 256, (8, 12, 3), dtype=np.uint8))
    recs = folders.folder_cycles(str(tmp_path / "seq"))
    assert [r["id"] for r in recs] == ["seq/frame0", "seq/frame1", "seq/frame2"]
    assert recs[0]["paths"][1].endswith("right/frame0.png") and recs[0]["paths"][2].endswith("left/frame1.jpg")
    assert len(folders.folder_cycles(str(tmp_path))) == 3                 # subfolder sequences
    ds = pipeline.make_train_dataset(pipeline.DataConfig(source="folder", data_dir=str(tmp_path), augment=False),
                                     global_batch=3, seed=0, height=8, width=12, process_index=0, process_count=1)
    b = next(iter(ds))["cycle"]
    assert b.shape == (3, 4, 8, 12, 3)
    # Raw-drive layout works as an own-data folder too.
    raw = make_fake_raw(str(tmp_path / "raw"), {"2011_09_26_drive_0009": 3}, height=8, width=12)
    assert len(folders.folder_cycles(raw)) == 2
    assert len(folders.folder_cycles(os.path.join(raw, "2011_09_26", "2011_09_26_drive_0009_sync"))) == 2


def test_shard_batch_onto_mesh():
    import jax
    mesh = jax.make_mesh((len(jax.devices()),), ("data",))
    n = len(jax.devices())
    batch = {"cycle": np.zeros((n, 4, 4, 6, 3), np.float32)}
    out = pipeline.shard_batch(batch, mesh)
    assert out["cycle"].shape == (n, 4, 4, 6, 3)
    assert len(out["cycle"].sharding.device_set) == n


def test_zoom_crop_keeps_stereo_rectified_and_scales_disparity():
    """A stereo pair with a constant disparity of 4 px (right = left shifted): after the zoom crop (same window
    in every frame) and the resize back to the working size, rows stay aligned and the disparity is 4 / s."""
    h, w = 64, 128
    base = np.random.default_rng(0).integers(0, 256, (h, w + 8), dtype=np.uint8)
    import cv2
    base = cv2.GaussianBlur(base, (0, 0), 2.0)
    left, right = base[:, 4:4 + w], base[:, 8:8 + w]  # right(x - 4) = base(x + 4) = left(x): disparity 4
    cycle = np.stack([np.repeat(f[..., None], 3, -1) for f in (left, right, left, right)])
    assert pipeline.zoom_crop(cycle, np.random.default_rng(1), 1.0) is cycle
    crop = pipeline.zoom_crop(cycle, np.random.default_rng(1), 0.5)
    r = np.random.default_rng(1)
    s = r.uniform(0.5, 1.0)
    ch, cw = int(round(s * h)), int(round(s * w))
    assert crop.shape == (4, ch, cw, 3)
    np.testing.assert_array_equal(crop[0], crop[2])  # the same window in every frame
    back = pipeline.resize_frames(crop, h, w)[..., 0].astype(np.float64)
    xs = np.arange(w, dtype=np.float64)
    # the disparity d that best aligns the resized frames: right sampled at x - d against left at x
    cands = np.arange(2.0, 16.0, 0.05)
    errs = [np.abs(back[0][:, 20:-20] - np.stack([np.interp(xs, xs + d, row) for row in back[1]])[:, 20:-20]
                   ).mean() for d in cands]
    best = cands[int(np.argmin(errs))]
    assert abs(best - 4.0 * w / cw) < 0.2, (best, 4.0 * w / cw)


def test_zoom_option_is_checked():
    with pytest.raises(ValueError, match="data.augment_zoom"):
        pipeline.DataConfig(augment_zoom=0.0)


def test_shift_crop_hand_case_windows_and_offset():
    """Frames that hold their own pixel coordinates: the t windows and the t+1 windows are the drawn ones, the
    two cameras of each time share a window, and the offset stays within the bound."""
    h, w = 40, 80
    ys, xs = np.mgrid[0:h, 0:w]
    frame = np.stack([ys, xs, np.zeros_like(ys)], -1).astype(np.uint8)
    cycle = np.stack([frame, frame + 0, frame, frame])
    assert pipeline.shift_crop(cycle, np.random.default_rng(0), 0.0) is cycle
    for seed in range(20):
        y0, x0, dy, dx = pipeline.draw_shift(np.random.default_rng(seed), h, w, 0.1)  # m = 4, mx = 8
        assert abs(dy) <= 4 and abs(dx) <= 8
        out = pipeline.shift_crop(cycle, np.random.default_rng(seed), 0.1)
        assert out.shape == (4, 36, 72, 3)
        assert out[0, 0, 0, 0] == y0 and out[0, 0, 0, 1] == x0 and out[1, 0, 0, 0] == y0
        assert out[2, 0, 0, 0] == y0 + dy and out[2, 0, 0, 1] == x0 + dx and out[3, -1, -1, 1] == x0 + dx + 71


def test_shift_crop_moves_the_flow_and_keeps_the_disparity():
    """On a rendered cycle with exact ground truth: after the shifted crop, left_t1 sampled at the old flow
    minus the window offset reconstructs left_t (and the old flow itself does not), and the right views still
    reconstruct the left ones with the old disparities (the pairs stay rectified)."""
    h, w = 96, 192
    s = synthetic.render_sample(21, h, w)
    for seed in (3, 4):
        y0, x0, dy, dx = pipeline.draw_shift(np.random.default_rng(seed), h, w, 0.1)
        if abs(dy) < 3:
            continue
        c = pipeline.shift_crop(s["cycle"], np.random.default_rng(seed), 0.1)
        ch, cw = c.shape[1:3]
        win = (slice(y0, y0 + ch), slice(x0, x0 + cw))
        gx, gy = np.meshgrid(np.arange(cw, dtype=np.float64), np.arange(ch, dtype=np.float64))
        fl, noc = s["flow"][win], s["noc_flow"][win]
        # the match must also fall inside the t+1 window
        noc = noc & (gx + fl[..., 0] - dx >= 0) & (gx + fl[..., 0] - dx <= cw - 1) \
            & (gy + fl[..., 1] - dy >= 0) & (gy + fl[..., 1] - dy <= ch - 1)
        err = lambda a, b, m: np.abs(a.astype(np.float64) / 255 - b / 255).mean(-1)[m]  # noqa: E731
        good = err(c[0], bilinear(c[2], gx + fl[..., 0] - dx, gy + fl[..., 1] - dy), noc)
        stale = err(c[0], bilinear(c[2], gx + fl[..., 0], gy + fl[..., 1]), noc)
        assert np.median(good) < 0.004 and np.median(stale) > 3 * np.median(good), (np.median(good), np.median(stale))
        d, dnoc = s["disp_t"][win], s["noc_disp_t"][win] & (gx - s["disp_t"][win] >= 0)
        assert err(c[0], bilinear(c[1], gx - d, gy), dnoc).mean() < 0.006
    assert pipeline.DataConfig(augment_shift=0.1).augment_shift == 0.1
    with pytest.raises(ValueError, match="data.augment_shift"):
        pipeline.DataConfig(augment_shift=0.5)


def test_t1_zoom_crop_hand_case_windows_and_scale():
    """Frames that hold their own pixel coordinates (a second camera offset by 50): the t frames are the drawn
    integer window; pixel (x, y) of each t+1 frame shows (x1 + (x + 0.5) / z - 0.5, y1 + (y + 0.5) / z - 0.5),
    the same point for both cameras; z stays within 1 +- amount."""
    h, w = 100, 200
    ys, xs = np.mgrid[0:h, 0:w]
    frame = np.stack([ys, xs, np.zeros_like(ys)], -1).astype(np.uint8)
    right = frame + np.array([0, 50, 0], np.uint8)  # xs + 50 <= 249: no wrap
    cycle = np.stack([frame, right, frame, right])
    assert pipeline.t1_zoom_crop(cycle, np.random.default_rng(0), 0.0) is cycle
    zooms = []
    for seed in range(12):
        z, ch, cw, y0, x0, y1, x1 = pipeline.draw_t1_zoom(np.random.default_rng(seed), h, w, 0.1)
        zooms.append(z)
        assert 0.9 <= z <= 1.1 and (ch, cw) == (90, 180)
        assert 0 <= y1 and y1 + ch / z <= h + 1e-9 and 0 <= x1 and x1 + cw / z <= w + 1e-9
        out = pipeline.t1_zoom_crop(cycle, np.random.default_rng(seed), 0.1)
        assert out.shape == (4, 90, 180, 3)
        np.testing.assert_array_equal(out[0], frame[y0:y0 + 90, x0:x0 + 180])
        np.testing.assert_array_equal(out[1], right[y0:y0 + 90, x0:x0 + 180])
        qy, qx = np.mgrid[0:90, 0:180]
        src_x, src_y = x1 + (qx + 0.5) / z - 0.5, y1 + (qy + 0.5) / z - 0.5
        inside = (src_x <= w - 1) & (src_y <= h - 1)  # the last source pixel's far half is clamped
        # uint8 rounding of a bilinearly sampled ramp: within half a level
        assert np.abs(out[2, ..., 1] - src_x)[inside].max() <= 0.51
        assert np.abs(out[2, ..., 0] - src_y)[inside].max() <= 0.51
        np.testing.assert_array_equal(out[3, ..., 1].astype(int) - 50, out[2, ..., 1])  # one window per time
        np.testing.assert_array_equal(out[3, ..., 0], out[2, ..., 0])
    assert min(zooms) < 0.97 and max(zooms) > 1.03  # both directions: expansion and contraction


def test_t1_zoom_crop_moves_the_flow_and_keeps_the_pairs_rectified():
    """On a rendered cycle with exact ground truth: after the zoom crop, left_t1 sampled where the old flow
    lands, mapped into the zoomed t+1 window (q = z (p + flow - (x1, y1) + 0.5) - 0.5), reconstructs left_t,
    and the old flow without the zoom does not; right_t1 still matches left_t1 along rows, at z x the disparity
    of the same point."""
    h, w = 96, 192
    s = synthetic.render_sample(21, h, w)
    checked = 0
    for seed in range(8):
        z, ch, cw, y0, x0, y1, x1 = pipeline.draw_t1_zoom(np.random.default_rng(seed), h, w, 0.1)
        if abs(z - 1.0) < 0.04:
            continue
        checked += 1
        c = pipeline.t1_zoom_crop(s["cycle"], np.random.default_rng(seed), 0.1)
        win = (slice(y0, y0 + ch), slice(x0, x0 + cw))
        gx, gy = np.meshgrid(np.arange(cw, dtype=np.float64), np.arange(ch, dtype=np.float64))
        fl, noc = s["flow"][win], s["noc_flow"][win]
        qx = z * (gx + x0 + fl[..., 0] - x1 + 0.5) - 0.5
        qy = z * (gy + y0 + fl[..., 1] - y1 + 0.5) - 0.5
        noc = noc & (qx >= 0) & (qx <= cw - 1) & (qy >= 0) & (qy <= ch - 1)
        err = lambda a, b, m: np.abs(a.astype(np.float64) / 255 - b / 255).mean(-1)[m]  # noqa: E731
        good = err(c[0], bilinear(c[2], qx, qy), noc)
        stale = err(c[0], bilinear(c[2], gx + fl[..., 0], gy + fl[..., 1]), noc)
        assert np.median(good) < 0.01 and np.median(stale) > 2 * np.median(good), (np.median(good), np.median(stale))
        d, dnoc = s["disp_t"][win], s["noc_disp_t"][win] & (gx - s["disp_t"][win] >= 0)
        assert err(c[0], bilinear(c[1], gx - d, gy), dnoc).mean() < 0.006  # the t pair: an integer crop
        # the t+1 pair: pixel q of the zoomed left_t1 shows the rendered point sx, sy; its match in the zoomed
        # right_t1 lies on the same row, z x that point's rendered disparity to the left
        sx, sy = x1 + (gx + 0.5) / z - 0.5, y1 + (gy + 0.5) / z - 0.5
        d1 = bilinear(s["disp_t1"][..., None].astype(np.float64), sx, sy)[..., 0]
        n1 = bilinear(s["noc_disp_t1"][..., None].astype(np.float64), sx, sy)[..., 0] > 0.999
        n1 = n1 & (gx - z * d1 >= 0)
        scaled = err(c[2], bilinear(c[3], gx - z * d1, gy), n1)
        unscaled = err(c[2], bilinear(c[3], gx - d1, gy), n1)
        assert np.median(scaled) < 0.01 and scaled.mean() < unscaled.mean(), (scaled.mean(), unscaled.mean())
    assert checked >= 2
    assert pipeline.DataConfig(augment_t1_zoom=0.1).augment_t1_zoom == 0.1
    with pytest.raises(ValueError, match="data.augment_t1_zoom"):
        pipeline.DataConfig(augment_t1_zoom=0.3)


def test_augment_shift_leaves_the_other_draws_alone():
    """Turning the shift on changes only the crop: the photometric and zoom draws come first, so the centre of
    an unshifted window (dy = dx = 0 draws aside) carries the same colours."""
    src = synthetic.render_sample(5, 64, 128)["cycle"]
    plain = pipeline._Augment(True).random_map({"cycle": src}, np.random.default_rng(9))["cycle"]
    shifted = pipeline._Augment(True, shift=0.1).random_map({"cycle": src}, np.random.default_rng(9))["cycle"]
    r = np.random.default_rng(9)
    pipeline.draw_augment(r)
    y0, x0, dy, dx = pipeline.draw_shift(r, 64, 128, 0.1)
    ch, cw = shifted.shape[1:3]
    np.testing.assert_array_equal(shifted[0], plain[0, y0:y0 + ch, x0:x0 + cw])
    np.testing.assert_array_equal(shifted[2], plain[2, y0 + dy:y0 + dy + ch, x0 + dx:x0 + dx + cw])
