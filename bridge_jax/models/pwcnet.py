"""PWC-Net (Sun et al. 2018), the backbone of the paper's supplementary variant, in the layout upstream uses.

Pipeline for a pair `(N, H, W, 6)` = [image_a, image_b] (H, W multiples of 64):
1. A shared 6-level feature pyramid: per level a stride-2 3x3 conv and two 3x3 convs, LeakyReLU(0.1),
   widths 16/32/64/96/128/196 (levels 1..6 at H/2 .. H/64).
2. Coarse to fine, levels 6..2: warp image_b's features by the upsampled flow of the level above (scaled by
   20/2^l as in PWC-Net), **cost volume** = correlation of image_a's features with the warped ones over a
   (2*md+1)^2 window (md=4, channel mean, zero padding) + LeakyReLU; a densely connected estimator
   (5 convs of 128/128/96/64/32, each output concatenated *in front of* its input) predicts the flow.
   Levels 6..3 also produce a 4x4/2 transposed-conv upsampled flow and feature for the next level.
3. A context network (dilated 3x3 convs, dilations 1/2/4/8/16/1, widths 128/128/128/96/64/32, then 2) refines
   the level-2 flow residually.

Output adapted like upstream (train.py with `--model_name pwc`) so the same losses apply: scale s (0..3) is
the level-(s+2) flow times 4, bilinearly resized (align_corners=True) to (H/2^s, W/2^s), used as **pixels at
that scale**; `frac = px / (W_s, H_s)`. Unlike resnet_md there is no 0.3*tanh bound.

Init as upstream: kaiming-normal (fan_in) weights, zero biases. Parameter names mirror upstream's module
attributes (conv1a, conv1aa, ..., conv6_0, predict_flow6, deconv6, upfeat6, ..., dc_conv7); upstream also
defines an unused `deconv2`, kept here so an upstream state dict maps one to one. Default size: 9,374,340 params.
`coords=True` (not upstream) appends normalised x, y channels to the images and to every estimator input.
"""
from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
from flax import nnx

from bridge_jax.geometry import resize_bilinear_align_corners
from bridge_jax.models.coordinates import coordinate_channels, with_coordinates
from bridge_jax.models.layers import (Conv, ConvLeaky, ConvTranspose, check_input_shape, fill_config, leaky_relu,
                                      pixel_and_fraction_maps)

DEFAULT_CONFIG = {
    "name": "pwcnet",
    "md": 4,
    "pyramid": [16, 32, 64, 96, 128, 196],
    "estimator": [128, 128, 96, 64, 32],
    "context": [128, 128, 128, 96, 64, 32],
    "dilations": [1, 2, 4, 8, 16, 1],
    "head_init": "kaiming_normal",
    "warp": "upstream",
    "coords": False,
}
HEAD_PREFIXES = ("predict_flow", "dc_conv7")
"""Top-level parameter names of the convs that output flow; `head_init="zeros"` starts them at zero (every
level's flow, and the context network's refinement, start at exactly 0)."""
HEAD_INITS = ("kaiming_normal", "zeros")
WARPS = ("upstream", "pixels")
"""How level l warps image_b's features (config key `warp`):

* `upstream`: by the transposed-conv upsampled flow times 20/2^l (PWC-Net's flow unit, 1/20 full-resolution
  pixels). But the loss trains each level's flow as *level-l pixels* (scale s = level s+2, times 4, resized),
  so these warps are 5, 2.5, 1.25 and 0.625x (levels 2..5) the motion the same network reports: the warp and
  the loss disagree unless the deconvs learn to undo it. Kept for converted upstream checkpoints.
* `pixels`: by the level-(l+1) flow bilinearly upsampled 2x and doubled (level-l pixels), the warp the loss
  implies. The deconv output still feeds the estimator, so parameters are the same in both modes."""
