"""Test-time photometric polish: the network's map improved locally at the working resolution.

The network answers at a quarter of its working size, and its maps come up to full size by bilinear
interpolation, smoothed by the training's smoothness prior. Two errors follow that a per-pixel look at the
images themselves can correct, with the same photometric criterion the network was trained on and no
ground truth:

1. **Bled motion boundaries** (`select_candidates`). Around an object that moves differently from its
   background the network's map blends the two motions over 10-30 pixels. The right motion is usually the
   map's own value a few pixels further into the region. Each pixel therefore tries its map's values 4, 8,
   16 and 24 pixels away in the 8 directions, scores each by the mean absolute difference of the
   locally normalised images over a (2r+1)^2 window (`matching_cost`), and takes the best candidate only if
   it costs at most `ratio` times its own value's cost, less a small margin (so that flat, textureless or
   occluded regions, where every candidate scores alike, keep the network's value). One candidate round, no
   iteration: a PatchMatch propagation step seeded by the network.
2. **Sub-pixel noise** (`lucas_kanade`). A few Gauss-Newton steps of windowed Lucas-Kanade on the residual
   between `a` and `b` warped by the map, each step at most one pixel per component, taken per pixel only
   where it lowers the windowed photometric error. Stereo rows solve for the horizontal component alone.

Both compare locally normalised grey images (zero mean, unit contrast over a 15x15 window,
`normalise_locally`): gain, offset and gamma differences between two cameras then cancel to first order,
which raw brightness constancy would read as motion. `b` is normalised *after* it is warped into `a`'s frame
(`warped_normalised`), so that both windows cover the same piece of the scene: normalised in its own frame,
`b`'s windows near its border are reflected where `a`'s are not, which biased every pixel whose match lies
near that border (on a hand-built translation, 0.21 px against 0.06 px this way).

Measured (experiments/results/real_images.md, 2026-12-04): every real-image number of both shipped models
improves; `long`'s photo flow 1.74 -> 1.46 px (DIS 1.21) and Motorcycle D1 14.6 -> 12.6 %, `demo`'s Motorcycle
D1 34.1 -> 20.3 % and photo flow 4.25 -> 2.72 px. The numbers are then the network's answer corrected by a local
search, no longer the network's alone; `polish="none"` gives those.
"""
from __future__ import annotations

from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import geometry

POLISH_MODES = ("none", "photometric")
"""Test-time polish of a predictor's maps: "none", or "photometric" (`polish_maps`)."""

NORMALISE_RADIUS = 7
"""Half size of the window `normalise_locally` takes the mean and contrast over (15x15)."""
CONTRAST_FLOOR = 0.05
"""Added to the local contrast before dividing (grey levels in [0, 1]): flat regions are not blown up into noise."""
CANDIDATE_DISTANCES = (4, 8, 16, 24)
"""How far (working pixels) `select_candidates` looks for another value of the map, in each of 8 directions."""
COST_RADIUS = 4
"""Half size of the window `matching_cost` averages over (9x9)."""
ACCEPT_RATIO = 0.7
"""A candidate replaces a pixel's own value only at no more than this share of its cost..."""
ACCEPT_MARGIN = 1e-4
"""...and at least this much below it (normalised grey levels): on a flat image every cost is float rounding
noise (~1e-7), and no ratio of two rounding noises means anything. A margin of 0.01 cost `long` 0.02 px on the
photo flow check (2026-12-04): weakly textured windows cost only a few hundredths."""
LK_STEPS = 3
"""Gauss-Newton steps of `lucas_kanade`."""
LK_SIGMA = 2.5
"""Standard deviation (pixels) of `lucas_kanade`'s Gaussian window."""
LK_PRIOR = 0.01
"""Tikhonov term added to the 2x2 normal equations of `lucas_kanade` (normalised grey levels squared):
keeps the step small where the window has no texture in some direction."""


def check_polish(polish: Any, option: str = "polish") -> str:
    """`polish` if it is one of `POLISH_MODES`, else a ValueError naming `option`."""
    if polish not in POLISH_MODES:
        raise ValueError(f"{option} {polish!r}: expected one of {', '.join(POLISH_MODES)}")
    return polish


