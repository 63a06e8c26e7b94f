"""Geometry of correspondence maps: warping, unit conversion, image pyramids, occlusion masks.

Conventions (the same as the upstream code's, so that its numbers can be reproduced):
  * Layout NHWC, float32.
  * A correspondence map D (..., H, W, 2) says where pixel (x, y) of the first image is found in the
    second: at (x + D_x, y + D_y). Channel 0 is horizontal, channel 1 vertical.
  * *Pixel* maps are in pixels of the map's own scale; *fraction* maps are ch0 / W_s and ch1 / H_s. The
    network outputs both; warps use pixel maps, the left-right term uses fractions.
  * warp(second, D) reconstructs the first image (paper eqs. 4-5).

All functions are pure, jit/vmap/grad-safe, and contain no Python loops over pixels.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jax.scipy.ndimage import map_coordinates

NUM_SCALES = 4


def _check_map(name: str, d, spatial=None):
    if d.ndim < 3 or d.shape[-1] != 2:
        raise ValueError(f"{name} must have shape (..., H, W, 2), got {tuple(d.shape)}")
    if spatial is not None and tuple(d.shape[-3:-1]) != tuple(spatial):
        raise ValueError(f"{name} has spatial size {tuple(d.shape[-3:-1])}, expected {tuple(spatial)} (the image's H, W)")


# ----------------------------------------------------------------------------------------- warping
def _warp_single(image, disp_px):
    """image (H, W, C), disp_px (H, W, 2) -> (H, W, C)."""
    h, w = image.shape[:2]
    ys, xs = jnp.meshgrid(jnp.arange(h, dtype=disp_px.dtype), jnp.arange(w, dtype=disp_px.dtype), indexing="ij")
    coords = (ys + disp_px[..., 1], xs + disp_px[..., 0])
    # mode='nearest' clamps each of the two integer corner indices into the image while the bilinear
    # weights come from the unclamped position: exactly flownet2 Resample2d / grid_sample(border,
    # align_corners=True). (mode='constant' in JAX is *not* scipy's constant mode.)
    sample = lambda channel: map_coordinates(channel, coords, order=1, mode="nearest")
    return jax.vmap(sample, in_axes=-1, out_axes=-1)(image)


def _warp_batched(single, image, disp_px):
    """`single` ((H, W, C), (H, W, 2)) -> (H, W, C) applied over the leading dims of `image (..., H, W, C)` and
    `disp_px (..., H, W, 2)`, after checking that their shapes agree (ValueError naming the mismatch)."""
    if image.ndim < 3:
        raise ValueError(f"image must have shape (..., H, W, C), got {tuple(image.shape)}")
    _check_map("disp_px", disp_px, image.shape[-3:-1])
    if image.shape[:-3] != disp_px.shape[:-3]:
        raise ValueError(f"image leading dims {image.shape[:-3]} differ from disp_px leading dims {disp_px.shape[:-3]}")
    lead = image.shape[:-3]
    img = image.reshape((-1,) + image.shape[-3:])
    d = disp_px.reshape((-1,) + disp_px.shape[-3:]).astype(img.dtype)
    out = jax.vmap(single)(img, d)
    return out.reshape(lead + out.shape[1:])


def warp(image, disp_px):
    """Backward-warp `image` by a pixel correspondence map.

    output(x, y) = image sampled bilinearly at (x + D_x, y + D_y), border-replicated outside.

    Args:
      image: (..., H, W, C) float.
      disp_px: (..., H, W, 2) offsets in **pixels** of this image's resolution; same leading dims.
    Returns:
      (..., H, W, C), the second image brought into the frame of the first.
    """
    return _warp_batched(_warp_single, image, disp_px)


CUBIC_A = -0.5
"""Keys' cubic convolution parameter of `warp_cubic`: -0.5 (Catmull-Rom) reproduces polynomials up to degree 2
exactly; OpenCV's INTER_CUBIC uses -0.75."""


