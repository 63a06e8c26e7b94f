"""Run a trained network on your own images: the one predictor of bridge_jax.

    from bridge_jax.inference import load_predictor
    pred = load_predictor("demo")                                   # the shipped model, or a checkpoint path
    flow = pred.predict_pair(frame_t, frame_t1)                     # (h, w, 2) pixels, uint8 or float images
    disp = pred.predict_pair(left, right, task="stereo")             # (h, w) disparity in pixels
    out = pred.predict_cycle(left_t, right_t, left_t1, right_t1)   # disp_t, disp_t1 (h, w), flow (h, w, 2)

Training's validation, `evaluate`, `predict`, `export` and the library all go through `Predictor`, so they
resize, batch and rescale the same way, which is the paper's evaluation protocol:

* images of any size are resized to the working size (default H=256, W=512; antialiased bilinear, like PIL),
  and the network runs once per pair (`run_network`, compiled once per working size and batch size; resizing
  runs in numpy, so new input sizes never recompile it);
* flow: the full-resolution pixel map is resized back to the input size with bilinear interpolation,
  align_corners=True, then u is scaled by w / W and v by h / H, giving pixels of the *input* image
  (`flow_to_input_resolution`);
* disparity = -u of a left -> right map; it is brought to the input size as a fraction of the width (u / W),
  resized with OpenCV's INTER_LINEAR and multiplied by the input width w (`disparity_to_input_resolution`).

The map for (a, b) says where pixel (x, y) of `a` is found in `b`: at (x + u, y + v). Parameters stay
float32; `dtype="bfloat16"` only changes the compute dtype.

`refine=K` runs the network K more times per pair, each on `a` and `b` warped by the estimate so far, and
composes the residual it finds with that estimate (`refine_maps`): test-time iterative residual refinement,
the same network with no new weights, at K + 1 times the cost. `symmetry="flips"` averages each estimate over
the pair as given and mirrored left-right, upside-down and both (`symmetric_estimate`; 4 times the cost,
"dihedral" adds the transposed copies for flow pairs). `polish="photometric"` then corrects the map locally
against the images at the working size (`bridge_jax.polish`: bled motion boundaries and sub-pixel noise, with
the training's photometric criterion). A shipped model's card may recommend a K, a symmetry and a polish.
"""
from __future__ import annotations

import copy
import json
import os
from collections.abc import Sequence
from typing import Any, Optional

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import checkpointing, compile_cache, executable_cache, geometry, memory, models, zoo
from bridge_jax.network import Network, check_separate_params, compute_dtype
from bridge_jax.polish import POLISH_MODES, check_polish, component_mask, polish_maps

DEFAULT_HEIGHT = 256
DEFAULT_WIDTH = 512
NATIVE = "native"
"""Working-size choice: run every input at (nearly) its own resolution (`native_working_size`)."""
DEFAULT_WORKING_SIZE = "trained"
"""What the commands run at when `--working-size` is not given and the model's card recommends nothing."""
NATIVE_MAX_PIXELS = 1024 * 768
"""Largest working size (pixels) the native rule picks: bigger inputs are run at this many pixels (same aspect)."""
ROW_BLOCK_PIXELS = 1 << 21
"""Maps brought to a large input's resolution are computed this many output pixels at a time (bounded memory)."""
REDUCED_READ_NOTICE = 8.0
"""An input more than this many times its working size per side gets a notice (and is read at a reduced size)."""
PAIR_KINDS = ("flow", "stereo")
"""What a pair is: consecutive frames ("flow") or a rectified left -> right pair ("stereo")."""
COMPILE_MODES = ("auto", "fast", "full")
"""How the network is compiled. "full": XLA's default optimisation. "fast": the LLVM back end at optimisation
level 0 (`xla_backend_optimization_level=0`). On a 2-core AVX-512 VM (2026-12-02) that cut pwc_lite's compile
from 8.3 to 3.7 s at 64x128 and from 19.9 to 6.3 s at 256x512 while each call got 12-26 % slower (20.5 -> 22.9 ms,
294 -> 371 ms): a few pairs answer sooner "fast", long runs sooner "full". "auto": `compile_mode_for`. The
polish is compiled at full optimisation whatever the mode (`Predictor._polish_program`)."""
MAX_REFINE = 8
"""The most refinement passes `Predictor(refine=)` accepts (each costs one more network call per pair)."""
SYMMETRY_MODES = ("none", "flips", "dihedral")
"""Test-time symmetry averaging (`symmetric_estimate`): "none"; "flips" = the pair as given and flipped
left-right, upside-down and both (4 network calls' worth); "dihedral" = those 4 and the same 4 transposed (8).
Stereo pairs count only the copies that are still left -> right stereo pairs: as given and upside-down."""
FAST_COMPILE_PAIRS = 64
"""`compile_mode_for("auto", n)`: runs of at most this many pairs per working size compile "fast" (at 256x512
the 13.6 s saved pay for ~180 slower calls; at 64x128 for ~2,000)."""


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


