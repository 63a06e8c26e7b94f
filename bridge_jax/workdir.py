"""A training workdir: its layout, the metrics log, the status file and what a finished run left there.

    <workdir>/
      config.json, model.json         the run's config and the model description (params-only loaders)
      checkpoints/<step>/{state,data} orbax: train state + grain iterator state (`checkpointing`)
      metrics.jsonl                   one JSON object per log/eval event (one run's history, also after resumes)
      tensorboard/                    tensorboardX event files (scalars, images)
      images/                         the same pictures as PNG files
      status.json                     what the run is doing or how it ended (`RunStatus`, `read_status`)
      .lock                           held by the trainer working in it (`WorkdirLock`): one trainer per workdir

The trainer writes it (`MetricsLogger`, `RunStatus`); `zoo.build_shipped` and a re-run of a finished run read
it back (`last_validation`); `bridge-train --status WORKDIR` prints `describe_status`. Nothing here knows how
training works.

status.json holds "status": "running" | "finished" | "interrupted" (a signal; checkpoint saved) | "aborted" (a
second signal: exited at once, nothing saved) | "failed" (an error, its first line in "reason"), the "step"
reached, "num_steps", "steps_per_s", "last_checkpoint", "started", "pid", "heartbeat" (a time),
"stale_after_s", and once this process's first step is done "first_step_s" (seconds from the start of the
process to the end of that step: the time to a first step, compile included) and "compile_s" (of those, the
seconds spent tracing and compiling, or loading from the compilation cache). A running trainer rewrites it (atomically) at every log interval and, from a background
thread, at least every `HEARTBEAT_S` seconds (so a long compilation or validation does not look dead). The
rule for readers: a "running" status whose heartbeat is older than "stale_after_s" (= `STALE_BEATS`
heartbeat periods) belongs to a process that is gone (killed, or its machine lost).

One trainer at a time: a trainer holds an exclusive OS lock (`fcntl.flock`) on `<workdir>/.lock` for its whole
run (`WorkdirLock`), with its PID written in the file; a second trainer on the same workdir finds it taken and
refuses, naming that PID (`lock_holder`). The kernel drops the lock when its process ends, however it ends (a
kill -9 included), so a lock never outlives its trainer and never has to be cleaned up by hand. Readers
(`bridge-train --status`, predict, evaluate) take no lock.
"""

from __future__ import annotations

import json
import math
import os
import socket
import threading
import time
from typing import Optional

import numpy as np
from tensorboardX import SummaryWriter

from bridge_jax import files, visualize

try:
    import fcntl
except ImportError:  # Windows: no flock; workdirs go unlocked there
    fcntl = None

METRICS_JSONL = "metrics.jsonl"
STATUS_JSON = "status.json"
TENSORBOARD_DIR = "tensorboard"
IMAGES_DIR = "images"
LOCK_FILE = ".lock"


def scalar(v) -> float:
    """A 0-d array (numpy or jax) or number as a Python float."""
    return float(np.asarray(v))


