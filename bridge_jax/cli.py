"""What the command-line entry points share: the parser with the full module docstring as its help epilog,
option parsing helpers, the one-line error report (tracebacks only with --debug or BRIDGE_JAX_DEBUG=1), and
`entry_point`, which every command's `main` is wrapped in.

A closed output pipe (`bridge-zoo | head -1`, `bridge-train --list-config | head`): the command stops quietly,
nothing on stderr, exit code 141 (`EXIT_PIPE_CLOSED`), as git and the coreutils do (they die of SIGPIPE, which a
shell reports as 128 + 13 = 141; `set -o pipefail` sees it, a plain pipeline does not).
"""

from __future__ import annotations

import argparse
import functools
import os
import select
import sys
import textwrap
import warnings

from bridge_jax import testtime

DEBUG_ENV = "BRIDGE_JAX_DEBUG"


class HelpFormatter(argparse.RawDescriptionHelpFormatter, argparse.ArgumentDefaultsHelpFormatter):
    """Keeps the docstring's layout (examples, output trees) and appends "(default: ...)" to every option that
    has a default worth showing."""

    def _get_help_string(self, action):
        text = action.help or ""
        # on/off flags (nargs=0) say what they do; "(default: True)" on a --no-x flag would only confuse
        if ("%(default)" in text or action.default in (None, False, argparse.SUPPRESS) or not action.option_strings
                or action.nargs == 0):
            return text
        return f"{text} (default: %(default)s)"


def _one_line_warning(message, category, filename, lineno, line=None):  # noqa: ARG001
    if category.__module__.startswith("bridge_jax"):
        return f"warning: {message}\n"
    return _default_formatwarning(message, category, filename, lineno, line)


_default_formatwarning = warnings.formatwarning


# The console commands of pyproject.toml's [project.scripts], by module: usage lines name the command.
COMMANDS = {"bridge_jax.train": "bridge-train", "bridge_jax.evaluate": "bridge-evaluate",
            "bridge_jax.predict": "bridge-predict", "bridge_jax.bench": "bridge-bench",
            "bridge_jax.convert": "bridge-convert", "bridge_jax.export": "bridge-export", "bridge_jax.demo": "bridge-demo",
            "bridge_jax.data.synthetic": "bridge-synthetic", "bridge_jax.data.videos": "bridge-frames",
            "bridge_jax.zoo": "bridge-zoo"}


def make_parser(prog: str, doc: str, **kwargs) -> argparse.ArgumentParser:
    """An ArgumentParser for `python -m <prog>`: the first paragraph of `doc` (the module docstring) as its
    description, the rest of it (examples, output layout) as the epilog of `--help`, defaults shown. Also makes
    bridge_jax's own warnings (a broken checkpoint skipped, ...) print as one `warning: ...` line."""
    warnings.formatwarning = _one_line_warning
    doc = textwrap.dedent(doc or "").strip("\n")
    first, _, rest = doc.partition("\n\n")
    return argparse.ArgumentParser(prog=COMMANDS.get(prog, f"python -m {prog}"), description=first.strip(),
                                   epilog=textwrap.dedent(rest).strip("\n") or None, formatter_class=HelpFormatter,
                                   **kwargs)


def add_debug_flag(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--debug", action="store_true",
                        help=f"show the full traceback of an error (also: environment variable {DEBUG_ENV}=1)")


def debug_enabled(args=None) -> bool:
    return bool(getattr(args, "debug", False)) or os.environ.get(DEBUG_ENV, "") not in ("", "0")


