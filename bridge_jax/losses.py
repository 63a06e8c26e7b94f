"""The paper's unsupervised loss terms and the cycle loss that combines them (pure JAX).

Terms (paper Sec. 3.3; exact upstream numerics in REFERENCE.md §1b):
  * reconstruction (photometric) loss  L_rec  = alpha * (1 - SSIM)/2 + (1 - alpha) * L1, under a mask
  * edge-aware 2nd-order smoothness     L_sm   (on the pixel map / 20, image weights exp(-beta |dI|))
  * left-right consistency              L_lr   (stereo pairs, fraction units)
  * 2-warp consistency                  L_2warp (full-1 / full-2 / full-3)

Units: images in [0, 1]; pixel maps in pixels of their scale; fraction maps in fractions of W_s / H_s.
All four scales are summed with equal weights, both directions of every pair are used.

Normalisation. Upstream divides masked means by the mean mask over the whole batch of cycles. Here
every masked term is computed per cycle as a (numerator mean, mask mean) pair; `reduction="cycle"`
(default) averages the per-cycle ratios over cycles, `reduction="batch"` divides the batch means (upstream
exactly). The two agree whenever the cycles of a batch are identical, and for a single cycle.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Mapping

import jax
import jax.numpy as jnp

from bridge_jax import cycle as cyc
from bridge_jax import geometry

TWO_WARP_TYPES = ("none", "full1", "full2", "full3")


@dataclasses.dataclass(frozen=True)
class LossConfig:
    """Hyper-parameters and paper/upstream switches of the cycle loss.

    Defaults follow the paper; `LossConfig.upstream()` reproduces upstream's code.
    """

    tasks: str = "flow_stereo"  # flow_stereo | stereo_only | flow_only
    two_warp: str = "none"  # none | full1 | full2 | full3
    # The 2-warp estimate is compared with the 1-warp reconstruction of the same frame (paper eq. 7 and
    # the author's stated intent) or with the real image (upstream code).
    two_warp_target: str = "reconstruction"  # reconstruction | image
    # paper: lambda_2warp = 0.2 times the sum of the variant's two terms; upstream: 0.1 per term.
    two_warp_weighting: str = "paper"  # paper | upstream
    # Occlusion threshold uses |W(D', D)|^2 (paper eq. 3) or the unwarped |D'|^2 (upstream code).
    occlusion_norm: str = "warped"  # warped | unwarped
    reduction: str = "cycle"  # cycle | batch (see module docstring)
    alpha: float = 0.85
    beta: float = 10.0
    lambda_sm: float = 10.0
    lambda_lr: float = 0.5
    lambda_2warp: float = 0.2
    occ_alpha1: float = 0.01
    occ_alpha2: float = 0.5
    border_ratio: float = 0.1
    mask_floor: float = 1e-3
    smooth_scale: float = 1.0 / 20.0  # upstream divides the pixel map by 20 before the smoothness term
    num_scales: int = 4

    def __post_init__(self):
        choices = {
            "tasks": cyc.TASKS,
            "two_warp": TWO_WARP_TYPES,
            "two_warp_target": ("reconstruction", "image"),
            "two_warp_weighting": ("paper", "upstream"),
            "occlusion_norm": ("warped", "unwarped"),
            "reduction": ("cycle", "batch"),
        }
        for field, allowed in choices.items():
            if getattr(self, field) not in allowed:
                raise ValueError(f"loss.{field} must be one of {allowed}, got {getattr(self, field)!r}")
        if self.two_warp != "none" and self.tasks != "flow_stereo":
            raise ValueError(f"loss.two_warp={self.two_warp!r} needs stereo and flow pairs (tasks='flow_stereo'), got tasks={self.tasks!r}")

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
        """Upstream code's behaviour (REFERENCE.md §1b), e.g. for parity with the peer fixture."""
        base = dict(two_warp_target="image", two_warp_weighting="upstream", occlusion_norm="unwarped", reduction="batch")
        base.update(overrides)
        return cls(**base)

    @property
    def pairs(self) -> tuple[int, ...]:
        return cyc.pairs_for_tasks(self.tasks)

    def two_warp_term_weight(self) -> float:
        """Multiplier of each 2-warp term (both variants have two terms)."""
        return self.lambda_2warp if self.two_warp_weighting == "paper" else 0.1


