"""Where the upstream parity fixture is: `../shared/peer/fixture/` beside the repository (it ships there with
`reference.npz` and `manifest.json`), or the folder in the environment variable BRIDGE_FIXTURE_DIR.

`weights.pth` (234 MB, for the converter parity) does not ship; the upstream harness writes it (see
experiments/README.md). A missing `reference.npz` fails the parity tests when CI is set (they must run there) and
skips them elsewhere; a missing `weights.pth` skips the converter parity test.
"""

from __future__ import annotations

import os
import pathlib

import pytest

REPO = pathlib.Path(__file__).resolve().parent.parent
DEFAULT_DIR = REPO.parent / "shared" / "peer" / "fixture"


def fixture_dir() -> pathlib.Path:
    return pathlib.Path(os.environ.get("BRIDGE_FIXTURE_DIR") or DEFAULT_DIR)


def fixture_file(name: str, *, required_in_ci: bool = True) -> pathlib.Path:
    """The fixture file `name`; fails under CI (if `required_in_ci`) or skips when it is missing."""
    path = fixture_dir() / name
    if not path.is_file():
        msg = f"upstream fixture file {path} not found (set BRIDGE_FIXTURE_DIR to the folder that holds it)"
        if required_in_ci and os.environ.get("CI"):
            pytest.fail(msg + "; CI must run the parity tests")
        pytest.skip(msg)
    return path
