"""`pwc_lite`: a small correlation network for stereo and flow pairs alike (beyond the paper).

The paper's encoder-decoder (`resnet_md`) has to learn matching from concatenated images; even supervised it
hardly beats a mean flow field. Unsupervised flow methods that work (UFlow, ARFlow, SMURF) all match through a
local cost volume on normalised features, coarse to fine. This model does that with few parameters, so it runs
on a laptop CPU, and outputs exactly what the cycle loss expects: `{"px", "frac"}` at 4 scales.

For a pair `(N, H, W, 6)` = [image_a, image_b] in [0, 1]:

1. **Feature pyramid** (shared by both images): per level l = 1..L a stride-2 3x3 conv and a 3x3 conv,
   LeakyReLU(0.1), widths `pyramid[l-1]`. The number of levels follows the input size
   (`pyramid_levels`): as many as fit with the coarsest level at least 4x8 (64x128: L = 4, 256x512: L = 6),
   capped by `len(pyramid)`; at least 3 (the coarsest output scale is H/8).
2. **Coarse to fine**, levels L..`finest_level`: image_b's features are warped by the level above's flow,
   upsampled x2 and doubled, i.e. in pixels of this level, which are the units the loss trains scale s in
   (scale s = level s). Both feature maps are normalised together (`normalize_features`), the cost volume is
   their channel-mean correlation over a (2r+1)^2 window (`radius` r, zero outside the image), LeakyReLU.
   The **one estimator shared by all levels** sees [cost volume, 1x1 projection of image_a's features,
   upsampled flow (+ coordinates)] and predicts a residual: flow_l = up(flow_{l+1}) + estimate.
3. A small **dilated context network** refines the finest level's flow residually.

Outputs: scale s (0..3) is level s's flow for s >= finest_level (the finest one refined), the refined finest
flow bilinearly upsampled by 2^(finest_level - s) (and multiplied by it) for finer scales; px in pixels of
scale s, frac = px / (W_s, H_s). Nothing is bounded (no tanh): matches of any size are representable.

`coords=True` appends normalised pixel coordinates (x, y in [-1, 1], `coordinates.coordinate_channels`) to each image
before the pyramid and to the estimator's input: under ego-motion flow depends on the position in the image,
which a convolution alone cannot see. Init: kaiming-normal weights and zero biases; the flow outputs start at
zero (`head_init="zeros"`, the default) so every map starts at the zero-motion solution.
"""
from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
from flax import nnx

from bridge_jax import geometry
from bridge_jax.models.coordinates import coordinate_channels, with_coordinates
from bridge_jax.models.layers import (Conv, ConvLeaky, check_input_shape, fill_config, leaky_relu,
                                      pixel_and_fraction_maps)
from bridge_jax.models.pwcnet import correlation

DEFAULT_CONFIG = {
    "name": "pwc_lite",
    "pyramid": [16, 32, 32, 48, 64, 64],
    "feature_width": 32,
    "radius": 4,
    "estimator": [64, 48, 32],
    "context": [48, 48, 32],
    "dilations": [1, 2, 4],
    "finest_level": 2,
    "coords": False,
    "head_init": "zeros",
}
"""`pyramid`: widths of levels 1..(at most) len(pyramid); `feature_width`: the per-level 1x1 projection of
image_a's features that the shared estimator sees; `radius`: the cost volume's search radius (pixels of each
level); `estimator` / `context`: conv widths (context with `dilations`); `finest_level`: the finest level the
estimator runs at (1 or 2; the finer output scales are its upsampled flow)."""
HEAD_PREFIXES = ("estimator_flow", "context_flow")
HEAD_INITS = ("zeros", "kaiming_normal")
MULTIPLE = 8
"""H and W must be multiples of 8 (output scale 3 is H/8); `pyramid_levels` decides how deep the pyramid goes."""
MIN_COARSEST = (4, 8)
MIN_LEVELS = 3


