"""Faults a run must survive with one clear line and a truthful workdir: a full disk while checkpointing, a
status.json that follows the run (heartbeat, every exit path, a dead process detectable), a second signal."""

from __future__ import annotations

import contextlib
import errno
import json
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import checkpointing, train, workdir
from tests.train_helpers import REPO, subprocess_env, tiny_config, train_cli

# ------------------------------------------------------------------------------------------------ a small disk


@contextlib.contextmanager
def _small_disk(path: Path, size: str = "3m"):
    """A tmpfs of `size` at `path` (root only); None when it cannot be mounted."""
    path.mkdir(parents=True, exist_ok=True)
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(path)], capture_output=True)
    if r.returncode != 0:
        yield None
        return
    try:
        yield path
    finally:
        subprocess.run(["umount", "-l", str(path)], capture_output=True)


def _fill(disk: Path, leave: int) -> None:
    """Fills `disk` up to `leave` free bytes."""
    import shutil
    free = shutil.disk_usage(disk).free
    with open(disk / "filler", "wb") as f:
        f.write(b"\0" * max(0, free - leave))


def _state(v: float, n: int = 150_000) -> dict:
    """~1.2 MB of incompressible values (orbax compresses), recognisable by `v`."""
    rng = np.random.default_rng(int(v))
    return {"params": {"w": jnp.asarray(rng.standard_normal(n, np.float32) + v)},
            "opt_state": {"mu": jnp.asarray(rng.standard_normal(n, np.float32))}, "step": jnp.int32(int(v))}


def test_a_full_disk_while_saving_is_one_error_naming_the_folder_and_the_space_and_keeps_the_last_step(
        tmp_path, monkeypatch):
    with _small_disk(tmp_path / "disk") as disk:
        wd = (disk if disk is not None else tmp_path) / "wd"
        ck = checkpointing.TrainCheckpointer(wd, save_every=1, keep=3, async_save=True)
        assert ck.save(1, _state(1.0), {"next_index": 1})
        ck.wait()
        if disk is not None:
            _fill(disk, 200_000)
        else:  # no tmpfs here: the writer reports ENOSPC as orbax does
            def full(*a, **k):
                (wd / "checkpoints" / "2.orbax-checkpoint-tmp").mkdir()
                raise OSError(errno.ENOSPC, "No space left on device")
            monkeypatch.setattr(ck.manager, "save", full)
        with pytest.raises(checkpointing.CheckpointSaveError) as info:
            ck.save(2, _state(2.0), {"next_index": 2})
            ck.wait()
        ck.close()
        msg = str(info.value)
        assert "\n" not in msg and msg.startswith(f"{wd / 'checkpoints'}: cannot save step 2 (No space left on device)")
        assert "one checkpoint takes about" in msg and "keeping 3 needs room for 4" in msg and "is free" in msg
        assert "step 1, is kept" in msg
        assert sorted(os.listdir(wd / "checkpoints")) == ["1"]  # the partial step 2 is gone
        restored, data = checkpointing.TrainCheckpointer(wd).restore(1, jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), _state(0.0)))
        np.testing.assert_array_equal(restored["params"]["w"], _state(1.0)["params"]["w"])
        assert data == {"next_index": 1}


def test_save_noise_filter_drops_only_records_about_the_failed_write():
    import logging

    def rec(name, msg):
        return logging.LogRecord(name, logging.ERROR, __file__, 1, msg, None, None)

    assert checkpointing._save_noise(rec("absl", "_SignalingThread.run() raised an exception: RESOURCE_EXHAUSTED: x"))
    assert checkpointing._save_noise(rec("absl", "[step=2][wait_until_finished] Save Finalize thread (save_finalize) "
                                                 "failed."))
    assert checkpointing._save_noise(rec("asyncio", "Future exception was never retrieved\nfuture: ... No space left "
                                                    "on device"))
    assert not checkpointing._save_noise(rec("asyncio", "Future exception was never retrieved: KeyError('x')"))
    assert not checkpointing._save_noise(rec("absl", "something else went wrong"))


@pytest.mark.slow
def test_cli_on_a_full_disk_exits_2_with_at_most_3_lines_status_failed_and_no_tmp_dir(tmp_path):
    with _small_disk(tmp_path / "disk") as disk:
        if disk is None:
            pytest.skip("cannot mount a tmpfs here (not root)")
        wd = disk / "w"
        r = subprocess.run(train_cli(str(wd), "--config.loop.num_train_steps=30", "--config.loop.checkpoint_every=1"),
                           env=subprocess_env(2), capture_output=True, text=True, timeout=600)
        err = [line for line in r.stderr.splitlines() if line.strip()]
        assert r.returncode == 2 and len(err) <= 3, r.stderr[-3000:]
        assert err[-1].startswith(f"error: {wd / 'checkpoints'}: cannot save step") and "No space left" in err[-1]
        status = json.loads((wd / "status.json").read_text())
        assert status["status"] == "failed" and "cannot save step" in status["reason"]
        assert not [p for p in os.listdir(wd / "checkpoints") if "tmp" in p]


# ------------------------------------------------------------------------------------------------ status.json


