"""Confidence and occlusion maps from the model's own consistency checks.

The paper's losses already rest on two checks; at test time they say where a map can be trusted:

* flow: the forward-backward check (eq. 6). Pixel x of `a` maps to x + D(x) in `b`; the backward map D' of
  (b, a), read there, should bring it back: D(x) + D'(x + D(x)) = 0;
* disparity: the left-right check (eq. 9), the same test on the horizontal axis. The right image's disparity
  comes from the same network: the pair (right, left) flipped left-right is again a left -> right stereo pair
  (the flipped right image is its left view), so its disparity, flipped back, is the right view's.

For each pixel the check's residual is scored against the same threshold as in training (`ALPHA1`, `ALPHA2`):

    score = |D + W(D', D)|^2 / (ALPHA1 * (|D|^2 + |W(D', D)|^2) + ALPHA2)

so score <= 1 passes the check in training. The **occlusion** mask (True = no visible match in the other image)
is score > the check's threshold (`OCCLUSION_THRESHOLD`), or a match outside the other image (out of view). The
threshold depends on what the backward maps ran with (`CHECK_MODES`): maps that went through the same test-time
stages agree closely where both are right (threshold 2), while a plain network map beside a polished one also
differs by the polish's corrections, so the check must fail by more (threshold 16) before it means "occluded".

A check cannot see an error that both maps share; the commonest one is at motion and depth edges, which the
network (answering at a quarter of its working size) blurs over a few pixels in both directions alike. So the
**confidence** adds the map's own variation around each pixel, scored against the same threshold:

    edge = R^2 / (ALPHA1 * |D|^2 + ALPHA2),    R = the length of (max - min) of D's two components over the
                                                   (2 * EDGE_RADIUS + 1)^2 window around the pixel
    confidence = 2^-(score + EDGE_WEIGHT * edge),  halved for out-of-view matches

1 = consistent and away from any edge, 0.5 where the check's residual reaches training's threshold, towards 0
for maps that disagree by many times it; an out-of-view match (a check that cannot be made) counts half. Both maps
are computed at the working size and brought to the input resolution (`to_input_resolution`).

The backward maps cost one more prediction per pair; `Predictor` runs them with the test-time stages of its
`check` record (`CHECK_MODES`, `default_check`).
"""
from __future__ import annotations

import functools
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import geometry
from bridge_jax.resizing import _resize, map_to_input_resolution, map_to_size, resize_weights_align_corners
from bridge_jax.testtime import (FILL_MAX_DIFFERENCE, FILL_MAX_DIFFERENCE_STEREO, FILL_MAX_RAISE, FILL_OCCLUSION_REACH,
                                 FILL_OCCLUSION_STEP, TestTime)

ALPHA1 = 0.01
"""Relative part of the consistency threshold (px^2 per px^2 of motion), the paper's eq. 6 value."""
ALPHA2 = 0.5
"""Constant part of the consistency threshold, px^2 of the working size (eq. 6)."""
EDGE_RADIUS = 3
"""Half-width of the window the map's local variation is taken over (a 7 x 7 window at the working size)."""
EDGE_WEIGHT = 0.1
"""Weight of the map's local variation in the confidence, against the check's score (weight 1). This and
`EDGE_RADIUS` were chosen on selection frames: the smallest summed relative AUSE of flow and disparity, the
smallest radius (then weight) within 0.005 of it."""
OUT_OF_VIEW_FACTOR = 0.5
"""Confidence of a pixel whose match lies outside the other image is multiplied by this (its check cannot be
made, so it counts as failed: below 0.5, as an occluded pixel's)."""


def reverse_job(task: str, image_a: Any, image_b: Any) -> tuple[str, Any, Any]:
    """The job whose map is the backward map of (task, a, b): flow b -> a; for a rectified stereo pair (left a,
    right b) the pair (b, a) flipped left-right, itself a left -> right stereo pair (`backward_map` flips its
    map back)."""
    if task == "flow":
        return "flow", image_b, image_a
    return "stereo", np.ascontiguousarray(np.asarray(image_b)[:, ::-1]), np.ascontiguousarray(np.asarray(image_a)[:, ::-1])


