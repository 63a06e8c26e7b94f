"""The paper's unsupervised loss: one pure function per equation, and the cycle loss that trains with them.

Equations of the paper (Sec. 3), each the function that the train step runs:

  eq. 6   occlusion (forward-backward check)    `geometry.occlusion_mask`
  eq. 7   reconstruction loss  L_rec            `photometric_loss`: alpha (1 - SSIM)/2 + (1 - alpha) L1, masked
  eq. 8   edge-aware smoothness  L_sm           `smoothness_loss` (2nd-order on the map, 1st-order on the image)
  eq. 9   left-right consistency  L_lr          `lr_consistency_loss` (stereo pairs, fraction units)
  eqs. 10-12  2-warp consistency  L_2warp      `two_warp_chains` (which images, maps and masks) +
                                               `two_warp_estimates` (eqs. 10-11), then eq. 7's function on
                                               their rows (eq. 12), in `scale_terms`' one `per_row` call
  eq. 13  total loss                            `cycle_loss`: the weighted sum over scales, pairs and directions

`cycle_loss` does the warps itself (for each scale one batched gather of everything that is warped by the same
maps: both reconstructions, the other direction's pixel map for eq. 6, its fraction map for eq. 9), so that the
equation functions take pre-warped inputs; that is both what the paper writes (each term compares a map or an
image with a warped one) and what compiles fast. For the same reason each equation runs once per scale on
stacked rows (`per_row`: both directions of every pair, and the 2-warp chains, in one call), not once per
direction or chain.

Units: images in [0, 1]; pixel maps in pixels of their scale; fraction maps in fractions of W_s / H_s. All four
scales are summed with equal weights, and both directions of every pair are used.

Where the upstream code differs from the paper, `LossConfig` has a switch (paper default; `LossConfig.upstream()`
for the code's behaviour): the 2-warp comparison target, the 2-warp weighting, the occlusion threshold's norm and
the normalisation over a batch. Fixed upstream details that are not in the paper: SSIM is computed on the masked
images with 3x3 mean windows (VALID); the smoothness term sees the pixel map divided by 20; masks have a border
band and a 1e-3 floor (see `geometry.occlusion_mask`).

Training switches beyond the paper (each a `LossConfig` field whose default is the paper's behaviour):
`photometric="census"` (`census_loss`: soft census transform, its Hamming distance, robust penalty, instead of
eq. 7's SSIM + L1), `scales="finest"` (only scale 0, the working size, instead of the sum over four scales),
`smoothness_order=1` (first differences, weight `lambda_sm1`, edge constant `beta1`) and `occlusion_start_step`
(flow pairs unmasked before that training step; the step comes from the train state) and `self_supervision`
(`self_supervision_loss`: the full-frame maps, gradient stopped, supervise the maps of cropped frames where the
teacher is confident; the train steps run the network on the crops and pass those maps as `Student`), and
`occlusion_fill` (`occlusion_fill_loss`: the stereo maps' untrusted pixels pulled towards the farther of their
row's nearest trusted neighbours, the background, with stopped gradient). Gradient
clipping is an optimiser setting (`train_step.OptimizerConfig.clip_grad_norm`).

Normalisation. A masked term sum(x * O) / sum(O) is kept per cycle as `Masked(mean(x * O), mean(O))`;
`reduction="cycle"` (default) averages the per-cycle ratios over the cycles of a batch, `reduction="batch"`
divides the batch means (upstream, which normalises over its whole 2-cycle batch). The two agree whenever the
cycles of a batch are identical, and for a single cycle.
"""

from __future__ import annotations

import dataclasses
import functools
from typing import Any, Mapping, NamedTuple, Optional

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import cycle as cyc
from bridge_jax import geometry

