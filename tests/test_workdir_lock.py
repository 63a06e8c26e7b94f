"""One trainer per workdir: the workdir lock (`workdir.WorkdirLock`), a second trainer refused naming the first
one's PID with nothing in the workdir changed, a killed holder leaving no lock behind, `--status` beside a
running trainer; and a resume whose config differs from the workdir's config.json (refused with the fields
listed, let through by --allow-config-change)."""
from __future__ import annotations

import json
import os
import shutil
import socket
import subprocess
import sys

import pytest

from bridge_jax import checkpointing, configs, setup, train, workdir as workdir_mod
from tests.train_helpers import REPO, enable_compilation_cache, subprocess_env, tiny_config, train_cli


def _snapshot(folder) -> dict:
    """{relative path: (bytes, mtime_ns)} of every file under `folder`, and the folders as (None, None)."""
    out = {}
    for root, dirs, names in os.walk(folder):
        for d in dirs:
            out[os.path.relpath(os.path.join(root, d), folder)] = (None, None)
        for n in names:
            path = os.path.join(root, n)
            with open(path, "rb") as f:
                out[os.path.relpath(path, folder)] = (f.read(), os.stat(path).st_mtime_ns)
    return out


# --------------------------------------------------------------------------------------------------------
# The lock itself
# --------------------------------------------------------------------------------------------------------

def test_the_lock_is_exclusive_names_its_holder_and_is_released(tmp_path):
    wd = tmp_path / "wd"
    assert workdir_mod.lock_holder(str(wd)) is None and not wd.exists()  # a probe creates nothing
    wd.mkdir()
    assert workdir_mod.lock_holder(str(wd)) is None and os.listdir(wd) == []

    lock = workdir_mod.WorkdirLock(str(wd))
    assert (wd / ".lock").read_text() == f"{os.getpid()}\n{socket.gethostname()}\n"
    assert workdir_mod.lock_holder(str(wd)) == f"PID {os.getpid()}"
    # a second lock is refused even in the same process (flock locks belong to the open file, not the process)
    with pytest.raises(workdir_mod.WorkdirInUse, match=rf"is in use by another trainer \(PID {os.getpid()}\)"):
        workdir_mod.WorkdirLock(str(wd))
    assert (wd / ".lock").read_text().startswith(f"{os.getpid()}\n")  # the refused one erased nothing
    lock.release()
    lock.release()  # idempotent
    assert workdir_mod.lock_holder(str(wd)) is None and (wd / ".lock").read_text() == ""
    with workdir_mod.WorkdirLock(str(wd)):
        assert workdir_mod.lock_holder(str(wd)) == f"PID {os.getpid()}"
    assert workdir_mod.lock_holder(str(wd)) is None

    # processes > 0 of a multi-host run hold nothing (process 0 locks for them)
    with workdir_mod.WorkdirLock(str(wd), enabled=False):
        assert workdir_mod.lock_holder(str(wd)) is None


def test_another_host_is_named_and_a_half_written_pid_is_said(tmp_path):
    assert workdir_mod._describe_holder(f"17\n{socket.gethostname()}\n") == "PID 17"
    assert workdir_mod._describe_holder("17\nother-host\n") == "PID 17 on other-host"
    assert workdir_mod._describe_holder("") == "PID not written yet"


_HOLD = ("import sys, time\nfrom bridge_jax import workdir\nlock = workdir.WorkdirLock(sys.argv[1])\n"
         "print('locked', flush=True)\ntime.sleep(120)\n")