def pyramid_levels(height: int, width: int, max_levels: int) -> int:
    """Number of pyramid levels for an input size: the largest L <= max_levels whose level H/2^L x W/2^L is
    exact (H, W divisible by 2^L) and at least 4x8. Raises ValueError when that is fewer than 3 levels."""
    levels = 0
    for lvl in range(1, max_levels + 1):
        f = 2 ** lvl
        if height % f or width % f or height // f < MIN_COARSEST[0] or width // f < MIN_COARSEST[1]:
            break
        levels = lvl
    if levels < MIN_LEVELS:
        raise ValueError(f"working size {height}x{width} (height x width) is too small for pwc_lite: it needs "
                         f"{MIN_LEVELS} pyramid levels with the coarsest at least {MIN_COARSEST[0]}x"
                         f"{MIN_COARSEST[1]}, i.e. at least 32x64 in multiples of 8")
    return levels


def normalize_features(f1: jax.Array, f2: jax.Array, eps: float = 1e-6) -> tuple[jax.Array, jax.Array]:
    """Centre and scale the two feature maps of each pair together (UFlow's normalisation before the cost
    volume): per pair, mean and variance over both images, all pixels and channels.

    Args:
      f1, f2: `(N, H, W, C)`.
    Returns:
      `((f1 - mu) / sigma, (f2 - mu) / sigma)`, sigma = sqrt(var + eps), mu and var per pair n.
    """
    both = jnp.stack([f1, f2], axis=1).astype(jnp.float32)  # (N, 2, H, W, C)
    mu = jnp.mean(both, axis=(1, 2, 3, 4), keepdims=True)
    var = jnp.mean(jnp.square(both - mu), axis=(1, 2, 3, 4), keepdims=True)
    out = ((both - mu) * jax.lax.rsqrt(var + eps)).astype(f1.dtype)
    return out[:, 0], out[:, 1]


def cost_volume(f1: jax.Array, f2: jax.Array, radius: int) -> jax.Array:
    """`(N, H, W, (2r+1)^2)`: channel `(dy + r)(2r + 1) + (dx + r)` is mean_c f1[y, x] * f2[y + dy, x + dx]
    (f2 zero outside the image), on features normalised by `normalize_features`."""
    f1, f2 = normalize_features(f1, f2)
    return correlation(f1, f2, radius)


def upsample_flow2x(flow: jax.Array) -> jax.Array:
    """Flow of level l+1 in level-(l+1) pixels -> level l (twice the size) in level-l pixels.

    Bilinear x2 with half-pixel centres and edge replication (taps 3/4, 1/4; the same as `jax.image.resize`
    "linear"), values doubled. `(N, h, w, 2) -> (N, 2h, 2w, 2)`.
    """
    def up(x, axis):
        n = x.shape[axis]
        prev = jnp.concatenate([jax.lax.slice_in_dim(x, 0, 1, axis=axis),
                                jax.lax.slice_in_dim(x, 0, n - 1, axis=axis)], axis=axis)
        nxt = jnp.concatenate([jax.lax.slice_in_dim(x, 1, n, axis=axis),
                               jax.lax.slice_in_dim(x, n - 1, n, axis=axis)], axis=axis)
        even, odd = 0.75 * x + 0.25 * prev, 0.75 * x + 0.25 * nxt
        out = jnp.stack([even, odd], axis=axis + 1)
        return out.reshape(x.shape[:axis] + (2 * n,) + x.shape[axis + 1:])

    return 2.0 * up(up(flow, 1), 2)


