"""Writing outputs so that a reader never sees them half-written.

Every command that writes results (train's JSON files, checkpoints, evaluate, predict, export, bench, the
synthetic data writer) goes through these helpers: a file is written to a temporary name in the same folder and
renamed over the target (`os.replace` is atomic on one file system); a folder is assembled in a temporary sibling
and renamed into place only when complete, so an interrupted or failed run leaves nothing under the requested
name (and an existing folder it replaces stays intact until the new one is ready).

Images are read and written here too (`imread`, `imwrite`): OpenCV's own file functions crash the process on a
file name that is not valid UTF-8 (Python hands such names on as surrogate escapes), so the bytes go through
Python's file functions and OpenCV only encodes and decodes them. OpenCV's video reader and writer can only take a
name: `opencv_can_open` tells whether a name is one they can take, `shown_name` prints any name.
"""
from __future__ import annotations

import contextlib
import json
import os
import shutil
import tempfile
from collections.abc import Iterator
from typing import Any

import numpy as np


def _read_umask() -> int:
    mask = os.umask(0)  # the only way to read it; set back at once (at import, before any thread starts)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def _temp_prefix(path: str, kind: str) -> str:
    """`.<name>.<kind>-` for a temporary sibling of `path`, the name cut to its first 64 bytes: the random
    suffix must still fit when `path`'s own name is near the 255-byte limit of a name (an output named after a
    long input name)."""
    head = os.fsencode(os.path.basename(path))[:64]
    return f".{os.fsdecode(head)}.{kind}-"


class OutputExistsError(ValueError):
    """The output folder exists and is not empty, and overwriting was not asked for."""


def write_bytes(path: str | os.PathLike, data: bytes) -> str:
    """Write `data` to `path` atomically (temporary file in the same folder, then rename). Returns the path; an
    OSError (a full disk, ...) names `path`."""
    path = os.path.abspath(os.fspath(path))
    folder = os.path.dirname(path)
    os.makedirs(folder, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=_temp_prefix(path, "tmp"))
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; outputs get the usual permissions
        os.replace(tmp, path)
    except BaseException as e:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.strerror and e.filename in (None, tmp):
            # a full disk fails in f.write, whose error names no file; the rename's error names the temporary file
            raise OSError(e.errno, e.strerror, path) from e
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
    tmp = tempfile.mkdtemp(prefix=_temp_prefix(out_dir, "tmp"), dir=parent)
    try:
        os.chmod(tmp, 0o777 & ~_UMASK)  # mkdtemp makes 0700 folders
        try:
            yield tmp
        except OSError as e:
            output_path_error(e, tmp, out_dir)
            raise
        if os.path.lexists(out_dir):
            old = tempfile.mkdtemp(prefix=_temp_prefix(out_dir, "old"), dir=parent)
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


# ----------------------------------------------------------------------------------------------------------
# Images under any file name
# ----------------------------------------------------------------------------------------------------------

def opencv_can_open(path: str | os.PathLike) -> bool:
    """Whether OpenCV's file functions (cv2.VideoCapture, cv2.VideoWriter, ...) can take `path`: a name that is
    valid UTF-8. Any other name (bytes that are not UTF-8, which Python passes on as surrogate escapes) crashes
    them with a segmentation fault instead of an error."""
    try:
        os.fspath(path).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


def shown_name(path: str | os.PathLike) -> str:
    """`path` as text that prints anywhere: bytes that are not UTF-8 appear as `\\xff` escapes."""
    return os.fsencode(path).decode("utf-8", "backslashreplace")


def imread(path: str | os.PathLike, flags: int | None = None) -> np.ndarray | None:
    """`cv2.imread(path, flags)` for any file name: the decoded image (BGR channel order, as OpenCV's), or None
    when the file is empty or OpenCV cannot decode it; OSError when it cannot be read. `flags` default:
    cv2.IMREAD_COLOR."""
    import cv2  # here, not at the top: most users of this module write no images

    data = np.fromfile(os.fspath(path), np.uint8)
    if data.size == 0:  # imdecode asserts on an empty buffer
        return None
    return cv2.imdecode(data, cv2.IMREAD_COLOR if flags is None else flags)


def imwrite(path: str | os.PathLike, image: np.ndarray) -> str:
    """`cv2.imwrite(path, image)` for any file name, atomically (`write_bytes`): `image` as OpenCV takes it (BGR
    channel order), in the format of the name's extension (.png, .jpg, ...). Returns the path; ValueError naming it
    when OpenCV cannot encode the image in that format."""
    import cv2

    ext = os.path.splitext(os.fspath(path))[1]
    if not ext.isascii() or len(ext) < 2:  # OpenCV picks the encoder by the extension, and crashes on non-UTF-8
        raise ValueError(f"cannot write image {shown_name(path)}: no image format extension (.png, .jpg, ...)")
    try:
        ok, buf = cv2.imencode(ext, np.ascontiguousarray(image))
    except cv2.error:  # an extension OpenCV has no encoder for, or an array it cannot encode
        ok = False
    if not ok:
        raise ValueError(f"cannot write image {shown_name(path)}: OpenCV cannot encode a {np.shape(image)} "
                         f"{np.asarray(image).dtype} array as {ext}")
    return write_bytes(path, buf)