# ------------------------------------------------------------------------------------- basic terms
def _avg_pool3(x):
    """3x3 mean pooling, stride 1, VALID: (..., H, W, C) -> (..., H-2, W-2, C)."""
    # Written as shifted slices rather than lax.reduce_window: it fuses with the SSIM arithmetic and
    # compiles several times faster on XLA:CPU.
    rows = x[..., :-2, :, :] + x[..., 1:-1, :, :] + x[..., 2:, :, :]
    return (rows[..., :-2, :] + rows[..., 1:-1, :] + rows[..., 2:, :]) / 9.0


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


def photometric_parts(estimate, target, mask):
    """The masked photometric terms as (numerator mean, mask mean) pairs (upstream's normalisation).

    l1   = mean(|est - I| * M)       / mean(M)
    ssim = mean(SSIM(est * M, I * M)) / mean(M)    (SSIM of the *masked images*, as upstream)
    Means run over every axis given (rows, pixels, channels).

    Args:
      estimate, target: (..., H, W, C) images in [0, 1].
      mask: (..., H, W, 1), 1 = use the pixel.
    Returns:
      dict "l1" / "ssim" -> (numerator mean, mask mean).
    """
    if estimate.shape != target.shape:
        raise ValueError(f"estimate {tuple(estimate.shape)} and target {tuple(target.shape)} must have the same shape")
    if mask.shape != estimate.shape[:-1] + (1,):
        raise ValueError(f"mask must have shape {estimate.shape[:-1] + (1,)}, got {tuple(mask.shape)}")
    m = jnp.mean(mask)
    l1 = jnp.mean(jnp.abs(estimate - target) * mask)
    s = jnp.mean(ssim(estimate * mask, target * mask))
    return {"l1": (l1, m), "ssim": (s, m)}


def photometric_loss(estimate, target, mask, *, alpha: float = 0.85):
    """alpha * SSIM term + (1 - alpha) * L1 term, each normalised by the mask mean (dimensionless)."""
    p = photometric_parts(estimate, target, mask)
    return alpha * p["ssim"][0] / p["ssim"][1] + (1 - alpha) * p["l1"][0] / p["l1"][1]


def smoothness_loss(disp_px, image, *, beta: float = 10.0, scale: float = 1.0 / 20.0):
    """Edge-aware second-order smoothness of a correspondence map.

    (mean(w_x |d2x (D * scale)|) + mean(w_y |d2y (D * scale)|)) / 2,  w = exp(-beta * mean_c |dI|)
    with the first image difference aligned to the second map difference as upstream ([1:] slice).

    Args:
      disp_px: (..., H, W, 2) pixel map (upstream smooths px / 20).
      image: (..., H, W, C) the image the map lives in (the first image of the pair).
    Returns:
      scalar (pixels * scale, per pixel); 0 for any map linear in x and y.
    """
    geometry._check_map("disp_px", disp_px, image.shape[-3:-1])
    d = disp_px * scale
    d2x = d[..., :, 2:, :] - 2 * d[..., :, 1:-1, :] + d[..., :, :-2, :]
    d2y = d[..., 2:, :, :] - 2 * d[..., 1:-1, :, :] + d[..., :-2, :, :]
    gx = jnp.mean(jnp.abs(image[..., :, 1:, :] - image[..., :, :-1, :]), axis=-1, keepdims=True)
    gy = jnp.mean(jnp.abs(image[..., 1:, :, :] - image[..., :-1, :, :]), axis=-1, keepdims=True)
    wx = jnp.exp(-beta * gx)[..., :, 1:, :]
    wy = jnp.exp(-beta * gy)[..., 1:, :, :]
    return (jnp.mean(wx * jnp.abs(d2x)) + jnp.mean(wy * jnp.abs(d2y))) / 2