def test_run_status_heartbeats_updates_and_ends_atomically(tmp_path):
    st = workdir.RunStatus(str(tmp_path), True, heartbeat_s=0.05, step=0, num_steps=10)
    first = workdir.read_status(str(tmp_path))
    assert first["status"] == "running" and first["stale_after_s"] == pytest.approx(0.15)
    st.progress(3)
    time.sleep(0.3)
    beat = workdir.read_status(str(tmp_path))
    assert beat["step"] == 3 and beat["heartbeat"] > first["heartbeat"]  # the thread wrote in between
    st.update(step=4, steps_per_s=2.5, last_checkpoint=4)
    st.end("finished", step=10)
    st.end("failed", reason="too late")  # the first end wins
    done = workdir.read_status(str(tmp_path))
    assert done["status"] == "finished" and done["step"] == 10 and "reason" not in done
    time.sleep(0.2)
    assert workdir.read_status(str(tmp_path))["heartbeat"] == done["heartbeat"]  # no beats after the end
    assert not [p for p in os.listdir(tmp_path) if p != "status.json"]  # no temporary files left


def test_stale_rule_and_status_command(tmp_path, capsys):
    workdir.write_status(str(tmp_path), "running", 7, num_steps=20, stale_after_s=90.0)
    st = workdir.read_status(str(tmp_path))
    assert not workdir.is_stale(st, now=st["heartbeat"] + 89) and workdir.is_stale(st, now=st["heartbeat"] + 91)
    assert train.main(["--status", str(tmp_path)]) == 0
    assert capsys.readouterr().out.startswith(f"{tmp_path}: running, step 7/20")
    st["heartbeat"] -= 100
    (tmp_path / "status.json").write_text(json.dumps(st))
    assert train.main(["--status", str(tmp_path)]) == 1
    assert "STALE: no heartbeat for over 90 s, the process is gone" in capsys.readouterr().out
    assert train.main(["--status", str(tmp_path / "nothing")]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_no_usable_checkpoint_leaves_status_failed_with_the_reason(tmp_path):
    wd = tmp_path / "wd"
    (wd / "checkpoints" / "5").mkdir(parents=True)  # an empty step dir: the only one
    workdir.write_status(str(wd), "finished", 5)  # what an earlier run left
    with pytest.raises(train.ConfigError, match="no usable checkpoint"):
        train.train_and_evaluate(tiny_config(), str(wd))
    status = workdir.read_status(str(wd))
    assert status["status"] == "failed" and "no usable checkpoint" in status["reason"]


_SECOND_SIGNAL = textwrap.dedent("""
    import os, signal, sys, time
    from bridge_jax import train
    def abort(signum):
        open(sys.argv[1], "w").write(str(signum))
    with train._StopSignals(announce=False, on_abort=abort) as stop:
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(0.2)
        assert stop.received == signal.SIGINT
        os.kill(os.getpid(), signal.SIGINT)
        time.sleep(5)
    print("not reached")
""")


def test_a_second_signal_runs_on_abort_and_exits_130_at_once(tmp_path):
    mark = tmp_path / "aborted"
    r = subprocess.run([sys.executable, "-c", _SECOND_SIGNAL, str(mark)], env=subprocess_env(1), capture_output=True,
                       text=True, timeout=120)
    assert r.returncode == 130 and "not reached" not in r.stdout, r.stderr[-2000:]
    assert mark.read_text() == str(int(signal.SIGINT))


def _wait_for_step(wd: Path, proc, timeout: float = 400) -> dict:
    end = time.time() + timeout
    while time.time() < end:
        assert proc.poll() is None, proc.stderr.read()[-3000:]
        with contextlib.suppress(ValueError):
            st = workdir.read_status(str(wd))
            if st["status"] == "running" and st.get("step", 0) >= 1:
                return st
        time.sleep(0.2)
    raise AssertionError("the run did not reach step 1")


@pytest.mark.slow
def test_status_after_two_ctrl_c_and_after_sigkill(tmp_path):
    env = dict(subprocess_env(2), BRIDGE_JAX_HEARTBEAT_S="0.5")
    wd = tmp_path / "twice"
    p = subprocess.Popen(train_cli(str(wd), "--config.loop.num_train_steps=100000",
                                   "--config.loop.checkpoint_every=1000"), env=env, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    _wait_for_step(wd, p)
    p.send_signal(signal.SIGINT)
    time.sleep(0.1)  # two identical signals sent at once are delivered as one (a person presses twice)
    p.send_signal(signal.SIGINT)
    assert p.wait(60) == 130, p.stderr.read()[-2000:]
    st = workdir.read_status(str(wd))
    assert st["status"] == "aborted" and st["signal"] == signal.SIGINT and st["step"] >= 1
    assert train.main(["--status", str(wd)]) == 1

    wd = tmp_path / "killed"
    p = subprocess.Popen(train_cli(str(wd), "--config.loop.num_train_steps=100000"), env=env,
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    st = _wait_for_step(wd, p)
    p.kill()
    p.wait(30)
    time.sleep(2.0)  # > 3 heartbeat periods of 0.5 s
    line, stale = workdir.describe_status(str(wd))
    assert stale and line.startswith(f"{wd}: running") and "STALE" in line
