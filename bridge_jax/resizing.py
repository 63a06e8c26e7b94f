"""Images in, maps out at the input's size: image conversion, resizing, and the rules that pick a working size.

* images of any size are resized to the working size (antialiased bilinear, like PIL; `resize_images`), in numpy,
  so new input sizes never recompile the network;
* flow: the full-resolution pixel map is resized back to the input size with bilinear interpolation,
  align_corners=True, then u is scaled by w / W and v by h / H, giving pixels of the *input* image
  (`flow_to_input_resolution`);
* disparity = -u of a left -> right map; it is brought to the input size as a fraction of the width (u / W),
  resized with OpenCV's INTER_LINEAR and multiplied by the input width w (`disparity_to_input_resolution`).

The working size is one frozen value, `WorkingSize`: a fixed H x W, or each input at (nearly) its own
resolution (`native`, at most `max_pixels`; `native_working_size`).
"""
from __future__ import annotations

import dataclasses
from typing import Any

import cv2
import numpy as np

from bridge_jax import models

DEFAULT_HEIGHT = 256
DEFAULT_WIDTH = 512
NATIVE = "native"
"""Working-size choice: run every input at (nearly) its own resolution (`native_working_size`)."""
TRAINED = "trained"
"""Working-size choice: the size the checkpoint was trained at."""
DEFAULT_WORKING_SIZE = TRAINED
"""What the commands run at when `--working-size` is not given and the model's card recommends nothing."""
NATIVE_MAX_PIXELS = 1024 * 768
"""Largest working size (pixels) the native rule picks: bigger inputs are run at this many pixels (same aspect)."""
ROW_BLOCK_PIXELS = 1 << 21
"""Maps brought to a large input's resolution are computed this many output pixels at a time (bounded memory)."""
REDUCED_READ_NOTICE = 8.0
"""An input more than this many times its working size per side gets a notice (and is read at a reduced size)."""
@dataclasses.dataclass(frozen=True)
class WorkingSize:
    """The size the network runs at: `height x width`, or with `native` each input's own (`native_working_size`,
    at most `max_pixels`; `height x width` is then only what `Predictor.lower` compiles for). Positive whole
    numbers; whether the model accepts the size is checked where the model is known (`models.check_working_size`)."""

    height: int = DEFAULT_HEIGHT
    width: int = DEFAULT_WIDTH
    native: bool = False
    max_pixels: int = NATIVE_MAX_PIXELS

    def __post_init__(self):
        for name in ("height", "width", "max_pixels"):
            value = getattr(self, name)
            if isinstance(value, bool) or not hasattr(value, "__index__") or int(value) < 1:
                raise ValueError(f"working size: {name} {value!r} is not a positive whole number")
            object.__setattr__(self, name, int(value))
        object.__setattr__(self, "native", bool(self.native))

    def for_input(self, model_name: str, height: int, width: int) -> tuple[int, int]:
        """(H, W) the network runs at for an input of `height x width`."""
        if self.native:
            return native_working_size(model_name, height, width, self.max_pixels)
        return self.height, self.width

    def __str__(self) -> str:
        return NATIVE if self.native else f"{self.height}x{self.width}"


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