TWO_WARP_TYPES = ("none", "full1", "full2", "full3")
PHOTOMETRIC_TYPES = ("ssim_l1", "census")


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Hyper-parameters and paper/upstream switches of the cycle loss.

    Defaults follow the paper; `LossConfig.upstream()` reproduces the upstream code.
    """

    tasks: str = "flow_stereo"  # which pairs train: flow_stereo | stereo_only | flow_only
    two_warp: str = "none"  # 2-warp consistency term (eqs. 10-12): none | full1 | full2 | full3
    # The 2-warp estimate is compared with the 1-warp reconstruction of the same frame (paper eq. 12 and the
    # author's stated intent) or with the real image (upstream code).
    two_warp_target: str = "reconstruction"  # what the 2-warp estimate is compared with: reconstruction | image
    # paper: lambda_2warp = 0.2 times the sum of the variant's two terms; upstream: 0.1 per term.
    two_warp_weighting: str = "paper"  # 2-warp weights: paper (0.2 x the sum) | upstream (0.1 per term)
    # Occlusion threshold uses |W(D', D)|^2 (paper eq. 6) or the unwarped |D'|^2 (upstream code).
    occlusion_norm: str = "warped"  # occlusion test on |W(D', D)|^2: warped (eq. 6) | unwarped (upstream)
    reduction: str = "cycle"  # how terms are averaged: cycle | batch (see the module docstring)
    alpha: float = 0.85  # SSIM weight of the SSIM + L1 photometric error (eq. 5)
    beta: float = 10.0  # edge constant of the 2nd-order smoothness (eq. 8)
    lambda_sm: float = 10.0  # weight of the 2nd-order smoothness term (eq. 13)
    lambda_lr: float = 0.5  # weight of the left-right consistency term (eq. 13)
    lambda_2warp: float = 0.2  # weight of the 2-warp term (eq. 13)
    occ_alpha1: float = 0.01  # occlusion threshold, relative part (eq. 6)
    occ_alpha2: float = 0.5  # occlusion threshold, constant part in pixels^2 (eq. 6)
    border_ratio: float = 0.1  # image border (fraction of the size) left out of the occlusion masks
    mask_floor: float = 1e-3  # smallest mask sum a masked mean divides by
    smooth_scale: float = 1.0 / 20.0  # the pixel map is scaled by this before the smoothness term (upstream)
    num_scales: int = 4  # pyramid scales of the network's maps
    # ---- training switches beyond the paper (each default is the paper's behaviour)
    # Photometric term: the paper's SSIM + L1 mix, or the census transform (7x7 soft ternary census, its soft
    # Hamming distance, robust penalty (|x| + 0.01)^0.4; DDFlow/UFlow), robust to brightness changes.
    photometric: str = "ssim_l1"  # photometric error: ssim_l1 (paper) | census
    # Scales the loss sums: the paper's 4 scales, or only the finest map (scale 0 = the working size), compared
    # with the full-resolution images (UFlow, SMURF, DDFlow).
    scales: str = "all"  # scales the loss sums: all (paper) | finest
    # Edge-aware smoothness of order 2 (paper eq. 8; weight lambda_sm, edge constant beta) or 1 (first
    # differences; its own weight lambda_sm1 and edge constant beta1).
    smoothness_order: int = 2  # edge-aware smoothness of order 2 (eq. 8) or 1
    lambda_sm1: float = 4.0  # weight of the 1st-order smoothness term
    beta1: float = 10.0  # edge constant of the 1st-order smoothness
    # Flow pairs use no occlusion mask (mask 1, as stereo pairs) before this training step; 0 = the paper.
    occlusion_start_step: int = 0  # flow pairs use no occlusion mask before this step (0 = the paper)
    # Stereo pairs masked by the same occlusion check (eq. 6 on D and D', the left-right check) as flow pairs.
    # The paper leaves them unmasked (mask 1): on a background pixel hidden behind a nearer object the
    # photometric term then rewards the nearer object's disparity, which lands on similar background beside the
    # object in the other view, and the network learns to bleed foreground disparity into occlusions.
    stereo_occlusion: bool = False  # mask stereo pairs by the occlusion check too (False = the paper)
    # Background fill of the stereo maps' untrusted pixels (beyond the paper; `occlusion_fill_loss`): where a
    # stereo map fails the forward-backward check or its match lies outside the other image, the images say
    # nothing about the disparity, and the nearer surface's disparity spills over the background it hides. This
    # term pulls each such pixel's horizontal component towards that of the nearest trusted pixel of its row on
    # the side whose disparity is smaller (the farther surface: what a nearer object hides is behind it), the
    # rule with which SGBM and the KITTI devkit fill their holes at test time. 0 = off (the paper).
    occlusion_fill: float = 0.0  # weight of the background-fill term (0 = off)
    # Self-supervision (SelFlow, SMURF, Flow2Stereo; `self_supervision_loss`): the weight of a term in which the
    # network's own scale-0 pixel maps on the full frames (the teacher: gradient stopped, only where its
    # forward-backward check passes and its match lies inside the image) supervise its maps on the cycle's four
    # frames cropped by `self_supervision_crop` px on every side (the student; a random window per cycle and
    # step). Near the crop border the photometric loss is blind, the teacher is not. 0 = off (the paper); e.g.
    # 0.3. The term is 0 before training step `self_supervision_start_step` (an untrained teacher teaches
    # nothing). The crop must be a multiple of 4 (2 * crop keeps H and W multiples of 8), and the cropped size
    # a valid working size of the model (resnet_md: 2 * crop a multiple of 64).
    self_supervision: float = 0.0  # weight of the self-supervision term (0 = off, the paper)
    self_supervision_start_step: int = 0  # the self-supervision term is 0 before this step
    self_supervision_crop: int = 32  # px cut from every side for the student (a multiple of 4)

    def __post_init__(self):
        choices = {
            "tasks": cyc.TASK_SETS,
            "two_warp": TWO_WARP_TYPES,
            "two_warp_target": ("reconstruction", "image"),
            "two_warp_weighting": ("paper", "upstream"),
            "occlusion_norm": ("warped", "unwarped"),
            "reduction": ("cycle", "batch"),
            "photometric": PHOTOMETRIC_TYPES,
            "scales": ("all", "finest"),
            "smoothness_order": (1, 2),
        }
        for field, allowed in choices.items():
            if getattr(self, field) not in allowed:
                raise ValueError(f"loss.{field} must be one of {allowed}, got {getattr(self, field)!r}")
        if not isinstance(self.occlusion_start_step, int) or self.occlusion_start_step < 0:
            raise ValueError(f"loss.occlusion_start_step must be an integer >= 0, got {self.occlusion_start_step!r}")
        for field in ("self_supervision", "occlusion_fill"):  # weights of terms beyond the paper
            value = getattr(self, field)
            if not (isinstance(value, (int, float)) and not isinstance(value, bool) and np.isfinite(value)
                    and value >= 0):
                raise ValueError(f"loss.{field} must be a number >= 0 (0 = off), got {value!r}")
        if self.occlusion_fill > 0 and self.tasks == "flow_only":
            raise ValueError("loss.occlusion_fill fills the stereo maps' occlusions: it needs stereo pairs "
                             f"(tasks 'flow_stereo' or 'stereo_only'), got tasks={self.tasks!r}")
        if not isinstance(self.self_supervision_start_step, int) or self.self_supervision_start_step < 0:
            raise ValueError(f"loss.self_supervision_start_step must be an integer >= 0, got "
                             f"{self.self_supervision_start_step!r}")
        c = self.self_supervision_crop
        if not isinstance(c, int) or isinstance(c, bool) or c < 0 or (self.self_supervision > 0 and (c <= 0 or c % 4)):
            raise ValueError(f"loss.self_supervision_crop must be a positive multiple of 4 (pixels cut from each side; "
                             f"H - 2 * crop and W - 2 * crop must stay multiples of 8), got {c!r}")
        if self.two_warp != "none" and self.tasks != "flow_stereo":
            raise ValueError(f"loss.two_warp={self.two_warp!r} needs stereo and flow pairs (tasks='flow_stereo'), "
                             f"got tasks={self.tasks!r}")

    @classmethod
    def from_dict(cls, d: Mapping[str, Any] | None = None, **overrides) -> "LossConfig":
        d = dict(d or {}, **overrides)
        known = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(d) - known)
        if unknown:
            raise ValueError(f"unknown loss config field(s) {unknown}; known fields: {sorted(known)}")
        return cls(**d)

    @classmethod
    def upstream(cls, **overrides) -> "LossConfig":
        """The upstream code's behaviour, e.g. for parity with its numbers."""
        base = dict(two_warp_target="image", two_warp_weighting="upstream", occlusion_norm="unwarped", reduction="batch")
        base.update(overrides)
        return cls(**base)

    @property
    def pairs(self) -> tuple[int, ...]:
        return cyc.pairs_for_tasks(self.tasks)

    @property
    def loss_scales(self) -> range:
        """The scales the loss sums over (0 = finest)."""
        return range(1 if self.scales == "finest" else self.num_scales)

    def smoothness_weight(self) -> float:
        """The smoothness term's weight in eq. 13 (lambda_sm for order 2, lambda_sm1 for order 1)."""
        return self.lambda_sm if self.smoothness_order == 2 else self.lambda_sm1

    def smoothness_edge_constant(self) -> float:
        """The edge constant of the smoothness weights exp(-beta |dI|) (beta for order 2, beta1 for order 1)."""
        return self.beta if self.smoothness_order == 2 else self.beta1

    def two_warp_term_weight(self) -> float:
        """Multiplier of each 2-warp term (every variant has two terms)."""
        return self.lambda_2warp if self.two_warp_weighting == "paper" else 0.1


# --------------------------------------------------------------------------------------------- term records
class Masked(NamedTuple):
    """A masked mean sum(x * M) / sum(M), kept as its two means (mean(x * M), mean(M)) until the reduction over
    cycles decides how to normalise (see the module docstring). A plain mean is Masked(mean, 1)."""

    num: Any
    den: Any


class Photometric(NamedTuple):
    """The two parts of the reconstruction loss (eq. 7): SSIM and L1 terms (`Masked` per cycle, scalars once
    reduced). Upstream normalises them separately (the SSIM map is 2 px smaller on each axis), so they are only
    mixed after the reduction, by `value`."""

    ssim: Any
    l1: Any

    def value(self, alpha: float):
        """alpha * SSIM term + (1 - alpha) * L1 term (of reduced terms)."""
        return alpha * self.ssim + (1 - alpha) * self.l1


# ----------------------------------------------------------------------------------- eq. 7: reconstruction
def _box3_sum(x):
    """3x3 box sum, stride 1, VALID, over axes -3, -2: (..., H, W, C) -> (..., H-2, W-2, C)."""
    rows = x[..., :-2, :, :] + x[..., 1:-1, :, :] + x[..., 2:, :, :]
    return rows[..., :-2, :] + rows[..., 1:-1, :] + rows[..., 2:, :]


@jax.custom_vjp
def _avg_pool3(x):
    """3x3 mean pooling, stride 1, VALID: (..., H, W, C) -> (..., H-2, W-2, C)."""
    # Shifted slices rather than lax.reduce_window: they fuse with the SSIM arithmetic and compile several
    # times faster on XLA:CPU.
    return _box3_sum(x) / 9.0


def _avg_pool3_fwd(x):
    return _avg_pool3(x), None


