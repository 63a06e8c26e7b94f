"""Reading and writing the common raw formats of flow and disparity: Middlebury/Sintel ``.flo`` and ``.pfm``.

    from bridge_jax import flowio
    flowio.write_flo("flow.flo", flow)            # flow (H, W, 2) float32 pixels (u right, v down)
    flow = flowio.read_flo("flow.flo")            # -> (H, W, 2) float32
    flowio.write_pfm("disp.pfm", disp)            # disp (H, W) -> "Pf"; (H, W, 3) -> "PF"
    disp = flowio.read_pfm("disp.pfm")            # -> (H, W) or (H, W, 3) float32, top row first
    flow, valid = flowio.read_flow("x.flo")       # by extension: .flo, .pfm, .png (KITTI), .npy
    disp, valid = flowio.read_disparity("x.pfm")  # by extension: .pfm, .png (KITTI), .npy

Byte layouts (both little-endian as written here):

* ``.flo`` (Middlebury, Sintel): float32 202021.25 (the bytes ``b"PIEH"``), int32 width, int32 height, then
  ``height * width * 2`` float32, row-major from the top row, ``u, v`` interleaved per pixel. Middlebury marks
  unknown flow with components above 1e9 (:data:`FLO_UNKNOWN`).
* ``.pfm`` (Scene Flow datasets, Middlebury 2014): the text lines ``"PF"`` (3 channels) or ``"Pf"``
  (1 channel), ``"<width> <height>"`` and the scale, each ended by ``\\n``, then float32 rows from the BOTTOM
  row up. A negative scale means little-endian data, a positive one big-endian; its absolute value is a
  scale factor the format carries along (1.0 here). Readers return top-row-first arrays.

Writers are atomic (`bridge_jax.files.write_bytes`); readers raise :class:`FlowFormatError` (a ValueError)
naming the file and what was expected for a wrong magic/header, truncated or trailing data, or absurd sizes.
"""

from __future__ import annotations

import os
import struct

import numpy as np

from bridge_jax import files

FLO_MAGIC = b"PIEH"
"""The first 4 bytes of a .flo file: float32 202021.25 in little-endian order."""
FLO_UNKNOWN = 1e9
"""Middlebury's convention: a flow component with absolute value above this is unknown."""
MAX_SIDE = 99999
"""Largest width or height accepted by the readers (Middlebury's own sanity bound); larger means garbage."""


class FlowFormatError(ValueError):
    """A .flo / .pfm file (or an array to write) is not what the format expects; the message names the file."""


def _read(path: str | os.PathLike) -> bytes:
    with open(path, "rb") as f:   # a missing file is an OSError naming the path, which the CLIs report as is
        return f.read()


def _check_side(path, what: str, value: int) -> None:
    if not 1 <= value <= MAX_SIDE:
        raise FlowFormatError(f"{path}: {what} {value} is not in 1..{MAX_SIDE} (not a valid file, or corrupt)")


def _check_data(path, fmt: str, got: int, width: int, height: int, channels: int) -> None:
    want = width * height * channels * 4
    if got != want:
        state = "truncated" if got < want else "has trailing bytes"
        raise FlowFormatError(f"{path}: {fmt} data {state}: expected {want} bytes for {width}x{height}x{channels} "
                              f"float32 (width x height x channels), got {got}")


# --------------------------------------------------------------------------------------------------------------
# .flo


def encode_flo(flow: np.ndarray) -> bytes:
    """The bytes of a .flo file of ``flow (H, W, 2)`` (pixels; any float or int dtype, stored as float32)."""
    flow = np.asarray(flow)
    if flow.ndim != 3 or flow.shape[-1] != 2 or flow.shape[0] < 1 or flow.shape[1] < 1:
        raise FlowFormatError(f".flo holds a (H, W, 2) flow, got an array of shape {flow.shape}")
    if not (np.issubdtype(flow.dtype, np.floating) or np.issubdtype(flow.dtype, np.integer)):
        raise FlowFormatError(f".flo holds numbers, got dtype {flow.dtype}")
    h, w = flow.shape[:2]
    # "<f4" fixes the byte order whatever the machine; row-major (H, W, 2) is exactly u, v interleaved per pixel
    return FLO_MAGIC + struct.pack("<ii", w, h) + np.ascontiguousarray(flow, dtype="<f4").tobytes()


def decode_flo(data: bytes, path: str = "<bytes>") -> np.ndarray:
    """.flo bytes → ``(H, W, 2)`` float32 flow in pixels; FlowFormatError naming `path` if malformed."""
    if len(data) < 12:
        raise FlowFormatError(f"{path}: not a .flo file: {len(data)} bytes, shorter than the 12-byte header")
    if data[:4] != FLO_MAGIC:
        raise FlowFormatError(f"{path}: not a .flo file: expected the magic bytes {FLO_MAGIC!r} (float32 "
                              f"202021.25), got {data[:4]!r}")
    w, h = struct.unpack("<ii", data[4:12])
    _check_side(path, ".flo width", w)
    _check_side(path, ".flo height", h)
    _check_data(path, ".flo", len(data) - 12, w, h, 2)
    return np.frombuffer(data, dtype="<f4", offset=12).reshape(h, w, 2).astype(np.float32)