class PWCLite(nnx.Module):
    """See the module docstring. `__call__(pair (N, H, W, 6)) -> {"px": (s0..s3), "frac": (s0..s3)}`."""

    def __init__(self, config: Mapping, *, rngs: nnx.Rngs):
        pyr, est, ctx, dil = (list(config[k]) for k in ("pyramid", "estimator", "context", "dilations"))
        self.radius = int(config["radius"])
        self.coords = bool(config["coords"])
        self.finest = int(config["finest_level"])
        self.max_levels = len(pyr)
        extra = 2 if self.coords else 0
        cin = 3 + extra
        for lvl, width in enumerate(pyr, start=1):
            setattr(self, f"pyramid{lvl}_0", ConvLeaky(cin, width, stride=2, rngs=rngs))
            setattr(self, f"pyramid{lvl}_1", ConvLeaky(width, width, rngs=rngs))
            if lvl >= self.finest:
                setattr(self, f"project{lvl}", ConvLeaky(width, int(config["feature_width"]), kernel=1, rngs=rngs))
            cin = width
        c = (2 * self.radius + 1) ** 2 + int(config["feature_width"]) + 2 + extra
        self.num_estimator, self.num_context = len(est), len(ctx)
        for j, width in enumerate(est):
            setattr(self, f"estimator{j}", ConvLeaky(c, width, rngs=rngs))
            c = width
        self.estimator_flow = Conv(c, 2, 3, init="kaiming_normal", rngs=rngs)
        c = c + 2
        for j, (width, d) in enumerate(zip(ctx, dil)):
            setattr(self, f"context{j}", ConvLeaky(c, width, dilation=d, rngs=rngs))
            c = width
        self.context_flow = Conv(c, 2, 3, init="kaiming_normal", rngs=rngs)

    def pyramid(self, img: jax.Array, levels: int) -> list[jax.Array]:
        """`(N, H, W, 3|5) -> [level 1 (H/2), ..., level L (H/2^L)]`."""
        feats, x = [], img
        for lvl in range(1, levels + 1):
            x = getattr(self, f"pyramid{lvl}_1")(getattr(self, f"pyramid{lvl}_0")(x))
            feats.append(x)
        return feats

    def __call__(self, pair: jax.Array) -> dict[str, tuple[jax.Array, ...]]:
        check_input_shape(pair, MULTIPLE)
        n, h, w, _ = pair.shape
        levels = pyramid_levels(h, w, self.max_levels)
        images = jnp.concatenate([pair[..., :3], pair[..., 3:]], axis=0)
        feats = self.pyramid(with_coordinates(images) if self.coords else images, levels)
        flow = hidden = None
        flows = {}
        for lvl in range(levels, self.finest - 1, -1):
            f1, f2 = feats[lvl - 1][:n], feats[lvl - 1][n:]
            if flow is None:
                flow = jnp.zeros(f1.shape[:3] + (2,), f1.dtype)
            else:
                flow = upsample_flow2x(flow)
                f2 = geometry.warp(f2, flow)
            x = [leaky_relu(cost_volume(f1, f2, self.radius)), getattr(self, f"project{lvl}")(f1), flow]
            if self.coords:
                x.append(coordinate_channels(n, *f1.shape[1:3], f1.dtype))
            hidden = jnp.concatenate(x, axis=-1)
            for j in range(self.num_estimator):
                hidden = getattr(self, f"estimator{j}")(hidden)
            flow = flow + self.estimator_flow(hidden)
            flows[lvl] = flow
        x = jnp.concatenate([hidden, flow], axis=-1)
        for j in range(self.num_context):
            x = getattr(self, f"context{j}")(x)
        flows[self.finest] = flow + self.context_flow(x)
        px = []
        for s in range(4):
            p = flows[max(s, self.finest)]
            for _ in range(self.finest - s):  # scales finer than the finest level: its flow upsampled
                p = upsample_flow2x(p)
            px.append(p)
        return pixel_and_fraction_maps(px)


def build(config: Mapping, rngs: nnx.Rngs) -> PWCLite:
    return PWCLite(config, rngs=rngs)


def normalize_config(config: Mapping) -> dict:
    out = fill_config(config, DEFAULT_CONFIG, lists=("pyramid", "estimator", "context", "dilations"),
                      ints=("radius", "feature_width", "finest_level"), bools=("coords",), head_inits=HEAD_INITS)
    if out["finest_level"] not in (1, 2):
        raise ValueError(f"model finest_level must be 1 or 2, got {out['finest_level']}")
    if len(out["pyramid"]) < MIN_LEVELS:
        raise ValueError(f"model pyramid needs at least {MIN_LEVELS} level widths, got {out['pyramid']}")
    if len(out["context"]) != len(out["dilations"]):
        raise ValueError(f"model context and dilations must have the same length, got {out['context']} and "
                         f"{out['dilations']}")
    if out["radius"] < 1:
        raise ValueError(f"model radius must be >= 1, got {out['radius']}")
    return out