def _avg_pool3_bwd(_, g):
    # The transpose of a VALID box filter is the same box filter over the cotangent zero-padded by 2 ("full").
    # Written out, it is one pad and one fused sum; autodiff of the six slices gave six padded copies, which
    # took a fifth of the demo train step on 2 cores.
    pad = [(0, 0)] * (g.ndim - 3) + [(2, 2), (2, 2), (0, 0)]
    return (_box3_sum(jnp.pad(g, pad)) / 9.0,)


_avg_pool3.defvjp(_avg_pool3_fwd, _avg_pool3_bwd)


def ssim(x, y, *, c1: float = 0.01**2, c2: float = 0.03**2):
    """SSIM dissimilarity map clamp((1 - SSIM) / 2, 0, 1) with 3x3 mean windows, VALID.

    Args:
      x, y: (..., H, W, C) images in [0, 1].
    Returns:
      (..., H-2, W-2, C); 0 where the images agree.
    """
    if x.shape != y.shape:
        raise ValueError(f"ssim inputs must have the same shape, got {tuple(x.shape)} and {tuple(y.shape)}")
    mu_x, mu_y = _avg_pool3(x), _avg_pool3(y)
    sigma_x = _avg_pool3(x * x) - mu_x**2
    sigma_y = _avg_pool3(y * y) - mu_y**2
    sigma_xy = _avg_pool3(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sigma_xy + c2)
    den = (mu_x**2 + mu_y**2 + c1) * (sigma_x + sigma_y + c2)
    return jnp.clip((1 - num / den) / 2, 0, 1)


def photometric_loss(estimate, target, mask) -> Photometric:
    """Reconstruction loss (paper eq. 7) of a reconstruction `estimate` of the image `target` under mask O.

        L_rec = alpha * SSIM term + (1 - alpha) * L1 term         (mixed by `Photometric.value(alpha)`)
        L1 term   = mean(|estimate - target| * O) / mean(O)
        SSIM term = mean(SSIM(estimate * O, target * O)) / mean(O)  (SSIM of the *masked images*, as upstream)

    Means run over every axis given (pairs, pixels, channels). The 2-warp loss (eq. 12) is the same function
    applied to a 2-warp estimate.

    Args:
      estimate, target: (..., H, W, C) images in [0, 1] (estimate = W(second image, D), pre-warped).
      mask: (..., H, W, 1), 1 = use the pixel.
    Returns:
      Photometric(ssim=Masked, l1=Masked) of scalars; `Masked.num / Masked.den` is the term of one cycle.
    """
    if estimate.shape != target.shape:
        raise ValueError(f"estimate {tuple(estimate.shape)} and target {tuple(target.shape)} must have the same shape")
    if mask.shape != estimate.shape[:-1] + (1,):
        raise ValueError(f"mask must have shape {estimate.shape[:-1] + (1,)}, got {tuple(mask.shape)}")
    m = jnp.mean(mask)
    l1 = jnp.mean(jnp.abs(estimate - target) * mask)
    s = jnp.mean(ssim(estimate * mask, target * mask))
    return Photometric(ssim=Masked(s, m), l1=Masked(l1, m))


class Census(NamedTuple):
    """The census photometric term (`census_loss`, `LossConfig.photometric="census"`): one `Masked` part, with the
    same `value` interface as `Photometric`."""

    census: Any

    def value(self, alpha: float):
        del alpha  # no mix: the census distance is the whole term
        return self.census


CENSUS_PATCH = 7


