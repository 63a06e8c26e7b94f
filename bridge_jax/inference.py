"""Run a trained network on your own images.

    from bridge_jax.inference import load_predictor
    pred = load_predictor("checkpoints/ver_a")                      # params-only dir, workdir or step dir
    flow = pred.predict_pair(frame_t, frame_t1)                     # (h, w, 2) pixels, uint8 or float images
    out = pred.predict_cycle(left_t, right_t, left_t1, right_t1)   # disp_t, disp_t1 (h, w), flow (h, w, 2)

As in the paper's evaluation (REFERENCE.md §1d): images of any size are resized to the working size
(default H=256, W=512; antialiased bilinear, like PIL), the network runs once on the pair, and its
full-resolution pixel map is resized back to the input size with bilinear interpolation, align_corners=True,
then u is scaled by w / W and v by h / H, giving pixels of the *input* image. The map for (a, b) says where
pixel (x, y) of `a` is found in `b`: at (x + u, y + v); so for a left->right stereo pair disparity = -u.

The network is jit-compiled once per (working size, batch size); resizing runs in numpy, so new input
sizes never recompile it. Parameters stay float32; `dtype="bfloat16"` only changes the compute dtype.
"""
from __future__ import annotations

import os
from collections.abc import Sequence
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import models

DEFAULT_HEIGHT = 256
DEFAULT_WIDTH = 512
_DTYPES = {None: None, "float32": None, "fp32": None, "bfloat16": jnp.bfloat16, "bf16": jnp.bfloat16}


def _parse_dtype(dtype: Any):
    if dtype is None or isinstance(dtype, str):
        if dtype not in _DTYPES:
            raise ValueError(f"dtype must be one of {sorted(k for k in _DTYPES if k)}, got {dtype!r}")
        return _DTYPES[dtype]
    d = jnp.dtype(dtype)
    if d == jnp.float32:
        return None
    if d == jnp.bfloat16:
        return jnp.bfloat16
    raise ValueError(f"dtype must be float32 or bfloat16, got {dtype!r}")


# --------------------------------------------------------------------------------------------------------
# Image preparation and resizing (numpy, separable weight matrices)
# --------------------------------------------------------------------------------------------------------

def to_rgb_float(image: Any, name: str = "image") -> np.ndarray:
    """`(h, w)`, `(h, w, 1)`, `(h, w, 3)` or `(h, w, 4)` uint8 / uint16 / float in [0, 1] -> float32 `(h, w, 3)`.

    Grayscale is replicated to RGB (KITTI 2012 evaluation uses grayscale frames); alpha is dropped.
    Raises ValueError for other shapes, dtypes, or float values outside [0, 1].
    """
    img = np.asarray(image)
    if img.ndim == 2:
        img = img[..., None]
    if img.ndim != 3 or img.shape[-1] not in (1, 3, 4) or img.shape[0] < 1 or img.shape[1] < 1:
        raise ValueError(f"{name}: expected an (h, w), (h, w, 1), (h, w, 3) or (h, w, 4) image, got shape {img.shape}")
    if img.shape[-1] == 1:
        img = np.repeat(img, 3, axis=-1)
    elif img.shape[-1] == 4:
        img = img[..., :3]
    if img.dtype == np.uint8:
        return img.astype(np.float32) / 255.0
    if img.dtype == np.uint16:
        return img.astype(np.float32) / 65535.0
    if np.issubdtype(img.dtype, np.floating):
        img = img.astype(np.float32)
        lo, hi = (float(img.min()), float(img.max()))
        if not (np.isfinite(lo) and np.isfinite(hi)) or lo < -1e-3 or hi > 1 + 1e-3:
            raise ValueError(f"{name}: float images must hold values in [0, 1], got range [{lo:g}, {hi:g}] "
                             f"(pass uint8, or divide by 255)")
        return np.clip(img, 0.0, 1.0)
    raise ValueError(f"{name}: unsupported dtype {img.dtype} (expected uint8, uint16 or float in [0, 1])")


def resize_weights_antialias(n_in: int, n_out: int) -> np.ndarray:
    """`(n_out, n_in)` weights of PIL-style bilinear resizing (triangle filter widened when downscaling)."""
    scale = n_in / n_out
    support = max(scale, 1.0)
    centers = (np.arange(n_out) + 0.5) * scale
    pos = np.arange(n_in) + 0.5
    w = np.maximum(0.0, 1.0 - np.abs(pos[None, :] - centers[:, None]) / support)
    w /= w.sum(axis=1, keepdims=True)
    return w.astype(np.float32)