def read_flo(path: str | os.PathLike) -> np.ndarray:
    """Reads a Middlebury/Sintel .flo file → ``(H, W, 2)`` float32 flow (u, v) in pixels."""
    return decode_flo(_read(path), os.fspath(path))


def write_flo(path: str | os.PathLike, flow: np.ndarray) -> str:
    """Writes ``flow (H, W, 2)`` (pixels) as a .flo file, atomically. Returns the path."""
    try:
        data = encode_flo(flow)
    except FlowFormatError as e:
        raise FlowFormatError(f"{os.fspath(path)}: {e}") from None
    return files.write_bytes(path, data)


# --------------------------------------------------------------------------------------------------------------
# .pfm


def encode_pfm(array: np.ndarray, scale: float = 1.0) -> bytes:
    """The bytes of a little-endian .pfm of ``(H, W)`` / ``(H, W, 1)`` ("Pf") or ``(H, W, 3)`` ("PF") float data
    (stored as float32, bottom row first; the header scale is ``-abs(scale)``, negative = little-endian)."""
    a = np.asarray(array)
    if a.ndim == 3 and a.shape[-1] == 1:
        a = a[..., 0]
    if not ((a.ndim == 2 or (a.ndim == 3 and a.shape[-1] == 3)) and a.shape[0] >= 1 and a.shape[1] >= 1):
        raise FlowFormatError(f".pfm holds an (H, W) or (H, W, 3) array, got shape {np.shape(array)}")
    if not (np.issubdtype(a.dtype, np.floating) or np.issubdtype(a.dtype, np.integer)):
        raise FlowFormatError(f".pfm holds numbers, got dtype {a.dtype}")
    scale = float(scale)
    if not (np.isfinite(scale) and scale != 0):
        raise FlowFormatError(f".pfm scale must be finite and non-zero, got {scale}")
    h, w = a.shape[:2]
    header = f"{'PF' if a.ndim == 3 else 'Pf'}\n{w} {h}\n{-abs(scale)!r}\n".encode("ascii")
    return header + np.ascontiguousarray(a[::-1], dtype="<f4").tobytes()


def _header_line(data: bytes, start: int, path, what: str) -> tuple[str, int]:
    end = data.find(b"\n", start, start + 256)   # header lines are short: a missing newline means garbage
    if end < 0:
        raise FlowFormatError(f"{path}: not a .pfm file: no end of line after the {what}")
    # non-ASCII bytes become U+FFFD, so that the caller's "expected ..., got ..." message reports them
    return data[start:end].decode("ascii", errors="replace").strip(), end + 1


def decode_pfm(data: bytes, path: str = "<bytes>", *, with_scale: bool = False):
    """.pfm bytes → ``(H, W)`` ("Pf") or ``(H, W, 3)`` ("PF") float32, top row first (the file stores the bottom
    row first); with `with_scale`, ``(array, abs(scale))``. FlowFormatError naming `path` if malformed."""
    kind, pos = _header_line(data, 0, path, "type line")
    if kind not in ("PF", "Pf"):
        raise FlowFormatError(f"{path}: not a .pfm file: expected the type line 'PF' (3 channels) or 'Pf' "
                              f"(1 channel), got {kind[:16]!r}")
    dims, pos = _header_line(data, pos, path, "size line")
    try:
        w, h = (int(v) for v in dims.split())
    except ValueError:
        raise FlowFormatError(f"{path}: .pfm size line must be '<width> <height>', got {dims[:32]!r}") from None
    _check_side(path, ".pfm width", w)
    _check_side(path, ".pfm height", h)
    scale_text, pos = _header_line(data, pos, path, "scale line")
    try:
        scale = float(scale_text)
    except ValueError:
        scale = float("nan")
    if not np.isfinite(scale) or scale == 0:
        raise FlowFormatError(f"{path}: .pfm scale line must be a non-zero number (negative = little-endian), "
                              f"got {scale_text[:32]!r}")
    channels = 3 if kind == "PF" else 1
    _check_data(path, ".pfm", len(data) - pos, w, h, channels)
    dtype = "<f4" if scale < 0 else ">f4"
    a = np.frombuffer(data, dtype=dtype, offset=pos).reshape((h, w, channels) if channels == 3 else (h, w))
    a = np.array(a[::-1], dtype=np.float32, order="C")   # bottom-to-top on disk → top row first; a writable copy
    return (a, abs(scale)) if with_scale else a