def lr_consistency_loss(frac_fw, frac_bw, px_fw):
    """Left-right correspondence consistency, in **fraction** units (upstream).

    mean | -W(frac', D) - frac |  over both channels: the backward fraction map brought into the first
    frame must be the negative of the forward one. Pass (bw, fw, px_bw) for the mirrored term.

    Args:
      frac_fw: (..., H, W, 2) forward fraction map; frac_bw: backward fraction map; px_fw: forward pixel map.
    """
    return lr_consistency_from_warped(frac_fw, geometry.warp(frac_bw, px_fw))


def lr_consistency_from_warped(frac_fw, frac_bw_warped):
    """mean | -W(frac', D) - frac | given the already warped backward fraction map W(frac', D)."""
    return jnp.mean(jnp.abs(-frac_bw_warped - frac_fw))


# ---------------------------------------------------------------------------------------- 2-warp
# Each chain: (name, source reconstruction, second map, target frame, mask, reconstruction-target).
# Notation per cycle: D_k / D'_k = forward / backward pixel map of pair k (cycle.PAIRS), est_fwd_k =
# W(latter_k, D_k) ~ former_k, est_bwd_k = W(former_k, D'_k) ~ latter_k; O_fw_k / O_bw_k = masks.
# The 1-warp reconstruction used as target (paper) is the one along the edge of the stereo-video
# square parallel to the chain's first warp (paper Fig. 4a: I^{r,t} from I^{r,t+1} for the chain
# L_t1 -> L_t -> R_t).
def two_warp_chains(variant: str):
    """Names of the 2-warp chains of a variant (documentation and tests)."""
    return {
        "none": (),
        # full-1: stereo then flow. (a) R_t1 -> L_t1 -> L_t, (b) R_t -> L_t -> L_t1.
        "full1": ("R_t1->L_t1->L_t", "R_t->L_t->L_t1"),
        # full-2: flow then stereo. (a) L_t1 -> L_t -> R_t, (b) R_t1 -> R_t -> L_t.
        "full2": ("L_t1->L_t->R_t", "R_t1->R_t->L_t"),
        # full-3: full-2 (a) plus L_t1 -> R_t1 -> R_t.
        "full3": ("L_t1->L_t->R_t", "L_t1->R_t1->R_t"),
    }[variant]


def _two_warp_chains(variant, px_f, px_b, est_f, est_b, m_f, m_b, former, latter, target_mode):
    """Per chain: (name, image to warp, its 2nd map, target, mask, mask_is_warped) for one cycle at one scale.

    Arguments are per-pair stacks (P=4, h, w, C) in cycle.PAIRS order. When mask_is_warped the mask is
    warped by the same map as the image (its gradient reaches that map, as upstream).
    """
    S1, FL, FR, S0 = cyc.STEREO_T1, cyc.FLOW_LEFT, cyc.FLOW_RIGHT, cyc.STEREO_T
    recon = target_mode == "reconstruction"
    chains = {
        # R_t1 -> L_t1 -> L_t: est(L_t1 from R_t1) warped by F(L_t -> L_t1); vs L_t (or est(L_t from R_t));
        # mask O(L_t -> L_t1).
        "R_t1->L_t1->L_t": (est_f[S1], px_f[FL], est_f[S0] if recon else former[FL], m_f[FL], False),
        # R_t -> L_t -> L_t1: est(L_t from R_t) warped by F(L_t1 -> L_t); vs L_t1 (or est(L_t1 from R_t1));
        # mask O(L_t1 -> L_t).
        "R_t->L_t->L_t1": (est_f[S0], px_b[FL], est_f[S1] if recon else latter[FL], m_b[FL], False),
        # L_t1 -> L_t -> R_t: est(L_t from L_t1) warped by D(R_t -> L_t); vs R_t (or est(R_t from R_t1));
        # mask O(L_t -> L_t1) warped by D(R_t1 -> L_t1): literally the paper's eq. 6.
        "L_t1->L_t->R_t": (est_f[FL], px_b[S0], est_f[FR] if recon else latter[S0], (m_f[FL], px_b[S1]), True),
        # R_t1 -> R_t -> L_t: est(R_t from R_t1) warped by D(L_t -> R_t); vs L_t (or est(L_t from L_t1));
        # mask O(R_t -> R_t1) warped by D(L_t1 -> R_t1).
        "R_t1->R_t->L_t": (est_f[FR], px_f[S0], est_f[FL] if recon else former[S0], (m_f[FR], px_f[S1]), True),
        # L_t1 -> R_t1 -> R_t: est(R_t1 from L_t1) warped by F(R_t -> R_t1); vs R_t (or est(R_t from L_t));
        # unwarped mask O(R_t -> R_t1).
        "L_t1->R_t1->R_t": (est_b[S1], px_f[FR], est_b[S0] if recon else former[FR], m_f[FR], False),
    }
    return [(name,) + chains[name] for name in two_warp_chains(variant)]


