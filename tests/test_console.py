"""console: XLA's slow-compile banner is kept out of stderr (and logged), everything else passes in order,
partial lines are not held back, and --debug (enabled=False) passes everything."""

from __future__ import annotations

import os
import pty
import subprocess
import sys

import pytest

from bridge_jax import console
from tests.train_helpers import REPO

BANNER = (b"E1202 00:27:29.247311    7061 slow_operation_alarm.cc:73] \n"
          b"********************************\n"
          b"[Compiling module jit_train_step for CPU] Very slow compile? If you want to file a bug, run with envvar "
          b"XLA_FLAGS=--xla_dump_to=DIR and attach the results.\n"
          b"********************************\n")
OTHER_ALARM = (b"E1202 00:27:30.000001    7061 slow_operation_alarm.cc:65] Constant folding an instruction is "
               b"taking > 1s:\n")

# A process that installs the filter, then writes like XLA does (os.write on fd 2) and like Python does.
SCRIPT = r"""
import os, sys, time
from bridge_jax import console
log = sys.argv[1] or None
f = console.install(log, enabled=sys.argv[2] == "1")
print("installed" if f else "not installed", sys.stderr.isatty(), flush=True)
banner = bytes.fromhex(sys.argv[3])
os.write(2, b"ordinary 1\n")
os.write(2, banner[:30])            # the banner arrives in pieces
time.sleep(0.3)
os.write(2, banner[30:] + b"ordinary 2\n")
os.write(2, b"*** not stars\n")
os.write(2, b"partial without newline")
time.sleep(1.0)
sys.stderr.write("python after partial\n")  # the partial line must be out by now
os.write(2, b" (the rest of it)\nlast\n")
"""


def _run(log: str, enabled: bool = True, stderr=subprocess.PIPE):
    return subprocess.run([sys.executable, "-c", SCRIPT, log, "1" if enabled else "0", BANNER.hex()],
                          stdout=subprocess.PIPE, stderr=stderr, timeout=60, env=dict(os.environ, PYTHONPATH=REPO))


def test_banner_goes_to_the_log_and_the_rest_to_stderr_in_order(tmp_path):
    log = tmp_path / "xla.log"
    r = _run(str(log))
    assert r.returncode == 0, r.stderr
    assert r.stdout.decode().split() == ["installed", "False"]
    assert r.stderr.decode() == ("ordinary 1\nordinary 2\n*** not stars\npartial without newline"
                                 "python after partial\n (the rest of it)\nlast\n")
    assert log.read_bytes() == BANNER


def test_disabled_passes_everything(tmp_path):
    log = tmp_path / "xla.log"
    r = _run(str(log), enabled=False)
    assert r.returncode == 0 and r.stdout.decode().split()[0] == "not"
    assert BANNER.decode() in r.stderr.decode() and "ordinary 1\n" in r.stderr.decode()
    assert not log.exists()


def test_python_stderr_stays_a_terminal():
    leader, follower = pty.openpty()
    try:
        r = _run("", stderr=follower)
    finally:
        os.close(follower)
        os.close(leader)
    assert r.returncode == 0 and r.stdout.decode().split() == ["installed", "True"]


@pytest.mark.parametrize("chunk", [1, 7, 1000])
def test_filter_byte_stream_in_any_chunks(chunk):
    dropped = []
    filt = console.BannerFilter(dropped.append)
    data = b"a\n" + BANNER + OTHER_ALARM + b"b\n" + BANNER[:-33] + b"not the end\n" + BANNER + b"tail"
    out = b"".join(filt.feed(data[i:i + chunk]) for i in range(0, len(data), chunk)) + filt.finish()
    # the other alarm and the unfinished banner (its last star line missing) are not the banner: they pass
    assert out == b"a\n" + OTHER_ALARM + b"b\n" + BANNER[:-33] + b"not the end\n" + b"tail"
    assert dropped == [BANNER, BANNER]


def test_only_a_possible_banner_start_waits_for_its_newline():
    filt = console.BannerFilter()
    assert filt.feed(b"loss 0.5") == b"loss 0.5"  # cannot start the banner: out at once
    for held in (b"E1202 00:27", b"E1202 00:27:29.247311    7061 slow_oper",
                 b"E1202 00:27:29.247311    7061 slow_operation_alarm.cc:73] "):
        assert console._may_start_banner(held), held
    assert not console._may_start_banner(b"E1202 00:27:29.247311    7061 compiler.cc:12] ")
    assert not console._may_start_banner(b"Epoch 3")
    assert filt.feed(b"E1202 00:27") == b"" and filt.flush_partial() == b"E1202 00:27"
