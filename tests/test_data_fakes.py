"""Helpers for the data tests (no tests here): tiny fake KITTI raw folders, an independent PNG reader/writer
(pure zlib + struct, so that it does not share OpenCV's channel conventions) and a numpy bilinear sampler."""
import os
import struct
import zlib

import cv2
import numpy as np

from bridge_jax.data import kitti

# Calibration numbers in KITTI's format (values of 2011_09_26, rounded).
CAM_TO_CAM = """calib_time: 09-Jan-2012 13:57:47
corner_dist: 9.950000e-02
R_rect_00: 9.999239e-01 9.837760e-03 -7.445048e-03 -9.869795e-03 9.999421e-01 -4.278459e-03 7.402527e-03 4.351614e-03 9.999631e-01
P_rect_02: 7.215377e+02 0.000000e+00 6.095593e+02 4.485728e+01 0.000000e+00 7.215377e+02 1.728540e+02 2.163791e-01 0.000000e+00 0.000000e+00 1.000000e+00 2.745884e-03
P_rect_03: 7.215377e+02 0.000000e+00 6.095593e+02 -3.395242e+02 0.000000e+00 7.215377e+02 1.728540e+02 2.199936e+00 0.000000e+00 0.000000e+00 1.000000e+00 2.729905e-03
"""
VELO_TO_CAM = """calib_time: 15-Mar-2012 11:37:16
R: 7.533745e-03 -9.999714e-01 -6.166020e-04 1.480249e-02 7.280733e-04 -9.998902e-01 9.998621e-01 7.523790e-03 1.480755e-02
T: -4.069766e-03 -7.631618e-02 -2.717806e-01
"""


def make_fake_raw(root, drives, height=16, width=32, ext=".png", seed=0):
    """Writes a tiny KITTI raw folder: drives = {"2011_09_26_drive_0001": num_frames, ...}."""
    rng = np.random.default_rng(seed)
    for name, n in drives.items():
        date = name[:10]
        ddir = os.path.join(root, date, name + "_sync")
        with open(os.path.join(_mk(os.path.join(root, date)), "calib_cam_to_cam.txt"), "w") as fh:
            fh.write(CAM_TO_CAM)
        with open(os.path.join(root, date, "calib_velo_to_cam.txt"), "w") as fh:
            fh.write(VELO_TO_CAM)
        for cam in ("image_02", "image_03"):
            d = _mk(os.path.join(ddir, cam, "data"))
            for k in range(n):
                img = rng.integers(0, 256, (height, width, 3), dtype=np.uint8)
                kitti.write_image(os.path.join(d, f"{k:010d}{ext}"), img)
    return root


def _mk(d):
    os.makedirs(d, exist_ok=True)
    return d


def write_stereo_sequence(root, stems, size=(8, 12), ext=".png", sizes=None, seed=0):
    """Writes ROOT/left/<stem><ext> and ROOT/right/<stem><ext> for every stem with cv2.imwrite: random uint8
    colour images of `size` (h, w); `sizes` = {"right/0003.png": (h, w), ...} overrides single files.
    Returns {relative path: absolute path}."""
    rng = np.random.default_rng(seed)
    sizes = dict(sizes or {})
    out = {}
    for side in ("left", "right"):
        d = _mk(os.path.join(root, side))
        for stem in stems:
            rel = f"{side}/{stem}{ext}"
            h, w = sizes.get(rel, size)
            path = os.path.join(d, f"{stem}{ext}")
            assert cv2.imwrite(path, rng.integers(0, 256, (h, w, 3), dtype=np.uint8))
            out[rel] = path
    return out


def truncate_file(path, keep=0.5):
    data = open(path, "rb").read()
    with open(path, "wb") as fh:
        fh.write(data[: int(len(data) * keep)])


# ---------------------------------------------------------------- independent PNG codec (8/16-bit, gray/RGB)

def png_bytes(array, bit_depth):
    """Minimal PNG encoder: array (H, W) gray or (H, W, 3) RGB (channel order as given = R, G, B)."""
    a = np.asarray(array)
    h, w = a.shape[:2]
    color_type = 2 if a.ndim == 3 else 0
    dtype = ">u2" if bit_depth == 16 else "u1"
    raw = b"".join(b"\x00" + a[y].astype(dtype).tobytes() for y in range(h))

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data) & 0xFFFFFFFF)

    ihdr = struct.pack(">IIBBBBB", w, h, bit_depth, color_type, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b"")


def png_read(data):
    """Minimal PNG decoder (no interlace; all 5 filters) → array (H, W) or (H, W, C) in file channel order."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    pos, idat = 8, b""
    while pos < len(data):
        (n,) = struct.unpack(">I", data[pos:pos + 4])
        tag, body = data[pos + 4:pos + 8], data[pos + 8:pos + 8 + n]
        if tag == b"IHDR":
            w, h, depth, ctype, _, _, interlace = struct.unpack(">IIBBBBB", body)
            assert interlace == 0
        elif tag == b"IDAT":
            idat += body
        pos += 12 + n
    chans = {0: 1, 2: 3, 4: 2, 6: 4}[ctype]
    bpp = chans * depth // 8
    stride = w * bpp
    raw = zlib.decompress(idat)
    out = np.zeros((h, stride), np.int64)
    prev = np.zeros(stride, np.int64)
    for y in range(h):
        ftype = raw[y * (stride + 1)]
        line = np.frombuffer(raw[y * (stride + 1) + 1:(y + 1) * (stride + 1)], np.uint8).astype(np.int64)
        cur = np.zeros(stride, np.int64)
        for i in range(stride):
            a = cur[i - bpp] if i >= bpp else 0
            b = prev[i]
            c = prev[i - bpp] if i >= bpp else 0
            if ftype == 0:
                pred = 0
            elif ftype == 1:
                pred = a
            elif ftype == 2:
                pred = b
            elif ftype == 3:
                pred = (a + b) // 2
            else:
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if (pa <= pb and pa <= pc) else (b if pb <= pc else c)
            cur[i] = (line[i] + pred) & 0xFF
        out[y] = cur
        prev = cur
    if depth == 16:
        vals = out[:, 0::2] * 256 + out[:, 1::2]
    else:
        vals = out
    vals = vals.reshape(h, w, chans)
    return vals[..., 0] if chans == 1 else vals


# ---------------------------------------------------------------- numpy bilinear sampler (border clamp)

def bilinear(img, x, y):
    """img (H, W, C) sampled at float coords x, y (H', W'), border clamp → (H', W', C) float64."""
    h, w = img.shape[:2]
    x = np.clip(x, 0, w - 1)
    y = np.clip(y, 0, h - 1)
    x0 = np.clip(np.floor(x).astype(int), 0, w - 2)
    y0 = np.clip(np.floor(y).astype(int), 0, h - 2)
    fx, fy = (x - x0)[..., None], (y - y0)[..., None]
    im = img.astype(np.float64)
    return ((1 - fx) * (1 - fy) * im[y0, x0] + fx * (1 - fy) * im[y0, x0 + 1]
            + (1 - fx) * fy * im[y0 + 1, x0] + fx * fy * im[y0 + 1, x0 + 1])