def cubic_weights(t, a: float = CUBIC_A):
    """Keys' cubic convolution weights of the four taps at offsets -1, 0, 1, 2 from floor(x), for t = x - floor(x)
    in [0, 1): a list of 4 arrays shaped like `t`, summing to 1."""
    def kernel(s):
        s = jnp.abs(s)
        near = ((a + 2.0) * s - (a + 3.0)) * s * s + 1.0
        far = ((a * s - 5.0 * a) * s + 8.0 * a) * s - 4.0 * a
        return jnp.where(s <= 1.0, near, jnp.where(s < 2.0, far, 0.0))
    return [kernel(t + 1.0), kernel(t), kernel(1.0 - t), kernel(2.0 - t)]


def _warp_cubic_single(image, disp_px, a):
    """image (H, W, C), disp_px (H, W, 2) -> (H, W, C), cubic convolution, border replicated."""
    h, w, c = image.shape
    ys, xs = jnp.meshgrid(jnp.arange(h, dtype=disp_px.dtype), jnp.arange(w, dtype=disp_px.dtype), indexing="ij")
    # the position is clamped into the image first, so that a match outside it reads the border pixel itself,
    # as the bilinear `warp` does (a tap beyond the edge inside the image replicates the edge pixel)
    x = jnp.clip(xs + disp_px[..., 0], 0.0, w - 1.0)
    y = jnp.clip(ys + disp_px[..., 1], 0.0, h - 1.0)
    x0, y0 = jnp.floor(x), jnp.floor(y)
    wx, wy = cubic_weights(x - x0, a), cubic_weights(y - y0, a)
    x0, y0 = x0.astype(jnp.int32), y0.astype(jnp.int32)
    cols = [jnp.clip(x0 + k - 1, 0, w - 1) for k in range(4)]
    rows = [jnp.clip(y0 + k - 1, 0, h - 1) for k in range(4)]
    # all 16 taps of every pixel in one gather: (H * W * 16,) flat indices into the (H * W, C) image
    index = jnp.stack([r * w + q for r in rows for q in cols], -1)
    weight = jnp.stack([u * v for u in wy for v in wx], -1)
    taps = jnp.take(image.reshape(h * w, c), index.reshape(-1), axis=0).reshape(h, w, 16, c)
    return jnp.sum(weight[..., None] * taps, axis=2)


def warp_cubic(image, disp_px, a: float = CUBIC_A):
    """Backward-warp `image` by a pixel correspondence map with Keys' cubic convolution (`cubic_weights`).

    output(x, y) = image sampled at (x + D_x, y + D_y) over its 4x4 neighbourhood, border-replicated outside.
    Bilinear sampling (`warp`) low-pass filters by an amount that depends on the fractional part of the position
    (none at whole pixels, most at half pixels), which draws sub-pixel estimates made by comparing warped images
    towards whole-pixel motion; the cubic kernel keeps far more of the image's detail at every offset. The
    training losses keep the paper's bilinear `warp`; the test-time polish's variational fit uses this one.

    Args:
      image: (..., H, W, C) float.
      disp_px: (..., H, W, 2) offsets in pixels of this image's resolution; same leading dims.
      a: the kernel's parameter (`CUBIC_A`).
    Returns:
      (..., H, W, C), the second image brought into the frame of the first.
    """
    return _warp_batched(lambda i, m: _warp_cubic_single(i, m, a), image, disp_px)


# --------------------------------------------------------------------------------- unit conversion
def map_scale(shape) -> jnp.ndarray:
    """(W_s, H_s) multipliers for a map of shape (..., H_s, W_s, 2)."""
    return jnp.array([shape[-2], shape[-3]], jnp.float32)


def frac_to_px(frac):
    """Fraction map (ch0 / W_s, ch1 / H_s) -> pixels at the map's own scale. (..., H_s, W_s, 2)."""
    _check_map("frac", frac)
    return frac * map_scale(frac.shape).astype(frac.dtype)