def read_pfm(path: str | os.PathLike, *, with_scale: bool = False):
    """Reads a .pfm file → ``(H, W)`` or ``(H, W, 3)`` float32, top row first (``(array, scale)`` with
    `with_scale`; the scale is the header's absolute value, which the data is NOT multiplied by)."""
    return decode_pfm(_read(path), os.fspath(path), with_scale=with_scale)


def write_pfm(path: str | os.PathLike, array: np.ndarray, scale: float = 1.0) -> str:
    """Writes ``(H, W)`` or ``(H, W, 3)`` values (e.g. disparity in pixels, depth in metres) as a little-endian
    .pfm (header scale ``-abs(scale)``, bottom row first), atomically. Returns the path."""
    try:
        data = encode_pfm(array, scale)
    except FlowFormatError as e:
        raise FlowFormatError(f"{os.fspath(path)}: {e}") from None
    return files.write_bytes(path, data)


# --------------------------------------------------------------------------------------------------------------
# By extension


def _ext(path) -> str:
    return os.path.splitext(os.fspath(path))[1].lower()


def read_flow(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Reads flow by extension → (flow ``(H, W, 2)`` float32 pixels, valid ``(H, W)`` bool).

    ``.flo``: valid = finite and both components ≤ 1e9 in magnitude (Middlebury's unknown marker); ``.pfm``
    (Scene Flow datasets store flow as 3 channels, the third 0): the first two channels, valid = finite;
    ``.png``: a KITTI 16-bit flow PNG with its valid bit; ``.npy``: an (H, W, 2) array, valid = finite.
    Invalid pixels are set to 0.
    """
    ext = _ext(path)
    if ext == ".flo":
        flow = read_flo(path)
        valid = np.all(np.isfinite(flow) & (np.abs(flow) <= FLO_UNKNOWN), axis=-1)
    elif ext == ".pfm":
        a = read_pfm(path)
        if a.ndim != 3:
            raise FlowFormatError(f"{os.fspath(path)}: a flow .pfm must have 3 channels ('PF'), this one has 1")
        flow = a[..., :2].copy()
        valid = np.all(np.isfinite(flow), axis=-1)
    elif ext == ".png":
        from bridge_jax.data import kitti  # imported here: OpenCV is only needed for PNGs
        return kitti.read_flow_png(os.fspath(path))
    elif ext == ".npy":
        flow = _load_npy(path, 3)
        valid = np.all(np.isfinite(flow), axis=-1)
    else:
        raise FlowFormatError(f"{os.fspath(path)}: unknown flow file type {ext or '(none)'!r}; expected .flo, "
                              ".pfm, .png (KITTI) or .npy")
    flow[~valid] = 0.0
    return flow, valid


def read_disparity(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Reads disparity by extension → (disparity ``(H, W)`` float32 pixels, valid ``(H, W)`` bool).

    ``.pfm``: one channel, valid = finite (Middlebury 2014 marks unknown pixels with inf); ``.png``: a KITTI
    16-bit disparity PNG (0 = invalid); ``.npy``: an (H, W) array, valid = finite. Invalid pixels are set to 0.
    """
    ext = _ext(path)
    if ext == ".pfm":
        disp = read_pfm(path)
        if disp.ndim != 2:
            raise FlowFormatError(f"{os.fspath(path)}: a disparity .pfm must have 1 channel ('Pf'), this one has 3")
    elif ext == ".png":
        from bridge_jax.data import kitti
        return kitti.read_disp_png(os.fspath(path))
    elif ext == ".npy":
        disp = _load_npy(path, 2)
    else:
        raise FlowFormatError(f"{os.fspath(path)}: unknown disparity file type {ext or '(none)'!r}; expected "
                              ".pfm, .png (KITTI) or .npy")
    valid = np.isfinite(disp)
    disp[~valid] = 0.0
    return disp, valid


def _load_npy(path, ndim: int) -> np.ndarray:
    try:
        a = np.load(path, allow_pickle=False)
    except ValueError as e:
        raise FlowFormatError(f"{os.fspath(path)}: not a readable .npy array ({e})") from None
    want = "(H, W, 2)" if ndim == 3 else "(H, W)"
    if a.ndim != ndim or (ndim == 3 and a.shape[-1] != 2) or not np.issubdtype(a.dtype, np.number):
        raise FlowFormatError(f"{os.fspath(path)}: expected a numeric {want} array, got shape {a.shape} "
                              f"dtype {a.dtype}")
    return np.array(a, np.float32)


__all__ = ["read_flo", "write_flo", "encode_flo", "decode_flo", "read_pfm", "write_pfm", "encode_pfm",
           "decode_pfm", "read_flow", "read_disparity", "FlowFormatError", "FLO_MAGIC", "FLO_UNKNOWN"]