def parse_size(text: str) -> tuple[int, int]:
    """``"256x512"`` → ``(256, 512)`` = (H, W); an argparse type."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW like 256x512, got {text!r}") from None
    if h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"expected positive HxW, got {text!r}")
    return h, w


WORKING_SIZE_HELP = ("network input size: HxW (multiples of the model's input multiple: 64 for resnet_md and "
                     "pwcnet, 8 for pwc_lite), 'native' (each input at its own resolution, rounded down to the "
                     "model's multiple, at most 1024x768 pixels) or 'trained' (the size the checkpoint was trained "
                     "at, else 256x512)")


def parse_working_size(text: str):
    """``--working-size``: ``"native"`` / ``"trained"`` (returned as such) or ``"HxW"`` → (H, W); an argparse
    type."""
    if text.strip().lower() in ("native", "trained"):
        return text.strip().lower()
    try:
        return parse_size(text)
    except argparse.ArgumentTypeError:
        raise argparse.ArgumentTypeError(f"expected HxW like 256x512, 'native' or 'trained', got {text!r}") from None


def add_test_time_options(parser: argparse.ArgumentParser) -> None:
    """``--refine K``, ``--symmetry MODE``, ``--polish MODE``: the fields of a `testtime.TestTime`; each None
    when not given (the model card's choice). `given_test_time` reads them back."""
    parser.add_argument("--refine", type=int, default=None, metavar="K",
                        help="test-time refinement: run the network K more times per pair, each on the second image "
                             "warped by the maps so far, and add what it still finds (K+1 times the cost; 0 = "
                             f"off, at most {testtime.MAX_REFINE}); default: what a shipped model's card "
                             "recommends, else 0")
    parser.add_argument("--symmetry", default=None, choices=testtime.SYMMETRY_MODES,
                        help="test-time symmetry averaging: average the network's maps over the pair as given and "
                             "mirrored left-right, upside-down and both ('flips', 4x the cost), plus those four "
                             "transposed for flow pairs ('dihedral', 8x); default: what a shipped model's card "
                             "recommends, else none")
    parser.add_argument("--polish", default=None, choices=testtime.POLISH_MODES,
                        help="test-time polish of the final maps: 'photometric' lets each pixel take a "
                             "neighbour's value where that matches the images clearly better (sharper motion "
                             "boundaries), then a variational fit (sub-pixel; textureless regions and the image "
                             "border take their neighbours' motion), twice; 'fill' predicts the reverse pair too and "
                             "corrects the pixels where the two maps disagree by more than "
                             f"{testtime.FILL_MAX_DIFFERENCE_STEREO:g} px (a flow: "
                             f"{testtime.FILL_MAX_DIFFERENCE:g} px plus a part relative to its length), or whose match "
                             "the other image does not see: "
                             "a disparity by its row's background (unless that is much nearer), a flow by its "
                             "look-alike neighbours' (twice the cost); 'photometric+fill' both, in that order; "
                             "'none' = the network's maps as they are; default: what a shipped model's "
                             "card recommends, else none")


def given_test_time(args: argparse.Namespace) -> dict:
    """The test-time settings the command line `args` gave (`add_test_time_options`): {field: value or None},
    for `inference.load_predictor(test_time=..., options=testtime.OPTIONS)`."""
    return {field: getattr(args, field, None) for field in testtime.OPTIONS}


def add_task_option(parser: argparse.ArgumentParser, help: str, default: str = "flow") -> None:
    """``--task flow|stereo``: what a pair is; ``--pair-kind`` is its old spelling (still read, with a note)."""
    parser.add_argument("--task", default=default, choices=("flow", "stereo"), help=help)
    parser.add_argument("--pair-kind", dest="task", choices=("flow", "stereo"), action=_OldSpelling,
                        help=argparse.SUPPRESS)


class _OldSpelling(argparse.Action):
    """Stores an option given by an old name and prints one note naming the new one."""

    def __call__(self, parser, namespace, values, option_string=None):
        new = "--" + self.dest.replace("_", "-")
        print(f"note: {option_string} is now {new}", file=sys.stderr)
        setattr(namespace, self.dest, values)


EXIT_PIPE_CLOSED = 141  # 128 + SIGPIPE: how a shell reports git or a coreutils command whose reader went away


def _closed_outputs() -> list[int]:
    """The file descriptors of stdout and stderr that are pipes whose reader has gone (poll reports an error on
    the write end): a broken pipe of the output, as opposed to some other pipe of the program breaking."""
    if not hasattr(select, "poll"):  # no poll (Windows): take it to be stdout
        return [1]
    closed = []
    for stream in (sys.stdout, sys.stderr):
        try:
            fd = stream.fileno()
        except (AttributeError, OSError, ValueError):  # replaced by a test's capture, or closed
            continue
        poller = select.poll()
        poller.register(fd, select.POLLOUT)
        if any(events & select.POLLERR for _, events in poller.poll(0)):
            closed.append(fd)
    return closed


def _stop_writing(fds: list[int]) -> int:
    """Points the closed outputs `fds` at the null device (what Python still buffers for them would fail again
    when flushed at exit, with an "Exception ignored" message) and returns `EXIT_PIPE_CLOSED`."""
    for fd in fds:
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, fd)
            os.close(null)
        except OSError:
            pass
    return EXIT_PIPE_CLOSED


def entry_point(main):
    """Wraps a command's `main(argv=None) -> exit code` (what pyproject's [project.scripts] and `python -m`
    call): when the reader of its output goes away, the command ends quietly with `EXIT_PIPE_CLOSED` instead of
    a BrokenPipeError traceback, also when the break shows only as the output is flushed (small outputs sit in
    Python's buffer until then) or in argparse's --help (a SystemExit)."""

    @functools.wraps(main)
    def wrapped(*args, **kwargs):
        try:
            try:
                code = main(*args, **kwargs)
            except SystemExit:
                sys.stdout.flush()  # here, where a closed pipe can still be caught, not at interpreter exit
                raise
            sys.stdout.flush()
            return code
        except BrokenPipeError:
            closed = _closed_outputs()
            if not closed:
                raise
            return _stop_writing(closed)

    return wrapped


def report_error(error: BaseException, code: int = 2, debug: bool | None = None) -> int:
    """Prints `error: <first line of the message>` to stderr and returns the exit code (user mistakes are one
    line, never a traceback; the traceback too with `debug` or BRIDGE_JAX_DEBUG=1). A closed output pipe (the
    commands catch OSError, BrokenPipeError included) is no error: nothing is printed, `EXIT_PIPE_CLOSED`."""
    closed = _closed_outputs() if isinstance(error, BrokenPipeError) else []
    if closed:
        return _stop_writing(closed)
    if debug or (debug is None and debug_enabled()):
        import traceback
        traceback.print_exception(error, file=sys.stderr)
    text = str(error).strip()
    if isinstance(error, OSError) and error.filename and error.strerror:
        text = f"{error.filename}: {error.strerror}"
    print(f"error: {text.splitlines()[0] if text else type(error).__name__}", file=sys.stderr)
    return code
