"""Working sizes that cannot fit in memory are refused before anything is allocated or written: the per-pixel
lower bounds of `bridge_jax.memory`, the limit they are compared with, and the train and predict commands."""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import time
import types

import cv2
import jax
import numpy as np
import pytest

from bridge_jax import configs, memory, predict, recipe, setup
from tests.train_helpers import subprocess_env

GIB = 2 ** 30


def test_the_estimates_are_the_documented_per_pixel_bounds():
    # training: 256 bytes per pixel and pair-forward, 48 (4 frames x 3 float32 channels) per pixel and cycle
    assert memory.training_bytes(64, 128, rows=8, cycles=1) == 64 * 128 * (8 * 256 + 48) == 17_170_432
    assert memory.training_bytes(256, 512, rows=16, cycles=2) == 256 * 512 * 4_192
    # prediction: 64 bytes per pixel and pair
    assert memory.prediction_bytes(100_000, 100_000) == 64 * 10 ** 10
    assert memory.prediction_bytes(128, 256, pairs=4) == 128 * 256 * 4 * 64


def test_sizes_the_project_uses_are_taken_on_a_small_machine(monkeypatch):
    """Every stage of the shipped recipes and the paper's config (up to 256x512 with 2 cycles, 16 pair-forwards)
    and a large explicit prediction size (the native rule stops at 1024x768) pass on a 2 GiB machine."""
    monkeypatch.setattr(memory, "_machine_bytes", lambda: 2 * GIB)
    sizes = set()
    for name in ("default", "long", "demo"):
        config = configs.load(name)
        stages = [recipe.stage_config(config, s) for s in recipe.stage_names(config)] if recipe.is_recipe(config) \
            else [config]
        for cfg in stages:
            run = setup.parse(cfg)
            sizes.add((run.height, run.width, run.global_batch))
    assert (256, 512, 2) in sizes
    memory.check_fits("--working-size", 2048, 4096, memory.prediction_bytes(2048, 4096), "a prediction")


def test_check_fits_refuses_only_above_the_limit_in_one_line(monkeypatch):
    monkeypatch.setattr(memory, "_machine_bytes", lambda: 8 * GIB)
    memory.check_fits("--working-size", 64, 128, 8 * GIB, "a prediction")  # exactly the limit: taken
    with pytest.raises(ValueError) as info:
        memory.check_fits("--working-size", 64, 128, 8 * GIB + 1, "a prediction")
    assert str(info.value) == ("--working-size 64x128 (height x width): a prediction needs at least 8.0 GiB at this "
                               "size, more than the 8.0 GiB of this machine's RAM")
    monkeypatch.setattr(memory, "_machine_bytes", lambda: None)  # unknown: nothing is refused
    memory.check_fits("--working-size", 64, 128, 10 ** 15, "a prediction")


def test_the_limit_is_the_machines_memory_or_the_containers_if_lower(tmp_path, monkeypatch):
    physical = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    v2, v1 = tmp_path / "memory.max", tmp_path / "memory.limit_in_bytes"
    monkeypatch.setattr(memory, "_CGROUP_LIMITS", (str(v2), str(v1)))
    assert memory.memory_limit() == (physical, "this machine's RAM")  # neither file: the machine's
    v2.write_text("max\n")
    assert memory.memory_limit()[0] == physical  # cgroup v2 without a limit
    v1.write_text(f"{2 * GIB}\n")
    assert memory.memory_limit()[0] == min(physical, 2 * GIB)
    v2.write_text(f"{GIB}\n")
    assert memory.memory_limit()[0] == min(physical, GIB)


def test_an_accelerator_is_compared_with_its_own_memory():
    gpu = types.SimpleNamespace(platform="gpu", device_kind="NVIDIA H100", memory_stats=lambda: {"bytes_limit": GIB})
    assert memory.memory_limit(gpu) == (GIB, "the NVIDIA H100's memory")
    silent = types.SimpleNamespace(platform="tpu", device_kind="TPU v4", memory_stats=lambda: None)
    assert memory.memory_limit(silent)[1] == "this machine's RAM"
    with pytest.raises(ValueError, match=r"^config.height/config.width 128x256 \(height x width\): x needs at least "
                                         r"1.0 GiB at this size, more than the 1.0 GiB of the NVIDIA H100's memory$"):
        memory.check_fits("config.height/config.width", 128, 256, GIB + 1, "x", gpu)