class MetricsLogger:
    """metrics.jsonl + TensorBoard (tensorboardX) on process 0; no-ops elsewhere.

    `resume_step`: the step the run (re)starts from, 0 for a start from scratch; None appends to what is there.
    Records of later steps (written by the previous run after its last checkpoint, and redone now) are dropped
    from metrics.jsonl and TensorBoard's events are purged past it, so both read as one run. A start from
    scratch drops every record of the run, those of step 0 too (a killed attempt that never finished a
    checkpoint logged steps that this start logs again, its step-0 validation included).

    `stage`: {"name", "offset"} of a recipe stage (`bridge_jax.recipe`) logging into the recipe's workdir: every
    record carries "stage" (its name) and "stage_step" (the step the caller passes, inside the stage), and its
    "step" and TensorBoard step are offset by the steps of the stages before it. A stage always truncates to
    its own restart (`resume_step`, 0 for a fresh start): records a killed attempt of it wrote are dropped (at
    the stage's first step, which is the previous stage's last, only its own)."""

    def __init__(self, workdir: str, enabled: bool, resume_step: Optional[int] = None,
                 stage: Optional[dict] = None):
        self.enabled = enabled
        self.image_dir = os.path.join(workdir, IMAGES_DIR)
        self.tb = None
        self.jsonl = None
        self.offset = int(stage["offset"]) if stage else 0
        self.tags = {"stage": stage["name"]} if stage else {}
        if stage:
            resume_step = resume_step or 0
        if enabled:
            path = os.path.join(workdir, METRICS_JSONL)
            purge_step = None
            if resume_step is not None:
                restart = int(resume_step) == 0
                truncate_metrics(path, self.offset + int(resume_step), restart=restart,
                                 stage=stage["name"] if stage else None)
                # TensorBoard purges by step alone: a stage's first step keeps the previous stage's events
                purge_step = self.offset + int(resume_step) + (0 if restart and not stage else 1)
            self.tb = SummaryWriter(os.path.join(workdir, TENSORBOARD_DIR), purge_step=purge_step)
            self.jsonl = open(path, "a")

    def _head(self, step: int, kind: str) -> dict:
        """The fields every record starts with: its step (across a recipe), kind, time, and a stage's tags."""
        head = {"step": self.offset + int(step), "kind": kind, "time": time.time(), **self.tags}
        if self.tags:
            head["stage_step"] = int(step)
        return head

    def scalars(self, step: int, values: dict, kind: str = "train") -> None:
        if not self.enabled:
            return
        clean = {k: scalar(v) for k, v in values.items()}
        rec = {**self._head(step, kind), **clean}
        self.jsonl.write(json.dumps(rec, allow_nan=True) + "\n")
        self.jsonl.flush()
        for k, v in clean.items():
            if math.isfinite(v):
                self.tb.add_scalar(k if "/" in k and kind == "train" else f"{kind}/{k}", v, self.offset + int(step))

    def record(self, step: int, kind: str, payload: dict) -> None:
        """A non-scalar event (e.g. the data-skip report) in metrics.jsonl only."""
        if self.enabled:
            self.jsonl.write(json.dumps({**self._head(step, kind), **payload}) + "\n")
            self.jsonl.flush()

    def stage_start(self, index: int, count: int, **payload) -> None:
        """Marks the start of a recipe stage: a "stage_start" record (with `payload`), TensorBoard text at the
        boundary, and the scalar `recipe/stage_index` (1-based) there (the trainer logs it again with every train
        record, so the curve steps up at each boundary)."""
        if not self.enabled or not self.tags:
            return
        self.record(0, "stage_start", {"stage_index": index + 1, "num_stages": count, **payload})
        self.tb.add_text("recipe/stage", f"stage {index + 1}/{count}: {self.tags['stage']} starts", self.offset)
        self.tb.add_scalar("recipe/stage_index", index + 1, self.offset)

    def image(self, step: int, tag: str, rgb: np.ndarray) -> None:
        """An RGB uint8 (H, W, 3) picture: TensorBoard (tensorboardX's add_image) and images/<tag>_<step>.png
        (the step across a recipe)."""
        if not self.enabled:
            return
        rgb = np.ascontiguousarray(np.asarray(rgb, np.uint8))
        step = self.offset + int(step)
        self.tb.add_image(tag, rgb, step, dataformats="HWC")
        os.makedirs(self.image_dir, exist_ok=True)
        visualize.write_image(os.path.join(self.image_dir, f"{tag.replace('/', '_')}_{step:07d}.png"), rgb)

    def close(self) -> None:
        if self.enabled:
            self.tb.close()
            self.jsonl.close()


def truncate_metrics(path: str, resume_step: int, *, restart: bool = False, stage: Optional[str] = None) -> int:
    """Drops the records of steps after `resume_step` from the metrics.jsonl at `path` (rewritten atomically);
    returns how many were dropped. A torn last line (a crash mid-write) is dropped too.

    `restart`: the run starts over at `resume_step` (from scratch, no checkpoint), so the records of that step
    are written again and go too: all of them, or only those of recipe stage `stage` when given (the step a
    stage starts at is the previous stage's last, whose records stay)."""
    if not os.path.exists(path):
        return 0
    kept, dropped = [], 0
    with open(path) as f:
        for line in f:
            try:
                rec = json.loads(line)
                step = int(rec.get("step", 0))
                keep = step < resume_step or (step == resume_step and not (
                    restart and (stage is None or rec.get("stage") == stage)))
            except (json.JSONDecodeError, TypeError, ValueError, AttributeError):
                keep = False
            if keep and line.endswith("\n"):
                kept.append(line)
            else:
                dropped += 1
    if dropped:
        files.write_text(path, "".join(kept))
    return dropped


def last_validation(workdir: str, stage: Optional[str] = None) -> dict:
    """The last "val" record of a workdir's metrics.jsonl (a finished run re-run does not validate again); of
    recipe stage `stage` only, when given (its "stage" and "stage_step" tags left out)."""
    last: dict = {}
    path = os.path.join(workdir, METRICS_JSONL)
    if os.path.exists(path):
        with open(path) as f:
            for line in f:
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:
                    continue
                if rec.get("kind") == "val" and (stage is None or rec.get("stage") == stage):
                    last = {k: v for k, v in rec.items() if k not in ("kind", "time", "step", "stage", "stage_step")}
    return last


HEARTBEAT_S = float(os.environ.get("BRIDGE_JAX_HEARTBEAT_S", "30"))
"""Seconds between two heartbeats of a running trainer at most (environment variable BRIDGE_JAX_HEARTBEAT_S)."""
STALE_BEATS = 3
"""A "running" status without a heartbeat for this many heartbeat periods is stale: the process is gone."""


