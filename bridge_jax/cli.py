"""What the command-line entry points share: option parsing helpers and the one-line error report."""

from __future__ import annotations

import argparse
import sys


def parse_size(text: str) -> tuple[int, int]:
    """``"256x512"`` → ``(256, 512)`` = (H, W); an argparse type."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW like 256x512, got {text!r}") from None
    if h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"expected positive HxW, got {text!r}")
    return h, w


def report_error(error: BaseException, code: int = 2) -> int:
    """Prints `error: <first line of the message>` to stderr and returns the exit code (user mistakes are one
    line, never a traceback)."""
    text = str(error).strip()
    print(f"error: {text.splitlines()[0] if text else type(error).__name__}", file=sys.stderr)
    return code