def _two_warp_terms(variant, px_f, px_b, est_f, est_b, m_f, m_b, former, latter, target_mode):
    """[(name, 2-warp estimate, target, mask)] of a variant at one scale; all warps in one batched call."""
    chains = _two_warp_chains(variant, px_f, px_b, est_f, est_b, m_f, m_b, former, latter, target_mode)
    # One warp call for both chains: rows = (chain image + mask), then (chain masks warped by their own map).
    srcs, disps = [], []
    for _, image, disp, _, mask, warped in chains:
        srcs.append(image)
        disps.append(disp)
    for _, _, _, _, mask, warped in chains:
        if warped:
            srcs.append(jnp.broadcast_to(mask[0], mask[0].shape[:-1] + (srcs[0].shape[-1],)))
            disps.append(mask[1])
    out = geometry.warp(jnp.stack(srcs), jnp.stack(disps))
    terms, k = [], len(chains)
    for i, (name, _, _, target, mask, warped) in enumerate(chains):
        if warped:
            mask = out[k][..., :1]
            k += 1
        terms.append((name, out[i], target, mask))
    return terms


# ------------------------------------------------------------------------------------- cycle loss
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


def cycle_loss_parts(maps, cycle, cfg: LossConfig, pyramid=None):
    """Every loss term of one cycle as (numerator mean, denominator mean) pairs.

    Args:
      maps: network output for the cycle's 2P inputs (cycle.pair_inputs order): {"px": (s0..s3),
        "frac": (s0..s3)}, each (2P, H_s, W_s, 2). With P = 4 (flow+stereo) rows 0..3 are the forward
        maps of PAIRS 0..3 and rows 4..7 the backward maps.
      cycle: (4, H, W, 3) frames in [0, 1].
      cfg: LossConfig.
      pyramid: optional tuple of per-scale (4, H_s, W_s, 3) frames; computed with
        geometry.image_pyramid when None.
    Returns:
      dict name -> (num, den); a term's value is num / den (den = 1 for plain means).
    """
    if cycle.ndim != 4 or cycle.shape[0] != 4 or cycle.shape[-1] != 3:
        raise ValueError(f"cycle must have shape (4, H, W, 3), got {tuple(cycle.shape)}")
    h, w = cycle.shape[1:3]
    f = 2 ** (cfg.num_scales - 1)
    if h % f or w % f:
        raise ValueError(f"cycle H and W must be divisible by {f} for {cfg.num_scales} scales, got {h}x{w}")
    pairs = cfg.pairs
    p = len(pairs)
    maps = _select_rows(maps, cfg)
    _check_maps(maps, 2 * p, h, w, cfg.num_scales)
    if pyramid is None:
        pyramid = geometry.image_pyramid(cycle, cfg.num_scales)
    stereo = jnp.array([cyc.PAIRS[k].is_stereo for k in pairs])[:, None, None, None]
    st = [i for i, k in enumerate(pairs) if cyc.PAIRS[k].is_stereo]
    one = jnp.ones((), jnp.float32)
    parts = {}
    for s in range(cfg.num_scales):
        frames = pyramid[s]
        former, latter = cyc.pair_images(frames, pairs)  # static slices, no gather
        px_f, px_b = cyc.split_directions(maps["px"][s], p)
        fr_f, fr_b = cyc.split_directions(maps["frac"][s], p)

        # Everything warped by D (rows 0..P-1) or D' (rows P..2P-1) in ONE gather: the reconstruction
        # (latter by D, former by D'), the other direction's pixel map (occlusion check) and its fraction
        # map (LR consistency). Fewer, wider gathers compile much faster on XLA:CPU than many small ones.
        src = jnp.concatenate([jnp.concatenate([latter, former]), jnp.concatenate([px_b, px_f]),
                               jnp.concatenate([fr_b, fr_f])], axis=-1)
        warped = geometry.warp(src, jnp.concatenate([px_f, px_b]))
        est_f, est_b = warped[:p, ..., :3], warped[p:, ..., :3]  # reconstructions of former / latter
        px_b_w, px_f_w = warped[:p, ..., 3:5], warped[p:, ..., 3:5]  # W(D', D), W(D, D')
        fr_b_w, fr_f_w = warped[:p, ..., 5:7], warped[p:, ..., 5:7]

        # Occlusion masks on flow pairs only; stereo pairs get mask 1 (paper Sec. 3.3). Detached.
        occ_f, occ_b = geometry.occlusion_from_warped(
            px_f, px_b, px_b_w, px_f_w, alpha1=cfg.occ_alpha1, alpha2=cfg.occ_alpha2,
            warped_bw_norm=cfg.occlusion_norm == "warped")
        m_f, m_b = geometry.masks_from_occlusion(occ_f, occ_b, border_ratio=cfg.border_ratio, floor=cfg.mask_floor)
        m_f = jax.lax.stop_gradient(jnp.where(stereo, 1.0, m_f))
        m_b = jax.lax.stop_gradient(jnp.where(stereo, 1.0, m_b))

        for direction, est, img, m in (("fwd", est_f, former, m_f), ("bwd", est_b, latter, m_b)):
            for name, part in photometric_parts(est, img, m).items():
                parts[f"{name}_{direction}/{s}"] = part
        parts[f"smooth_fwd/{s}"] = (smoothness_loss(px_f, former, beta=cfg.beta, scale=cfg.smooth_scale), one)
        parts[f"smooth_bwd/{s}"] = (smoothness_loss(px_b, latter, beta=cfg.beta, scale=cfg.smooth_scale), one)

        if st:  # left-right consistency, stereo pairs only, fraction units: mean |-W(frac', D) - frac|
            rows = lambda x: jnp.stack([x[i] for i in st])
            parts[f"lr_fwd/{s}"] = (lr_consistency_from_warped(rows(fr_f), rows(fr_b_w)), one)
            parts[f"lr_bwd/{s}"] = (lr_consistency_from_warped(rows(fr_b), rows(fr_f_w)), one)

        if cfg.two_warp != "none":
            terms = _two_warp_terms(cfg.two_warp, px_f, px_b, est_f, est_b, m_f, m_b, former, latter, cfg.two_warp_target)
            for tag, (name, est, target, mask) in zip("ab", terms):
                for pname, part in photometric_parts(est, target, mask).items():
                    parts[f"two_warp_{tag}_{pname}/{s}"] = part
    return parts