def px_to_frac(px):
    """Pixel map at its own scale -> fraction map. (..., H_s, W_s, 2)."""
    _check_map("px", px)
    return px / map_scale(px.shape).astype(px.dtype)


# ----------------------------------------------------------------------------------------- resizing
def resize_bilinear(x, out_hw, *, antialias: bool = True):
    """Bilinear resize of (..., H, W, C) to out_hw = (H', W').

    With antialias=True and downscaling, the kernel is a triangle stretched by the scale factor, which is
    what Pillow's BILINEAR does (taps 1/8, 3/8, 3/8, 1/8 for x2), with half-pixel centres and edge taps
    renormalised. This is the resize upstream uses for its image pyramids.
    """
    shape = x.shape[:-3] + tuple(out_hw) + x.shape[-1:]
    return jax.image.resize(x, shape, method="linear", antialias=antialias)


def resize_bilinear_align_corners(x, out_hw):
    """Bilinear resize with align_corners=True semantics (corner pixels map to corner pixels).

    This is how upstream brings predicted maps to the ground-truth resolution (F.interpolate(...,
    mode='bilinear', align_corners=True)). (..., H, W, C) -> (..., H', W', C); values are not rescaled.
    """
    h, w = x.shape[-3:-1]
    oh, ow = out_hw

    def axis_weights(n_in, n_out):
        if n_out == 1 or n_in == 1:
            pos = jnp.zeros((n_out,), jnp.float32)
        else:
            pos = jnp.arange(n_out, dtype=jnp.float32) * ((n_in - 1) / (n_out - 1))
        lo = jnp.clip(jnp.floor(pos).astype(jnp.int32), 0, n_in - 1)
        hi = jnp.clip(lo + 1, 0, n_in - 1)
        t = pos - lo.astype(jnp.float32)
        return lo, hi, t

    ylo, yhi, ty = axis_weights(h, oh)
    xlo, xhi, tx = axis_weights(w, ow)
    ty = ty[:, None, None].astype(x.dtype)
    tx = tx[None, :, None].astype(x.dtype)
    rows = jnp.take(x, ylo, axis=-3) * (1 - ty) + jnp.take(x, yhi, axis=-3) * ty
    return jnp.take(rows, xlo, axis=-2) * (1 - tx) + jnp.take(rows, xhi, axis=-2) * tx


def image_pyramid(images, num_scales: int = NUM_SCALES):
    """Multi-scale images, finest first: (..., H, W, C) -> (full, H/2, H/4, H/8) for num_scales=4.

    Each level is resized directly from the full-resolution image with the antialiased bilinear
    (triangle) kernel, like upstream's PIL pyramid. Residual difference to upstream: upstream first
    truncates the image to uint8 and rounds the result to uint8, i.e. up to ~1/255 per pixel; the
    parity tests therefore feed upstream's stored pyramids to the loss and test this resize separately.
    """
    h, w = images.shape[-3:-1]
    f = 2 ** (num_scales - 1)
    if h % f or w % f:
        raise ValueError(f"images must have H and W divisible by {f} for a {num_scales}-scale pyramid, got {h}x{w}")
    levels = [images]
    for s in range(1, num_scales):
        levels.append(resize_bilinear(images, (h >> s, w >> s)))
    return tuple(levels)


# -------------------------------------------------------------------------------------------- masks
def border_mask(h: int, w: int, ratio: float = 0.1, dtype=jnp.float32):
    """(H, W, 1) mask: 0 on a frame of ceil(ratio * H) px on all four sides (width from H, as upstream)."""
    b = int(math.ceil(h * ratio))
    ys = jnp.arange(h)[:, None]
    xs = jnp.arange(w)[None, :]
    inside = (ys >= b) & (ys < h - b) & (xs >= b) & (xs < w - b)
    return inside.astype(dtype)[..., None]


def _length_sq(x):
    return jnp.sum(jnp.square(x), axis=-1, keepdims=True)


