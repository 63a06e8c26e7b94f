"""Writing outputs so that a reader never sees them half-written.

Every command that writes results (train's JSON files, checkpoints, evaluate, predict, export, bench, the
synthetic data writer) goes through these helpers: a file is written to a temporary name in the same folder and
renamed over the target (`os.replace` is atomic on one file system); a folder is assembled in a temporary sibling
and renamed into place only when complete, so an interrupted or failed run leaves nothing under the requested
name (and an existing folder it replaces stays intact until the new one is ready).
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from typing import Any


def _read_umask() -> int:
    mask = os.umask(0)  # the only way to read it; set back at once (at import, before any thread starts)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


class OutputExistsError(ValueError):
    """The output folder exists and is not empty, and overwriting was not asked for."""


def write_bytes(path: str | os.PathLike, data: bytes) -> str:
    """Write `data` to `path` atomically (temporary file in the same folder, then rename). Returns the path; an
    OSError (a full disk, ...) names `path`."""
    path = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{os.path.basename(path)}.tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; outputs get the usual permissions
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.filename is None and e.strerror:
            e.filename = path  # a full disk fails in f.write, whose error names no file
        raise
    return path


def write_text(path: str | os.PathLike, text: str) -> str:
    """`write_bytes` of UTF-8 text."""
    return write_bytes(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any, *, indent: int = 2) -> str:
    """Pretty JSON (sorted keys, non-JSON values as their str) written atomically, with a final newline."""
    return write_text(path, json.dumps(obj, indent=indent, sort_keys=True, default=str) + "\n")


def check_output_dir(out_dir: str | os.PathLike, overwrite: bool, option: str = "--overwrite") -> None:
    """Refuse an existing non-empty output folder unless `overwrite` (the error names the path and `option`)."""
    out_dir = os.fspath(out_dir)
    if os.path.exists(out_dir):
        if not os.path.isdir(out_dir):
            raise OutputExistsError(f"output path {out_dir} exists and is not a folder")
        if os.listdir(out_dir) and not overwrite:
            raise OutputExistsError(f"output folder {out_dir} exists and is not empty (use {option})")


@contextlib.contextmanager
def staged_dir(out_dir: str | os.PathLike, *, overwrite: bool = False,
               option: str = "--overwrite") -> Iterator[str]:
    """Yields a new temporary folder beside `out_dir`; when the block ends without an error, it replaces
    `out_dir` (an existing folder is moved aside first and deleted only after the rename), otherwise it is
    deleted. `out_dir` is refused up front when it exists and is not empty, unless `overwrite`. An OSError
    from the block that names a file in the temporary folder names it under `out_dir` instead
    (`output_path_error`): the temporary folder is gone when the error is shown."""
    check_output_dir(out_dir, overwrite, option)
    out_dir = os.path.abspath(os.fspath(out_dir))
    parent = os.path.dirname(out_dir)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(out_dir)}.tmp-", dir=parent)
    try:
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700 folders
        try:
            yield tmp
        except OSError as e:
            output_path_error(e, tmp, out_dir)
            raise
        if os.path.lexists(out_dir):
            old = tempfile.mkdtemp(prefix=f".{os.path.basename(out_dir)}.old-", dir=parent)
            os.rename(out_dir, os.path.join(old, "previous"))
            os.rename(tmp, out_dir)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out_dir)
    finally:
        if os.path.exists(tmp):
            shutil.rmtree(tmp, ignore_errors=True)


def output_path_error(error: OSError, tmp: str, out_dir: str) -> OSError:
    """Renames the file names of `error` (`filename`, `filename2`) that lie in the temporary folder `tmp` to
    the same place in `out_dir`, the folder the user asked for; returns `error`."""
    for attr in ("filename", "filename2"):
        name = getattr(error, attr, None)
        name = os.fspath(name) if isinstance(name, os.PathLike) else name
        if not isinstance(name, str):
            continue  # None, a file descriptor or bytes: nothing to rename
        name = os.path.abspath(name)
        if name == tmp:
            setattr(error, attr, out_dir)
        elif name.startswith(tmp + os.sep):
            setattr(error, attr, os.path.join(out_dir, os.path.relpath(name, tmp)))
    return error
