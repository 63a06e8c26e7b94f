"""Run an exported ONNX model on two images without JAX: numpy, OpenCV and onnxruntime only.

    bridge-export --checkpoint demo --format onnx --out demo.onnx      # once, where bridge_jax is installed
    python experiments/onnx_predict.py demo.onnx frame_t.png frame_t1.png --out flow.png [--npy flow.npy]

The two images are read (any format OpenCV reads; grey and 16-bit work too), resized to the model's working size
(its input is `pairs (B, H, W, 6)`) with the antialiased bilinear filter `bridge-predict` uses, run through
onnxruntime, and the map `px0` (working pixels) is brought back to the images' own size as `bridge-predict` does
(bilinear with aligned corners, u scaled by w / W and v by h / H). `--out` gets the flow as a Middlebury
colour-wheel picture (hue = direction, saturation = speed relative to the fastest pixel), `--npy` the
`(h, w, 2)` float32 flow in pixels of the input. For a stereo model (`--task stereo` at export) the disparity is
-u of that map. Prints one JSON line: the files written, the model's working size, seconds per pair.

Errors (a file that cannot be read, images of different sizes, a model that is not a bridge_jax export) are one
`error: ...` line and exit 2; outputs are written atomically (nothing half-written is ever left under their name).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time

import cv2
import numpy as np
import onnxruntime as ort


def read_image(path: str, option: str) -> np.ndarray:
    """An image file -> float32 RGB (h, w, 3) in [0, 1]."""
    try:
        data = np.fromfile(path, np.uint8)
    except OSError as e:
        raise ValueError(f"{option} {path}: {e.strerror or e}") from None
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED) if data.size else None
    if img is None:
        raise ValueError(f"{option} {path}: not an image OpenCV can read")
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[-1] == 4:
        img = cv2.cvtColor(img, cv2.COLOR_BGRA2BGR)
    return (img[..., ::-1].astype(np.float32) / np.float32(scale)).copy()  # BGR -> RGB


def antialias_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of PIL-style bilinear resizing (triangle filter widened when shrinking)."""
    scale = n_in / n_out
    support = max(scale, 1.0)
    centres = (np.arange(n_out) + 0.5) * scale
    w = np.maximum(0.0, 1.0 - np.abs(np.arange(n_in)[None, :] + 0.5 - centres[:, None]) / support)
    return (w / w.sum(axis=1, keepdims=True)).astype(np.float32)