def forward_backward_occlusion(d_fw, d_bw, d_bw_warped=None, d_fw_warped=None, *, alpha1: float = 0.01,
                               alpha2: float = 0.5, warped_bw_norm: bool = True):
    """Forward-backward consistency check (paper eq. 6, after Meister et al.): which pixels are occluded.

    A pixel of the first image is occluded if
        |D + W(D', D)|^2  >  alpha1 * (|D|^2 + |W(D', D)|^2) + alpha2        (warped_bw_norm=True, paper)
        |D + W(D', D)|^2  >  alpha1 * (|D|^2 + |D'|^2) + alpha2              (warped_bw_norm=False, upstream code)
    and symmetrically for D'. Thresholds are in px^2 of the maps' scale.

    Args:
      d_fw: (..., H, W, 2) forward pixel map D (first -> second).
      d_bw: (..., H, W, 2) backward pixel map D' (second -> first).
      d_bw_warped, d_fw_warped: W(D', D) and W(D, D') when the caller has them already (the cycle loss warps
        them in the same gather as the images); computed here when None.
    Returns:
      (occ_fw, occ_bw): float {0, 1} (..., H, W, 1), 1 = occluded; occ_fw lives in the first image's
      frame, occ_bw in the second's. No gradient flows through them.
    """
    _check_map("d_fw", d_fw)
    _check_map("d_bw", d_bw, d_fw.shape[-3:-1])
    d_fw = jax.lax.stop_gradient(d_fw)
    d_bw = jax.lax.stop_gradient(d_bw)
    d_bw_warped = warp(d_bw, d_fw) if d_bw_warped is None else jax.lax.stop_gradient(d_bw_warped)
    d_fw_warped = warp(d_fw, d_bw) if d_fw_warped is None else jax.lax.stop_gradient(d_fw_warped)
    diff_fw = _length_sq(d_fw + d_bw_warped)
    diff_bw = _length_sq(d_bw + d_fw_warped)
    if warped_bw_norm:
        thr_fw = alpha1 * (_length_sq(d_fw) + _length_sq(d_bw_warped)) + alpha2
        thr_bw = alpha1 * (_length_sq(d_bw) + _length_sq(d_fw_warped)) + alpha2
    else:
        thr_fw = thr_bw = alpha1 * (_length_sq(d_fw) + _length_sq(d_bw)) + alpha2
    return (diff_fw > thr_fw).astype(d_fw.dtype), (diff_bw > thr_bw).astype(d_fw.dtype)


def occlusion_mask(d_fw, d_bw, d_bw_warped=None, d_fw_warped=None, *, alpha1: float = 0.01, alpha2: float = 0.5,
                   warped_bw_norm: bool = True, border_ratio: float = 0.1, floor: float = 1e-3):
    """The occlusion maps O of a pair (1 = use the pixel) as the reconstruction loss weighs them (eq. 7).

    mask = border * (1 - occluded) + floor, for both directions, gradients stopped; `occluded` is
    `forward_backward_occlusion` (eq. 6). The band of ceil(border_ratio * H_s) px on all four sides (where
    warps read clamped border pixels) and the +1e-3 floor are the upstream code's, not in the paper. Stereo
    pairs are not masked (their mask is 1) unless `LossConfig.stereo_occlusion`: that choice is made by the
    caller (`losses.cycle_loss`).

    Args:
      d_fw, d_bw: (..., H, W, 2) forward / backward pixel maps; d_bw_warped, d_fw_warped: optional
        W(D', D), W(D, D') (see `forward_backward_occlusion`).
    Returns:
      (mask_fw (..., H, W, 1) in the first frame, mask_bw (..., H, W, 1) in the second frame).
    """
    occ_fw, occ_bw = forward_backward_occlusion(d_fw, d_bw, d_bw_warped, d_fw_warped, alpha1=alpha1, alpha2=alpha2,
                                                warped_bw_norm=warped_bw_norm)
    h, w = occ_fw.shape[-3:-1]
    border = border_mask(h, w, border_ratio, occ_fw.dtype)
    return border * (1 - occ_fw) + floor, border * (1 - occ_bw) + floor