def _census_kernel(patch: int) -> np.ndarray:
    """(patch, patch, 1, patch^2) conv kernel whose output channel k is g(x + o_k) - g(x)."""
    r = patch // 2
    k = np.zeros((patch, patch, 1, patch * patch), np.float32)
    for i in range(patch * patch):
        k[i // patch, i % patch, 0, i] = 1.0
    k[r, r, 0, :] -= 1.0
    return k


def census_transform(image, patch: int = CENSUS_PATCH):
    """Soft ternary census transform (DDFlow/UFlow) of an RGB image.

        g = 255 * gray(image)  (ITU-R 601 weights 0.2989, 0.5870, 0.1140)
        t_k(x) = (g(x + o_k) - g(x)) / sqrt(0.81 + (g(x + o_k) - g(x))^2),   o_k over the patch x patch offsets

    with g zero outside the image (the pixels within patch // 2 of the border are excluded by `census_loss`).
    The differences are one convolution with a fixed kernel: its gradient is a transposed convolution, several
    times faster on XLA:CPU than the gradient of patch^2 shifted slices.

    Args:
      image: (..., H, W, 3) in [0, 1].
    Returns:
      (..., H, W, patch^2), offsets in row-major order (dy, then dx).
    """
    r = patch // 2
    lead, (h, w) = image.shape[:-3], image.shape[-3:-1]
    gray = 255.0 * (0.2989 * image[..., 0] + 0.5870 * image[..., 1] + 0.1140 * image[..., 2])
    t = jax.lax.conv_general_dilated(gray.reshape((-1, h, w, 1)), jnp.asarray(_census_kernel(patch), gray.dtype),
                                     (1, 1), [(r, r), (r, r)], dimension_numbers=("NHWC", "HWIO", "NHWC"))
    t = t.reshape(lead + (h, w, patch * patch))
    return t * jax.lax.rsqrt(0.81 + jnp.square(t))


def soft_hamming_distance(t1, t2):
    """Soft Hamming distance of two census transforms: sum_k d_k^2 / (0.1 + d_k^2), d = t1 - t2; (..., H, W, 1)."""
    sq = jnp.square(t1 - t2)
    return jnp.sum(sq / (0.1 + sq), axis=-1, keepdims=True)


def robust_penalty(x, eps: float = 0.01, q: float = 0.4):
    """The generalised Charbonnier-like penalty (|x| + eps)^q of DDFlow/UFlow (0.01^0.4 = 0.158 at x = 0)."""
    return jnp.power(jnp.abs(x) + eps, q)


def census_loss(estimate, target, mask, patch: int = CENSUS_PATCH) -> Census:
    """Census photometric loss of a reconstruction `estimate` of `target` under mask O (replaces eq. 7 when
    `LossConfig.photometric="census"`):

        L_census = sum(rho(H(C(estimate), C(target))) * O_c) / sum(O_c)

    C = `census_transform`, H = `soft_hamming_distance`, rho = `robust_penalty`; O_c = O with a zero band of
    patch // 2 pixels on every side (where the census patch leaves the image).

    Args:
      estimate, target: (..., H, W, 3) in [0, 1]; mask: (..., H, W, 1).
    Returns:
      Census(Masked) of scalars.
    """
    if estimate.shape != target.shape:
        raise ValueError(f"estimate {tuple(estimate.shape)} and target {tuple(target.shape)} must have the same shape")
    if mask.shape != estimate.shape[:-1] + (1,):
        raise ValueError(f"mask must have shape {estimate.shape[:-1] + (1,)}, got {tuple(mask.shape)}")
    r = patch // 2
    h, w = estimate.shape[-3:-1]
    inside = jnp.zeros((h, w, 1), mask.dtype).at[r:h - r, r:w - r].set(1.0)
    m = mask * inside
    dist = robust_penalty(soft_hamming_distance(census_transform(estimate, patch), census_transform(target, patch)))
    return Census(Masked(jnp.mean(dist * m), jnp.mean(m)))


PHOTOMETRIC_LOSSES = {"ssim_l1": photometric_loss, "census": census_loss}
"""`LossConfig.photometric` -> the function (estimate, target, mask) -> Photometric | Census."""


# --------------------------------------------------------------------------------------- eq. 8: smoothness
def smoothness_loss(disp_px, image, *, beta: float = 10.0, scale: float = 1.0 / 20.0, order: int = 2):
    """Edge-aware second-order smoothness of a correspondence map (paper eq. 8), or first-order (`order=1`).

        L_sm = (mean(w_x |d2x (D * scale)|) + mean(w_y |d2y (D * scale)|)) / 2,   w = exp(-beta * mean_c |dI|)

    The first image difference is aligned with the second map difference as upstream does (the [1:] slice):
    the second difference centred at x is weighted by the image step between x and x + 1. With order=1 the
    first differences d1x D(x) = D(x + 1) - D(x) are weighted by the image step between the same two pixels.

    Args:
      disp_px: (..., H, W, 2) pixel map (upstream smooths px / 20: `scale`).
      image: (..., H, W, C) the image the map lives in (the first image of the pair).
    Returns:
      scalar (pixels * scale, per pixel); 0 for any map linear in x and y (order 2) / any constant map (order 1).
    """
    geometry._check_map("disp_px", disp_px, image.shape[-3:-1])
    d = disp_px * scale
    gx = jnp.mean(jnp.abs(image[..., :, 1:, :] - image[..., :, :-1, :]), axis=-1, keepdims=True)
    gy = jnp.mean(jnp.abs(image[..., 1:, :, :] - image[..., :-1, :, :]), axis=-1, keepdims=True)
    if order == 1:
        d1x = d[..., :, 1:, :] - d[..., :, :-1, :]
        d1y = d[..., 1:, :, :] - d[..., :-1, :, :]
        return (jnp.mean(jnp.exp(-beta * gx) * jnp.abs(d1x)) + jnp.mean(jnp.exp(-beta * gy) * jnp.abs(d1y))) / 2
    if order != 2:
        raise ValueError(f"smoothness order must be 1 or 2, got {order!r}")
    d2x = d[..., :, 2:, :] - 2 * d[..., :, 1:-1, :] + d[..., :, :-2, :]
    d2y = d[..., 2:, :, :] - 2 * d[..., 1:-1, :, :] + d[..., :-2, :, :]
    wx = jnp.exp(-beta * gx)[..., :, 1:, :]
    wy = jnp.exp(-beta * gy)[..., 1:, :, :]
    return (jnp.mean(wx * jnp.abs(d2x)) + jnp.mean(wy * jnp.abs(d2y))) / 2


# --------------------------------------------------------------------------------- eq. 9: left-right
def lr_consistency_loss(frac, frac_other_warped):
    """Left-right correspondence consistency (paper eq. 9), in **fraction** units as upstream.

        L_lr = mean | D + W(D', D) |  over both channels

    The backward map brought into the first frame must be the negative of the forward map. For the mirrored
    term pass (D', W(D, D')).

    Args:
      frac: (..., H, W, 2) fraction map D of the stereo pairs.
      frac_other_warped: (..., H, W, 2) W(D', D), the other direction's fraction map warped by D's pixel map.
    """
    return jnp.mean(jnp.abs(-frac_other_warped - frac))


# ----------------------------------------------------------------------------------- eqs. 10-12: 2-warp
class PairMaps(NamedTuple):
    """Everything of one cycle at one scale that the 2-warp chains pick from, per pair (4, h, w, C) in
    `cycle.PAIRS` order: images, pixel maps D (forward) and D' (backward), the 1-warp reconstructions
    W(latter, D) ~ former and W(former, D') ~ latter, and the loss masks (1 on stereo pairs)."""

    former: Any
    latter: Any
    px_fwd: Any
    px_bwd: Any
    est_fwd: Any
    est_bwd: Any
    mask_fwd: Any
    mask_bwd: Any


class TwoWarpChain(NamedTuple):
    """One 2-warp term: eq. 11 warps `image` (a 1-warp reconstruction) by `flow`; eq. 12 compares the result
    with `target` under `mask`, which eq. 10 first warps by `mask_flow` (None: the mask is used as it is)."""

    name: str
    image: Any
    flow: Any
    target: Any
    mask: Any
    mask_flow: Optional[Any]


TWO_WARP_CHAINS = {
    "none": (),
    # full-1: stereo then flow. (a) R_t1 -> L_t1 -> L_t, (b) R_t -> L_t -> L_t1.
    "full1": ("R_t1->L_t1->L_t", "R_t->L_t->L_t1"),
    # full-2: flow then stereo. (a) L_t1 -> L_t -> R_t (the paper's worked example, eqs. 10-12),
    # (b) R_t1 -> R_t -> L_t.
    "full2": ("L_t1->L_t->R_t", "R_t1->R_t->L_t"),
    # full-3: full-2 (a) plus L_t1 -> R_t1 -> R_t.
    "full3": ("L_t1->L_t->R_t", "L_t1->R_t1->R_t"),
}
"""The chains of each 2-warp variant, "source -> via -> target frame"."""


def two_warp_chains(variant: str, p: PairMaps, target: str = "reconstruction") -> tuple[TwoWarpChain, ...]:
    """The 2-warp chains of a variant (paper Fig. 4, eqs. 10-11) for one cycle at one scale.

    Each chain starts from a 1-warp reconstruction (warped once along one edge of the stereo-video square) and
    warps it along the adjacent edge; the result is compared (eq. 12) with the 1-warp reconstruction of the same
    frame along the parallel edge (`target="reconstruction"`, the paper) or with the real frame (`"image"`,
    upstream code). Flow chains are masked by the flow pair's occlusion map; chains whose second warp is a
    stereo warp carry that mask across with the stereo map of the other time (eq. 10), and the mask's gradient
    then reaches that map, as upstream.
    """
    if variant not in TWO_WARP_CHAINS:
        raise ValueError(f"two_warp must be one of {TWO_WARP_TYPES}, got {variant!r}")
    S1, FL, FR, S0 = cyc.STEREO_T1, cyc.FLOW_LEFT, cyc.FLOW_RIGHT, cyc.STEREO_T
    recon = target == "reconstruction"
    chains = {
        # W(L_t1 <- R_t1) warped by F(L_t -> L_t1) ~ L_t, vs W(L_t <- R_t) (or L_t); mask O(L_t -> L_t1).
        "R_t1->L_t1->L_t": TwoWarpChain("R_t1->L_t1->L_t", p.est_fwd[S1], p.px_fwd[FL],
                                        p.est_fwd[S0] if recon else p.former[FL], p.mask_fwd[FL], None),
        # W(L_t <- R_t) warped by F(L_t1 -> L_t) ~ L_t1, vs W(L_t1 <- R_t1) (or L_t1); mask O(L_t1 -> L_t).
        "R_t->L_t->L_t1": TwoWarpChain("R_t->L_t->L_t1", p.est_fwd[S0], p.px_bwd[FL],
                                       p.est_fwd[S1] if recon else p.latter[FL], p.mask_bwd[FL], None),
        # W(L_t <- L_t1) warped by D(R_t -> L_t) ~ R_t, vs W(R_t <- R_t1) (or R_t); mask O(L_t -> L_t1) warped by
        # D(R_t1 -> L_t1): literally the paper's eqs. 10-11.
        "L_t1->L_t->R_t": TwoWarpChain("L_t1->L_t->R_t", p.est_fwd[FL], p.px_bwd[S0],
                                       p.est_fwd[FR] if recon else p.latter[S0], p.mask_fwd[FL], p.px_bwd[S1]),
        # W(R_t <- R_t1) warped by D(L_t -> R_t) ~ L_t, vs W(L_t <- L_t1) (or L_t); mask O(R_t -> R_t1) warped by
        # D(L_t1 -> R_t1).
        "R_t1->R_t->L_t": TwoWarpChain("R_t1->R_t->L_t", p.est_fwd[FR], p.px_fwd[S0],
                                       p.est_fwd[FL] if recon else p.former[S0], p.mask_fwd[FR], p.px_fwd[S1]),
        # W(R_t1 <- L_t1) warped by F(R_t -> R_t1) ~ R_t, vs W(R_t <- L_t) (or R_t); unwarped mask O(R_t -> R_t1).
        "L_t1->R_t1->R_t": TwoWarpChain("L_t1->R_t1->R_t", p.est_bwd[S1], p.px_fwd[FR],
                                        p.est_bwd[S0] if recon else p.former[FR], p.mask_fwd[FR], None),
    }
    return tuple(chains[name] for name in TWO_WARP_CHAINS[variant])


def two_warp_estimates(chains: tuple[TwoWarpChain, ...]):
    """Eqs. 10-11 of every chain: `(estimates, targets, masks)`, each stacked over the chains `(K, h, w, C)`
    (masks `(K, h, w, 1)`).

        O'      = W(O, mask_flow)     (eq. 10; O itself when the chain has no mask_flow)
        I_2warp = W(image, flow)      (eq. 11; `image` is already a 1-warp reconstruction)

    All warps of the chains (images, then the masks that are warped) go through one gather. Eq. 12 is eq. 7's
    function on these rows, photometric(I_2warp, target, O'): `scale_terms` stacks them after the 1-warp rows in
    its one `per_row` call and takes one `group_mean` per chain.
    """
    srcs = [c.image for c in chains]
    flows = [c.flow for c in chains]
    for c in chains:
        if c.mask_flow is not None:
            srcs.append(jnp.broadcast_to(c.mask, c.mask.shape[:-1] + (srcs[0].shape[-1],)))
            flows.append(c.mask_flow)
    out = geometry.warp(jnp.stack(srcs), jnp.stack(flows))
    masks, k = [], len(chains)
    for c in chains:
        if c.mask_flow is not None:
            masks.append(out[k][..., :1])
            k += 1
        else:
            masks.append(c.mask)
    return out[:len(chains)], jnp.stack([c.target for c in chains]), jnp.stack(masks)


def per_row(term, *args):
    """A term function applied to each row of its stacked arguments (`jax.vmap` over axis 0): the terms of rows
    of the same shape are one computation, which XLA compiles once instead of once per call. Each `Masked` of
    the result holds per-row means `(R,)`; `group_mean` turns a range of rows back into one term."""
    return jax.vmap(term)(*args)


def group_mean(rows, start: int, stop: int):
    """The term of rows `start:stop` of a `per_row` result: the mean over those rows of every per-row mean
    (rows have equal sizes, so this is the mean over all their pixels)."""
    return jax.tree.map(lambda x: jnp.mean(x[start:stop]), rows)


# ------------------------------------------------------------------------ self-supervision (beyond the paper)
class Student(NamedTuple):
    """The student of the self-supervision term (`LossConfig.self_supervision`): the network's scale-0 pixel maps
    of the cropped cycles and where each crop window lies in its cycle's frames."""

    px: Any  # (B * 2P, H - 2c, W - 2c, 2), rows as the full-frame maps (`cycle.batch_pair_inputs` of the crops)
    offsets: Any  # (B, 2) int32: (y, x) of each crop window's top-left pixel in the full frames, each in [0, 2c]


def self_supervision_offsets(num_cycles: int, crop: int, rng=None):
    """(B, 2) int32 crop offsets (y, x) in [0, 2 * crop]: uniform per cycle from `rng` (a PRNG key; the train
    steps pass `fold_in(state["rng"], 1)`), or the centre window (crop, crop) when `rng` is None."""
    if rng is None:
        return jnp.full((num_cycles, 2), crop, jnp.int32)
    return jax.random.randint(rng, (num_cycles, 2), 0, 2 * crop + 1, dtype=jnp.int32)


def crop_cycles(cycles, offsets, crop: int):
    """The student's frames: each cycle's four frames cut to the same (H - 2c, W - 2c) window at its offset.

    Args:
      cycles: (B, 4, H, W, 3); offsets: (B, 2) int32 (y, x), see `self_supervision_offsets`.
    Returns:
      (B, 4, H - 2c, W - 2c, 3). Pixel units are unchanged: a crop does not rescale correspondences.
    """
    _, _, h, w, ch = cycles.shape
    size = (4, h - 2 * crop, w - 2 * crop, ch)
    return jax.vmap(lambda c, o: jax.lax.dynamic_slice(c, (0, o[0], o[1], 0), size))(cycles, offsets)


def self_supervision_mask(px, num_pairs: int, cfg: LossConfig):
    """Where the teacher is trusted, per row: (2P, H, W, 1) float {0, 1}, no gradient.

    1 where the forward-backward check passes (`geometry.forward_backward_occlusion`, paper eq. 6, with the
    config's alpha1, alpha2 and norm; on stereo pairs too, which the photometric term leaves unmasked) AND the
    match x + D lies inside the full image ([0, W - 1] x [0, H - 1]). Unlike `geometry.occlusion_mask` there is no
    border band and no floor: a confident teacher is exactly what the border band is blind to.

    Args:
      px: (2P, H, W, 2) scale-0 pixel maps of one cycle (forward rows, then backward).
    """
    px = jax.lax.stop_gradient(px)
    fwd, bwd = cyc.split_directions(px, num_pairs)
    warped = geometry.warp(jnp.concatenate([bwd, fwd]), px)  # W(D', D), then W(D, D'): one gather
    occ_f, occ_b = geometry.forward_backward_occlusion(fwd, bwd, warped[:num_pairs], warped[num_pairs:],
                                                       alpha1=cfg.occ_alpha1, alpha2=cfg.occ_alpha2,
                                                       warped_bw_norm=cfg.occlusion_norm == "warped")
    h, w = px.shape[-3:-1]
    x = jnp.arange(w, dtype=px.dtype)[None, :] + px[..., 0]
    y = jnp.arange(h, dtype=px.dtype)[:, None] + px[..., 1]
    inside = (x >= 0) & (x <= w - 1) & (y >= 0) & (y <= h - 1)
    return jax.lax.stop_gradient((1 - jnp.concatenate([occ_f, occ_b])) * inside[..., None].astype(px.dtype))


SELF_SUPERVISION_EPS = 1e-6
"""Added to the teacher-mask count that normalises the self-supervision term (an empty mask gives 0, not NaN)."""


def self_supervision_penalty(d):
    """The robust penalty of a student-teacher difference d (..., 2): (|d| + 0.01)^0.4 - 0.01^0.4 (the census
    path's `robust_penalty` shifted to 0 at d = 0), averaged over the two channels; (..., 1)."""
    return jnp.mean(robust_penalty(d) - 0.01**0.4, axis=-1, keepdims=True)


def self_supervision_loss(teacher_px, student_px, offset, cfg: LossConfig) -> Masked:
    """Self-supervision term of one cycle (beyond the paper; SelFlow / SMURF / Flow2Stereo):

        L_self = sum(rho(S - crop(T)) * M) / (sum(M) + eps)

    over all rows (both directions of every active pair) and pixels of the crop window. T = the full-frame maps
    with stopped gradient (teacher), S = the maps of the cropped frames (student), crop = the student's window
    (pixel units need no change), M = `self_supervision_mask` of T cropped to the window, rho =
    `self_supervision_penalty`, eps = `SELF_SUPERVISION_EPS`.

    Args:
      teacher_px: (2P, H, W, 2) scale-0 pixel maps of the full frames.
      student_px: (2P, H - 2c, W - 2c, 2) scale-0 pixel maps of the cropped frames (c = cfg.self_supervision_crop).
      offset: (2,) int32 (y, x) of the window's top-left pixel in the full frames.
    Returns:
      Masked(sum(rho M) / N, (sum(M) + eps) / N) (N = the window's row-pixel count), reduced over cycles like
      every other term (`reduce_over_cycles`).
    """
    rows, h, w, _ = teacher_px.shape
    c = cfg.self_supervision_crop
    want = (rows, h - 2 * c, w - 2 * c, 2)
    if tuple(student_px.shape) != want:
        raise ValueError(f"student maps must have shape {want} (the teacher's {tuple(teacher_px.shape)} cropped by "
                         f"loss.self_supervision_crop={c} on each side), got {tuple(student_px.shape)}")
    teacher = jax.lax.stop_gradient(teacher_px)
    mask = self_supervision_mask(teacher, rows // 2, cfg)
    window = lambda x: jax.lax.dynamic_slice(x, (0, offset[0], offset[1], 0), want[:3] + x.shape[-1:])
    m = window(mask)
    n = m.size
    pen = self_supervision_penalty(student_px - window(teacher))
    return Masked(jnp.sum(pen * m) / n, (jnp.sum(m) + SELF_SUPERVISION_EPS) / n)


def _check_student(student: Student, num_cycles: int, hw, cfg: LossConfig) -> None:
    c, rows = cfg.self_supervision_crop, cyc.rows_per_cycle(cfg.pairs)
    want = (num_cycles * rows, hw[0] - 2 * c, hw[1] - 2 * c, 2)
    if tuple(student.px.shape) != want:
        raise ValueError(f"student maps must have shape {want} ({num_cycles} cycles of {rows} rows, the frames "
                         f"cropped by loss.self_supervision_crop={c} on each side), got {tuple(student.px.shape)}")
    if tuple(student.offsets.shape) != (num_cycles, 2):
        raise ValueError(f"student offsets must have shape {(num_cycles, 2)} (y, x per cycle), got "
                         f"{tuple(student.offsets.shape)}")


def add_self_supervision(total, terms: dict, term, cfg: LossConfig, step=None):
    """The total loss with the reduced self-supervision term added, and the terms with it as "self_supervision"
    (unweighted; 0 before `cfg.self_supervision_start_step`; step None = after it) and the new "total"."""
    if cfg.self_supervision_start_step > 0 and step is not None:
        term = jnp.where(step >= cfg.self_supervision_start_step, term, jnp.zeros_like(term))
    total = total + cfg.self_supervision * term
    return total, dict(terms, self_supervision=term, total=total)


# ------------------------------------------------------------- background fill of stereo occlusions (beyond the paper)
def occlusion_fill_targets(px, num_pairs: int, cfg: LossConfig):
    """Where each row's map is untrusted and what the background fill says it should be, no gradient.

    Trusted = `self_supervision_mask` (the forward-backward check passes and the match lies inside the other
    image). For an untrusted pixel, the nearest trusted pixels of the same image row to its left and to its
    right; the target is the horizontal component of the one with the smaller magnitude (the farther surface),
    or of the only one there is. A row with no trusted pixel gives no target.

    Args:
      px: (2P, H, W, 2) scale-0 pixel maps of P pairs (forward rows, then backward).
    Returns:
      (target (2P, H, W) px, mask (2P, H, W) float {0, 1}: untrusted pixels with a target).
    """
    px = jax.lax.stop_gradient(px)
    trusted = self_supervision_mask(px, num_pairs, cfg)[..., 0] > 0
    w = px.shape[-2]
    cols = jnp.arange(w, dtype=jnp.int32)
    axis = trusted.ndim - 1
    left = jax.lax.cummax(jnp.where(trusted, cols, -1), axis=axis)  # nearest trusted column at or left of x
    right = jax.lax.cummin(jnp.where(trusted, cols, w), axis=axis, reverse=True)  # ... at or right of x
    u = px[..., 0]
    u_left = jnp.take_along_axis(u, jnp.clip(left, 0, w - 1), axis=axis)
    u_right = jnp.take_along_axis(u, jnp.clip(right, 0, w - 1), axis=axis)
    has_left, has_right = left >= 0, right < w
    take_left = has_left & (~has_right | (jnp.abs(u_left) <= jnp.abs(u_right)))
    target = jnp.where(take_left, u_left, u_right)
    mask = (~trusted & (has_left | has_right)).astype(px.dtype)
    return target, mask  # from the stopped maps: no gradient


def occlusion_fill_penalty(d):
    """The fill term's robust penalty of a difference d (px): (d^2 + 0.01^2)^0.2 - 0.01^0.4, i.e. about
    |d|^0.4 as `robust_penalty`, but smooth at d = 0 (its gradient there is 0, not +-0.4 * 0.01^-0.6: a pixel
    already at its fill value is not pushed either way)."""
    return jnp.power(jnp.square(d) + 0.01 ** 2, 0.2) - 0.01 ** 0.4


def occlusion_fill_loss(px, cfg: LossConfig) -> Masked:
    """Background-fill term of one cycle (`LossConfig.occlusion_fill`; beyond the paper):

        L_fill = sum(rho(u - t) * M) / N

    over the stereo pairs' rows (both directions) of the scale-0 maps: u = a map's horizontal component, t and
    M = `occlusion_fill_targets` (the fill value and where it applies), rho = `occlusion_fill_penalty`,
    N = the rows' pixel count (a plain mean, like the smoothness term: the term grows with the
    share of untrusted pixels).

    Args:
      px: (2P, H, W, 2) scale-0 pixel maps of one cycle (the active pairs' forward rows, then backward).
    Returns:
      Masked(L_fill, 1), reduced over cycles like every other term.
    """
    p = px.shape[0] // 2
    stereo = [i for i, k in enumerate(cfg.pairs) if cyc.PAIRS[k].task == "stereo"]
    # the stereo pairs' rows alone, still forward then backward: the check pairs each row with its reverse
    stereo_px = px[np.array(stereo + [p + i for i in stereo])]
    target, mask = occlusion_fill_targets(stereo_px, len(stereo), cfg)
    pen = occlusion_fill_penalty(stereo_px[..., 0] - target)
    return Masked(jnp.sum(pen * mask) / mask.size, jnp.ones((), px.dtype))


# ----------------------------------------------------------------------------------- eq. 13: cycle loss
class ScaleTerms(NamedTuple):
    """Every unweighted term of one cycle at one scale (`Masked` per cycle; scalars once reduced)."""

    photo_fwd: Photometric  # eq. 7: former vs W(latter, D)
    photo_bwd: Photometric  # eq. 7: latter vs W(former, D')
    smooth_fwd: Masked  # eq. 8 of D (in the former frame), a plain mean
    smooth_bwd: Masked  # eq. 8 of D' (in the latter frame)
    lr_fwd: Optional[Masked]  # eq. 9 of the stereo pairs' D, a plain mean (None without stereo pairs)
    lr_bwd: Optional[Masked]  # eq. 9 of the stereo pairs' D'
    two_warp: tuple  # eq. 12, one Photometric per chain of the 2-warp variant


def _check_maps(maps, rows: int, h: int, w: int, num_scales: int):
    if not isinstance(maps, Mapping) or "px" not in maps or "frac" not in maps:
        raise ValueError("maps must be a dict with 'px' and 'frac' tuples of per-scale (N, H_s, W_s, 2) arrays")
    for key in ("px", "frac"):
        if len(maps[key]) < num_scales:
            raise ValueError(f"maps[{key!r}] has {len(maps[key])} scales, expected {num_scales}")
        for s in range(num_scales):
            m = maps[key][s]
            want = (rows, h >> s, w >> s, 2)
            if tuple(m.shape) != want:
                raise ValueError(f"maps[{key!r}][{s}] must have shape {want} (rows, H/2^s, W/2^s, 2), got {tuple(m.shape)}")


def _select_rows(maps, cfg: LossConfig):
    """Accept either all 8 rows (then pick the active pairs) or exactly the active pairs' 2P rows."""
    pairs = cfg.pairs
    n = maps["px"][0].shape[0]
    if n == 8 and len(pairs) != 4:
        idx = list(pairs) + [4 + k for k in pairs]
        return {k: tuple(jnp.stack([m[i] for i in idx]) for m in v) for k, v in maps.items()}
    return maps


def scale_terms(px, frac, frames, cfg: LossConfig, step=None) -> ScaleTerms:
    """Every term of one cycle at one scale.

    Args:
      px, frac: (2P, h, w, 2) pixel and fraction maps of the cycle's active pairs (forward rows, then backward).
      frames: (4, h, w, 3) the cycle's frames at this scale.
      step: the training step (int32 scalar), read only with `cfg.occlusion_start_step > 0`: before that step
        flow pairs are not masked. None = after it (masks on).
    """
    pairs = cfg.pairs
    p = len(pairs)
    former, latter = cyc.pair_images(frames, pairs)  # static slices, no gather
    px_f, px_b = cyc.split_directions(px, p)
    fr_f, fr_b = cyc.split_directions(frac, p)

    # Everything warped by D (rows 0..P-1) or D' (rows P..2P-1) in ONE gather: the reconstructions (latter by
    # D, former by D'), the other direction's pixel map (eq. 6) and its fraction map (eq. 9). Fewer, wider
    # gathers compile much faster on XLA:CPU than many small ones.
    src = jnp.concatenate([jnp.concatenate([latter, former]), jnp.concatenate([px_b, px_f]),
                           jnp.concatenate([fr_b, fr_f])], axis=-1)
    warped = geometry.warp(src, jnp.concatenate([px_f, px_b]))
    est_f, est_b = warped[:p, ..., :3], warped[p:, ..., :3]  # W(latter, D) ~ former, W(former, D') ~ latter
    px_b_w, px_f_w = warped[:p, ..., 3:5], warped[p:, ..., 3:5]  # W(D', D), W(D, D')
    fr_b_w, fr_f_w = warped[:p, ..., 5:7], warped[p:, ..., 5:7]

    # Occlusion masks (eq. 6) on flow pairs only; stereo pairs get mask 1 (paper Sec. 3.3) unless
    # `stereo_occlusion`. Detached.
    m_f, m_b = geometry.occlusion_mask(px_f, px_b, px_b_w, px_f_w, alpha1=cfg.occ_alpha1, alpha2=cfg.occ_alpha2,
                                       warped_bw_norm=cfg.occlusion_norm == "warped",
                                       border_ratio=cfg.border_ratio, floor=cfg.mask_floor)
    unmasked = jnp.array([cyc.PAIRS[k].task == "stereo" and not cfg.stereo_occlusion
                          for k in pairs])[:, None, None, None]
    if cfg.occlusion_start_step > 0 and step is not None:  # before the start step flow pairs are unmasked too
        unmasked = unmasked | (step < cfg.occlusion_start_step)
    m_f = jax.lax.stop_gradient(jnp.where(unmasked, 1.0, m_f))
    m_b = jax.lax.stop_gradient(jnp.where(unmasked, 1.0, m_b))

    # Every term compares rows of the same shape, so each is ONE computation over stacked rows (`per_row`),
    # not one call per direction and chain: the SSIM / census graph is built once per scale (eq. 7 for D and
    # D', eq. 12 for the 2-warp chains), which is most of what XLA compiles for the loss.
    photometric = PHOTOMETRIC_LOSSES[cfg.photometric]
    estimates, targets, masks = [est_f, est_b], [former, latter], [m_f, m_b]
    chains = ()
    if cfg.two_warp != "none":
        chains = two_warp_chains(cfg.two_warp, PairMaps(former, latter, px_f, px_b, est_f, est_b, m_f, m_b),
                                 cfg.two_warp_target)
        for part, x in zip((estimates, targets, masks), two_warp_estimates(chains)):
            part.append(x)
    photo = per_row(photometric, jnp.concatenate(estimates), jnp.concatenate(targets), jnp.concatenate(masks))
    photo_fwd, photo_bwd = group_mean(photo, 0, p), group_mean(photo, p, 2 * p)
    two_warp = tuple(group_mean(photo, 2 * p + i, 2 * p + i + 1) for i in range(len(chains)))

    one = jnp.ones((), jnp.float32)  # plain means are Masked(x, 1): every term is reduced the same way
    smooth = functools.partial(smoothness_loss, beta=cfg.smoothness_edge_constant(), scale=cfg.smooth_scale,
                               order=cfg.smoothness_order)
    smooth_rows = per_row(smooth, px, jnp.concatenate([former, latter]))  # D in the former, D' in the latter
    smooth_fwd = Masked(group_mean(smooth_rows, 0, p), one)
    smooth_bwd = Masked(group_mean(smooth_rows, p, 2 * p), one)

    st = [i for i, k in enumerate(pairs) if cyc.PAIRS[k].task == "stereo"]
    lr_fwd = lr_bwd = None
    if st:  # stereo pairs only: (D, W(D', D)) rows, then (D', W(D, D')) rows
        rows = lambda x: jnp.stack([x[i] for i in st])
        lr_rows = per_row(lr_consistency_loss, jnp.concatenate([rows(fr_f), rows(fr_b)]),
                          jnp.concatenate([rows(fr_b_w), rows(fr_f_w)]))
        lr_fwd = Masked(group_mean(lr_rows, 0, len(st)), one)
        lr_bwd = Masked(group_mean(lr_rows, len(st), 2 * len(st)), one)
    return ScaleTerms(photo_fwd, photo_bwd, smooth_fwd, smooth_bwd, lr_fwd, lr_bwd, two_warp)


def cycle_terms(maps, cycle, cfg: LossConfig, pyramid=None, step=None) -> tuple[ScaleTerms, ...]:
    """`scale_terms` of one cycle at every scale the loss sums (`cfg.loss_scales`: all four, or only the finest,
    compared with the full-resolution frames).

    Args:
      maps: network output for the cycle's 2P inputs (`cycle.pair_inputs` order): {"px": (s0..s3), "frac":
        (s0..s3)}, each (2P, H_s, W_s, 2); all 8 rows are accepted too for a task subset.
      cycle: (4, H, W, 3) frames in [0, 1].
      pyramid: optional tuple of per-scale (4, H_s, W_s, 3) frames; `geometry.image_pyramid` when None.
      step: the training step (see `scale_terms`).
    """
    if cycle.ndim != 4 or cycle.shape[0] != 4 or cycle.shape[-1] != 3:
        raise ValueError(f"cycle must have shape (4, H, W, 3), got {tuple(cycle.shape)}")
    h, w = cycle.shape[1:3]
    f = 2 ** (cfg.num_scales - 1)
    if h % f or w % f:
        raise ValueError(f"cycle H and W must be divisible by {f} for {cfg.num_scales} scales, got {h}x{w}")
    maps = _select_rows(maps, cfg)
    _check_maps(maps, 2 * len(cfg.pairs), h, w, cfg.num_scales)
    if pyramid is None:
        pyramid = (cycle,) if cfg.scales == "finest" else geometry.image_pyramid(cycle, cfg.num_scales)
    return tuple(scale_terms(maps["px"][s], maps["frac"][s], pyramid[s], cfg, step) for s in cfg.loss_scales)


def reduce_over_cycles(terms, reduction: str):
    """Per-cycle `Masked` terms (leading axis = cycles) -> scalars, normalised per cycle (reduction="cycle": the
    mean of the ratios) or over the batch ("batch", upstream: the ratio of the means)."""
    def reduce(x: Masked):
        return jnp.mean(x.num) / jnp.mean(x.den) if reduction == "batch" else jnp.mean(x.num / x.den)

    return jax.tree.map(reduce, terms, is_leaf=lambda x: isinstance(x, Masked))


def total_loss(scales: tuple[ScaleTerms, ...], cfg: LossConfig):
    """The total loss (paper eq. 13) from reduced per-scale terms, and every term by name (for logging).

        total = sum_s [photo_fwd + photo_bwd] + lambda_sm * sum_s [smooth_fwd + smooth_bwd]
                + lambda_lr * sum_s [lr_fwd + lr_bwd] + w_2warp * sum_s [two_warp_a + two_warp_b]

    s runs over `cfg.loss_scales`; lambda_sm is `cfg.smoothness_weight()` (lambda_sm1 for first order); w_2warp =
    lambda_2warp (paper) or 0.1 (upstream), see `LossConfig.two_warp_term_weight`.
    Term names: "<term>_<fwd|bwd>/<scale>" per scale ("l1_", "ssim_" or "census_", "photo_", "smooth_",
    "left_right_"), "two_warp_<a|b>/<scale>", and the sums over scales "photo_fwd", "photo_bwd", "smooth_fwd",
    "smooth_bwd", "left_right" (the LR consistency term; "lr" in the logs is the learning rate), "two_warp_a", "two_warp_b", "two_warp", "total".
    """
    a = cfg.alpha
    terms = {}
    for s, t in enumerate(scales):
        for d, photo in (("fwd", t.photo_fwd), ("bwd", t.photo_bwd)):
            for part, value in photo._asdict().items():  # l1 and ssim, or census
                terms[f"{part}_{d}/{s}"] = value
            terms[f"photo_{d}/{s}"] = photo.value(a)
        terms[f"smooth_fwd/{s}"], terms[f"smooth_bwd/{s}"] = t.smooth_fwd, t.smooth_bwd
        if t.lr_fwd is not None:
            terms[f"left_right_fwd/{s}"], terms[f"left_right_bwd/{s}"] = t.lr_fwd, t.lr_bwd
        for tag, photo in zip("ab", t.two_warp):
            terms[f"two_warp_{tag}/{s}"] = photo.value(a)
    n = range(len(scales))
    for d in ("fwd", "bwd"):
        terms[f"photo_{d}"] = sum(terms[f"photo_{d}/{s}"] for s in n)
        terms[f"smooth_{d}"] = sum(terms[f"smooth_{d}/{s}"] for s in n)
    # "left_right", not "lr": in the logs "lr" is the learning rate
    terms["left_right"] = (sum(terms[f"left_right_fwd/{s}"] + terms[f"left_right_bwd/{s}"] for s in n)
                           if "left_right_fwd/0" in terms else jnp.zeros(()))
    two_warp = jnp.zeros(())
    for tag in "ab"[:len(scales[0].two_warp)]:
        terms[f"two_warp_{tag}"] = sum(terms[f"two_warp_{tag}/{s}"] for s in n)
        two_warp = two_warp + terms[f"two_warp_{tag}"]
    terms["two_warp"] = two_warp
    total = (terms["photo_fwd"] + terms["photo_bwd"]
             + cfg.smoothness_weight() * (terms["smooth_fwd"] + terms["smooth_bwd"])
             + cfg.lambda_lr * terms["left_right"] + cfg.two_warp_term_weight() * two_warp)
    terms["total"] = total
    return total, terms


def cycle_loss(maps, cycles, cfg: LossConfig, pyramids=None, step=None, student: Optional[Student] = None):
    """The training loss of a batch of cycles (paper eq. 13): `cycle_terms` vmapped over the cycles, reduced
    over them (`cfg.reduction`), weighted by `total_loss`; with `cfg.occlusion_fill > 0` plus that weight times
    the `occlusion_fill_loss` of the scale-0 maps; with `cfg.self_supervision > 0` plus that weight times
    the `self_supervision_loss` of the full-frame scale-0 maps (teacher) and `student` (`add_self_supervision`).

    Args:
      maps: network output for `cycle.batch_pair_inputs(cycles, cfg.pairs)`: {"px", "frac"} tuples of
        per-scale (B * 2P, H_s, W_s, 2) maps (cycle-major).
      cycles: (B, 4, H, W, 3) frames in [0, 1]; a single cycle (4, H, W, 3) is a batch of one.
      pyramids: optional per-scale (B, 4, H_s, W_s, 3) frames (computed when None).
      step: the training step, an int32 scalar (read only with `cfg.occlusion_start_step > 0` or
        `cfg.self_supervision_start_step > 0`).
      student: the self-supervision student (`Student`), needed exactly when `cfg.self_supervision > 0`.
    Returns:
      (total scalar, dict of every term by name; see `total_loss`, and "occlusion_fill" (unweighted,
      `occlusion_fill_loss`) and "self_supervision" when they are on).
    """
    if cycles.ndim == 4:
        cycles = cycles[None]
        pyramids = None if pyramids is None else tuple(p[None] for p in pyramids)
    if cycles.ndim != 5:
        raise ValueError(f"cycles must have shape (B, 4, H, W, 3), got {tuple(cycles.shape)}")
    b = cycles.shape[0]
    n = maps["px"][0].shape[0]
    if n % b:
        raise ValueError(f"maps have {n} rows, not a multiple of the {b} cycles")
    if (student is not None) != (cfg.self_supervision > 0):
        raise ValueError("the student maps (`student`) are needed exactly when loss.self_supervision > 0, got "
                         f"self_supervision={cfg.self_supervision} and student "
                         f"{'given' if student is not None else None}")
    if student is not None:
        _check_student(student, b, cycles.shape[2:4], cfg)
    per_cycle = cyc.unbatch_maps(maps, b)
    terms = jax.vmap(lambda m, c, p: cycle_terms(m, c, cfg, p, step))(per_cycle, cycles, pyramids)
    total, named = total_loss(reduce_over_cycles(terms, cfg.reduction), cfg)
    rows = cyc.rows_per_cycle(cfg.pairs)
    finest = per_cycle["px"][0]  # (B, 2P or 8, H, W, 2); as `_select_rows`, all 8 rows are accepted
    if finest.shape[1] != rows:
        finest = finest[:, np.array(list(cfg.pairs) + [4 + k for k in cfg.pairs])]
    if cfg.occlusion_fill > 0:
        fill = reduce_over_cycles(jax.vmap(lambda m: occlusion_fill_loss(m, cfg))(finest), cfg.reduction)
        total = total + cfg.occlusion_fill * fill
        named = dict(named, occlusion_fill=fill, total=total)
    if student is None:
        return total, named
    teacher = finest
    students = student.px.reshape((b, rows) + student.px.shape[1:])
    term = jax.vmap(lambda t, s, o: self_supervision_loss(t, s, o, cfg))(teacher, students, student.offsets)
    return add_self_supervision(total, named, reduce_over_cycles(term, cfg.reduction), cfg, step)
