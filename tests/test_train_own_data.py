"""Training on your own stereo video: folder data, validation on held-out frames (`config.data.val_dir`, no ground
truth), the data-skip report, and the one-line errors before anything is written."""
from __future__ import annotations

import json
import os

import cv2
import pytest

from bridge_jax import train
from bridge_jax.data import synthetic
from tests.test_data_fakes import truncate_file, write_stereo_sequence
from tests.train_helpers import H, W, enable_compilation_cache, tiny_config


@pytest.fixture(scope="module", autouse=True)
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


def _write_video(root, num_frames, seed):
    """A stereo video folder root/left, root/right of `num_frames` synthetic frames (consecutive samples are
    not one scene, which does not matter for these checks)."""
    for side in ("left", "right"):
        os.makedirs(os.path.join(root, side), exist_ok=True)
    for k in range(num_frames // 2):
        cyc = synthetic.render_sample(synthetic.sample_seed(seed, k), H, W, with_gt=False)["cycle"]
        for j, side in enumerate(("left", "right", "left", "right")):
            cv2.imwrite(os.path.join(root, side, f"{2 * k + j // 2:04d}.png"), cyc[j][..., ::-1])


def _jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


def test_own_video_trains_validates_photometrically_and_reports_skipped_cycles(tmp_path):
    train_dir, val_dir = tmp_path / "video", tmp_path / "heldout"
    _write_video(str(train_dir), 8, seed=3)
    _write_video(str(val_dir), 4, seed=4)
    truncate_file(str(train_dir / "right" / "0005.png"), keep=0.5)  # decodes badly at run time
    wd = str(tmp_path / "wd")
    cfg = tiny_config(**{"loop.num_train_steps": 4, "loop.eval_every": 2, "data.source": "folder",
                         "data.data_dir": str(train_dir), "data.val_dir": str(val_dir), "data.augment": False,
                         "eval.num_samples": 8})
    res = train.train_and_evaluate(cfg, wd)
    assert res["step"] == 4
    recs = _jsonl(os.path.join(wd, "metrics.jsonl"))
    vals = [r for r in recs if r["kind"] == "val"]
    assert [r["step"] for r in vals] == [2, 4]
    v = vals[-1]
    assert v["num_cycles"] == 3  # 4 held-out frames -> 3 consecutive cycles
    for key in ("stereo_photo_ssim_l1", "flow_photo_ssim_l1", "zero_stereo_photo_ssim_l1",
                "stereo_photo_ssim_l1_vs_zero", "stereo_lr_consistency_px"):
        assert key in v, key
    assert v["stereo_photo_ssim_l1_vs_zero"] == pytest.approx(v["stereo_photo_ssim_l1"] / v["zero_stereo_photo_ssim_l1"],
                                                              rel=1e-6)
    # the truncated right frame 0005 spoils the two cycles using it (0004->0005 and 0005->0006), once each
    skips = [r for r in recs if r["kind"] == "data_skips"]
    assert len(skips) == 1 and skips[0]["cycles"] >= 1
    assert any(p.endswith(os.path.join("right", "0005.png")) for p in skips[0]["files"])
    assert os.listdir(os.path.join(wd, "images")), "pictures of the user's own validation cycles"


def test_bad_val_dir_and_mismatched_frame_sizes_are_one_error_and_nothing_is_written(tmp_path):
    train_dir = tmp_path / "video"
    _write_video(str(train_dir), 4, seed=3)
    wd = tmp_path / "wd"
    cfg = tiny_config(**{"data.source": "folder", "data.data_dir": str(train_dir),
                         "data.val_dir": str(tmp_path / "missing"), "loop.eval_every": 2})
    with pytest.raises(train.ConfigError, match="config.data.val_dir"):
        train.train_and_evaluate(cfg, str(wd))
    assert not wd.exists()
    odd = tmp_path / "odd"
    write_stereo_sequence(str(odd), [f"{i:04d}" for i in range(4)], size=(64, 128),
                          sizes={f"right/{i:04d}.png": (60, 120) for i in range(4)})
    cfg = tiny_config(**{"data.source": "folder", "data.data_dir": str(odd)})
    with pytest.raises(train.ConfigError, match=r"left and right differ in size: .*left/0000.png is 64x128, "
                                                r".*right/0000.png is 60x120"):
        train.train_and_evaluate(cfg, str(wd))
    assert not wd.exists()


@pytest.mark.slow
def test_readme_walkthrough_own_video_fine_tune_then_predict(tmp_path):
    """README "Using it" 2-4 from a folder outside the repo: frames → fine-tune the shipped model with held-out
    validation → predict a stereo folder with the result."""
    import subprocess
    import sys

    from tests.train_helpers import subprocess_env
    _write_video(str(tmp_path / "my_video"), 8, seed=3)
    _write_video(str(tmp_path / "my_video_heldout"), 4, seed=5)
    env = subprocess_env(1)
    r = subprocess.run([sys.executable, "-m", "bridge_jax.train", "--config=demo", "--workdir=work/mine_ft",
                        "--config.init_from=demo", "--config.data.source=folder", "--config.data.data_dir=my_video",
                        "--config.data.val_dir=my_video_heldout", "--config.loop.num_train_steps=2",
                        "--config.loop.eval_every=1", "--config.loop.progress_bar=False"],
                       cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-3000:]
    lines = r.stdout.splitlines()
    assert any(line.startswith("step 1 validation: flow photometric error") for line in lines), r.stdout
    assert any("initialised from demo" in line for line in lines), r.stdout
    r = subprocess.run([sys.executable, "-m", "bridge_jax.predict", "--checkpoint", "work/mine_ft",
                        "my_video_heldout", "--out", "out"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-3000:]
    assert sorted(os.listdir(tmp_path / "out" / "disparity")) == ["0000.png", "0001.png", "0002.png", "0003.png"]