# ------------------------------------------------------------------------------------------ filters
def _separable(x: jax.Array, taps: np.ndarray) -> jax.Array:
    """`(N, H, W)` filtered by the 1-D kernel `taps` along H and then W, edges reflected (no new dark border)."""
    r = len(taps) // 2
    k = jnp.asarray(taps, x.dtype)
    y = jnp.pad(x, ((0, 0), (r, r), (r, r)), mode="reflect")
    h, w = x.shape[1:]
    y = sum(k[i] * y[:, i:i + h, :] for i in range(len(taps)))
    return sum(k[i] * y[:, :, i:i + w] for i in range(len(taps)))


def box_filter(x: jax.Array, radius: int) -> jax.Array:
    """Mean over the (2r+1)^2 window of each pixel of `(N, H, W)`, edges reflected."""
    return _separable(x, np.full(2 * radius + 1, 1.0 / (2 * radius + 1), np.float32))


def gaussian_filter(x: jax.Array, sigma: float) -> jax.Array:
    """`(N, H, W)` smoothed by a normalised Gaussian of `sigma` pixels (truncated at 2 sigma), edges reflected."""
    r = int(np.ceil(2 * sigma))
    t = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    return _separable(x, (t / t.sum()).astype(np.float32))


def normalise_locally(grey: jax.Array, radius: int = NORMALISE_RADIUS, floor: float = CONTRAST_FLOOR) -> jax.Array:
    """`(N, H, W)` grey image minus its local mean, over its local contrast (std) plus `floor`."""
    centred = grey - box_filter(grey, radius)
    return centred / (jnp.sqrt(box_filter(centred * centred, radius)) + floor)


def gradients(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Central differences of `(N, H, W)` along W and H (one-sided half steps at the edges: edge replicated)."""
    px = jnp.pad(x, ((0, 0), (0, 0), (1, 1)), mode="edge")
    py = jnp.pad(x, ((0, 0), (1, 1), (0, 0)), mode="edge")
    return 0.5 * (px[:, :, 2:] - px[:, :, :-2]), 0.5 * (py[:, 2:] - py[:, :-2])


def _warp_grey(image: jax.Array, maps: jax.Array) -> jax.Array:
    """`(N, H, W)` image sampled at x + map (bilinear, border clamp; `geometry.warp`)."""
    return geometry.warp(image[..., None], maps)[..., 0]


def warped_normalised(grey_b: jax.Array, maps: jax.Array) -> jax.Array:
    """`(N, H, W)` grey image `b` warped into `a`'s frame by `maps`, then normalised there (`normalise_locally`)."""
    return normalise_locally(_warp_grey(grey_b, maps))


# ------------------------------------------------------------------------------ candidate selection
def matching_cost(norm_a: jax.Array, grey_b: jax.Array, maps: jax.Array, radius: int = COST_RADIUS) -> jax.Array:
    """Windowed mean |norm(a) - norm(warp(b, map))| (`(N, H, W)`: `a` normalised, `b` grey; `maps (N, H, W, 2)`)."""
    return box_filter(jnp.abs(warped_normalised(grey_b, maps) - norm_a), radius)


def _shifted(maps: jax.Array, dx: jax.Array, dy: jax.Array) -> jax.Array:
    """`maps` read (dx, dy) pixels away: out[y, x] = maps[clip(y + dy), clip(x + dx)]."""
    h, w = maps.shape[1:3]
    rows = jnp.clip(jnp.arange(h) + dy, 0, h - 1)
    cols = jnp.clip(jnp.arange(w) + dx, 0, w - 1)
    return maps[:, rows][:, :, cols]


def candidate_offsets(distances=CANDIDATE_DISTANCES) -> np.ndarray:
    """`(8 * len(distances), 2)` int (dx, dy): each distance in the 8 directions of the compass."""
    dirs = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)]
    return np.array([(ux * d, uy * d) for d in distances for ux, uy in dirs], np.int32)


