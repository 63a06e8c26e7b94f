"""Procedural stereo video (bridge_jax.data.synthetic): exact-GT self-checks, determinism, CLI."""
import os
import subprocess
import sys

import numpy as np
import pytest

from bridge_jax.data import kitti, synthetic
from tests.test_data_fakes import bilinear

H, W = 96, 192


@pytest.fixture(scope="module")
def samples():
    return [synthetic.render_sample(s, H, W) for s in (11, 12, 13)]


def _grid():
    return np.meshgrid(np.arange(W, dtype=np.float64), np.arange(H, dtype=np.float64))


def _err(img_a, img_b_sampled, mask):
    return np.abs(img_a.astype(np.float64) / 255 - img_b_sampled / 255).mean(-1)[mask]


def test_deterministic_and_seed_dependent():
    a = synthetic.render_sample(5, 32, 64)
    b = synthetic.render_sample(5, 32, 64)
    c = synthetic.render_sample(6, 32, 64)
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert not np.array_equal(a["cycle"], c["cycle"])


def test_shapes_dtypes_and_masks(samples):
    s = samples[0]
    assert s["cycle"].shape == (4, H, W, 3) and s["cycle"].dtype == np.uint8
    for k in ("disp_t", "disp_t1", "disp_t1_ref_t"):
        assert s[k].shape == (H, W) and s[k].dtype == np.float32
    assert s["flow"].shape == (H, W, 2) and s["flow"].dtype == np.float32
    for s in samples:
        assert (s["disp_t"][s["valid_disp_t"]] > 0).all()
        assert not (s["noc_disp_t"] & ~s["valid_disp_t"]).any()
        assert not (s["noc_flow"] & ~s["valid_flow"]).any()
        assert s["focal"] == pytest.approx(721.5377 * W / 1242) and s["baseline"] == 0.54
    # Over the samples: occlusions and out-of-view motion exist, but most pixels are non-occluded.
    noc_d = np.mean([s["noc_disp_t"].mean() for s in samples])
    noc_f = np.mean([s["noc_flow"].mean() for s in samples])
    assert 0.6 < noc_d < 0.995 and 0.4 < noc_f < 0.995
    # Disparity = f·B/Z exactly.
    s = samples[0]
    m = s["valid_disp_t"]
    np.testing.assert_allclose(s["disp_t"][m], s["focal"] * 0.54 / s["depth_t"][m], rtol=1e-5)


def test_right_image_at_x_minus_d_reproduces_left(samples):
    xs, ys = _grid()
    for s in samples:
        c = s["cycle"]
        for left, right, disp, noc in ((0, 1, s["disp_t"], s["noc_disp_t"]), (2, 3, s["disp_t1"], s["noc_disp_t1"])):
            good = _err(c[left], bilinear(c[right], xs - disp, ys), noc).mean()
            off = _err(c[left], bilinear(c[right], xs - disp - 1.0, ys), noc).mean()
            assert good < 0.006, good               # interpolation + uint8 noise only
            assert off > 3 * good, (good, off)       # and the check is sensitive to a 1 px error


def test_t1_image_at_x_plus_flow_reproduces_t(samples):
    xs, ys = _grid()
    for s in samples:
        c, fl, noc = s["cycle"], s["flow"], s["noc_flow"]
        good = _err(c[0], bilinear(c[2], xs + fl[..., 0], ys + fl[..., 1]), noc).mean()
        off = _err(c[0], bilinear(c[2], xs + fl[..., 0] + 1.0, ys + fl[..., 1]), noc).mean()
        assert good < 0.008, good
        assert off > 2.5 * good, (good, off)
        # Scene-flow GT (KITTI disp_*_1): right_t1 at (x + u - d1, y + v) reproduces left_t on noc pixels.
        m = s["noc_disp_t1_ref_t"]
        assert m.mean() > 0.3 and not (m & ~noc).any()
        x_r1 = xs + fl[..., 0] - s["disp_t1_ref_t"]
        assert _err(c[0], bilinear(c[3], x_r1, ys + fl[..., 1]), m).mean() < 0.008


def test_gt_with_geometry_warp(samples):
    geometry = pytest.importorskip("bridge_jax.geometry")
    s = samples[1]
    c = s["cycle"].astype(np.float32) / 255
    d = np.stack([-s["disp_t"], np.zeros_like(s["disp_t"])], -1)
    rec = np.asarray(geometry.warp(c[1][None], d[None]))[0]
    assert np.abs(rec - c[0]).mean(-1)[s["noc_disp_t"]].mean() < 0.006
    rec = np.asarray(geometry.warp(c[2][None], s["flow"][None]))[0]
    assert np.abs(rec - c[0]).mean(-1)[s["noc_flow"]].mean() < 0.008


def test_textures_have_natural_image_structure(samples):
    for s in samples:
        img = s["cycle"][0].astype(np.float64) / 255
        gx = np.abs(np.diff(img.mean(-1), axis=1))
        assert gx.mean() > 0.01                       # not flat
        assert (gx > 0.1).mean() > 0.002              # some sharp edges
        chroma = np.abs(img[..., 0] - img[..., 1]).mean() + np.abs(img[..., 1] - img[..., 2]).mean()
        assert chroma > 0.02                          # coloured
        assert 0.15 < img.mean() < 0.85


def test_grain_source():
    src = synthetic.SyntheticCycles(num=3, seed=2, height=32, width=64)
    assert len(src) == 3
    r = src[1]
    assert set(r) == {"cycle", "id"} and r["cycle"].shape == (4, 32, 64, 3) and r["id"] == "synthetic-2-000001"
    np.testing.assert_array_equal(r["cycle"], synthetic.render_sample(synthetic.sample_seed(2, 1), 32, 64)["cycle"])


def test_cli_writes_kitti_layout_and_refuses_to_overwrite(tmp_path):
    out = tmp_path / "syn"
    cmd = [sys.executable, "-m", "bridge_jax.data.synthetic", "--out", str(out), "--num", "2", "--seed", "4",
           "--height", "32", "--width", "64"]
    env = dict(os.environ, JAX_PLATFORMS="cpu")
    r = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r.returncode == 0, r.stderr
    for d in ("image_2", "image_3", "disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1", "flow_occ", "flow_noc"):
        assert sorted(os.listdir(out / d))[:1] == ["000000_10.png"], d
    assert sorted(os.listdir(out / "image_2")) == ["000000_10.png", "000000_11.png", "000001_10.png",
                                                   "000001_11.png"]
    f, b = kitti.focal_baseline(kitti.read_calib_file(str(out / "calib_cam_to_cam" / "000001.txt")))
    assert f == pytest.approx(721.5377 * 64 / 1242) and b == pytest.approx(0.54)
    ref = synthetic.render_sample(synthetic.sample_seed(4, 1), 32, 64)
    np.testing.assert_array_equal(kitti.read_image(str(out / "image_3" / "000001_11.png")), ref["cycle"][3])
    d1, v1 = kitti.read_disp_png(str(out / "disp_occ_1" / "000001_10.png"))
    assert np.abs(d1 - ref["disp_t1_ref_t"])[v1].max() < 0.003
    r2 = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert r2.returncode != 0 and "exists" in r2.stderr and "Traceback" not in r2.stderr
    assert not [p for p in os.listdir(tmp_path) if ".tmp-" in p]