def backward_map(task: str, reverse_map: np.ndarray) -> np.ndarray:
    """The working-size map `(H, W, 2)` of `reverse_job` -> the backward map D' in b's frame, b -> a, pixels.

    Stereo: the flipped pair's map (-d'(x'), 0) is the disparity d' of the flipped right image; flipped back,
    the right image's pixel x is found in the left image at x + d_R(x), so D' = (d_R, 0)."""
    if task == "flow":
        return np.asarray(reverse_map, np.float32)
    d_right = -np.asarray(reverse_map, np.float32)[:, ::-1, 0]
    return np.stack([d_right, np.zeros_like(d_right)], axis=-1)


def _length_sq(x):
    return jnp.sum(jnp.square(x), axis=-1)


@jax.jit
def backward_at_match(d_fw: jax.Array, d_bw: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The backward maps read where the forward maps send each pixel, and whether that lies outside the image.

    Args:
      d_fw: `(N, H, W, 2)` forward pixel maps D, a -> b.
      d_bw: `(N, H, W, 2)` backward pixel maps D', b -> a (in b's frame).
    Returns:
      D'(x + D(x)) `(N, H, W, 2)` (bilinear, border clamp) and out_of_view `(N, H, W)` bool (x + D(x) outside
      [0, W - 1] x [0, H - 1]), both in a's frame.
    """
    warped = geometry.warp(d_bw, d_fw)
    h, w = d_fw.shape[-3:-1]
    xs = jnp.arange(w, dtype=d_fw.dtype)[None, None, :] + d_fw[..., 0]
    ys = jnp.arange(h, dtype=d_fw.dtype)[None, :, None] + d_fw[..., 1]
    return warped, (xs < 0) | (xs > w - 1) | (ys < 0) | (ys > h - 1)


@jax.jit
def consistency_score(d_fw: jax.Array, d_bw: jax.Array) -> tuple[jax.Array, jax.Array]:
    """The consistency score `(N, H, W)` float32 of forward maps `d_fw` against backward maps `d_bw` (see the module
    docstring; <= 1: the check passes) and the out-of-view mask, both in a's frame (`backward_at_match`)."""
    warped, out_of_view = backward_at_match(d_fw, d_bw)   # D'(x + D(x))
    score = _length_sq(d_fw + warped) / (ALPHA1 * (_length_sq(d_fw) + _length_sq(warped)) + ALPHA2)
    return score, out_of_view


@functools.partial(jax.jit, static_argnames="radius")
def edge_score(d: jax.Array, radius: int = EDGE_RADIUS) -> jax.Array:
    """`(N, H, W)` the local variation of maps `d (N, H, W, 2)` (see the module docstring): the range of each
    component over the (2 * radius + 1)^2 window (clipped at the image's border), as a length, squared and
    divided by ALPHA1 * |D|^2 + ALPHA2."""
    window, pad = (1, 2 * radius + 1, 2 * radius + 1), ((0, 0), (radius, radius), (radius, radius))
    ranges = []
    for c in range(2):
        x = d[..., c]
        high = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, window, (1, 1, 1), pad)
        low = jax.lax.reduce_window(x, jnp.inf, jax.lax.min, window, (1, 1, 1), pad)
        ranges.append(high - low)
    return (jnp.square(ranges[0]) + jnp.square(ranges[1])) / (ALPHA1 * _length_sq(d) + ALPHA2)


