"""Keeps XLA's "Very slow compile?" banner out of the console.

During a long compile XLA's C++ logging writes to file descriptor 2, in the middle of the progress bar:

    E1202 00:27:29.247311    7061 slow_operation_alarm.cc:73]
    ********************************
    [Compiling module jit_train_step for CPU] Very slow compile? If you want to file a bug, run with envvar ...
    ********************************

It reads like a crash, and it is not one. `install` puts a filter on fd 2: Python's `sys.stderr` moves to a
duplicate of the original descriptor (tqdm, print and logging write straight to the terminal, `isatty()`
unchanged), and fd 2 becomes a pipe read by a small helper process (this file run as a script) that forwards
everything except that banner to the original stderr, and appends the banner to a log file when one is given
(training: `<workdir>/xla.log`). A helper process rather than a thread: if XLA aborts the process, its last
words (a failed check) are in the pipe, and only a reader that outlives the process can still print them.

`--debug` (or BRIDGE_JAX_DEBUG=1) installs nothing: everything reaches the console as it was written. Only
POSIX systems are filtered. The filter is undone at exit (fd 2 restored, the pipe drained).
"""

from __future__ import annotations

import atexit
import io
import os
import re
import select
import signal
import subprocess
import sys

# The banner, line by line: the alarm line has no message of its own (other alarms, "Constant folding an
# instruction is taking > 1s", carry theirs on it and are left alone); then stars, the message, stars.
_ALARM = re.compile(rb"[IWEF]\d{4} [\d:.]+\s+\d+ slow_operation_alarm\.cc:\d+\]\s*$")
_STARS = re.compile(rb"\*{8,}\s*$")
_SLOW = re.compile(rb".*Very slow compile\?")
_BANNER = (_ALARM, _STARS, _SLOW, _STARS)
# What the start of an alarm line looks like before its newline has arrived: severity, date, time, thread id,
# then the file name so far.
_ALARM_START = re.compile(rb"[IWEF]\d{0,4}(?: [\d:.]*(?:\s+\d*(?: (\S*)\s*)?)?)?$")
_ALARM_FILE = re.compile(rb"slow_operation_alarm\.cc:\d+\]?$")
# A partial line that could start the banner waits this long at most for its newline. absl writes a whole
# message at once, so the rest comes within microseconds; anything else is not held up for long.
_PARTIAL_WAIT_S = 2.0


def _may_start_banner(partial: bytes) -> bool:
    """Whether bytes without their newline yet could be the start of the banner's alarm line."""
    m = _ALARM_START.match(partial)
    if not m:
        return False
    name = m.group(1)
    return name is None or b"slow_operation_alarm.cc:".startswith(name) or bool(_ALARM_FILE.match(name))


class BannerFilter:
    """Bytes in, bytes out, the banner removed. `feed` returns what can be forwarded now; lines that may be
    the banner are held until they are known to be it (handed to `on_banner`, not forwarded) or not (forwarded
    in order). A partial line is forwarded at once unless it could be the start of the banner (`forward` lets
    such a line go when its newline has not come within `_PARTIAL_WAIT_S`)."""

    def __init__(self, on_banner=None):
        self.on_banner = on_banner
        self.held: list[bytes] = []  # complete lines of a banner in progress
        self.partial = b""

    def feed(self, data: bytes) -> bytes:
        *lines, self.partial = (self.partial + data).split(b"\n")
        out = [self._line(line + b"\n") for line in lines]
        if self.partial and not self.held and not _may_start_banner(self.partial):
            out.append(self.partial)
            self.partial = b""
        return b"".join(out)

    def _line(self, line: bytes) -> bytes:
        if _BANNER[len(self.held)].match(line.rstrip(b"\r\n")):
            self.held.append(line)
            if len(self.held) == len(_BANNER):
                banner, self.held = b"".join(self.held), []
                if self.on_banner is not None:
                    self.on_banner(banner)
            return b""
        if not self.held:
            return line
        released, self.held = b"".join(self.held), []  # not the banner after all: the held lines go out first
        return released + self._line(line)

    def flush_partial(self) -> bytes:
        """A partial line that waited long enough goes out (unless a banner is in progress)."""
        if self.held:
            return b""
        out, self.partial = self.partial, b""
        return out

    def finish(self) -> bytes:
        """Everything still held (an unfinished banner included): the stream has ended."""
        out = b"".join(self.held) + self.partial
        self.held, self.partial = [], b""
        return out