def test_parse_compares_the_train_step_bound_with_the_memory(monkeypatch):
    """default:local at 128x256 with 2 cycles (16 pair-forwards; on this test session's fake CPU devices, which
    share the machine's RAM, all of them count): 128 * 256 * (16 * 256 + 2 * 48) bytes, refused one byte below."""
    config = configs.load("default:local")
    needed = 128 * 256 * (16 * 256 + 2 * 48)
    for devices in (jax.devices()[:1], jax.devices()[:2]):
        monkeypatch.setattr(memory, "_machine_bytes", lambda: needed)
        assert setup.parse(config, devices=devices).height == 128
        monkeypatch.setattr(memory, "_machine_bytes", lambda: needed - 1)
        on = " on this machine" if len(devices) > 1 else ""
        with pytest.raises(setup.ConfigError, match=rf"^config.height/config.width 128x256 \(height x width\): a train "
                                                    rf"step of 16 pair-forwards{on} \(at least 256 bytes per pixel "
                                                    r"each\) needs at least 0.1 GiB at this size, more than"):
            setup.parse(config, devices=devices)


def test_train_command_refuses_a_huge_size_in_one_line_and_writes_nothing(tmp_path):
    """The real command (its own process, as a user runs it): the demo's pwc_lite takes 100000 (a multiple of 8),
    so only the memory bound refuses it, before the recipe's workdir is created."""
    workdir = tmp_path / "w"
    cmd = [sys.executable, "-m", "bridge_jax.train", "--config=demo", f"--workdir={workdir}",
           "--config.height=100000", "--config.width=100000"]
    r = subprocess.run(cmd, cwd=tmp_path, env=subprocess_env(1), capture_output=True, text=True, timeout=120)
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 2 and len(lines) == 1, r.stderr
    assert lines[0].startswith("error: stage coarse: config.height/config.width 100000x100000 (height x width): a "
                               "train step of 8 pair-forwards (at least 256 bytes per pixel each) needs at least "
                               "19,520.5 GiB at this size, more than the "), lines
    assert not workdir.exists() and os.listdir(tmp_path) == []


def test_predict_command_refuses_a_huge_working_size_quickly_without_allocating(tmp_path, capsys):
    """`--working-size 100000x100000` with the shipped demo model (pwc_lite: a multiple of 8, so only the memory
    bound refuses it): one line, exit 2, in well under the seconds a load would take, and the process's peak
    memory does not grow by the gigabytes the old path allocated before failing."""
    a, b = str(tmp_path / "a.png"), str(tmp_path / "b.png")
    for path in (a, b):
        assert cv2.imwrite(path, np.zeros((64, 128, 3), np.uint8))
    peak_before = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux
    t0 = time.perf_counter()
    code = predict.main(["--checkpoint", "demo", a, b, "--out", str(tmp_path / "out"), "--working-size",
                         "100000x100000", "--no-progress"])
    seconds = time.perf_counter() - t0
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1, err
    assert err[0].startswith("error: --working-size 100000x100000 (height x width): a prediction (one pair per call) "
                             "needs at least 596.0 GiB at this size, more than the "), err
    assert seconds < 5, seconds
    assert resource.getrusage(resource.RUSAGE_SELF).ru_maxrss - peak_before < 512 * 1024
    assert not (tmp_path / "out").exists()


def test_predict_names_a_frame_of_another_size_height_by_width(tiny_checkpoint, tmp_path, capsys):
    """Sizes read as the option writes them (--working-size HxW): a folder frame of another size is named height x
    width, as the first frame is (it read "200x96, but the first frame is 200x100", width first)."""
    folder = tmp_path / "frames"
    folder.mkdir()
    assert cv2.imwrite(str(folder / "0.png"), np.zeros((100, 200, 3), np.uint8))
    assert cv2.imwrite(str(folder / "1.png"), np.zeros((96, 200, 3), np.uint8))
    code = predict.main(["--checkpoint", tiny_checkpoint, str(folder), "--out", str(tmp_path / "out"),
                         "--working-size", "64x128", "--no-progress"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and err == [f"error: {folder / '1.png'} is 96x200, but the first frame is 100x200 (height x "
                                 "width)"], err
