"""KITTI formats, calibration, layouts, splits and Velodyne GT (bridge_jax.data.kitti)."""
import os

import numpy as np
import pytest

from bridge_jax.data import kitti
from tests.test_data_fakes import CAM_TO_CAM, make_fake_raw, png_bytes, png_read


# ------------------------------------------------------------------------------------------------ flow PNG

def test_flow_png_hand_written_2x2_decodes_to_known_values(tmp_path):
    # File channel order is R, G, B = u, v, valid (KITTI devkit); value = flow·64 + 2^15.
    rgb = np.array([[[32768 + 64, 32768 - 128, 1], [32768 - 32, 32768 + 16, 1]],
                    [[40000, 50000, 0], [32768, 32768, 1]]], np.uint16)
    p = tmp_path / "f.png"
    p.write_bytes(png_bytes(rgb, 16))
    flow, valid = kitti.read_flow_png(str(p))
    np.testing.assert_array_equal(valid, [[True, True], [False, True]])
    np.testing.assert_array_equal(flow[..., 0], [[1.0, -0.5], [0.0, 0.0]])
    np.testing.assert_array_equal(flow[..., 1], [[-2.0, 0.25], [0.0, 0.0]])


def test_flow_png_written_in_kitti_channel_order(tmp_path):
    flow = np.array([[[3.0, -1.5], [-100.25, 7.0]]], np.float32)
    valid = np.array([[True, False]])
    p = tmp_path / "w.png"
    kitti.write_flow_png(str(p), flow, valid)
    raw = png_read(p.read_bytes())          # independent decoder: R, G, B as stored
    assert raw.shape == (1, 2, 3)
    np.testing.assert_array_equal(raw[0, 0], [3 * 64 + 32768, -1.5 * 64 + 32768, 1])
    np.testing.assert_array_equal(raw[0, 1], [0, 0, 0])


def test_flow_png_round_trip_with_invalid_and_negative(tmp_path, rng):
    flow = rng.uniform(-300, 300, (7, 9, 2)).astype(np.float32)
    valid = rng.uniform(size=(7, 9)) < 0.7
    p = str(tmp_path / "r.png")
    kitti.write_flow_png(p, flow, valid)
    f2, v2 = kitti.read_flow_png(p)
    np.testing.assert_array_equal(v2, valid)
    assert np.abs(f2[valid] - flow[valid]).max() <= 0.5 / 64 + 1e-6
    assert (f2[~valid] == 0).all()
    assert (f2[valid] < 0).any()
    exact = np.round(flow * 64) / 64
    kitti.write_flow_png(p, exact, valid)
    np.testing.assert_array_equal(kitti.read_flow_png(p)[0][valid], exact[valid])


# ------------------------------------------------------------------------------------------------ disparity PNG

def test_disp_png_hand_written_2x2(tmp_path):
    p = tmp_path / "d.png"
    p.write_bytes(png_bytes(np.array([[0, 256], [12800, 65535]], np.uint16), 16))
    d, v = kitti.read_disp_png(str(p))
    np.testing.assert_array_equal(v, [[False, True], [True, True]])
    np.testing.assert_array_equal(d, [[0, 1.0], [50.0, 65535 / 256]])


def test_disp_png_round_trip(tmp_path, rng):
    disp = rng.uniform(0, 200, (5, 6)).astype(np.float32)
    valid = rng.uniform(size=(5, 6)) < 0.6
    disp[0, 0], valid[0, 0] = 0.001, True      # tiny but valid: must stay valid
    p = str(tmp_path / "d.png")
    kitti.write_disp_png(p, disp, valid)
    d2, v2 = kitti.read_disp_png(p)
    np.testing.assert_array_equal(v2, valid)
    assert d2[0, 0] == 1 / 256
    valid[0, 0] = False
    assert np.abs(d2[valid] - disp[valid]).max() <= 0.5 / 256 + 1e-6
    assert (d2[~v2] == 0).all()
    assert png_read(open(p, "rb").read())[1, 1] == (round(disp[1, 1] * 256) if valid[1, 1] else 0)