def resize_weights_align_corners(n_in: int, n_out: int) -> np.ndarray:
    """`(n_out, n_in)` weights of bilinear resizing with align_corners=True (PyTorch UpsamplingBilinear2d)."""
    w = np.zeros((n_out, n_in), np.float64)
    pos = np.zeros(n_out) if n_out == 1 or n_in == 1 else np.arange(n_out) * ((n_in - 1) / (n_out - 1))
    i0 = np.clip(np.floor(pos).astype(int), 0, n_in - 1)
    i1 = np.minimum(i0 + 1, n_in - 1)
    t = pos - i0
    np.add.at(w, (np.arange(n_out), i0), 1 - t)
    np.add.at(w, (np.arange(n_out), i1), t)
    return w.astype(np.float32)


def _taps(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Dense `(n_out, n_in)` interpolation weights -> (indices, weights) of the non-zero taps, `(n_out, T)`."""
    nz = weights != 0
    t = max(1, int(nz.sum(axis=1).max()))
    idx = np.argsort(~nz, axis=1, kind="stable")[:, :t]  # non-zero columns first, in order
    return idx, np.take_along_axis(weights, idx, axis=1)


def _resize(x: np.ndarray, wy: np.ndarray, wx: np.ndarray) -> np.ndarray:
    """Apply separable weights to `(..., h, w, C)`: rows by `wy (H, h)`, columns by `wx (W, w)`.

    Uses only the few non-zero taps per output row/column (a dense matmul would cost O(H h w C))."""
    x = np.asarray(x, np.float32)
    iy, ty = _taps(wy)
    ix, tx = _taps(wx)
    rows = sum(x[..., iy[:, k], :, :] * ty[:, k, None, None] for k in range(iy.shape[1]))
    return sum(rows[..., ix[:, k], :] * tx[:, k, None] for k in range(ix.shape[1])).astype(np.float32)


def resize_images(images: np.ndarray, height: int, width: int) -> np.ndarray:
    """Antialiased bilinear resize of float `(..., h, w, C)` to `(..., height, width, C)`."""
    h, w = images.shape[-3:-1]
    if (h, w) == (height, width):
        return images.astype(np.float32)
    return _resize(images, resize_weights_antialias(h, height), resize_weights_antialias(w, width))


def maps_to_input_resolution(px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Working-resolution pixel maps `(..., H, W, 2)` -> `(..., height, width, 2)` in pixels of the input size.

    Bilinear with align_corners=True, then u *= width / W and v *= height / H (REFERENCE.md §1d).
    """
    H, W = px.shape[-3:-1]
    if (H, W) == (height, width):
        return np.asarray(px, np.float32)
    out = _resize(px, resize_weights_align_corners(H, height), resize_weights_align_corners(W, width))
    return out * np.array([width / W, height / H], np.float32)


# --------------------------------------------------------------------------------------------------------
# Predictor
# --------------------------------------------------------------------------------------------------------

class Predictor:
    """A network bound to its params and a working size, with numpy-in / numpy-out prediction.

    Args:
      graphdef, params: from `bridge_jax.models.init` or a checkpoint. With `separate=True`, params is
        `{"stereo": ..., "flow": ...}` (two networks; stereo pairs use the first, flow pairs the second).
      height, width: working size; multiples of 64. Default 256 x 512 (the paper's).
      dtype: compute dtype, None/"float32" or "bfloat16" (params stay float32).
      model_cfg: the model config (for the input-size multiple and for export metadata).
    Attributes:
      trace_count: how many times the network function was traced (== compiled) so far.
    """

    def __init__(self, graphdef, params, *, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH,
                 dtype: Any = None, model_cfg: dict | None = None, separate: bool = False):
        name = (model_cfg or {}).get("name", "resnet_md")
        multiple = models.INPUT_MULTIPLE.get(name, 64)
        if (not isinstance(height, (int, np.integer)) or not isinstance(width, (int, np.integer)) or height <= 0
                or width <= 0 or height % multiple or width % multiple):
            raise ValueError(f"working size must be positive multiples of {multiple}, got height={height}, "
                             f"width={width}")
        self.graphdef = graphdef
        self.height, self.width = int(height), int(width)
        self.dtype = _parse_dtype(dtype)
        self.model_cfg = dict(model_cfg) if model_cfg else None
        self.separate = separate
        if separate and not (isinstance(params, dict) and set(params) == {"stereo", "flow"}):
            raise ValueError("separate=True needs params {'stereo': ..., 'flow': ...}")
        self.params = jax.device_put(params)
        self.trace_count = 0
        self._net = jax.jit(self._forward)

    def _forward(self, params, pairs):
        self.trace_count += 1  # Python side effect: runs once per trace
        return models.apply(self.graphdef, params, pairs, dtype=self.dtype)["px"][0]

    def _params(self, task: str):
        if not self.separate:
            return self.params
        if task not in ("stereo", "flow"):
            raise ValueError(f"task must be 'stereo' or 'flow' for a separate-networks model, got {task!r}")
        return self.params[task]

    def run_network(self, pairs: np.ndarray, task: str = "flow") -> np.ndarray:
        """`(N, H, W, 6)` float32 working-size pairs -> `(N, H, W, 2)` pixels at the working size."""
        return np.asarray(self._net(self._params(task), jnp.asarray(pairs, jnp.float32)))

    def prepare(self, images_a: Sequence, images_b: Sequence) -> tuple[np.ndarray, tuple[int, int]]:
        """Validate, convert and resize N pairs -> (`(N, H, W, 6)` float32, (h, w) of the inputs)."""
        if len(images_a) != len(images_b) or len(images_a) == 0:
            raise ValueError(f"need the same, non-zero number of first and second images, got {len(images_a)} "
                             f"and {len(images_b)}")
        a = [to_rgb_float(x, f"image_a[{i}]") for i, x in enumerate(images_a)]
        b = [to_rgb_float(x, f"image_b[{i}]") for i, x in enumerate(images_b)]
        size = a[0].shape[:2]
        for i, img in enumerate(a + b):
            if img.shape[:2] != size:
                which = f"image_a[{i}]" if i < len(a) else f"image_b[{i - len(a)}]"
                raise ValueError(f"all images must have the same size: image_a[0] is {size[0]}x{size[1]}, "
                                 f"{which} is {img.shape[0]}x{img.shape[1]} (h x w)")
        pairs = np.concatenate([np.stack(a), np.stack(b)], axis=-1)
        return resize_images(pairs, self.height, self.width), size

    def predict_pairs(self, images_a: Sequence, images_b: Sequence, task: str = "flow") -> np.ndarray:
        """N pairs (sequences or `(N, h, w, C)` arrays of same-size images) -> `(N, h, w, 2)` float32 pixels."""
        pairs, (h, w) = self.prepare(images_a, images_b)
        return maps_to_input_resolution(self.run_network(pairs, task), h, w)

    def predict_pair(self, image_a: Any, image_b: Any, task: str = "flow") -> np.ndarray:
        """Correspondence from `image_a` to `image_b`: `(h, w, 2)` float32, pixels of the input resolution."""
        return self.predict_pairs([image_a], [image_b], task)[0]

    def predict_cycle(self, left_t: Any, right_t: Any, left_t1: Any, right_t1: Any) -> dict[str, np.ndarray]:
        """Disparity at t and t+1 and left-camera optical flow t -> t+1 for two stereo frames.

        Returns:
          {"disp_t": (h, w), "disp_t1": (h, w)} = -u of left->right (pixels, >= 0 for a sensible model),
          {"flow": (h, w, 2)} = map of (left_t, left_t1) in pixels.
        """
        if self.separate:
            disp = self.predict_pairs([left_t, left_t1], [right_t, right_t1], task="stereo")
            flow = self.predict_pairs([left_t], [left_t1], task="flow")[0]
        else:
            out = self.predict_pairs([left_t, left_t1, left_t], [right_t, right_t1, left_t1])
            disp, flow = out[:2], out[2]
        return {"disp_t": -disp[0, ..., 0], "disp_t1": -disp[1, ..., 0], "flow": flow}


def trained_working_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(height, width) a training workdir (or one of its step dirs) was trained at, from its config.json;
    None for params-only checkpoints or when unknown."""
    import json

    from bridge_jax import checkpointing

    try:
        model_json, _, _ = checkpointing.resolve_checkpoint(path)
        with open(model_json.parent / checkpointing.CONFIG_JSON) as f:
            cfg = json.load(f)
        return int(cfg["height"]), int(cfg["width"])
    except (ValueError, OSError, KeyError, TypeError):
        return None


def load_predictor(path: str | os.PathLike, *, height: int | None = None, width: int | None = None,
                   dtype: Any = None) -> Predictor:
    """A Predictor from any checkpoint `bridge_jax.checkpointing.load_params` accepts.

    Working size: `height`/`width` if given, else the size a training workdir was trained at (its
    config.json; a net trained at 64x128 sees 4x larger motions at 256x512), else 256 x 512 (the paper's).
    `dtype=None` uses the model config's "dtype" if it has one, else float32.
    """
    from bridge_jax import checkpointing

    if height is None or width is None:
        trained = trained_working_size(path) or (DEFAULT_HEIGHT, DEFAULT_WIDTH)
        height = trained[0] if height is None else height
        width = trained[1] if width is None else width
    cfg, params = checkpointing.load_params(path)
    separate = bool(cfg.pop("separate_networks", False))
    graphdef, _ = models.abstract_init(cfg)
    if dtype is None:
        dtype = cfg.get("dtype")
    return Predictor(graphdef, params, height=height, width=width, dtype=dtype, model_cfg=cfg, separate=separate)


__all__ = ["Predictor", "load_predictor", "trained_working_size", "to_rgb_float", "resize_images", "maps_to_input_resolution"]