def test_a_holder_killed_with_sigkill_leaves_no_lock(tmp_path):
    wd = tmp_path / "wd"
    p = subprocess.Popen([sys.executable, "-c", _HOLD, str(wd)], stdout=subprocess.PIPE, text=True,
                         env=dict(os.environ, PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", "")))
    try:
        assert p.stdout.readline().strip() == "locked"
        assert workdir_mod.lock_holder(str(wd)) == f"PID {p.pid}"
        with pytest.raises(workdir_mod.WorkdirInUse, match=f"PID {p.pid}"):
            workdir_mod.WorkdirLock(str(wd))
    finally:
        p.kill()
        p.wait(30)
    # the kernel dropped the lock with the process; its PID is still written in the file, and does not matter
    assert (wd / ".lock").read_text().startswith(f"{p.pid}\n")
    assert workdir_mod.lock_holder(str(wd)) is None
    with workdir_mod.WorkdirLock(str(wd)):
        assert (wd / ".lock").read_text().startswith(f"{os.getpid()}\n")


# --------------------------------------------------------------------------------------------------------
# A second trainer
# --------------------------------------------------------------------------------------------------------

def test_a_second_trainer_exits_2_naming_the_pid_and_changes_nothing_and_status_still_works(tmp_path, capsys):
    wd = tmp_path / "wd"
    wd.mkdir()
    (wd / "config.json").write_text('{"keep": "me"}')
    workdir_mod.write_status(str(wd), "running", 3, num_steps=10, pid=os.getpid())
    with workdir_mod.WorkdirLock(str(wd)):  # the first trainer: this test process
        before = _snapshot(wd)
        r = subprocess.run(train_cli(str(wd), "--config.loop.num_train_steps=2"), env=subprocess_env(2),
                           capture_output=True, text=True, timeout=300)
        err = [line for line in r.stderr.splitlines() if line.strip()]
        assert r.returncode == 2, r.stderr[-2000:]
        assert len(err) == 1 and err[0].startswith(f"error: --workdir={wd} is in use by another trainer "
                                                   f"(PID {os.getpid()})"), err
        assert _snapshot(wd) == before  # no file written, none touched: not even the lock file

        # --status only reads: it works beside the running trainer (in this process: a lock attempt would fail)
        assert train.main(["--status", str(wd)]) == 0
        assert capsys.readouterr().out.startswith(f"{wd}: running, step 3/10")
        # the library call says the same, before anything is built
        with pytest.raises(train.ConfigError, match=rf"is in use by another trainer \(PID {os.getpid()}\)"):
            train.train_and_evaluate(tiny_config(num_train_steps=2), str(wd))
        assert _snapshot(wd) == before


def test_a_recipe_refuses_a_workdir_in_use_before_writing_its_record(tmp_path):
    wd = tmp_path / "recipe"
    config = configs.load("demo:short")
    with workdir_mod.WorkdirLock(str(wd)):
        before = _snapshot(wd)
        with pytest.raises(train.ConfigError, match=rf"--workdir={wd} is in use by another trainer \(PID "):
            train.run_recipe(config, str(wd))
        assert _snapshot(wd) == before  # no recipe.json, no stages/


# --------------------------------------------------------------------------------------------------------
# Resuming with another config
# --------------------------------------------------------------------------------------------------------

_ITEMS = ["height=64", "width=128", "num_devices=2", "global_batch=2", "micro_batch=0", "loop.steps_per_epoch=100",
          "loop.num_train_steps=4", "loop.progress_bar=False", "eval.num_samples=2", "data.synthetic_num=32"]


def _resumable_workdir(wd, run: setup.Run, **changed) -> None:
    """A workdir that `_check_workdir` takes for a run to resume (model.json, a step dir with its state item) whose
    config.json is `run`'s with the dotted fields `changed` set otherwise."""
    cfg = json.loads(json.dumps(run.config_json))
    for key, value in changed.items():
        node = cfg
        *path, last = key.split(".")
        for part in path:
            node = node[part]
        node[last] = value
    (wd / "checkpoints" / "4" / "state").mkdir(parents=True)
    (wd / "config.json").write_text(json.dumps(cfg))
    (wd / "model.json").write_text(json.dumps(run.model.model_json()))


def test_config_changes_are_listed_as_dotted_fields_old_to_new():
    old = {"lr": 1e-4, "seed": 0, "loop": {"num_train_steps": 4, "log_every": 1}, "gone": 1, "data": {"source": "a"}}
    new = {"lr": 2e-4, "seed": 0, "loop": {"num_train_steps": 8, "log_every": 1}, "added": 2, "data": {"source": "b"}}
    changes = train.config_changes(old, new)
    assert changes == {"lr": (1e-4, 2e-4), "loop.num_train_steps": (4, 8), "data.source": ("a", "b")}
    assert train.describe_changes(changes) == "lr 0.0001 -> 0.0002, loop.num_train_steps 4 -> 8, data.source 'a' -> 'b'"
    assert train.describe_changes(changes, limit=1) == "lr 0.0001 -> 0.0002 and 2 more"
    assert train.config_changes(old, old) == {}


def test_a_resume_with_another_config_is_refused_listing_the_fields_unless_allowed(tmp_path):
    run = setup.parse(train.load_config("default:local", _ITEMS))
    wd = tmp_path / "wd"
    _resumable_workdir(wd, run, **{"lr": 5e-5, "loss.lambda_sm": 1.0, "loop.num_train_steps": 2,
                                   "loop.log_every": 7, "num_devices": 4})
    before = _snapshot(wd)
    with pytest.raises(train.ConfigError) as info:
        train._check_workdir(run, str(wd))
    msg = str(info.value)
    assert "\n" not in msg and msg.startswith(f"--workdir={wd} was started with another config (its config.json): ")
    assert f"lr 5e-05 -> {run.config_json['lr']!r}" in msg and "loss.lambda_sm 1.0 -> 10.0" in msg
    # what a resume may change (the length, the intervals, the devices) is not held against it
    assert "num_train_steps" not in msg and "log_every" not in msg and "num_devices" not in msg
    assert "--allow-config-change" in msg
    assert train._check_workdir(run, str(wd), allow_config_change=True) is True
    assert _snapshot(wd) == before

    allowed = tmp_path / "allowed"  # only fields a resume may change: resumed without the flag
    _resumable_workdir(allowed, run, **{"loop.num_train_steps": 2, "loop.checkpoint_every": 5, "micro_batch": 2})
    assert train._check_workdir(run, str(allowed)) is True
    fresh = tmp_path / "fresh"  # a config.json without a checkpoint (killed before its first one): a new start
    fresh.mkdir()
    (fresh / "config.json").write_text(json.dumps(dict(run.config_json, lr=1.0)))
    assert train._check_workdir(run, str(fresh)) is False


def test_the_command_line_refuses_in_one_line_and_passes_the_flag(tmp_path, capsys, monkeypatch):
    run = setup.parse(train.load_config("default:local", _ITEMS))
    wd = tmp_path / "wd"
    _resumable_workdir(wd, run, seed=7)
    before = _snapshot(wd)
    argv = ["--config=default:local", f"--workdir={wd}", *(f"--config.{item}" for item in _ITEMS)]
    assert train.main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: --workdir={wd} was started with another config") \
        and "seed 7 -> 0" in err[0], err
    assert _snapshot(wd) == before

    seen = {}

    def fake(config, workdir, **kwargs):
        seen.update(kwargs)
        return {"interrupted": False, "step": 4, "checkpoint": None, "workdir": workdir}

    monkeypatch.setattr(train, "train_and_evaluate", fake)
    assert train.main([*argv, "--allow-config-change"]) == 0
    assert seen["allow_config_change"] is True
    assert train.main(argv) == 0 and seen["allow_config_change"] is False


# --------------------------------------------------------------------------------------------------------
# End to end: a real run holds the lock; resumes with another config; a lost first checkpoint; a failed save
# --------------------------------------------------------------------------------------------------------

def _jsonl(path):
    with open(path) as f:
        return [json.loads(line) for line in f if line.strip()]


@pytest.mark.slow
def test_training_holds_the_lock_resumes_truthfully_and_says_what_changed(tmp_path, monkeypatch):
    restore = enable_compilation_cache()
    try:
        _end_to_end(tmp_path, monkeypatch)
    finally:
        restore()


def _end_to_end(tmp_path, monkeypatch):
    wd = tmp_path / "wd"
    holders = []
    first_step = train._first_step

    def spy(*args, **kwargs):  # during the run: who holds the workdir
        holders.append(workdir_mod.lock_holder(str(wd)))
        return first_step(*args, **kwargs)

    monkeypatch.setattr(train, "_first_step", spy)
    cfg = dict(num_train_steps=2, checkpoint_every=2, log_every=1)
    train.train_and_evaluate(tiny_config(**cfg), str(wd))
    assert holders == [f"PID {os.getpid()}"] and workdir_mod.lock_holder(str(wd)) is None

    # killed while its first checkpoint was being written: no checkpoint, metrics of steps 1-2 on disk
    shutil.rmtree(wd / "checkpoints" / "2")
    assert [r["step"] for r in _jsonl(wd / "metrics.jsonl") if r["kind"] == "train"] == [1, 2]
    res = train.train_and_evaluate(tiny_config(**cfg), str(wd))
    assert res["start_step"] == 0 and res["step"] == 2
    assert [r["step"] for r in _jsonl(wd / "metrics.jsonl") if r["kind"] == "train"] == [1, 2]  # not [1, 2, 1, 2]

    # another seed (the data order changes; the compiled step does not): refused, nothing changed; with the flag:
    # resumed, the change printed, recorded in metrics.jsonl and kept in config.json
    before = _snapshot(wd)
    with pytest.raises(train.ConfigError, match=r"seed 0 -> 1[;,]"):
        train.train_and_evaluate(tiny_config(seed=1, **dict(cfg, num_train_steps=4)), str(wd))
    assert _snapshot(wd) == before
    res = train.train_and_evaluate(tiny_config(seed=1, **dict(cfg, num_train_steps=4)), str(wd),
                                   allow_config_change=True)
    assert res["start_step"] == 2 and res["step"] == 4
    recs = _jsonl(wd / "metrics.jsonl")
    assert [r["step"] for r in recs if r["kind"] == "train"] == [1, 2, 3, 4]
    assert [(r["step"], r["changes"]) for r in recs if r["kind"] == "config_change"] == [
        (2, {"seed": [0, 1], "loop.num_train_steps": [2, 4]})]
    assert json.loads((wd / "config.json").read_text())["seed"] == 1

    # a save that fails (a full disk) after step 5 was saved: status.json names step 5, the checkpoint there
    save = checkpointing.TrainCheckpointer.save

    def full_at_6(self, step, *args, **kwargs):
        if int(step) == 6:
            self.wait()
            raise checkpointing.CheckpointSaveError(f"{self.directory}: cannot save step 6 (No space left on device)")
        return save(self, step, *args, **kwargs)

    monkeypatch.setattr(checkpointing.TrainCheckpointer, "save", full_at_6)
    with pytest.raises(checkpointing.CheckpointSaveError):
        train.train_and_evaluate(tiny_config(seed=1, num_train_steps=8, checkpoint_every=1, log_every=100), str(wd))
    status = workdir_mod.read_status(str(wd))
    assert status["status"] == "failed" and status["last_checkpoint"] == 5
    assert sorted(os.listdir(wd / "checkpoints")) == ["2", "4", "5"]  # the partial step 6 is not there
    assert workdir_mod.lock_holder(str(wd)) is None  # released on the way out of a failed run too