def confidence_from_score(score: np.ndarray, out_of_view: np.ndarray, edge: Any = 0.0,
                          edge_weight: float = EDGE_WEIGHT) -> np.ndarray:
    """Confidence in [0, 1] (float32): 2^-(score + edge_weight * edge), times `OUT_OF_VIEW_FACTOR` out of view."""
    total = np.maximum(np.asarray(score, np.float32), 0.0) + edge_weight * np.maximum(np.asarray(edge, np.float32), 0.0)
    conf = np.exp2(-total)
    return np.where(out_of_view, OUT_OF_VIEW_FACTOR * conf, conf).astype(np.float32)


def occlusion_from_score(score: np.ndarray, out_of_view: np.ndarray, threshold: float = 1.0) -> np.ndarray:
    """Occlusion mask (bool, True = no visible match): the check fails (score > `threshold`, the check mode's
    `OCCLUSION_THRESHOLD`) or the match is out of view."""
    return (np.asarray(score) > threshold) | np.asarray(out_of_view, bool)


def to_input_resolution(score: np.ndarray, out_of_view: np.ndarray, height: int, width: int,
                        edge: Any = None, threshold: float = 1.0,
                        edge_weight: float = EDGE_WEIGHT) -> tuple[np.ndarray, np.ndarray]:
    """Working-size check score, out-of-view mask and edge score `(H, W)` -> (confidence, occlusion)
    `(height, width)` at the input resolution: the three resized bilinearly as the maps are (align_corners, the
    mask thresholded at 0.5), then `confidence_from_score` (with `edge_weight`) and `occlusion_from_score` (at
    `threshold`). `edge` None = 0."""
    score = np.asarray(score, np.float32)
    edge = np.zeros_like(score) if edge is None else np.asarray(edge, np.float32)
    oov = np.asarray(out_of_view, np.float32)
    h, w = score.shape
    if (h, w) != (height, width):
        wy, wx = resize_weights_align_corners(h, height), resize_weights_align_corners(w, width)
        planes = _resize(np.stack([score, oov, edge], -1), wy, wx)
        score, oov, edge = planes[..., 0], planes[..., 1], planes[..., 2]
    oov = oov > 0.5
    return confidence_from_score(score, oov, edge, edge_weight), occlusion_from_score(score, oov, threshold)


