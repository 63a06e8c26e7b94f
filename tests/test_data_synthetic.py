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


# ----------------------------------------------------------------------------------------------------------
# Scene variations (photo textures, uniform regions, slants, spins, rigs, camera response)
# ----------------------------------------------------------------------------------------------------------

def _no_photometric(name, **kw):
    import dataclasses
    return dataclasses.replace(synthetic.SCENE_PRESETS[name], photometric=0.0, **kw)


@pytest.mark.parametrize("scene", [
    _no_photometric("real"),
    _no_photometric("heldout"),
    _no_photometric("real_motion"),
    synthetic.SceneConfig(moving_prob=1.0, spin_prob=1.0, max_spin=0.3, slant_prob=1.0),  # every object turns
    synthetic.SceneConfig(max_ego_pitch=0.08, max_ego_roll=0.06, max_ego_vertical=0.3, moving_prob=1.0,
                          max_object_vertical_speed=1.0),  # strong vertical motion
    synthetic.SceneConfig(photo_texture_prob=1.0),
])
def test_scene_variations_keep_the_ground_truth_exact(scene):
    """Photo textures, slanted and rotating objects and varied rigs change the images and the GT together:
    warping with the GT still reconstructs (same bounds as the demo scenes), and a 1 px error is seen."""
    xs, ys = _grid()
    for seed in (21, 22):
        s = synthetic.render_sample(seed, H, W, scene=scene)
        c = s["cycle"]
        good = _err(c[0], bilinear(c[1], xs - s["disp_t"], ys), s["noc_disp_t"])
        off = _err(c[0], bilinear(c[1], xs - s["disp_t"] - 1.0, ys), s["noc_disp_t"])
        assert good.mean() < 0.006 and off.mean() > 3 * good.mean(), (good.mean(), off.mean())
        # Flow: larger motions (forward motion, zoom) make a few pixels' bilinear/mip sampling differ more
        # between the frames, so the bound is on the median pixel; a 1 px error moves the median pixel a lot.
        fl, noc = s["flow"], s["noc_flow"]
        good = _err(c[0], bilinear(c[2], xs + fl[..., 0], ys + fl[..., 1]), noc)
        off = _err(c[0], bilinear(c[2], xs + fl[..., 0] + 1.0, ys + fl[..., 1]), noc)
        assert np.median(good) < 0.004 and good.mean() < 0.012, (np.median(good), good.mean())
        # (1.5x: the vertical-motion scenes move up to ~6 px vertically, where the mip levels of the two frames
        # differ more; the other scenes clear 2x)
        assert np.median(off) > 1.5 * np.median(good), (np.median(good), np.median(off))


def test_rotating_object_flow_is_not_a_translation():
    """A spinning object's flow varies across it (a pure translation would not), and still reconstructs."""
    scene = synthetic.SceneConfig(min_objects=1, max_objects=1, moving_prob=1.0, spin_prob=1.0, max_spin=0.3,
                                  facade_prob=0.0)
    spread = []
    for seed in range(30, 36):
        s = synthetic.render_sample(seed, H, W, scene=scene)
        depth = s["depth_t"]
        obj = np.isfinite(depth) & (depth < 35.0) & s["noc_flow"]
        if obj.sum() > 200:
            spread.append(np.std(s["flow"][obj], axis=0).max())
    assert spread and max(spread) > 0.5


def test_photometric_differences_touch_the_images_only():
    """The camera response changes each view differently, never the ground truth: the GT arrays equal those
    rendered without it, and warping with them reconstructs up to the added gain/offset/gamma/noise."""
    xs, ys = _grid()
    with_p = synthetic.render_sample(41, H, W, scene="real")
    without = synthetic.render_sample(41, H, W, scene=_no_photometric("real"))
    for k in with_p:
        if k != "cycle":
            np.testing.assert_array_equal(with_p[k], without[k])
    assert not np.array_equal(with_p["cycle"], without["cycle"])
    # the four views differ photometrically (not only by noise): mean colours move apart
    diffs = [np.abs(with_p["cycle"][v].astype(float).mean((0, 1)) - without["cycle"][v].astype(float).mean((0, 1)))
             for v in range(4)]
    assert max(d.max() for d in diffs) > 2.0
    c = with_p["cycle"]
    err = _err(c[0], bilinear(c[1], xs - with_p["disp_t"], ys), with_p["noc_disp_t"]).mean()
    assert 0.006 < err < 0.12  # worse than exact (the response differs) but still a reconstruction


def test_camera_response_hand_case():
    """Strength 0 is the identity; otherwise gain, offset and gamma follow the drawn values (no blur, no noise
    drawn by a generator whose draws we replay)."""
    img = np.full((4, 5, 3), 0.5, np.float32)
    assert synthetic.camera_response(img, np.random.default_rng(0), 0.0) is img
    rng = np.random.default_rng(3)
    out = synthetic.camera_response(img, rng, 1.0)
    r = np.random.default_rng(3)
    gain, offset = 1 + r.uniform(-0.12, 0.12, 3), r.uniform(-0.04, 0.04, 3)
    gamma = 1 + r.uniform(-0.15, 0.15)
    blur, _, noise = r.uniform() < 0.5, r.uniform(0.2, 0.7), r.uniform(0.0, 0.015)
    expect = np.clip(0.5 * gain + offset, 0, 1) ** gamma
    # a uniform image is unchanged by blur; the noise is at most a few std
    assert np.abs(out.mean((0, 1)) - expect).max() < 4 * noise / np.sqrt(20) + 1e-6