def compile_mode_for(mode: str, num_pairs: Optional[int]) -> str:
    """"fast" or "full" for a run of `num_pairs` pairs (None = unknown) under `mode` (one of `COMPILE_MODES`;
    "auto" = "fast" up to `FAST_COMPILE_PAIRS` pairs, else "full")."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode {mode!r}: expected one of {', '.join(COMPILE_MODES)}")
    if mode != "auto":
        return mode
    return "fast" if num_pairs is not None and num_pairs <= FAST_COMPILE_PAIRS else "full"


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


def _check_task(task: str) -> bool:
    """True for a stereo pair; ValueError for an unknown task."""
    if task not in PAIR_KINDS:
        raise ValueError(f"task must be one of {PAIR_KINDS}, got {task!r}")
    return task == "stereo"


def check_refine(refine: Any, option: str = "refine") -> int:
    """`refine` as an int in 0..`MAX_REFINE`; ValueError naming `option` otherwise."""
    if isinstance(refine, bool) or not isinstance(refine, (int, np.integer)) or not 0 <= refine <= MAX_REFINE:
        raise ValueError(f"{option} {refine!r}: expected a whole number of refinement passes from 0 to {MAX_REFINE}")
    return int(refine)


def refine_maps(estimate, pairs: jax.Array, maps: jax.Array, keep_vertical: jax.Array, passes: int) -> jax.Array:
    """Test-time iterative residual refinement of correspondence maps.

    Each pass backward-warps image b by the current map D (`geometry.warp`, bilinear, border clamp), so that
    what is left to find is a small residual R between a and warp(b, D), asks the network for it, and composes
    the two: pixel x of a is found at x + R(x) in warp(b, D), which is b at x + R(x) + D(x + R(x)), so
    D'(x) = R(x) + D(x + R(x)) (D sampled at the residual's end point, again by `geometry.warp`).

    Args:
      estimate: pair inputs `(N, H, W, 6)` -> maps `(N, H, W, 2)` in working pixels (the network).
      pairs: `(N, H, W, 6)` = [image a, image b].
      maps: `(N, H, W, 2)`, the first estimate.
      keep_vertical: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows, whose vertical component is
        dropped before each warp (a stereo match lies on the same row).
      passes: how many passes (static); one compiled copy of the network serves them all (`lax.fori_loop`).
    Returns:
      `(N, H, W, 2)` refined maps.
    """
    image_a, image_b = pairs[..., :3], pairs[..., 3:]
    mask = component_mask(keep_vertical)

    def one_pass(_, d):
        d = d * mask
        residual = estimate(jnp.concatenate([image_a, geometry.warp(image_b, d)], axis=-1)) * mask
        return residual + geometry.warp(d, residual)

    return jax.lax.fori_loop(0, passes, one_pass, maps)


def check_symmetry(symmetry: Any, option: str = "symmetry") -> str:
    """`symmetry` if it is one of `SYMMETRY_MODES`, else a ValueError naming `option`."""
    if symmetry not in SYMMETRY_MODES:
        raise ValueError(f"{option} {symmetry!r}: expected one of {', '.join(SYMMETRY_MODES)}")
    return symmetry


def _flip(x: jax.Array, left_right: bool, up_down: bool) -> jax.Array:
    """`(N, H, W, C)` flipped along W and/or H (pixel x -> W - 1 - x: exact, no resampling)."""
    if left_right:
        x = x[:, :, ::-1]
    if up_down:
        x = x[:, ::-1]
    return x


def symmetric_estimate(estimate, pairs: jax.Array, symmetry: str,
                       keep_vertical: Optional[jax.Array] = None) -> jax.Array:
    """The network's map averaged over mirrored and transposed copies of each pair (test-time augmentation).

    A correspondence map commutes with the image's symmetries: if both images are flipped left-right, pixel
    (W - 1 - x, y) of the flipped `a` is found at (W - 1 - x - u, y + v) of the flipped `b`, so the flipped
    pair's map, flipped back, is (-u, v); upside-down flips negate v; a transposed pair's map, transposed back,
    has u and v swapped. The network does not know these symmetries exactly (it was trained on rigs that move
    forward, with mostly horizontal stereo), and its sub-pixel errors on the copies are partly independent, so
    their mean is more precise than any one of them; the monodepth family's flip post-processing is the
    one-flip case of the same idea. All flipped copies of one orientation run as one batch (one traced copy of
    the network per orientation).

    Measured (experiments/results/real_images.md, 2026-12-03): on `long`, "flips" lowered every real-image
    error (photo flow 1.90 -> 1.74 px, Motorcycle D1 14.9 -> 14.6 %); "dihedral" lowers the photo flow further
    (1.53 px) but raises the synthetic driving flow (the transposed view of a forward-moving rig is a scene the
    network never saw). On `demo`, "flips" helps its flow and hurts its stereo (Motorcycle D1 28.9 -> 35.9 %).

    Args:
      estimate: `(M, h, w, 6)` pair inputs -> `(M, h, w, 2)` maps in working pixels, for any M and any (h, w)
        the network accepts (a transposed pair is `(N, W, H, 6)`; working sizes are multiples of the model's
        input multiple both ways).
      pairs: `(N, H, W, 6)` = [image a, image b].
      symmetry: one of `SYMMETRY_MODES`.
      keep_vertical: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows (as for `refine_maps`). A stereo
        row counts only its copies that are stereo pairs of the same kind: as given and flipped upside-down (a
        left-right flip turns a left -> right pair into one whose matches lie to the right, a transposition
        into a vertical one). None = all rows are flow.
    Returns:
      `(N, H, W, 2)` maps.
    """
    if symmetry == "none":
        return estimate(pairs)
    n = pairs.shape[0]
    flips = ((False, False), (True, False), (False, True), (True, True))
    views = (False, True) if symmetry == "dihedral" else (False,)
    flow_rows = jnp.ones((n,), jnp.float32) if keep_vertical is None else keep_vertical.astype(jnp.float32)
    total = jnp.zeros(pairs.shape[:3] + (2,), jnp.float32)
    count = jnp.zeros((n,), jnp.float32)
    for transposed in views:
        view = jnp.swapaxes(pairs, 1, 2) if transposed else pairs
        maps = estimate(jnp.concatenate([_flip(view, lr, ud) for lr, ud in flips])).astype(jnp.float32)
        for k, (lr, ud) in enumerate(flips):
            weight = flow_rows if (lr or transposed) else jnp.ones((n,), jnp.float32)
            m = _flip(maps[k * n:(k + 1) * n], lr, ud) * jnp.array([-1.0 if lr else 1.0, -1.0 if ud else 1.0])
            total = total + weight[:, None, None, None] * (jnp.swapaxes(m, 1, 2)[..., ::-1] if transposed else m)
            count = count + weight
    return total / count[:, None, None, None]


_POLISH_JIT = jax.jit(polish_maps)
"""The polish as its own program (`Predictor._polish_program`)."""


def predicted_maps(network: Network, params, pairs: jax.Array, rows: tuple[bool, ...], keep_vertical: jax.Array,
                   refine: int, symmetry: str, polish: str = "none") -> jax.Array:
    """What a predictor answers for `pairs`: the network's scale-0 pixel map (averaged over the `symmetry`
    copies, `symmetric_estimate`), then `refine` refinement passes (`refine_maps`, each pass's residual averaged
    the same way), then the `polish` ("photometric": `polish.polish_maps`). `network(params, x, rows)`: a
    `Network` and its static rows (`Network.static_rows`, one per pair); `pairs (N, H, W, 6)`, `keep_vertical
    (N,)` as for `refine_maps`. Returns `(N, H, W, 2)`."""
    n = pairs.shape[0]
    # symmetric_estimate stacks copies of the N pairs on the batch axis: separate networks need their rows repeated
    net = lambda x: network(params, x, rows * (x.shape[0] // n))["px"][0]
    estimate = lambda x: symmetric_estimate(net, x, symmetry, keep_vertical)
    maps = estimate(pairs)
    if refine:
        maps = refine_maps(estimate, pairs, maps, keep_vertical, refine)
    return polish_maps(pairs, maps, keep_vertical) if polish == "photometric" else maps


# --------------------------------------------------------------------------------------------------------
# Predictor
# --------------------------------------------------------------------------------------------------------

class Predictor:
    """A network bound to its params and a working size, with numpy-in / numpy-out prediction.

    Args:
      graphdef, params: from `bridge_jax.models.init` or a checkpoint. With `separate=True`, params is
        `{"stereo": ..., "flow": ...}` (two networks; stereo pairs use the first, flow pairs the second).
      height, width: working size; multiples of the model's input multiple (64). Default 256 x 512 (the paper's).
      dtype: compute dtype, None/"float32" or "bfloat16" (params stay float32).
      model_cfg: the model config (for the input-size multiple and for export metadata).
      mesh: optional 1-D device mesh; pairs are then sharded over it (padded to a multiple of its size) and the
        maps come back replicated (training's validation runs on the training mesh). Default: one device.
      native: run each pair at its own resolution (`native_working_size`, capped at `max_pixels`) instead of
        `height x width`; each new size compiles the network once (then it is cached).
      compile_mode: "full" (default) or "fast" (`COMPILE_MODES`: quicker to compile, slower per call), or
        "auto" = "full"; settable later through the `compile_mode` attribute (`compile_mode_for` picks one for a
        run whose number of pairs is known, as the commands do).
      refine: test-time refinement passes after the first estimate (`refine_maps`; 0 = none, at most
        `MAX_REFINE`); settable later through the `refine` attribute (each value compiles once).
      symmetry: test-time symmetry averaging of every estimate (`SYMMETRY_MODES`, `symmetric_estimate`;
        "none" = off); settable later through the `symmetry` attribute (each value compiles once).
      polish: test-time polish of the final maps (`POLISH_MODES`; "photometric" = `polish.polish_maps`,
        "none" = off); settable later through the `polish` attribute (each value compiles once).
      executable_cache: a folder (the commands pass the compilation cache's) where each compiled network is
        kept whole (`bridge_jax.executable_cache`), so that a later process with the same code, model and
        shapes loads it without tracing or lowering; None (default) = off. Needs `model_cfg`; one device only.
    Attributes:
      trace_count: how many times the network function was traced (== compiled) so far.
    """

    native = False
    max_pixels = NATIVE_MAX_PIXELS
    model_name = "resnet_md"
    refine = 0

    def __init__(self, graphdef, params, *, height: int = DEFAULT_HEIGHT, width: int = DEFAULT_WIDTH,
                 dtype: Any = None, model_cfg: Optional[dict] = None, separate: bool = False, mesh=None,
                 native: bool = False, max_pixels: int = NATIVE_MAX_PIXELS, compile_mode: str = "full",
                 refine: int = 0, symmetry: str = "none", polish: str = "none",
                 executable_cache: Optional[str] = None):
        self.refine = check_refine(refine)
        self.symmetry = check_symmetry(symmetry)
        self.polish = check_polish(polish)
        self.executable_cache = executable_cache
        # (mode, shape, rows, refine, symmetry, polish) -> kept compiled network (`_program`)
        self._kept: dict[tuple, Any] = {}
        self.model_cfg = dict(model_cfg) if model_cfg else None
        self.model_name = (model_cfg or {}).get("name", "resnet_md")
        models.check_working_size(self.model_name, height, width)
        self.native, self.max_pixels = bool(native), int(max_pixels)
        check_separate_params(params, separate)
        self.net = Network(graphdef, separate=separate, dtype=compute_dtype(dtype))
        self.graphdef, self.separate, self.dtype = graphdef, separate, self.net.dtype
        self.height, self.width = int(height), int(width)
        self.mesh = mesh
        self.trace_count = 0
        self.compile_mode = compile_mode_for(compile_mode, None)
        self._jits: dict[str, Any] = {}  # compile mode -> jitted network (each keeps its own executables)
        if mesh is None:
            self.params = jax.device_put(params)
        else:
            self._pairs_sharding = NamedSharding(mesh, P(mesh.axis_names[0]))
            self.params = params

    @property
    def _net(self):
        """The jitted network for the current `compile_mode`."""
        fn = self._jits.get(self.compile_mode)
        if fn is None:
            options = {"xla_backend_optimization_level": 0} if self.compile_mode == "fast" else None
            shardings = {} if self.mesh is None else {"out_shardings": NamedSharding(self.mesh, P())}
            fn = self._jits[self.compile_mode] = jax.jit(self._forward, static_argnums=(2, 4, 5),
                                                         compiler_options=options, **shardings)
        return fn

    def _forward(self, params, pairs, rows, keep_vertical, refine, symmetry):
        self.trace_count += 1  # Python side effect: runs once per trace
        # no polish here: `forward` runs it as a program of its own (`_polish_program`)
        return predicted_maps(self.net, params, pairs, rows, keep_vertical, refine, symmetry)

    def with_params(self, params) -> "Predictor":
        """The same predictor (and compiled function) with other params, e.g. a training state's."""
        other = copy.copy(self)
        other.params = params  # the shallow copy shares `_jits`: the compiled functions do not depend on the values
        return other

    def forward(self, pairs: jax.Array, is_stereo: Sequence[bool]) -> jax.Array:
        """The compiled network on device arrays: `(N, H, W, 6)` -> `(N, H, W, 2)` working-size pixel maps
        (N a multiple of the mesh size); `is_stereo` one bool per row. With `refine`, refined (`refine_maps`);
        with `polish`, polished (`polish.polish_maps`) by a program of its own (`_polish_program`)."""
        keep_vertical = _keep_vertical(is_stereo)
        args = (self.params, pairs, self.net.static_rows(is_stereo), keep_vertical, self.refine, self.symmetry)
        maps = self._program(args)(*args)
        if self.polish == "none":
            return maps
        polish_args = (pairs, maps, keep_vertical)
        return self._polish_program(polish_args)(*polish_args)

    def _polish_program(self, args):
        """`polish_maps` jitted at XLA's full optimisation whatever `compile_mode` (with `executable_cache`,
        compiled once and kept there). The polish is all elementwise loops, which XLA:CPU's optimisation level 0
        leaves unvectorised: in one "fast" program with the network it took 2.44 s per 256x512 pair against
        0.63 s (2026-12-04, 2-core AVX-512 VM), while the network's convolutions (library calls) do not care."""
        if self.executable_cache is None or self.mesh is not None:
            return _POLISH_JIT
        pairs = args[0]
        key = ("polish", tuple(pairs.shape), str(pairs.dtype), self.executable_cache)
        fn = self._kept.get(key)
        if fn is None:
            fn = self._kept[key] = executable_cache.cached_compile(
                _POLISH_JIT, args, config={"program": "polish"}, folder=self.executable_cache)
        return fn

    def _program(self, args):
        """The jitted network, or with `executable_cache` the compiled network for these arguments, loaded
        from that folder or compiled and kept there (`executable_cache.cached_compile`)."""
        if self.executable_cache is None or self.mesh is not None or self.model_cfg is None:
            return self._net
        pairs, rows = args[1], args[2]
        key = (self.compile_mode, tuple(pairs.shape), str(pairs.dtype), rows, self.refine, self.symmetry,
               self.executable_cache)
        fn = self._kept.get(key)
        if fn is None:
            # What the network function closes over besides its arguments: the model, the compute dtype, one or
            # two networks and the compile options.
            config = {"program": "predictor", "model": self.model_cfg, "dtype": str(self.dtype),
                      "separate": self.separate, "compile_mode": self.compile_mode}
            fn = self._kept[key] = executable_cache.cached_compile(self._net, args, config=config,
                                                                   folder=self.executable_cache,
                                                                   static_argnums=(2, 4, 5))
        return fn

    def lower(self, batch: int, is_stereo: bool = False):
        """`jax.stages.Lowered` of the network for `batch` pairs (compile time, cost and memory analysis), with
        its refinement passes and symmetry averaging and without the polish (a program of its own)."""
        spec = jax.ShapeDtypeStruct((batch, self.height, self.width, 6), jnp.float32)
        rows = (is_stereo,) * batch
        return self._net.lower(self.params, spec, self.net.static_rows(rows), _keep_vertical(rows), self.refine,
                               self.symmetry)

    def run_network(self, pairs: np.ndarray, is_stereo: bool | Sequence[bool] = False) -> np.ndarray:
        """`(N, H, W, 6)` float32 working-size pairs -> `(N, H, W, 2)` pixel maps at the working size.

        `is_stereo`: one bool for all rows or one per row (only separate networks look at it).
        """
        pairs = np.asarray(pairs, np.float32)
        n = pairs.shape[0]
        rows = (bool(is_stereo),) * n if isinstance(is_stereo, (bool, np.bool_)) else tuple(map(bool, is_stereo))
        if self.mesh is None:
            x = jax.device_put(pairs)  # not jnp.asarray: that compiles a small program per new shape
        else:
            pad = (-n) % self.mesh.size
            if pad:
                pairs = np.concatenate([pairs, np.repeat(pairs[-1:], pad, 0)])
                rows = rows + (rows[-1],) * pad
            x = jax.make_array_from_callback(pairs.shape, self._pairs_sharding, lambda idx: pairs[idx])
        return np.asarray(self.forward(x, rows))[:n]

    def working_size(self, height: int, width: int) -> tuple[int, int]:
        """(H, W) the network runs at for an input of `height x width`: the fixed working size, or with
        `native` the input's own (`native_working_size`)."""
        if self.native:
            return native_working_size(self.model_name, height, width, self.max_pixels)
        return self.height, self.width

    def prepare(self, images_a: Sequence, images_b: Sequence) -> tuple[np.ndarray, tuple[int, int]]:
        """Validate, convert and resize N pairs -> (`(N, H, W, 6)` float32 at `working_size(h, w)`, (h, w) of
        the inputs)."""
        if len(images_a) != len(images_b) or len(images_a) == 0:
            raise ValueError(f"need the same, non-zero number of first and second images, got {len(images_a)} "
                             f"and {len(images_b)}")
        full = input_size(images_a[0])
        a = [to_rgb_float(x, f"image_a[{i}]") for i, x in enumerate(images_a)]
        b = [to_rgb_float(x, f"image_b[{i}]") for i, x in enumerate(images_b)]
        size = a[0].shape[:2]
        for i, img in enumerate(a + b):
            if img.shape[:2] != size:
                which = f"image_a[{i}]" if i < len(a) else f"image_b[{i - len(a)}]"
                raise ValueError(f"all images must have the same size: image_a[0] is {size[0]}x{size[1]}, "
                                 f"{which} is {img.shape[0]}x{img.shape[1]} (height x width)")
        low = minimum_input_size(self.model_name)
        if full[0] < low[0] or full[1] < low[1]:
            raise ValueError(f"a {full[0]}x{full[1]} input is smaller than model {self.model_name} accepts (at least "
                             f"{low[0]}x{low[1]} pixels, height x width)")
        pairs = np.concatenate([np.stack(a), np.stack(b)], axis=-1)
        return resize_images(pairs, *self.working_size(*full)), full

    def working_maps(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        """Working-size pixel maps `(H, W, 2)` of `jobs` = [(task, image a, image b), ...], a -> b.

        The network is called on exactly `batch` pairs at a time (default: all jobs at once; the last call
        padded by repetition), so one compiled function serves a whole run; each pair is resized on its own,
        so images of different sizes can share a call (with `native`, pairs share a call when their working
        sizes agree). Separate networks get one call per task.
        """
        out: list[Optional[np.ndarray]] = [None] * len(jobs)
        stereo = [_check_task(task) for task, _, _ in jobs]
        # one shared network: no need to split (and pad) by task; the rows still say which are stereo (refining)
        groups = stereo if self.separate else [False] * len(jobs)
        sizes = [self.working_size(*input_size(a)) for _, a, _ in jobs]
        for kind in dict.fromkeys(zip(groups, sizes)):
            idx = [i for i, key in enumerate(zip(groups, sizes)) if key == kind]
            size = batch or len(idx)
            for start in range(0, len(idx), size):
                chunk = idx[start:start + size]
                pairs = np.concatenate([self.prepare([jobs[i][1]], [jobs[i][2]])[0] for i in chunk])
                rows = [stereo[i] for i in chunk]
                if len(chunk) < size:
                    pairs = np.concatenate([pairs, np.repeat(pairs[-1:], size - len(chunk), 0)])
                    rows += rows[-1:] * (size - len(chunk))
                for i, m in zip(chunk, self.run_network(pairs, rows)):
                    out[i] = m
        return out  # type: ignore[return-value]

    def predict(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        """Predictions of `jobs` = [(task, image a, image b), ...] at each pair's input size: flow `(h, w, 2)`
        for "flow" jobs, disparity `(h, w)` for "stereo" jobs (see the module docstring); `batch` as in
        `working_maps`."""
        maps = self.working_maps(jobs, batch)
        return [map_to_input_resolution(task, m, *input_size(a)) for (task, a, _), m in zip(jobs, maps)]

    def predict_pairs(self, images_a: Sequence, images_b: Sequence, task: str = "flow") -> np.ndarray:
        """N pairs (sequences or `(N, h, w, C)` arrays of same-size images) -> predictions at the input
        resolution, by the task's rule (`map_to_input_resolution`): flow `(N, h, w, 2)` float32 pixels for
        "flow" pairs, disparity `(N, h, w)` float32 pixels for "stereo" pairs (as `predict` gives them)."""
        pairs, (h, w) = self.prepare(images_a, images_b)
        maps = self.run_network(pairs, _check_task(task))
        if task == "flow":
            return flow_to_input_resolution(maps, h, w)
        return np.stack([map_to_input_resolution(task, m, h, w) for m in maps])

    def predict_pair(self, image_a: Any, image_b: Any, task: str = "flow") -> np.ndarray:
        """The prediction of one pair at the input resolution: flow `(h, w, 2)` from `image_a` to `image_b`
        ("flow"), or the disparity `(h, w)` of a left image `image_a` against its right image `image_b`
        ("stereo"); float32 pixels of the input resolution."""
        return self.predict_pairs([image_a], [image_b], task)[0]

    def predict_cycle(self, left_t: Any, right_t: Any, left_t1: Any, right_t1: Any) -> dict[str, np.ndarray]:
        """Disparity at t and t+1 and left-camera optical flow t -> t+1 for two stereo frames.

        Returns:
          {"disp_t": (h, w), "disp_t1": (h, w)} = disparity of left_t / left_t1 (pixels, >= 0 for a sensible
          model), {"flow": (h, w, 2)} = flow left_t -> left_t1 in pixels; as `evaluate` and `predict` compute
          them.
        """
        disp_t, disp_t1, flow = self.predict([("stereo", left_t, right_t), ("stereo", left_t1, right_t1),
                                              ("flow", left_t, left_t1)])
        return {"disp_t": disp_t, "disp_t1": disp_t1, "flow": flow}


def _keep_vertical(is_stereo: Sequence[bool]) -> np.ndarray:
    """`(N,)` float32: 0 for stereo rows (their vertical component is dropped while refining), 1 for flow."""
    return np.array([0.0 if s else 1.0 for s in is_stereo], np.float32)


def trained_working_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(height, width) a training workdir (or one of its step dirs) was trained at, from its config.json, or a
    shipped model (by name) was trained at; None for params-only checkpoints or when unknown."""
    try:
        if zoo.is_name(path):
            return zoo.trained_size(path) or trained_working_size(zoo.resolve_path(path))
        model_json, _, _ = checkpointing.resolve_checkpoint(path)
        with open(model_json.parent / checkpointing.CONFIG_JSON) as f:
            cfg = json.load(f)
        return int(cfg["height"]), int(cfg["width"])
    except (ValueError, OSError, KeyError, TypeError):
        return None


def resize_notice(predictor: Predictor, height: int, width: int, factor: float = 2.0) -> Optional[str]:
    """One line for the user when an input of `height x width` is resized by more than `factor` on a side to
    run, naming the native size where that is another one: shrunk (fine structure and small motions are lost
    there), or upscaled (each pair then costs a network call at the larger working size and gains no detail).
    None otherwise."""
    wh, ww = predictor.working_size(height, width)
    native = native_working_size(predictor.model_name, height, width, predictor.max_pixels)
    hint = "" if (wh, ww) == native else f"; --working-size native runs it at {native[0]}x{native[1]}"
    shrink = max(height / wh, width / ww)
    if shrink > factor:
        if shrink > REDUCED_READ_NOTICE:
            hint += ("; it is decoded at a reduced size to save memory, and the maps are written at the input's "
                     f"{height}x{width}")
        return f"note: the {height}x{width} input runs at {wh}x{ww} ({shrink:.1f}x smaller per side){hint}"
    grow = max(wh / height, ww / width)
    if grow > factor:
        return (f"note: the {height}x{width} input runs at {wh}x{ww} ({grow:.1f}x larger per side: upscaled, each "
                f"pair costs a {wh}x{ww} network call){hint}")
    return None


def load_predictor(path: str | os.PathLike, *, height: int | None = None, width: int | None = None,
                   dtype: Any = None, size_option: str = "working size", native: bool = False,
                   max_pixels: int = NATIVE_MAX_PIXELS, working_size: Any = None,
                   compile_mode: str = "full", refine: Optional[int] = None,
                   refine_option: str = "refine", symmetry: Optional[str] = None, symmetry_option: str = "symmetry",
                   polish: Optional[str] = None, polish_option: str = "polish",
                   executable_cache: Optional[str] = "auto") -> Predictor:
    """A Predictor from a shipped model's name (`"demo"`, see `bridge_jax.zoo`) or any checkpoint
    `bridge_jax.checkpointing.read_params` accepts (params-only dir, training workdir, step dir).

    Working size: `height`/`width` if given, else the size a training workdir or shipped model was trained at
    (a net trained at 64x128 sees 4x larger motions at 256x512), else 256 x 512 (the paper's). `native=True`
    runs each input at its own resolution instead (`native_working_size`; that size is then only the fallback).
    `dtype=None` uses the model config's "dtype" if it has one, else float32. `compile_mode`: see `Predictor`.
    `working_size` is the command-line form of the same choice (`cli.parse_working_size`): (H, W), "native",
    "trained", or None: the size the card recommends (chosen by its real-image checks), else
    `DEFAULT_WORKING_SIZE`. `refine`: test-time refinement passes (`Predictor`); None = what the card
    recommends (`zoo.default_refine`), else 0. `symmetry`: test-time symmetry averaging (`Predictor`);
    None = what the card recommends (`zoo.default_symmetry`), else "none". `polish`: test-time
    polish (`Predictor`); None = what the card recommends (`zoo.default_polish`), else "none". "The card":
    that of the shipped model `path` names or was fine-tuned from (`zoo.defaults_source`, which follows a
    checkpoint's recorded `init_from`).
    `executable_cache`: the folder where compiled networks are kept whole (see `Predictor`); "auto" (the
    default) = the folder of JAX's persistent compilation cache, turning on the one the commands use first when
    none is on (`compile_cache.enable("auto")`: $BRIDGE_JAX_CACHE_DIR, else ~/.cache/bridge_jax/xla), so that a
    second Python process gets its first answer as fast as `bridge-predict` does; None = off (every process
    compiles afresh).
    Raises ValueError naming the checkpoint (missing, unreadable), `size_option` (how the caller's user
    gave the size, e.g. "--working-size") with the model's input multiple and a size that fits, or for a size
    that cannot fit in memory (`memory.check_fits`, before the weights are read), or
    `refine_option` for a refine count out of range, `symmetry_option` for an unknown symmetry, or
    `polish_option` for an unknown polish.
    """
    if executable_cache == "auto":
        executable_cache = compile_cache.active_dir() or compile_cache.enable("auto", option="executable_cache")
    refine = check_refine(zoo.default_refine(path) if refine is None else refine, refine_option)
    symmetry = check_symmetry(zoo.default_symmetry(path) if symmetry is None else symmetry, symmetry_option)
    polish = check_polish(zoo.default_polish(path) if polish is None else polish, polish_option)
    if working_size is None and height is None and width is None and not native:
        working_size = zoo.default_working_size(path) or DEFAULT_WORKING_SIZE
    if working_size == NATIVE:
        native = True
    elif isinstance(working_size, tuple):
        height, width = working_size
    elif working_size not in ("trained", None):  # None: explicit height/width or native given
        raise ValueError(f"{size_option} {working_size!r}: expected HxW, 'native' or 'trained'")
    if height is None or width is None:
        trained = trained_working_size(path) or (DEFAULT_HEIGHT, DEFAULT_WIDTH)
        height = trained[0] if height is None else height
        width = trained[1] if width is None else width
    if all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (height, width)):
        # before the weights are read: a size that cannot fit is refused without allocating anything
        memory.check_fits(size_option, height, width, memory.prediction_bytes(height, width),
                          "a prediction (one pair per call)", jax.devices()[0])
    cfg, params = zoo.load_params(path)
    models.check_working_size(cfg["name"], height, width, what=size_option)
    separate = bool(cfg.pop("separate_networks", False))
    graphdef, _ = models.abstract_init(cfg)
    if dtype is None:
        dtype = cfg.get("dtype")
    return Predictor(graphdef, params, height=height, width=width, dtype=dtype, model_cfg=cfg, separate=separate,
                     native=native, max_pixels=max_pixels, compile_mode=compile_mode, refine=refine,
                     symmetry=symmetry, polish=polish, executable_cache=executable_cache)


__all__ = ["Predictor", "load_predictor", "trained_working_size", "native_working_size", "NATIVE", "resize_notice",
           "to_rgb_float", "resize_images", "COMPILE_MODES", "compile_mode_for",
           "flow_to_input_resolution", "disparity_to_input_resolution", "map_to_input_resolution", "PAIR_KINDS",
           "input_size", "minimum_input_size", "SYMMETRY_MODES", "symmetric_estimate",
           "POLISH_MODES"]