def align_corners_weights(n_in: int, n_out: int) -> np.ndarray:
    """(n_out, n_in) weights of bilinear resizing with aligned corners (the end pixels of both grids coincide)."""
    pos = np.zeros(n_out) if n_out == 1 or n_in == 1 else np.arange(n_out) * ((n_in - 1) / (n_out - 1))
    i0 = np.clip(np.floor(pos).astype(int), 0, n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    w = np.zeros((n_out, n_in))
    np.add.at(w, (np.arange(n_out), i0), 1 - (pos - i0))
    np.add.at(w, (np.arange(n_out), i1), pos - i0)
    return w.astype(np.float32)


def separable(x: np.ndarray, wy: np.ndarray, wx: np.ndarray) -> np.ndarray:
    """(h, w, C) -> (H, W, C) by row weights wy (H, h) and column weights wx (W, w), summing only the non-zero taps
    (a dense product would cost H h w C)."""
    def taps(weights):
        count = max(1, int((weights != 0).sum(axis=1).max()))
        idx = np.argsort(weights == 0, axis=1, kind="stable")[:, :count]
        return idx, np.take_along_axis(weights, idx, axis=1)

    iy, ty = taps(wy)
    ix, tx = taps(wx)
    rows = sum(x[iy[:, k]] * ty[:, k, None, None] for k in range(iy.shape[1]))
    return sum(rows[:, ix[:, k]] * tx[:, k, None] for k in range(ix.shape[1])).astype(np.float32)


def resize(image: np.ndarray, height: int, width: int) -> np.ndarray:
    """(h, w, C) -> (height, width, C), antialiased bilinear (as bridge-predict resizes its inputs)."""
    h, w = image.shape[:2]
    if (h, w) == (height, width):
        return image
    return separable(image, antialias_weights(h, height), antialias_weights(w, width))


def to_input_resolution(px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Working-size map (H, W, 2) in working pixels -> (height, width, 2) in pixels of the input: bilinear with
    aligned corners, u *= width / W, v *= height / H (as bridge-predict brings its maps back)."""
    H, W = px.shape[:2]
    if (H, W) == (height, width):
        return px.astype(np.float32)
    out = separable(px.astype(np.float32), align_corners_weights(H, height), align_corners_weights(W, width))
    return out * np.array([width / W, height / H], np.float32)


def flow_picture(flow: np.ndarray) -> np.ndarray:
    """(h, w, 2) flow -> (h, w, 3) uint8 BGR, the Middlebury colour wheel (saturation = speed / fastest)."""
    ramps = ((15, 0, 1, +1), (6, 1, 0, -1), (4, 1, 2, +1), (11, 2, 1, -1), (13, 2, 0, +1), (6, 0, 2, -1))
    wheel = []
    for n, keep, change, sign in ramps:  # RY, YG, GC, CB, BM, MR (channel indices in RGB)
        col = np.zeros((n, 3))
        col[:, keep] = 255
        ramp = np.floor(255.0 * np.arange(n) / n)
        col[:, change] = ramp if sign > 0 else 255 - ramp
        wheel.append(col)
    wheel = np.concatenate(wheel) / 255.0
    flow = np.where(np.isfinite(flow), flow, 0.0).astype(np.float64)
    radius = np.sqrt((flow ** 2).sum(-1))
    top = max(float(radius.max()), 1e-9)
    u, v, rad = flow[..., 0] / top, flow[..., 1] / top, radius / top
    fk = (np.arctan2(-v, -u) / np.pi + 1.0) / 2.0 * (len(wheel) - 1)
    k0 = np.floor(fk).astype(np.int64)
    f = (fk - k0)[..., None]
    col = (1.0 - f) * wheel[k0 % len(wheel)] + f * wheel[(k0 + 1) % len(wheel)]
    col = 1.0 - rad[..., None] * (1.0 - col)
    return np.floor(255.0 * np.clip(col, 0.0, 1.0)).astype(np.uint8)[..., ::-1]


def write_atomically(path: str, data: bytes) -> None:
    folder = os.path.dirname(os.path.abspath(path))
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=f".{os.path.basename(path)[:64]}.tmp-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.chmod(tmp, 0o644)
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def load_model(path: str, threads: int) -> tuple[ort.InferenceSession, tuple[int, int, int]]:
    """An onnxruntime session and the model's (B, H, W)."""
    if not os.path.isfile(path):
        raise ValueError(f"model {path}: no such file")
    options = ort.SessionOptions()
    options.log_severity_level = 3  # the converter's shape notes are not errors
    if threads:
        options.intra_op_num_threads = threads
    try:
        sess = ort.InferenceSession(path, options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime raises its own exception types
        raise ValueError(f"model {path}: onnxruntime cannot load it ({str(e).strip().splitlines()[0]})") from None
    inputs = sess.get_inputs()
    shape = inputs[0].shape if len(inputs) == 1 else None
    if not shape or len(shape) != 4 or shape[-1] != 6 or not all(isinstance(d, int) for d in shape):
        raise ValueError(f"model {path}: expected one input (B, H, W, 6) (a bridge-export --format onnx model), "
                         f"got {[(i.name, i.shape) for i in inputs]}")
    return sess, tuple(shape[:3])


def predict(sess: ort.InferenceSession, size: tuple[int, int, int], image_a: np.ndarray,
            image_b: np.ndarray) -> np.ndarray:
    """Flow (h, w, 2) of a pair of float RGB images at their own size."""
    batch, height, width = size
    pair = np.concatenate([resize(image_a, height, width), resize(image_b, height, width)], -1)
    pairs = np.repeat(pair[None], batch, axis=0)  # a model exported with --batch B takes B pairs
    px = sess.run(None, {sess.get_inputs()[0].name: pairs})[0][0]
    return to_input_resolution(px, *image_a.shape[:2])


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("model", help="an ONNX model written by bridge-export --format onnx")
    ap.add_argument("image_a", help="the first image (frame t, or the left image)")
    ap.add_argument("image_b", help="the second image (frame t+1, or the right image)")
    ap.add_argument("--out", default="flow.png", help="the flow picture to write (PNG, JPEG, ...)")
    ap.add_argument("--npy", default=None, help="also write the flow (h, w, 2) float32 pixels as a .npy file")
    ap.add_argument("--threads", type=int, default=0, help="onnxruntime's intra-op threads (0: its default)")
    args = ap.parse_args(argv)
    try:
        if args.threads < 0:
            raise ValueError(f"--threads must be >= 0, got {args.threads}")
        ext = os.path.splitext(args.out)[1].lower() or ".png"
        if not cv2.haveImageWriter("x" + ext):
            raise ValueError(f"--out {args.out}: OpenCV cannot write {ext} pictures (try .png)")
        if args.npy is not None and not args.npy.endswith(".npy"):
            raise ValueError(f"--npy {args.npy}: the name must end in .npy")
        image_a = read_image(args.image_a, "image_a")
        image_b = read_image(args.image_b, "image_b")
        if image_a.shape != image_b.shape:
            raise ValueError(f"image_b {args.image_b}: {image_b.shape[0]}x{image_b.shape[1]}, but image_a is "
                             f"{image_a.shape[0]}x{image_a.shape[1]} (height x width): the pair must be the same size")
        sess, size = load_model(args.model, args.threads)
        start = time.perf_counter()
        flow = predict(sess, size, image_a, image_b)
        seconds = time.perf_counter() - start
        ok, png = cv2.imencode(ext, flow_picture(flow))
        if not ok:
            raise ValueError(f"--out {args.out}: OpenCV could not encode the picture")
        write_atomically(args.out, png.tobytes())
        if args.npy is not None:
            import io
            buf = io.BytesIO()
            np.save(buf, flow)
            write_atomically(args.npy, buf.getvalue())
    except (ValueError, OSError) as e:
        text = f"{e.filename}: {e.strerror}" if isinstance(e, OSError) and e.filename else str(e)
        print(f"error: {text.strip().splitlines()[0]}", file=sys.stderr)
        return 2
    print(json.dumps({"out": args.out, "npy": args.npy, "working_size": list(size[1:]), "input_size":
                      list(image_a.shape[:2]), "seconds": round(seconds, 3)}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