def test_default_scene_is_unchanged_by_the_new_switches():
    """The default (demo) scenes draw nothing from the variations' generator: a known pixel and GT value of
    sample 5 stay what they were before the switches existed."""
    a = synthetic.render_sample(5, 32, 64)
    b = synthetic.render_sample(5, 32, 64, scene="demo")
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])
    assert a["focal"] == pytest.approx(721.5377 * 64 / 1242) and a["baseline"] == 0.54


def test_rig_ranges_and_textureless_layers():
    s = synthetic.render_sample(8, H, W, scene=synthetic.SceneConfig(focal_range=(2.0, 2.0),
                                                                     baseline_range=(0.5, 0.5)))
    assert s["focal"] == pytest.approx(2 * 721.5377 * W / 1242) and s["baseline"] == pytest.approx(0.27)
    flat = synthetic.render_sample(8, H, W, scene=synthetic.SceneConfig(textureless_prob=1.0))
    textured = synthetic.render_sample(8, H, W)
    grad = [np.abs(np.diff(x["cycle"][0].astype(float).mean(-1), axis=1)).mean() for x in (flat, textured)]
    assert grad[0] < 0.3 * grad[1]


def test_scene_presets_and_bad_values():
    with pytest.raises(ValueError, match="synthetic scene must be one of"):
        synthetic.render_sample(1, 32, 64, scene="nope")
    with pytest.raises(ValueError, match="slant_prob"):
        synthetic.SceneConfig(slant_prob=1.5)
    with pytest.raises(ValueError, match="focal_range"):
        synthetic.SceneConfig(focal_range=(2.0, 1.0))
    from bridge_jax.data import pipeline
    with pytest.raises(ValueError, match="data.synthetic_scene"):
        pipeline.DataConfig(synthetic_scene="nope")


def test_photo_sets_are_disjoint():
    from bridge_jax.data import photos
    assert not set(photos.TRAIN_PHOTOS) & set(photos.HELDOUT_PHOTOS)
    crops = photos.photo_textures("heldout")
    assert crops and all(c.shape == (photos.TEXTURE_SIZE, photos.TEXTURE_SIZE, 3) and c.dtype == np.uint8
                         for c in crops)


def test_vertical_motion_switches():
    """The rig's pitch, roll and vertical motion and the objects' vertical speed give the flow a vertical part
    the `real` scenes lack, and the moved rig stays rectified: right_t1 sampled at the t+1 disparities still
    reconstructs left_t1. The scenes without the switches are unchanged (their draws come after the others)."""
    xs, ys = _grid()
    real, motion = [], []
    for seed in range(60, 64):
        a = synthetic.render_sample(seed, H, W, scene=_no_photometric("real"))
        b = synthetic.render_sample(seed, H, W, scene=_no_photometric("real_motion"))
        real.append(np.median(np.abs(a["flow"][..., 1][a["noc_flow"]])))
        motion.append(np.median(np.abs(b["flow"][..., 1][b["noc_flow"]])))
        np.testing.assert_array_equal(a["disp_t"], b["disp_t"])  # frame t is the same scene
        c = b["cycle"]
        good = _err(c[2], bilinear(c[3], xs - b["disp_t1"], ys), b["noc_disp_t1"])
        off = _err(c[2], bilinear(c[3], xs - b["disp_t1"], ys + 1.0), b["noc_disp_t1"])
        assert good.mean() < 0.006 and off.mean() > 2 * good.mean(), (good.mean(), off.mean())
    assert np.mean(motion) > 1.0 and np.mean(motion) > 3 * np.mean(real), (real, motion)
    with pytest.raises(ValueError, match="max_ego_pitch"):
        synthetic.SceneConfig(max_ego_pitch=-0.1)


def test_rig_pitch_alone_is_a_rotation_about_the_baseline():
    """With the rig only pitching (no other motion, nothing moving), the flow is the rotation homography
    K R K^-1 of one angle: the angle read off the principal point's flow predicts every other pixel's flow."""
    scene = synthetic.SceneConfig(max_ego_forward=0.0, max_ego_lateral=0.0, max_ego_yaw=0.0, moving_prob=0.0,
                                  max_ego_pitch=0.05)
    cx, cy = (W - 1) / 2.0, 0.46 * H
    iy, ix = int(round(cy)), int(round(cx))
    for seed in range(70, 90):  # a draw with a clear pitch
        s = synthetic.render_sample(seed, H, W, scene=scene)
        f, fl, ok = s["focal"], s["flow"], s["valid_flow"]
        y_c = iy + fl[iy, ix, 1]  # where the ray through (ix, iy) lands
        theta = np.arctan2(y_c - cy, f) - np.arctan2(iy - cy, f)  # the pitch, as seen at the principal column
        if abs(theta) > 0.02:
            break
    assert abs(theta) > 0.02
    xs, ys = _grid()
    a, b = (xs - cx) / f, (ys - cy) / f
    # a ray (a, b, 1) turned by theta about x: (a, b cos - sin, b sin + cos) up to the sign the GT decides
    den = b * np.sin(theta) + np.cos(theta)
    x1, y1 = cx + f * a / den, cy + f * (b * np.cos(theta) - np.sin(theta)) / den
    if np.median(np.abs(y1 - ys - fl[..., 1])[ok]) > 0.5:  # the other sign convention
        den = -b * np.sin(theta) + np.cos(theta)
        x1, y1 = cx + f * a / den, cy + f * (b * np.cos(theta) + np.sin(theta)) / den
    np.testing.assert_allclose(fl[..., 0][ok], (x1 - xs)[ok], atol=0.02)
    np.testing.assert_allclose(fl[..., 1][ok], (y1 - ys)[ok], atol=0.02)