def write_status(workdir: str, status: str, step: int, **extra) -> None:
    """status.json: {"status", "step", "time", "heartbeat", **extra}, written atomically."""
    now = time.time()
    files.write_json(os.path.join(workdir, STATUS_JSON), {"status": status, "step": int(step), "time": now,
                                                         "heartbeat": now, **extra})


class RunStatus:
    """The status.json of a running trainer: `update` at every log interval, a heartbeat thread in between, and
    `end` on every way out (finished, interrupted, aborted, failed). A no-op when not `enabled` (processes > 0).
    Writes are serialised; one that fails (a full disk) is retried by the next one."""

    def __init__(self, workdir: str, enabled: bool, *, heartbeat_s: float | None = None, **fields):
        self.path = os.path.join(workdir, STATUS_JSON)
        self.enabled = enabled
        self.heartbeat_s = float(HEARTBEAT_S if heartbeat_s is None else heartbeat_s)
        self.fields = {"status": "running", "started": time.time(), "pid": os.getpid(),
                       "heartbeat_every_s": self.heartbeat_s, "stale_after_s": STALE_BEATS * self.heartbeat_s,
                       **fields}
        self._lock = threading.RLock()  # RLock: `end` may run in a signal handler interrupting a write
        self._stop = threading.Event()
        self._thread = None
        if enabled:
            self._write()
            self._thread = threading.Thread(target=self._beat, name="bridge_jax-heartbeat", daemon=True)
            self._thread.start()

    def _write(self) -> None:
        with self._lock:
            now = time.time()
            self.fields.update(time=now, heartbeat=now)
            try:
                files.write_json(self.path, self.fields)
            except OSError:  # a full disk: the next write tries again; the run's own error says what happened
                pass

    def _beat(self) -> None:
        while not self._stop.wait(self.heartbeat_s):
            self._write()

    def progress(self, step: int) -> None:
        """The step reached, written with the next heartbeat or update."""
        self.fields["step"] = int(step)

    def update(self, **fields) -> None:
        """New values (step, steps_per_s, last_checkpoint, ...) written now."""
        if self.enabled:
            self.fields.update(fields)
            self._write()

    def end(self, status: str, **fields) -> None:
        """The final status (heartbeats stop); safe to call from a signal handler; the first call wins."""
        if not self.enabled or self._stop.is_set():
            return
        self._stop.set()
        self.fields.update(fields, status=status, ended=time.time())
        self._write()


def read_status(workdir: str) -> dict:
    """The status.json of `workdir` (ValueError naming the file when missing or unreadable)."""
    path = os.path.join(workdir, STATUS_JSON)
    try:
        with open(path) as f:
            status = json.load(f)
    except FileNotFoundError:
        raise ValueError(f"{path}: no such file (not a training workdir, or its run has not started)") from None
    except (OSError, json.JSONDecodeError) as e:
        raise ValueError(f"{path}: unreadable ({e})") from None
    if not isinstance(status, dict) or "status" not in status:
        raise ValueError(f"{path}: not a status file (expected a JSON object with 'status')")
    return status


def stage_seconds_before(workdir: str, name: str) -> float:
    """The seconds earlier runs of recipe stage `name` took before they were stopped (killed, interrupted,
    crashed), from the recipe's status.json (`read_status`) when it names that stage: that run's own
    `stage_seconds_before` plus its time from its start to its last heartbeat (or its end). 0 when the status
    names another stage or there is none readable. A kill -9 loses at most one heartbeat interval; the start-up
    before the status was first written is not counted."""
    try:
        status = read_status(workdir)
        if status.get("stage") != name:
            return 0.0
        own = max(0.0, float(status.get("ended", status.get("heartbeat"))) - float(status["started"]))
        return float(status.get("stage_seconds_before", 0.0)) + own
    except (ValueError, KeyError, TypeError):
        return 0.0


def is_stale(status: dict, now: float | None = None) -> bool:
    """Whether a "running" status has missed its heartbeats (see the module docstring): its process is gone."""
    if status.get("status") != "running":
        return False
    now = time.time() if now is None else now
    beat = status.get("heartbeat", status.get("time", 0.0))
    return now - float(beat) > float(status.get("stale_after_s", STALE_BEATS * HEARTBEAT_S))