def _append(path: str, data: bytes) -> None:
    try:
        with open(path, "ab") as f:
            f.write(data)
    except OSError:  # no log folder (yet): the banner is noise either way, never a reason to fail
        pass


def _write_all(fd: int, data: bytes) -> None:
    try:
        while data:
            data = data[os.write(fd, data):]
    except OSError:  # the terminal is gone: keep reading, so that the writers never block on a full pipe
        pass


def forward(src: int, dst: int, log_path: str | None) -> None:
    """Copies `src` to `dst` until end of file, without the banner (appended to `log_path` if given)."""
    filt = BannerFilter((lambda banner: _append(log_path, banner)) if log_path else None)
    while True:
        if filt.partial and not filt.held:  # do not keep a partial line waiting for a newline that may not come
            ready, _, _ = select.select([src], [], [], _PARTIAL_WAIT_S)
            if not ready:
                _write_all(dst, filt.flush_partial())
                continue
        data = os.read(src, 65536)
        if not data:
            _write_all(dst, filt.finish())
            return
        _write_all(dst, filt.feed(data))


class StderrFilter:
    """The installed filter (see the module docstring); `restore` undoes it (also run at exit)."""

    def __init__(self, saved_fd: int, helper: subprocess.Popen, old_stderr, new_stderr):
        self.saved_fd, self.helper, self.old_stderr, self.new_stderr = saved_fd, helper, old_stderr, new_stderr
        self.restored = False

    def restore(self, timeout: float = 5.0) -> None:
        """Points fd 2 and `sys.stderr` back at the original stderr and waits (at most `timeout` s) until the
        helper has forwarded what is still in the pipe. The helper ends when the last writer closes the pipe;
        a child process still holding it keeps it running, forwarding, after this process has gone."""
        if self.restored:
            return
        self.restored = True
        for stream in (self.new_stderr, self.old_stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os.dup2(self.saved_fd, 2)  # closes this process's write end of the pipe
        if sys.stderr is self.new_stderr:
            sys.stderr = self.old_stderr
        try:
            self.helper.wait(timeout)
        except subprocess.TimeoutExpired:
            pass
        # `saved_fd` stays open: a tqdm bar or a logging handler may still hold `new_stderr`


_installed: StderrFilter | None = None


def install(log_path: str | None = None, *, enabled: bool = True) -> StderrFilter | None:
    """Filters the banner out of fd 2 for the rest of the process (appending it to `log_path` if given);
    returns the filter, or None when nothing was installed: `enabled` False (--debug), not a POSIX system,
    no usable fd 2, installed already, the helper process could not start, or `sys.stderr` is not the
    process's own (a test harness or a notebook has redirected it: its owner decides where output goes)."""
    global _installed
    if (not enabled or os.name != "posix" or _installed is not None or not sys.executable
            or sys.stderr is not sys.__stderr__):
        return None
    try:
        os.fstat(2)
    except OSError:
        return None
    old = sys.stderr
    try:
        old.flush()
    except (AttributeError, OSError, ValueError):
        pass
    saved = os.dup(2)  # not inheritable: child processes get the pipe, like this process's C++ code
    r, w = os.pipe()
    try:
        helper = subprocess.Popen([sys.executable, "-I", "-S", os.path.abspath(__file__), log_path or ""],
                                  stdin=r, stdout=saved, stderr=saved, close_fds=True)
    except OSError:
        for fd in (saved, r, w):
            os.close(fd)
        return None
    os.close(r)
    os.dup2(w, 2)
    os.close(w)
    new = io.TextIOWrapper(io.FileIO(saved, "w", closefd=False), encoding=getattr(old, "encoding", None) or "utf-8",
                           errors="backslashreplace", line_buffering=True, write_through=True)
    sys.stderr = new
    _installed = StderrFilter(saved, helper, old, new)
    atexit.register(_installed.restore)
    return _installed


def _helper_main(argv: list[str]) -> None:
    # Ctrl-C and a scheduler's SIGTERM reach the whole process group: the helper must keep forwarding while the
    # trainer saves its checkpoint and says so; it ends when the pipe closes.
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, signal.SIG_IGN)
    forward(0, 1, argv[1] if len(argv) > 1 and argv[1] else None)


if __name__ == "__main__":
    _helper_main(sys.argv)