def test_corrupt_png_raises_named_error(tmp_path):
    p = tmp_path / "t.png"
    kitti.write_image(str(p), np.zeros((8, 8, 3), np.uint8))
    data = p.read_bytes()
    p.write_bytes(data[: len(data) // 2])
    with pytest.raises(kitti.CorruptImageError, match="t.png"):
        kitti.read_image(str(p))
    with pytest.raises(kitti.CorruptImageError, match="missing.png"):
        kitti.read_image(str(tmp_path / "missing.png"))
    # libjpeg "decodes" a truncated JPEG (grey bottom rows): it must be rejected too.
    j = tmp_path / "t.jpg"
    kitti.write_image(str(j), np.random.default_rng(0).integers(0, 256, (32, 48, 3), dtype=np.uint8))
    assert kitti.read_image(str(j)).shape == (32, 48, 3)
    data = j.read_bytes()
    j.write_bytes(data[: 2 * len(data) // 3])
    with pytest.raises(kitti.CorruptImageError, match="truncated JPEG"):
        kitti.read_image(str(j))


# ------------------------------------------------------------------------------------------------ calibration

def test_focal_baseline_from_cam_to_cam(tmp_path):
    p = tmp_path / "calib_cam_to_cam.txt"
    p.write_text(CAM_TO_CAM)
    cal = kitti.read_calib_file(str(p))
    assert "calib_time" not in cal and cal["P_rect_02"].shape == (12,)
    f, b = kitti.focal_baseline(cal, (2, 3))
    assert f == pytest.approx(721.5377)
    # baseline = (339.5242 + 44.85728) / 721.5377 (x offsets of cameras 3 and 2)
    assert b == pytest.approx((339.5242 + 44.85728) / 721.5377, rel=1e-9)
    assert 0.53 < b < 0.54


def test_velodyne_depth_map_hand_case(tmp_path):
    # Identity extrinsics/rectification, P = [[10,0,5,0],[0,10,4,0],[0,0,1,0]] so a LiDAR point (x, y, z) lands at
    # u = 10x/z + 5, v = 10y/z + 4; depth stored = LiDAR x (vel_depth) -> here x is camera z as well.
    (tmp_path / "calib_cam_to_cam.txt").write_text(
        "R_rect_00: 1 0 0 0 1 0 0 0 1\nP_rect_02: 10 0 5 0 0 10 4 0 0 0 1 0\n")
    (tmp_path / "calib_velo_to_cam.txt").write_text("R: 0 -1 0 0 0 -1 1 0 0\nT: 0 0 0\n")
    # velo (x fwd, y left, z up) -> cam (x right = -y_v, y down = -z_v, z fwd = x_v)
    pts = np.array([[10.0, 0.0, 0.0, 1],    # cam (0,0,10) -> u=5, v=4 -> round-1 = (4, 3)
                    [5.0, 0.0, 0.0, 1],     # same pixel, closer -> kept (5)
                    [-3.0, 0.0, 0.0, 1],    # behind -> dropped
                    [4.0, -2.0, -0.8, 1]],  # cam (2, 0.8, 4) -> u=10, v=6 -> (9, 5)
                   np.float32)
    pts.tofile(tmp_path / "v.bin")
    d = kitti.velodyne_depth_map(str(tmp_path), str(tmp_path / "v.bin"), (8, 12))
    expect = np.zeros((8, 12), np.float32)
    expect[3, 4] = 5.0
    expect[5, 9] = 4.0
    np.testing.assert_array_equal(d, expect)


# ------------------------------------------------------------------------------------------------ splits

def test_split_files_have_paper_counts():
    assert len(kitti.kitti_split_ids()) == 28968
    eig = kitti.read_split_ids("eigen_train_cycles_8000")
    assert len(eig) == 8000 and len(set(eig)) == 8000
    test = kitti.eigen_test_ids()
    assert len(test) == 697
    assert not {d for d, _ in eig} & {d for d, _ in test}          # no training drive in the Eigen test set
    kdrives = {d for d, _ in kitti.kitti_split_ids()}
    excluded = set(open(os.path.join(kitti.SPLITS_DIR, "kitti_split_excluded_drives_29.txt")).read().split())
    assert len(kdrives) == 32 and not kdrives & excluded


def test_raw_cycles_all_and_kitti_split(tmp_path):
    root = make_fake_raw(str(tmp_path), {"2011_09_26_drive_0001": 4, "2011_09_26_drive_0005": 3})
    recs = kitti.raw_cycles(root, "all")
    assert [r["id"] for r in recs] == ["2011_09_26_drive_0001/0000000000", "2011_09_26_drive_0001/0000000001",
                                       "2011_09_26_drive_0001/0000000002", "2011_09_26_drive_0005/0000000000",
                                       "2011_09_26_drive_0005/0000000001"]
    assert recs[1]["paths"][2].endswith("image_02/data/0000000002.png")
    assert recs[1]["paths"][3].endswith("image_03/data/0000000002.png")
    # drive_0001 is a KITTI-split drive, drive_0005 is excluded (it holds KITTI 2015 scenes).
    ks = kitti.raw_cycles(root, "kitti")
    assert {r["id"].split("/")[0] for r in ks} == {"2011_09_26_drive_0001"} and len(ks) == 3
    f, b = kitti.raw_focal_baseline(os.path.dirname(os.path.dirname(recs[0]["paths"][0])).rsplit("/", 2)[0])
    assert f == pytest.approx(721.5377)
    lst = tmp_path / "list.txt"
    lst.write_text("2011_09_26/2011_09_26_drive_0005_sync/image_02/data/0000000001.jpg x y z\n")
    assert [r["id"] for r in kitti.raw_cycles(root, str(lst))] == ["2011_09_26_drive_0005/0000000001"]


def test_raw_cycles_empty_folder_error_names_layout(tmp_path):
    with pytest.raises(ValueError, match="image_02/data"):
        kitti.raw_cycles(str(tmp_path), "all")


def test_a_png_cut_inside_its_signature_is_reported_as_truncated_not_empty(tmp_path):
    from bridge_jax.data import folders
    path = tmp_path / "cut.png"
    path.write_bytes(b"\x89PNG")
    with pytest.raises(kitti.CorruptImageError, match=r"cut.png: truncated PNG \(only 4 bytes\)"):
        kitti.read_image(str(path))
    with pytest.raises(kitti.CorruptImageError, match=r"truncated PNG: only 4 bytes"):
        folders.image_size(str(path))