def reduce_parts(parts, cfg: LossConfig):
    """Combine per-cycle parts (leading axis = cycles, or scalars for one cycle) into term values."""
    out = {}
    for k, (num, den) in parts.items():
        if cfg.reduction == "batch":
            out[k] = jnp.mean(num) / jnp.mean(den)
        else:
            out[k] = jnp.mean(num / den)
    return out


def combine_terms(values, cfg: LossConfig):
    """Weighted total and the summary terms from per-scale values (see module docstring)."""
    a = cfg.alpha
    terms = {}
    scales = range(cfg.num_scales)
    for d in ("fwd", "bwd"):
        for s in scales:
            terms[f"photo_{d}/{s}"] = a * values[f"ssim_{d}/{s}"] + (1 - a) * values[f"l1_{d}/{s}"]
        terms[f"photo_{d}"] = sum(terms[f"photo_{d}/{s}"] for s in scales)
        terms[f"smooth_{d}"] = sum(values[f"smooth_{d}/{s}"] for s in scales)
    has_lr = "lr_fwd/0" in values
    terms["lr"] = sum(values[f"lr_fwd/{s}"] + values[f"lr_bwd/{s}"] for s in scales) if has_lr else jnp.zeros(())
    two_warp = jnp.zeros(())
    if cfg.two_warp != "none":
        for tag in "ab":
            for s in scales:
                terms[f"two_warp_{tag}/{s}"] = a * values[f"two_warp_{tag}_ssim/{s}"] + (1 - a) * values[f"two_warp_{tag}_l1/{s}"]
            terms[f"two_warp_{tag}"] = sum(terms[f"two_warp_{tag}/{s}"] for s in scales)
            two_warp = two_warp + terms[f"two_warp_{tag}"]
    terms["two_warp"] = two_warp
    total = (terms["photo_fwd"] + terms["photo_bwd"] + cfg.lambda_sm * (terms["smooth_fwd"] + terms["smooth_bwd"])
             + cfg.lambda_lr * terms["lr"] + cfg.two_warp_term_weight() * two_warp)
    terms.update({k: v for k, v in values.items() if k.startswith(("l1_", "ssim_", "smooth_", "lr_"))})
    terms["total"] = total
    return total, terms