def describe_status(workdir: str, now: float | None = None) -> tuple[str, bool]:
    """(one line for `bridge-train --status`, stale)."""
    st = read_status(workdir)
    now = time.time() if now is None else now
    stale = is_stale(st, now)
    step = f"step {st.get('step', '?')}" + (f"/{st['num_steps']}" if st.get("num_steps") else "")
    parts = [f"{workdir}: {st['status']}", step]
    if st.get("stage"):  # a recipe (bridge_jax.recipe): which stage the status and the step are of
        parts[0] = f"{workdir}: stage {st.get('stage_index', '?')}/{st.get('num_stages', '?')} {st['stage']} {st['status']}"
        if st["status"] == "finished" and st.get("stage_index") != st.get("num_stages"):
            parts[0] += " (the recipe goes on with the next stage)"
    if st.get("steps_per_s"):
        parts.append(f"{float(st['steps_per_s']):.2f} steps/s")
    if st.get("last_checkpoint"):
        parts.append(f"last checkpoint {st['last_checkpoint']}")
    beat = st.get("heartbeat", st.get("time"))
    if beat is not None:
        parts.append(f"heartbeat {max(0.0, now - float(beat)):.0f} s ago")
    if st.get("reason"):
        parts.append(str(st["reason"]).splitlines()[0])
    line = ", ".join(parts)
    if stale:
        line += (f"; STALE: no heartbeat for over {float(st.get('stale_after_s', 0)):.0f} s, the process is gone "
                 "(killed or its machine lost); run the same command to resume")
    return line, stale


# ----------------------------------------------------------------------------------------------------------
# One trainer per workdir
# ----------------------------------------------------------------------------------------------------------

class WorkdirInUse(ValueError):
    """Another process holds the workdir's lock; `holder` says which ("PID 1234", "PID 1234 on host")."""

    def __init__(self, workdir: str, holder: str):
        super().__init__(f"{workdir} is in use by another trainer ({holder})")
        self.workdir, self.holder = workdir, holder


def _describe_holder(text: str) -> str:
    """Who wrote a lock file's text (its PID, then its host name, one a line): "PID 1234", with " on <host>"
    when that is another machine."""
    pid, _, host = text.strip().partition("\n")
    if not pid.strip().isdigit():  # locked an instant ago: the holder has not written its PID yet
        return "PID not written yet"
    host = host.strip()
    return f"PID {pid.strip()}" + (f" on {host}" if host and host != socket.gethostname() else "")


def lock_holder(workdir: str) -> Optional[str]:
    """Who holds `workdir`'s lock ("PID 1234", "PID 1234 on host"), or None when nobody does. Creates nothing: a
    workdir without a lock file has no holder. The probe takes a shared lock for an instant; a trainer locking
    at that very moment retries (`WorkdirLock`)."""
    if fcntl is None:
        return None
    try:
        fd = os.open(os.path.join(workdir, LOCK_FILE), os.O_RDONLY)
    except (FileNotFoundError, NotADirectoryError):
        return None
    try:
        try:
            fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)
        except BlockingIOError:
            return _describe_holder(os.pread(fd, 256, 0).decode("utf-8", "replace"))
        fcntl.flock(fd, fcntl.LOCK_UN)
        return None
    finally:
        os.close(fd)


class WorkdirLock:
    """An exclusive lock on a workdir for this process: `fcntl.flock` on `<workdir>/.lock`, taken when
    constructed (the workdir and the lock file are created if missing), this process's PID and host name written
    into the file, released by `release` (or leaving a `with` block) or by the kernel when the process ends.
    Raises `WorkdirInUse` naming the holder when another process has it. `enabled=False` (processes > 0 of a
    multi-host run: process 0 locks for all of them) holds nothing.

    The file stays when released (emptied): removing it would let a process that opened the old file and one
    that creates a new one both "hold" the lock."""

    RETRY_S = 0.5  # how long a taken lock is retried: a `lock_holder` probe holds it for an instant

    def __init__(self, workdir: str, enabled: bool = True):
        self.path = os.path.join(workdir, LOCK_FILE)
        self.fd: Optional[int] = None
        if not enabled or fcntl is None:
            return
        os.makedirs(workdir, exist_ok=True)
        # no O_TRUNC: the file may hold the PID of a holder that this open must not erase
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        deadline = time.monotonic() + self.RETRY_S
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                break
            except BlockingIOError:
                if time.monotonic() < deadline:
                    time.sleep(0.02)
                    continue
                holder = _describe_holder(os.pread(fd, 256, 0).decode("utf-8", "replace"))
                os.close(fd)
                raise WorkdirInUse(workdir, holder) from None
            except BaseException:
                os.close(fd)
                raise
        self.fd = fd
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n{socket.gethostname()}\n".encode(), 0)

    def release(self) -> None:
        """Empties the lock file and unlocks it; a no-op when nothing is held (idempotent)."""
        if self.fd is None:
            return
        fd, self.fd = self.fd, None
        try:
            os.ftruncate(fd, 0)  # no stale PID for a person reading the file
        except OSError:
            pass
        finally:
            os.close(fd)  # closing the last descriptor of the open file drops the flock

    def __enter__(self) -> "WorkdirLock":
        return self

    def __exit__(self, *exc) -> bool:
        self.release()
        return False