def select_candidates(norm_a: jax.Array, grey_b: jax.Array, maps: jax.Array, mask: jax.Array, *,
                      distances=CANDIDATE_DISTANCES, radius: int = COST_RADIUS,
                      ratio: float = ACCEPT_RATIO, margin: float = ACCEPT_MARGIN) -> jax.Array:
    """Each pixel's map value replaced by the best of its neighbours' (`candidate_offsets`) where that one
    matches clearly better (cost < `ratio` x its own - `margin`; then the cheapest wins).

    Args:
      norm_a: `(N, H, W)` grey image `a`, locally normalised (`normalise_locally`).
      grey_b: `(N, H, W)` grey image `b` (normalised after each warp, `warped_normalised`).
      maps: `(N, H, W, 2)` pixel maps a -> b.
      mask: `(N, 1, 1, 2)` 1 for the components a row keeps (stereo rows: (1, 0)).
    Returns:
      `(N, H, W, 2)` maps.
    """
    own = matching_cost(norm_a, grey_b, maps, radius)

    def try_one(carry, offset):
        best_cost, best = carry
        cand = _shifted(maps, offset[0], offset[1]) * mask
        cost = matching_cost(norm_a, grey_b, cand, radius)
        better = cost < best_cost
        return (jnp.where(better, cost, best_cost), jnp.where(better[..., None], cand, best)), None

    (_, best), _ = jax.lax.scan(try_one, (own * ratio - margin, maps), jnp.asarray(candidate_offsets(distances)))
    return best


# ----------------------------------------------------------------------------------- Lucas-Kanade
def lucas_kanade(norm_a: jax.Array, grey_b: jax.Array, maps: jax.Array, keep_vertical: jax.Array, *,
                 steps: int = LK_STEPS, sigma: float = LK_SIGMA, prior: float = LK_PRIOR) -> jax.Array:
    """Windowed Lucas-Kanade steps on the residual of `maps`.

    With I_t = norm(warp(b, D)) - norm(a) and the mean of both images' gradients g = (g_x, g_y), the step d solves
    (sum w g g^T + prior I) d = -sum w g I_t over a Gaussian window w (stereo rows: d_x = -sum w g_x I_t /
    (sum w g_x^2 + prior), d_y = 0). Each component is clipped to [-1, 1] (the linearisation holds about a
    pixel) and a pixel takes its step only if the windowed squared residual goes down.

    Args:
      norm_a: `(N, H, W)` grey image `a`, locally normalised.
      grey_b: `(N, H, W)` grey image `b` (normalised after each warp, `warped_normalised`).
      maps: `(N, H, W, 2)` pixel maps a -> b.
      keep_vertical: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows.
    Returns:
      `(N, H, W, 2)` maps.
    """
    ax, ay = gradients(norm_a)
    flow_row = (keep_vertical > 0.5)[:, None, None]
    win = lambda x: gaussian_filter(x, sigma)

    def step(_, carry):
        d, warped = carry
        it = warped - norm_a
        bx, by = gradients(warped)
        gx, gy = 0.5 * (ax + bx), 0.5 * (ay + by)
        sxx, sxy, syy = win(gx * gx) + prior, win(gx * gy), win(gy * gy) + prior
        sxt, syt = win(gx * it), win(gy * it)
        det = sxx * syy - sxy * sxy
        du = jnp.where(flow_row, -(syy * sxt - sxy * syt) / det, -sxt / sxx)
        dv = jnp.where(flow_row, -(sxx * syt - sxy * sxt) / det, 0.0)
        new = d + jnp.clip(jnp.stack([du, dv], -1), -1.0, 1.0)
        new_warped = warped_normalised(grey_b, new)
        better = win((new_warped - norm_a) ** 2) < win(it * it)
        return jnp.where(better[..., None], new, d), jnp.where(better, new_warped, warped)

    out, _ = jax.lax.fori_loop(0, steps, step, (maps, warped_normalised(grey_b, maps)))
    return out


def polish_maps(pairs: jax.Array, maps: jax.Array, keep_vertical: jax.Array) -> jax.Array:
    """The "photometric" polish: `select_candidates`, then `lucas_kanade`.

    Args:
      pairs: `(N, H, W, 6)` = [image a, image b], RGB in [0, 1] at the working size.
      maps: `(N, H, W, 2)` working-pixel maps a -> b (the network's, refined and averaged as asked).
      keep_vertical: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows (their vertical component stays 0).
    Returns:
      `(N, H, W, 2)` polished maps.
    """
    pairs, maps = pairs.astype(jnp.float32), maps.astype(jnp.float32)
    keep_vertical = keep_vertical.astype(jnp.float32)
    norm_a = normalise_locally(pairs[..., :3].mean(-1))
    grey_b = pairs[..., 3:].mean(-1)
    mask = jnp.stack([jnp.ones_like(keep_vertical), keep_vertical], -1)[:, None, None, :]
    maps = select_candidates(norm_a, grey_b, maps * mask, mask)
    return lucas_kanade(norm_a, grey_b, maps, keep_vertical)