def cycle_loss(maps, cycle, cfg: LossConfig, pyramid=None):
    """Total loss of one cycle and a dict of every term (unweighted; 'total' is the weighted sum).

    total = sum_s [photo_fwd + photo_bwd] + lambda_sm * sum_s [smooth_fwd + smooth_bwd]
            + lambda_lr * sum_s [lr_fwd + lr_bwd] + w_2warp * sum_s [two_warp_a + two_warp_b]

    Args: see cycle_loss_parts. Returns (total scalar, terms dict of scalars).
    """
    parts = cycle_loss_parts(maps, cycle, cfg, pyramid)
    return combine_terms(reduce_parts(parts, cfg), cfg)


def batch_cycle_loss(maps, cycles, cfg: LossConfig, pyramids=None):
    """Cycle loss of a batch, vmapped over cycles (any number of cycles).

    Args:
      maps: network output for cycle.batch_pair_inputs(cycles): per scale (B * 2P, H_s, W_s, 2).
      cycles: (B, 4, H, W, 3).
      pyramids: optional per-scale (B, 4, H_s, W_s, 3).
    Returns:
      (total, terms): per-cycle ratios averaged over cycles (reduction="cycle") or batch-normalised
      (reduction="batch", upstream).
    """
    if cycles.ndim != 5:
        raise ValueError(f"cycles must have shape (B, 4, H, W, 3), got {tuple(cycles.shape)}")
    b = cycles.shape[0]
    n = maps["px"][0].shape[0]
    if n % b:
        raise ValueError(f"maps have {n} rows, not a multiple of the {b} cycles")
    per_cycle = cyc.unbatch_maps(maps, b)
    fn = lambda m, c, p: cycle_loss_parts(m, c, cfg, p)
    parts = jax.vmap(fn)(per_cycle, cycles, pyramids)
    return combine_terms(reduce_parts(parts, cfg), cfg)


def two_warp_loss(px_fwd, px_bwd, former, latter, mask_fwd, mask_bwd, cfg: LossConfig):
    """2-warp consistency loss of one cycle at one scale (paper eq. 7), weighted as cfg says.

    Args:
      px_fwd, px_bwd: (4, H, W, 2) forward / backward pixel maps of the 4 PAIRS of a cycle.
      former, latter: (4, H, W, 3) the pairs' images at this scale.
      mask_fwd, mask_bwd: (4, H, W, 1) loss masks (1 for stereo pairs), in the former / latter frame.
      cfg: LossConfig with two_warp in {full1, full2, full3}.
    Returns:
      (weighted loss, dict chain-name -> unweighted photometric term).
    """
    if cfg.two_warp == "none":
        raise ValueError("two_warp_loss needs cfg.two_warp in ('full1', 'full2', 'full3')")
    est_f = geometry.warp(jnp.concatenate([latter, former]), jnp.concatenate([px_fwd, px_bwd]))
    est_f, est_b = est_f[:4], est_f[4:]
    terms = {}
    for name, est, target, mask in _two_warp_terms(cfg.two_warp, px_fwd, px_bwd, est_f, est_b, mask_fwd, mask_bwd,
                                                   former, latter, cfg.two_warp_target):
        terms[name] = photometric_loss(est, target, mask, alpha=cfg.alpha)
    return cfg.two_warp_term_weight() * sum(terms.values()), terms
