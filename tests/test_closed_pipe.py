"""Every command stops quietly when the reader of its output goes away (`bridge-zoo | head -1`): no traceback, no
"error:" line, exit code 141 (`cli.EXIT_PIPE_CLOSED`, what a shell reports for git or coreutils then); a broken
pipe that is not the output is still an error."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from bridge_jax import cli, workdir as workdir_mod
from tests.train_helpers import REPO

# (module, arguments): the commands' `python -m` forms (the console scripts call the same `main`)
PRINTING = [
    ("bridge_jax.train", ["--list-config", "demo"]),
    ("bridge_jax.train", ["--status", "{wd}"]),
    ("bridge_jax.zoo", []),
    ("bridge_jax.zoo", ["show", "demo"]),
]
HELP = [(module, ["--help"]) for module in sorted(cli.COMMANDS)]


def _env(buffered: bool = True) -> dict:
    """The subprocess environment; `buffered`: stdout block-buffered as a pipe normally is (PYTHONUNBUFFERED
    unset), so that a short output reaches the pipe only when flushed, at the latest at exit."""
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    if buffered:
        env.pop("PYTHONUNBUFFERED", None)
    else:
        env["PYTHONUNBUFFERED"] = "1"
    return env


def _run_into_a_closed_pipe(argv: list[str], buffered: bool = True) -> subprocess.CompletedProcess:
    """Runs `argv` with stdout a pipe whose reader has gone before the command writes its first byte (the
    reader of `cmd | head -1` after its line: deterministic, where a reader closing after one line races with a
    short output that fits in the pipe's buffer)."""
    read, write = os.pipe()
    os.close(read)
    try:
        return subprocess.run(argv, stdout=write, stderr=subprocess.PIPE, text=True, env=_env(buffered),
                              timeout=120)
    finally:
        os.close(write)


def _ids(value):
    return value if isinstance(value, str) else " ".join(value) or "-"


@pytest.mark.parametrize("buffered", [True, False], ids=["buffered", "unbuffered"])
@pytest.mark.parametrize("module,args", PRINTING, ids=_ids)
def test_a_command_whose_output_pipe_closes_exits_quietly(tmp_path, module, args, buffered):
    """Unbuffered, the first print fails; buffered, the flush at the end (before: "Exception ignored ...
    BrokenPipeError" from the interpreter's own flush at exit, exit code 120)."""
    workdir_mod.write_status(str(tmp_path), "finished", 4, num_steps=4)
    r = _run_into_a_closed_pipe([sys.executable, "-m", module, *(a.format(wd=tmp_path) for a in args)], buffered)
    assert r.returncode == cli.EXIT_PIPE_CLOSED and r.stderr == "", r.stderr[-2000:]


@pytest.mark.parametrize("module,args", HELP, ids=_ids)
def test_every_command_is_wrapped_help_into_a_closed_pipe_is_quiet(module, args):
    """A help text longer than the stdout buffer fails as argparse writes it, which argparse ignores (exit 0); a
    shorter one sits in the buffer and would fail only in the interpreter's flush at exit (exit 120 and
    "Exception ignored ... BrokenPipeError" before): every command's `main` flushes it inside `cli.entry_point`."""
    r = _run_into_a_closed_pipe([sys.executable, "-m", module, *args])
    assert r.returncode in (0, cli.EXIT_PIPE_CLOSED) and r.stderr == "", (r.returncode, r.stderr[-2000:])


def test_a_reader_that_stops_after_one_line(tmp_path):
    """`bridge-train --list-config demo | head -1` itself: whether the command is still writing when the reader
    stops or has written everything by then, nothing reaches stderr and the first line came through."""
    p = subprocess.Popen([sys.executable, "-m", "bridge_jax.train", "--list-config", "demo"], stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True, env=_env(buffered=False))
    first = p.stdout.readline()
    p.stdout.close()
    err = p.stderr.read()
    assert p.wait(60) in (0, cli.EXIT_PIPE_CLOSED) and err == "", err
    assert first.startswith("adam_b1 = ")


def test_a_broken_pipe_that_is_not_the_output_is_still_an_error(capsys):
    def main(argv=None):
        raise BrokenPipeError(32, "Broken pipe")  # e.g. a subprocess's pipe, while stdout is fine

    with pytest.raises(BrokenPipeError):
        cli.entry_point(main)()
    assert cli.report_error(BrokenPipeError(32, "Broken pipe")) == 2
    assert capsys.readouterr().err.strip() == "error: [Errno 32] Broken pipe"
    assert cli.entry_point(lambda argv=None: 3)() == 3 and cli.entry_point(main).__name__ == "main"