def flow_to_input_resolution(px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Working-resolution pixel maps `(..., H, W, 2)` -> `(..., height, width, 2)` in pixels of the input size.

    Bilinear with align_corners=True, then u *= width / W and v *= height / H (how the paper's flow evaluation
    brings its predictions to the KITTI resolution).
    """
    H, W = px.shape[-3:-1]
    if (H, W) == (height, width):
        return np.asarray(px, np.float32)
    wy, wx = resize_weights_align_corners(H, height), resize_weights_align_corners(W, width)
    scale = np.array([width / W, height / H], np.float32)
    out = np.empty(px.shape[:-3] + (height, width, px.shape[-1]), np.float32)
    rows = max(1, ROW_BLOCK_PIXELS // max(1, width))  # output rows per block: no full-size temporaries
    for r0 in range(0, height, rows):
        block = out[..., r0:r0 + rows, :, :]
        block[...] = _resize(px, wy[r0:r0 + rows], wx)
        block *= scale
    return out


def disparity_to_input_resolution(disp_px: np.ndarray, height: int, width: int) -> np.ndarray:
    """Disparity `(H, W)` in working pixels -> `(height, width)` float32 in pixels of the input size.

    The fraction disp / W is resized with OpenCV INTER_LINEAR and multiplied by `width` (how the paper's stereo
    evaluation brings its predictions to the KITTI resolution); unchanged when the sizes agree.
    """
    h, w = disp_px.shape
    if (h, w) == (height, width):
        return np.asarray(disp_px, np.float32)
    frac = np.asarray(disp_px, np.float32) / np.float32(w)
    out = cv2.resize(frac, (width, height), interpolation=cv2.INTER_LINEAR)
    out *= np.float32(width)  # in place: one full-size array, not two
    return out


def map_to_input_resolution(task: str, working_map: np.ndarray, height: int, width: int) -> np.ndarray:
    """A working-size map `(H, W, 2)` of a pair -> its prediction at the input size: flow `(height, width, 2)`
    for a "flow" pair, disparity `(height, width)` (= -u) for a "stereo" pair."""
    if task == "flow":
        return flow_to_input_resolution(working_map, height, width)
    return disparity_to_input_resolution(-working_map[..., 0], height, width)


def map_to_size(task: str, working_map: np.ndarray, height: int, width: int) -> np.ndarray:
    """A working-size map `(H, W, 2)` brought to `height x width` by `map_to_input_resolution`'s rule, as a
    map again: `(height, width, 2)` pixels of the new size, a "stereo" map's vertical component 0."""
    value = map_to_input_resolution(task, working_map, height, width)
    if task == "flow":
        return value
    return np.stack([-value, np.zeros_like(value)], -1)


def native_working_size(model_name: str, height: int, width: int,
                        max_pixels: int = NATIVE_MAX_PIXELS) -> tuple[int, int]:
    """The working size that runs an `height x width` input at (nearly) its own resolution.

    Each side is rounded *down* to a multiple of `models.NATIVE_MULTIPLE[model_name]` (for pwc_lite 64, so its
    feature pyramid keeps all its levels and its coarse-to-fine search its full range), never below one
    multiple, after shrinking both sides by the same factor when the input has more than `max_pixels` pixels.
    Inputs smaller than the model's minimum come back at that minimum (they are upsampled).

      native_working_size("pwc_lite", 500, 741) == (448, 704)
      native_working_size("pwc_lite", 375, 1242) == (320, 1216)
    """
    multiple = models.NATIVE_MULTIPLE[model_name]
    h, w = float(height), float(width)
    if h * w > max_pixels:
        shrink = (max_pixels / (h * w)) ** 0.5
        h, w = h * shrink, w * shrink
    size = (max(multiple, int(h) // multiple * multiple), max(multiple, int(w) // multiple * multiple))
    return models.suggest_working_size(model_name, *size) or size



def input_size(image: Any) -> tuple[int, int]:
    """(h, w) of the input an image stands for: its own shape, or for an image read at a reduced size
    (`predict.ImageReader`) the size of the file (`full_size`): maps come back at that size."""
    full = getattr(image, "full_size", None)
    return tuple(int(v) for v in (full if full is not None else np.shape(image)[:2]))


MAX_UPSAMPLING = 4
"""Inputs are refused when the model's smallest working size is more than this many times larger per side."""


def minimum_input_size(model_name: str) -> tuple[int, int]:
    """The smallest input (h, w) the model is run on: its smallest working size / `MAX_UPSAMPLING` (rounded
    up). A smaller input would only be blown up (a 1x1 image has no structure to match)."""
    low = models.suggest_working_size(model_name, 1, 1) or (models.INPUT_MULTIPLE[model_name],) * 2
    return tuple(-(-v // MAX_UPSAMPLING) for v in low)




__all__ = ["WorkingSize", "NATIVE", "TRAINED", "DEFAULT_WORKING_SIZE", "DEFAULT_HEIGHT",
           "DEFAULT_WIDTH", "NATIVE_MAX_PIXELS", "to_rgb_float", "resize_images", "flow_to_input_resolution",
           "disparity_to_input_resolution", "map_to_input_resolution", "map_to_size", "native_working_size",
           "input_size", "minimum_input_size", "MAX_UPSAMPLING"]