def checked_map(task: str, forward: np.ndarray, reverse_map: np.ndarray, height: int, width: int,
                threshold: float, *, radius: int = EDGE_RADIUS,
                edge_weight: float = EDGE_WEIGHT) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One pair's (prediction, confidence, occlusion) at the input resolution `height x width`.

    Args:
      task: "flow" or "stereo".
      forward: the pair's map `(H, W, 2)` at the size its last stage ran at (`Predictor.stage_maps`: the working
        size, or the input size where the polish ran there; a stereo map's vertical component is dropped: a
        stereo match stays on its row).
      reverse_map: the map of its `reverse_job` (`backward_map` turns it into D'), brought to the forward map's
        size first when it has another (`resizing.map_to_size`).
      threshold: the occlusion threshold (`OCCLUSION_THRESHOLD` of the check's mode).
      radius, edge_weight: the edge term's window and weight.
    Returns:
      the prediction as `resizing.map_to_input_resolution` gives it, confidence `(height, width)` float32,
      occlusion `(height, width)` bool.
    """
    if task == "stereo":
        forward = forward * np.array([1.0, 0.0], np.float32)
    if reverse_map.shape[:2] != forward.shape[:2]:
        # a map polished at the input size against a backward map of the working size (check mode "network"):
        # the check runs at the forward map's size, the prediction's own
        reverse_map = map_to_size(task, reverse_map, *forward.shape[:2])
    score, out_of_view = consistency_score(forward[None], backward_map(task, reverse_map)[None])
    edge = edge_score(forward[None], radius=radius)
    conf, occ = to_input_resolution(np.asarray(score[0]), np.asarray(out_of_view[0]), height, width,
                                    np.asarray(edge[0]), threshold, edge_weight=edge_weight)
    return map_to_input_resolution(task, forward, height, width), conf, occ


CHECK_MODES = ("network", "same")
"""What the backward maps of a check run with: "network" = one plain network call per reverse pair (no symmetry,
refinement or polish: about one eighth of `long`'s own stages, so the confidence costs little more than the
prediction), "same" = the prediction's own test-time stages (twice the prediction's cost; its occlusion masks
are sharper, since both maps went through the same stages)."""
OCCLUSION_THRESHOLD = {"network": 16.0, "same": 2.0}
"""The score above which a pixel is occluded, per check mode (see the module docstring); chosen on selection
frames (the best summed F1 score of the flow and disparity masks, the smallest threshold within 0.02 of it)."""
DEFAULT_CHECK = "network"
"""The check mode a predictor uses unless told otherwise. On the selection frames the two modes were chosen on,
the disagreement between the staged forward map and the plain backward one ranked disparity errors better than
the same stages both ways (and costs about 1.1x instead of 2x); the flow errors the other way round."""


# ----------------------------------------------------------------------------------------------------------
# The fill: the polish's "fill" step (`testtime.POLISH_MODES`), left-right for disparity, forward-backward for flow
# ----------------------------------------------------------------------------------------------------------

GUIDED_FILL_RADIUS = 7
"""Half-width of the window the flow fill (`guided_fill`) takes consistent neighbours from, px of the input
resolution. This and the two below were set once, before any score was looked at: a window about the size of
the network's own detail (it answers at a quarter of its working size), a colour tolerance of a few percent of
the range, a few rounds for occlusions a few tens of pixels wide."""
GUIDED_FILL_COLOUR_SIGMA = 0.08
"""Colour tolerance of the flow fill (RGB distance in [0, 1] units): a neighbour 0.08 away weighs exp(-1/2)."""
GUIDED_FILL_ROUNDS = 4
"""Rounds of the flow fill before the nearest-neighbour rest (`guided_fill`)."""


def left_right_difference(d_left: np.ndarray, d_right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """How far the two views' disparities disagree, per pixel of the left view.

    Left pixel (x, y) with disparity d_L is seen by the right camera at x - d_L; the right view's disparity
    there, d_R(x - d_L) (linear along the row, clamped at the row's ends), should bring it back.

    Args:
      d_left: `(H, W)` the left view's disparity, px (>= 0 for a sensible map).
      d_right: `(H, W)` the right view's disparity, px: right pixel x sees left pixel x + d_R(x).
    Returns:
      |d_L(x) - d_R(x - d_L(x))| `(H, W)` float32, and `(H, W)` bool: x - d_L(x) lies outside [0, W - 1]
      (the right camera does not see the pixel; its difference is then read at the clamped end).
    """
    d_left = np.asarray(d_left, np.float32)
    d_right = np.asarray(d_right, np.float32)
    if d_left.ndim != 2 or d_right.shape != d_left.shape:
        raise ValueError(f"left_right_difference: expected two (H, W) disparities of one shape, got "
                         f"{d_left.shape} and {d_right.shape}")
    # as pixel maps: left x goes to x - d_L (D = (-d_L, 0)), right x to x + d_R (D' = (d_R, 0)); d_R is read at
    # (x - d_L, y) by the forward-backward check's own reading (bilinear, border clamp: linear along the row)
    zero = np.zeros_like(d_left)
    at_match, out_of_view = backward_at_match(np.stack([-d_left, zero], -1)[None], np.stack([d_right, zero], -1)[None])
    return np.abs(d_left - np.asarray(at_match)[0, ..., 0]).astype(np.float32), np.asarray(out_of_view)[0]


def background_fill(disp: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Fill holes like the KITTI devkit's background interpolation (`interpolateBackground`): row by row, each
    run of invalid pixels between two valid ones takes the smaller (farther) of their two disparities, a run
    touching the row's left or right end takes its one valid neighbour; then a row without any valid pixel takes,
    column by column, the filled row nearest above or below it (the smaller of the two where it lies between
    filled rows: the devkit fills only those above the first and below the last). No valid pixel at all: 0.

    Args:
      disp: ``(H, W)`` disparity px; valid: ``(H, W)`` bool.
    Returns:
      ``(H, W)`` float32, dense.
    """
    disp = np.asarray(disp, np.float32)
    valid = np.asarray(valid, bool)
    if disp.ndim != 2 or valid.shape != disp.shape:
        raise ValueError(f"background_fill: expected (H, W) disparity and mask of one shape, got "
                         f"{disp.shape} and {valid.shape}")
    h, w = disp.shape
    rows = np.arange(h)[:, None]
    cols = np.broadcast_to(np.arange(w)[None, :], (h, w))
    # the nearest valid column at or left of each pixel (-1: none), and at or right of it (w: none)
    left_idx = np.maximum.accumulate(np.where(valid, cols, -1), axis=1)
    right_idx = np.minimum.accumulate(np.where(valid, cols, w)[:, ::-1], axis=1)[:, ::-1]
    left = np.where(left_idx >= 0, disp[rows, np.clip(left_idx, 0, w - 1)], np.inf)
    right = np.where(right_idx < w, disp[rows, np.clip(right_idx, 0, w - 1)], np.inf)
    out = np.where(valid, disp, np.minimum(left, right))  # one end missing: min picks the other one
    row_ok = valid.any(axis=1)
    if not row_ok.any():
        return np.zeros((h, w), np.float32)
    if not row_ok.all():  # the same two scans along the columns, over whole rows
        r = np.arange(h)
        above = np.maximum.accumulate(np.where(row_ok, r, -1))
        below = np.minimum.accumulate(np.where(row_ok, r, h)[::-1])[::-1]
        up = np.where((above >= 0)[:, None], out[np.clip(above, 0, h - 1)], np.inf)
        down = np.where((below < h)[:, None], out[np.clip(below, 0, h - 1)], np.inf)
        out = np.where(row_ok[:, None], out, np.minimum(up, down))
    return out.astype(np.float32)


def widen_occlusion_runs(failed: np.ndarray, d_left: np.ndarray, step: float = FILL_OCCLUSION_STEP,
                         reach: int = FILL_OCCLUSION_REACH) -> np.ndarray:
    """`failed` with each occlusion run widened `reach` px to its left.

    A run of failing pixels in a row of the left view whose passing neighbour on the right is more than `step` px
    nearer than its passing neighbour on the left lies where a left view's occlusions lie: background left of a
    nearer surface's left edge, which the right camera cannot see. A network's map climbs from the background to
    the nearer surface over a few pixels, and the lower part of that climb passes the check (the right view's map
    climbs alike), so the run's left neighbour already carries part of the nearer disparity and the fill would
    take it as the run's background. Widened to its left, the run takes its background from below the climb and
    brings the climb down with it. Runs that touch the row's end are left as they are.

    Args:
      failed: `(H, W)` bool, the pixels that fail the left-right check.
      d_left: `(H, W)` left view's disparity px.
      step: the jump in disparity across the run that makes it an occlusion, px.
      reach: how far the run is widened to its left, px.
    Returns:
      `(H, W)` bool, `failed` and the pixels the widening adds.
    """
    failed = np.asarray(failed, bool)
    width = failed.shape[1]
    before = np.pad(failed, ((0, 0), (1, 0)))[:, :-1]  # the pixel to the left fails (False at the row's start)
    after = np.pad(failed, ((0, 0), (0, 1)))[:, 1:]
    # runs in row-major order: their first and last pixels pair up one to one
    rows, first = np.nonzero(failed & ~before)
    _, last = np.nonzero(failed & ~after)
    inner = (first > 0) & (last < width - 1)
    rows, first, last = rows[inner], first[inner], last[inner]
    occlusion = d_left[rows, last + 1] > d_left[rows, first - 1] + step
    rows, first = rows[occlusion], first[occlusion]
    out = failed.copy()
    for k in range(1, reach + 1):
        ok = first - k >= 0
        out[rows[ok], first[ok] - k] = True
    return out


def left_right_fill(d_left: np.ndarray, d_right: np.ndarray, max_difference: float = FILL_MAX_DIFFERENCE_STEREO,
                    max_raise: float = FILL_MAX_RAISE, occlusion_reach: int = FILL_OCCLUSION_REACH
                    ) -> tuple[np.ndarray, np.ndarray]:
    """The left view's disparity with the pixels that fail the left-right check given their row's background
    (the step that makes a semi-global matcher's maps strong, here on a network's two maps).

    A pixel fails when `left_right_difference` exceeds `max_difference` px or its match lies outside the right
    image; a run of failing pixels with a nearer surface on its right is widened `occlusion_reach` px to its left
    first (`widen_occlusion_runs`). Each run of these pixels in a row has a background, the smaller (farther)
    disparity of its two remaining ends (`background_fill`, the KITTI devkit's interpolation; a run touching the
    row's end: its one end), which replaces the run's pixels:

    * out of view (x - d outside the right image: the strip along the left border the right camera does not
      see): always, nothing can be matched there;
    * in view, where the background is farther than the pixel (a nearer surface's disparity bled over background
      it hides in the right view: the error the check exists for) or nearer by less than `max_raise` px (a
      mismatch, smoothed over). A background `max_raise` px or more nearer than the pixel says that both ends of
      its run lie on a nearer surface than it claims to be, as where a floor is seen through a gap of a nearer
      object; unlike a matcher's hole, a network's failing pixel has a value of its own, and it keeps it.

    Args:
      d_left, d_right: `(H, W)` disparities of the left and the right view, px (`left_right_difference`).
      max_difference: the check's tolerance, px (`testtime.FILL_MAX_DIFFERENCE_STEREO`).
      max_raise: how much nearer than an in-view failing pixel its background may be and still replace it, px
        (`numpy.inf`: always, the devkit's rule for a matcher's holes).
      occlusion_reach: how far an occlusion run is widened to its left, px (0: not at all).
    Returns:
      (filled `(H, W)` float32, failed `(H, W)` bool: the pixels that fail the check; the filled map differs from
      `d_left` only there and at the pixels the widening adds).
    """
    difference, out_of_view = left_right_difference(d_left, d_right)
    failed = (difference > max_difference) | out_of_view
    d_left = np.asarray(d_left, np.float32)
    treated = widen_occlusion_runs(failed, d_left, reach=occlusion_reach)  # reach 0: `failed` as it is
    background = background_fill(d_left, ~treated)
    replace = out_of_view | (treated & (background < d_left + max_raise))
    return np.where(replace, background, d_left).astype(np.float32), failed


def forward_backward_difference(flow: np.ndarray, backward: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How far a flow and its backward flow disagree, per pixel of the first image.

    Pixel x of `a` is found at x + F(x) in `b`; the backward flow B (b -> a, in b's frame), read there, should
    bring it back: F(x) + B(x + F(x)) = 0.

    Args:
      flow: `(H, W, 2)` flow F from a to b, px (x, y).
      backward: `(H, W, 2)` flow B from b to a, px, of the same size.
    Returns:
      |F(x) + B(x + F(x))| `(H, W)` float32; B(x + F(x)) `(H, W, 2)` float32 (bilinear, clamped at the border);
      `(H, W)` bool: x + F(x) lies outside the image (b does not see the pixel).
    """
    flow = np.asarray(flow, np.float32)
    backward = np.asarray(backward, np.float32)
    if flow.ndim != 3 or flow.shape[-1] != 2 or backward.shape != flow.shape:
        raise ValueError(f"forward_backward_difference: expected two (H, W, 2) flows of one shape, got "
                         f"{flow.shape} and {backward.shape}")
    at_match, out_of_view = (np.asarray(x[0]) for x in backward_at_match(flow[None], backward[None]))
    return np.sqrt(np.sum(np.square(flow + at_match), -1)).astype(np.float32), at_match, out_of_view


def nearest_fill(values: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """`values` `(H, W, C)` with each invalid pixel given the value of the nearest valid one (Euclidean distance,
    OpenCV's 5x5 approximation; ties as OpenCV breaks them). No valid pixel: unchanged."""
    import cv2  # here, not at the top: the checks above run without OpenCV
    valid = np.asarray(valid, bool)
    if valid.all() or not valid.any():
        return values
    _, labels = cv2.distanceTransformWithLabels((~valid).astype(np.uint8), cv2.DIST_L2, 5,
                                                labelType=cv2.DIST_LABEL_PIXEL)
    # labels number the valid pixels (the zeros of the input) from 1 in raster order
    ys, xs = np.nonzero(valid)
    return values[ys[labels - 1], xs[labels - 1]]


def guided_fill(values: np.ndarray, valid: np.ndarray, image: np.ndarray, radius: int = GUIDED_FILL_RADIUS,
                colour_sigma: float = GUIDED_FILL_COLOUR_SIGMA, rounds: int = GUIDED_FILL_ROUNDS) -> np.ndarray:
    """Fill the invalid pixels of `values` from the valid pixels around them that look like them.

    Each invalid pixel x takes the average of the valid values in the (2 radius + 1)^2 window around it, weighted
    by exp(-|I(y) - I(x)|^2 / (2 colour_sigma^2) - |y - x|^2 / (2 (radius / 2)^2)): a pixel hidden behind a
    moving object takes the motion of the surface it belongs to (its colour), not the object's. A round fills
    every invalid pixel whose weights add up to more than 1e-6; the pixels it filled count as valid in the next round,
    so a hole `rounds * radius` px wide closes from its sides. What is left after `rounds` takes its nearest valid
    pixel's value (`nearest_fill`).

    Args:
      values: `(H, W, C)` float maps (flow: C = 2).
      valid: `(H, W)` bool, True = keep.
      image: `(H, W, 3)` float32 RGB in [0, 1], the image the values belong to.
    Returns:
      `(H, W, C)` float32, dense (unchanged when nothing or everything is valid).
    """
    out = np.array(values, np.float32)
    ok = np.array(valid, bool)
    image = np.asarray(image, np.float32)
    if out.ndim != 3 or ok.shape != out.shape[:2] or image.shape[:2] != out.shape[:2]:
        raise ValueError(f"guided_fill: expected (H, W, C) values with an (H, W) mask and an (H, W, 3) image, got "
                         f"{out.shape}, {ok.shape} and {image.shape}")
    if ok.all() or not ok.any():
        return out
    h, w = ok.shape
    spatial = 2.0 * (radius / 2.0) ** 2
    for _ in range(rounds):
        ys, xs = np.nonzero(~ok)
        if len(ys) == 0:
            break
        num = np.zeros((len(ys), out.shape[-1]), np.float64)
        den = np.zeros(len(ys), np.float64)
        colour = image[ys, xs]
        for dy in range(-radius, radius + 1):
            yy = ys + dy
            in_rows = (yy >= 0) & (yy < h)
            yy = np.clip(yy, 0, h - 1)
            for dx in range(-radius, radius + 1):
                xx = xs + dx
                inside = in_rows & (xx >= 0) & (xx < w)
                xx = np.clip(xx, 0, w - 1)
                near = np.sum(np.square(image[yy, xx] - colour), -1)
                weight = (inside & ok[yy, xx]) * np.exp(-near / (2.0 * colour_sigma ** 2)
                                                        - (dx * dx + dy * dy) / spatial)
                num += weight[:, None] * out[yy, xx]
                den += weight
        # a pixel whose window holds no valid pixel that looks like it (every weight below ~1e-6: a colour
        # distance above ~0.35 even next to it) waits for a later round, or the nearest-pixel rest
        got = den > 1e-6
        out[ys[got], xs[got]] = (num[got] / den[got, None]).astype(np.float32)
        ok[ys[got], xs[got]] = True
    return nearest_fill(out, ok)


def forward_backward_fill(flow: np.ndarray, backward: np.ndarray, image: np.ndarray,
                          max_difference: float = FILL_MAX_DIFFERENCE) -> tuple[np.ndarray, np.ndarray]:
    """The flow with the pixels that fail the forward-backward check replaced from their consistent neighbours
    of the same look (`guided_fill`).

    A pixel fails when its match lies outside the second image, or when
    |F + B(x + F)|^2 > ALPHA1 (|F|^2 + |B(x + F)|^2) + max_difference^2
    (`forward_backward_difference`): the paper's check (eq. 6) with its relative part (a flow of 30 px may be off
    by 3 px before it fails) and, in place of its constant part of the working size, the fill's tolerance in
    pixels of the input resolution (`testtime.FILL_MAX_DIFFERENCE`; the left-right fill's is
    `testtime.FILL_MAX_DIFFERENCE_STEREO`).

    Args:
      flow: `(H, W, 2)` flow a -> b, px; backward: `(H, W, 2)` flow b -> a, px (the same stages' map of (b, a)).
      image: `(H, W, 3)` float32 RGB in [0, 1], the first image a.
    Returns:
      (filled `(H, W, 2)` float32, failed `(H, W)` bool: the pixels that were replaced).
    """
    flow = np.asarray(flow, np.float32)
    difference, at_match, out_of_view = forward_backward_difference(flow, backward)
    limit = ALPHA1 * (np.sum(np.square(flow), -1) + np.sum(np.square(at_match), -1)) + max_difference ** 2
    failed = (np.square(difference) > limit) | out_of_view
    return guided_fill(flow, ~failed, image), failed


def right_view_disparity(reverse_prediction: np.ndarray) -> np.ndarray:
    """The right view's disparity `(H, W)` from the prediction of a stereo pair's `reverse_job` (the pair
    swapped and flipped left-right, a left -> right pair itself) at the input resolution: flipped back."""
    return np.ascontiguousarray(np.asarray(reverse_prediction, np.float32)[:, ::-1])


def check_record(mode: str, test_time: TestTime, option: str = "check mode") -> TestTime:
    """The `TestTime` the backward maps run with under check `mode` (`CHECK_MODES`) for a prediction running
    `test_time`; ValueError naming `option` for an unknown mode."""
    if mode not in CHECK_MODES:
        raise ValueError(f"{option} {mode!r}: expected one of {', '.join(CHECK_MODES)}")
    return test_time if mode == "same" else TestTime()


def check_mode(check: TestTime, test_time: TestTime) -> str:
    """The mode (`CHECK_MODES`) of backward maps run with `check` beside forward maps run with `test_time`:
    "same" when the two records are one (both maps went through the same stages), else "network"."""
    return "same" if check == test_time else "network"


def default_check(test_time: TestTime) -> TestTime:
    """The record the backward maps run with unless a predictor's `check` says otherwise:
    `check_record(DEFAULT_CHECK, test_time)`."""
    return check_record(DEFAULT_CHECK, test_time)


__all__ = ["ALPHA1", "ALPHA2", "EDGE_RADIUS", "EDGE_WEIGHT", "OUT_OF_VIEW_FACTOR", "reverse_job", "backward_map",
           "consistency_score", "edge_score", "CHECK_MODES", "DEFAULT_CHECK", "OCCLUSION_THRESHOLD", "check_record", "check_mode",
           "confidence_from_score", "occlusion_from_score", "to_input_resolution", "checked_map", "default_check"]