MULTIPLE = 64
FLOW_SCALE = 20.0
"""PWC-Net's internal flow unit: the warp at level l uses flow * 20 / 2^l (upstream: 0.625, 1.25, 2.5, 5)."""
OUTPUT_GAIN = 4.0
"""Upstream multiplies each level's flow by 4 before resizing it to the output scale."""


CORRELATION_TILE = 16
"""Columns per block of `correlation`'s matmuls: each block of f1 is matched against the t + 2d columns of f2 it
can reach, so the products computed and thrown away are (t + 2d) / (2d + 1) times the needed ones (2.7x for d = 4)."""


def correlation(f1: jax.Array, f2: jax.Array, max_displacement: int = 4) -> jax.Array:
    """Cost volume (FlowNet/PWC `Correlation`, kernel 1, strides 1), pure JAX and differentiable.

    Args:
      f1, f2: `(N, H, W, C)` feature maps.
      max_displacement: d; displacements (dy, dx) in [-d, d]^2.
    Returns:
      `(N, H, W, (2d+1)^2)`; channel `(dy + d) * (2d + 1) + (dx + d)` holds
      `mean_c f1[n, y, x, c] * f2[n, y + dy, x + dx, c]` with f2 zero outside the image.

    Computed as matmuls, not as (2d+1)^2 shifted products: for each vertical offset dy, every block of
    `CORRELATION_TILE` columns of f1 is multiplied by the block of f2 it can reach (`(t, C) @ (C, t + 2d)`), and
    the 2d + 1 diagonals of each product are the horizontal offsets. XLA:CPU reduces over a short channel axis
    slowly and compiles one kernel per shifted product: this form made pwc_lite's forward + gradient ~1.5x
    faster on 2 cores and its compile ~40 % shorter.
    """
    d = max_displacement
    n, h, w, c = f1.shape
    k = 2 * d + 1
    t = CORRELATION_TILE if w > CORRELATION_TILE and CORRELATION_TILE >= 2 * d else w
    nb = -(-w // t)  # blocks; f1 is zero-padded on the right to nb * t columns (those outputs are cropped)
    wp = nb * t
    a = jnp.pad(f1, ((0, 0), (0, 0), (0, wp - w), (0, 0))).reshape(n, h, nb, t, c)
    # f2 at columns -d .. wp + t - d - 1 (zero outside the image), so block b's window, f2 columns
    # [b t - d, b t + t + d), is padded block b followed by the first 2d columns of padded block b + 1.
    extra = t if nb > 1 else 2 * d
    b2 = jnp.pad(f2, ((0, 0), (d, d), (d, wp - w + extra - d), (0, 0)))
    out = []
    for dy in range(k):
        rows = b2[:, dy:dy + h]
        if nb > 1:
            rows = rows.reshape(n, h, nb + 1, t, c)
            win = jnp.concatenate([rows[:, :, :-1], rows[:, :, 1:, :2 * d]], axis=3)
        else:
            win = rows.reshape(n, h, 1, t + 2 * d, c)
        prod = jnp.einsum("nhbtc,nhbvc->nhbtv", a, win)  # (n, h, nb, t, t + 2d): f1 column i x window column j
        # The diagonals j = i + (dx + d): flattened row-major, element (i, i + m) sits at i (t + 2d + 1) + m,
        # so t zeros appended and a reshape to rows of t + 2d + 1 put diagonal m in column m.
        flat = jnp.pad(prod.reshape(n, h, nb, t * (t + 2 * d)), ((0, 0), (0, 0), (0, 0), (0, t)))
        band = flat.reshape(n, h, nb, t, t + 2 * d + 1)[..., :k]
        out.append(band.reshape(n, h, wp, k)[:, :, :w])
    return jnp.concatenate(out, axis=-1) / c


def warp_zero(x: jax.Array, flow: jax.Array) -> jax.Array:
    """Backward-warp `x` by `flow` pixels with zero padding, masked like upstream PWC-Net.

    Samples x bilinearly at (x + flow_x, y + flow_y) (grid_sample, align_corners=True, zeros padding) and
    multiplies by a mask that is 1 only where the whole bilinear footprint lies inside the image, i.e. where
    the in-image bilinear weights sum to 1 (within 1e-4). Upstream computes floor(clamp(grid_sample(ones))),
    which float rounding also sets to 0 at many interior pixels (weights summing to 0.99999994); we
    implement the intent instead. With upstream's mask replaced by this one, converted upstream weights give
    the same maps to 3e-5 px (checked at 128x256). The mask is not differentiated.

    Args:
      x: `(N, H, W, C)`; flow: `(N, H, W, 2)` pixels (ch0 x, ch1 y).
    Returns:
      `(N, H, W, C)`.
    """
    n, h, w, c = x.shape
    gy, gx = jnp.meshgrid(jnp.arange(h, dtype=flow.dtype), jnp.arange(w, dtype=flow.dtype), indexing="ij")
    px = gx[None] + flow[..., 0]
    py = gy[None] + flow[..., 1]
    x0 = jnp.floor(px)
    y0 = jnp.floor(py)
    flat = x.reshape(n, h * w, c)
    out = jnp.zeros_like(x)
    inside_weight = jnp.zeros((n, h, w), flow.dtype)
    for oy in (0, 1):
        for ox in (0, 1):
            xi = x0 + ox
            yi = y0 + oy
            wgt = (1 - jnp.abs(px - xi)) * (1 - jnp.abs(py - yi))
            valid = (xi >= 0) & (xi <= w - 1) & (yi >= 0) & (yi <= h - 1)
            idx = (jnp.clip(yi, 0, h - 1) * w + jnp.clip(xi, 0, w - 1)).astype(jnp.int32).reshape(n, h * w, 1)
            vals = jnp.take_along_axis(flat, idx, axis=1).reshape(n, h, w, c)
            wv = jnp.where(valid, wgt, 0.0)
            out = out + vals * wv[..., None].astype(x.dtype)
            inside_weight = inside_weight + wv
    mask = jax.lax.stop_gradient((inside_weight >= 1.0 - 1e-4).astype(x.dtype))
    return out * mask[..., None]


class PWCNet(nnx.Module):
    """See the module docstring. `__call__(pair (N, H, W, 6)) -> {"px": (s0..s3), "frac": (s0..s3)}`."""

    def __init__(self, config: Mapping, *, rngs: nnx.Rngs):
        pyr, est, ctx, dil = (list(config[k]) for k in ("pyramid", "estimator", "context", "dilations"))
        self.md = int(config["md"])
        self.warp = config["warp"]  # normalize_config fills the default
        if len(pyr) != 6 or len(est) != 5 or len(ctx) != 6 or len(dil) != 6:
            raise ValueError("pwcnet config needs 6 pyramid widths, 5 estimator widths, 6 context widths/dilations")
        self.coords = bool(config["coords"])
        extra = 2 if self.coords else 0  # coordinate channels on the images and on every estimator input
        cin = 3 + extra
        for lvl in range(1, 7):
            names = ("conv6aa", "conv6a", "conv6b") if lvl == 6 else (f"conv{lvl}a", f"conv{lvl}aa", f"conv{lvl}b")
            for j, name in enumerate(names):
                setattr(self, name, ConvLeaky(cin, pyr[lvl - 1], stride=2 if j == 0 else 1, rngs=rngs))
                cin = pyr[lvl - 1]
        nd = (2 * self.md + 1) ** 2
        dense = sum(est)
        for lvl in range(6, 1, -1):
            od = (nd if lvl == 6 else nd + pyr[lvl - 1] + 4) + extra
            c = od
            for j, width in enumerate(est):
                setattr(self, f"conv{lvl}_{j}", ConvLeaky(c, width, rngs=rngs))
                c += width
            setattr(self, f"predict_flow{lvl}", Conv(od + dense, 2, 3, init="kaiming_normal", rngs=rngs))
            setattr(self, f"deconv{lvl}", ConvTranspose(2, 2, 4, rngs=rngs))  # deconv2: unused, as upstream
            if lvl > 2:
                setattr(self, f"upfeat{lvl}", ConvTranspose(od + dense, 2, 4, rngs=rngs))
        c = nd + pyr[1] + 4 + extra + dense
        for j, (width, d) in enumerate(zip(ctx, dil)):
            setattr(self, f"dc_conv{j + 1}", ConvLeaky(c, width, dilation=d, rngs=rngs))
            c = width
        self.dc_conv7 = Conv(c, 2, 3, init="kaiming_normal", rngs=rngs)

    def pyramid(self, img: jax.Array) -> list[jax.Array]:
        """`(N, H, W, 3) -> [level1 (H/2), ..., level6 (H/64)]`."""
        feats, x = [], img
        for lvl in range(1, 7):
            names = ("conv6aa", "conv6a", "conv6b") if lvl == 6 else (f"conv{lvl}a", f"conv{lvl}aa", f"conv{lvl}b")
            for name in names:
                x = getattr(self, name)(x)
            feats.append(x)
        return feats

    def _estimate(self, lvl: int, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        for j in range(5):
            x = jnp.concatenate([getattr(self, f"conv{lvl}_{j}")(x), x], axis=-1)
        return x, getattr(self, f"predict_flow{lvl}")(x)

    def __call__(self, pair: jax.Array) -> dict[str, tuple[jax.Array, ...]]:
        check_input_shape(pair, MULTIPLE)
        n, h, w, _ = pair.shape
        images = jnp.concatenate([pair[..., :3], pair[..., 3:]], axis=0)
        feats = self.pyramid(with_coordinates(images) if self.coords else images)
        f1 = [f[:n] for f in feats]
        f2 = [f[n:] for f in feats]
        flows = {}
        x = leaky_relu(correlation(f1[5], f2[5], self.md))
        up_flow = up_feat = None
        for lvl in range(6, 1, -1):
            if lvl < 6:
                if self.warp == "pixels":
                    hl, wl = f1[lvl - 1].shape[1:3]
                    warp_flow = 2.0 * resize_bilinear_align_corners(flows[lvl + 1], (hl, wl))
                else:
                    warp_flow = up_flow * (FLOW_SCALE / 2 ** lvl)
                warped = warp_zero(f2[lvl - 1], warp_flow)
                corr = leaky_relu(correlation(f1[lvl - 1], warped, self.md))
                x = jnp.concatenate([corr, f1[lvl - 1], up_flow, up_feat], axis=-1)
            if self.coords:
                x = jnp.concatenate([x, coordinate_channels(n, *x.shape[1:3], x.dtype)], axis=-1)
            x, flow = self._estimate(lvl, x)
            if lvl > 2:
                up_flow = getattr(self, f"deconv{lvl}")(flow)
                up_feat = getattr(self, f"upfeat{lvl}")(x)
            flows[lvl] = flow
        for j in range(1, 7):
            x = getattr(self, f"dc_conv{j}")(x)
        flows[2] = flows[2] + self.dc_conv7(x)
        px = [resize_bilinear_align_corners(flows[s + 2].astype(jnp.float32) * OUTPUT_GAIN, (h >> s, w >> s))
              for s in range(4)]
        return pixel_and_fraction_maps(px)


def build(config: Mapping, rngs: nnx.Rngs) -> PWCNet:
    return PWCNet(config, rngs=rngs)


def normalize_config(config: Mapping) -> dict:
    out = fill_config(config, DEFAULT_CONFIG, lists=("pyramid", "estimator", "context", "dilations"), ints=("md",),
                      bools=("coords",), head_inits=HEAD_INITS)
    if out["warp"] not in WARPS:
        raise ValueError(f"model warp must be one of {list(WARPS)}, got {out['warp']!r}")
    return out
