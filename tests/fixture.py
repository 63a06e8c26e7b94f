"""Where the upstream parity fixtures are.

* `tests/data/parity/reference.npz` ships with the repository: the upstream harness's fixture at a small size
  (how it was made: `tests/data/parity/README.md`). Every clone runs the parity tests on it; when it is missing
  they fail, never skip.
* The harness's full fixture, an extra check where it exists: the folder in the environment variable
  BRIDGE_FIXTURE_DIR, else `../shared/peer/fixture/` beside the repository (`reference.npz`, and `weights.pth`,
  234 MB, for the converter parity, which skips without it).
"""

from __future__ import annotations

import os
import pathlib

import pytest

REPO = pathlib.Path(__file__).resolve().parent.parent
IN_REPO_DIR = REPO / "tests" / "data" / "parity"
DEFAULT_DIR = REPO.parent / "shared" / "peer" / "fixture"


def fixture_dir() -> pathlib.Path:
    """The folder of the full (external) fixture."""
    return pathlib.Path(os.environ.get("BRIDGE_FIXTURE_DIR") or DEFAULT_DIR)


def reference_files() -> dict[str, pathlib.Path]:
    """{"in_repo": the shipped reference.npz, "full": the external one (only where it exists)}: what the parity
    tests run on. The shipped one is always listed, so that a missing file fails its tests."""
    files = {"in_repo": IN_REPO_DIR / "reference.npz"}
    full = fixture_dir() / "reference.npz"
    if full.is_file():
        files["full"] = full
    return files


def reference_file(which: str) -> pathlib.Path:
    """The reference.npz `which` names (`reference_files`); fails the test when it is missing."""
    path = reference_files().get(which, fixture_dir() / "reference.npz")
    if not path.is_file():
        pytest.fail(f"upstream parity fixture {path} not found (the repository ships tests/data/parity/; "
                    f"restore it with git)")
    return path


def fixture_file(name: str, *, required_in_ci: bool = True) -> pathlib.Path:
    """The external fixture's file `name`; fails under CI (if `required_in_ci`) or skips when it is missing."""
    path = fixture_dir() / name
    if not path.is_file():
        msg = f"upstream fixture file {path} not found (set BRIDGE_FIXTURE_DIR to the folder that holds it)"
        if required_in_ci and os.environ.get("CI"):
            pytest.fail(msg + "; CI must run the parity tests")
        pytest.skip(msg)
    return path
