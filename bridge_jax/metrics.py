"""Stereo, optical-flow, scene-flow and depth metrics, computed as the benchmarks do (numpy, float64).

Every metric exists in two reductions, named explicitly in every report:

* **per-image mean** — the metric is computed on each image, then averaged over images (what the paper and the
  monodepth-lineage scripts report);
* **pooled** — errors are summed over *all* valid pixels of the whole set and divided once (what the KITTI devkit
  reports for its Fl / D1 / SF rates).

Units: flow and disparity errors are in **pixels of the ground-truth resolution**; outlier rates (``fl_*``,
``d1_*``, ``d2_*``, ``sf_*``) are **percent** (0..100); depth errors are in **metres**; ``a1..a3`` (δ < 1.25^k)
are fractions (0..1), as in the paper's tables.

Outliers follow the KITTI devkit: a pixel is wrong if its end-point error is **> 3 px and > 5 %** of the
ground-truth magnitude (strict ``>``). ``*_all`` metrics use the ``*_occ`` ground truth (all valid pixels),
``*_noc`` metrics the ``*_noc`` ground truth, and ``*_occ`` metrics (EPE-occ / Fl-occ of the paper's Table 3)
the pixels that are valid in ``*_occ`` but not in ``*_noc`` (occluded pixels only).

The stereo script the paper used (monodepth lineage, upstream ``evaluate_kitti.py``) counted its ``d1_all`` with
``>=`` on both thresholds; that variant is reported as ``d1_all_paper`` (on ``disp_occ``, the file upstream reads)
and ``d1_noc_paper`` (on ``disp_noc``, the file the original Monodepth script reads); see :func:`disparity_sums`.

The building block is a dict ``{metric name: (sum, count)}`` of one image ("sums"); :class:`MetricAccumulator`
collects them and reduces both ways. ``rmse`` / ``rmse_log`` sums are sums of *squared* errors, and the square root
is taken at reduction time (per image for the mean, once for the pooled value).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Optional

import numpy as np

OUTLIER_PX = 3.0
"""Absolute outlier threshold in pixels (KITTI)."""
OUTLIER_REL = 0.05
"""Relative outlier threshold, fraction of the ground-truth magnitude (KITTI)."""
MIN_DEPTH = 1e-3
"""Predicted depth is clamped to [MIN_DEPTH, MAX_DEPTH] metres (paper protocol)."""
MAX_DEPTH = 80.0

SQRT_METRICS = frozenset({"rmse", "rmse_log"})
"""Metrics whose sums hold squared errors; the square root is applied after averaging."""

Sums = dict[str, tuple[float, int]]

__all__ = [
    "OUTLIER_PX", "OUTLIER_REL", "MIN_DEPTH", "MAX_DEPTH", "MetricAccumulator",
    "endpoint_error", "outliers", "flow_sums", "disparity_sums", "scene_flow_sums", "depth_sums",
    "disparity_to_depth", "finalize", "flow_metrics", "disparity_metrics", "depth_metrics",
    "scene_flow_metrics", "garg_crop_mask", "SPARSIFICATION_FRACTIONS", "sparsification", "mask_scores",
]


# --------------------------------------------------------------------------------------------------------------
# Per-pixel errors


def endpoint_error(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """Per-pixel end-point error in pixels, float64.

    Args:
      pred, gt: flow ``(H, W, 2)`` or disparity ``(H, W)``, pixels.
    Returns:
      ``(H, W)``: Euclidean norm of ``pred - gt`` for flow, ``|pred - gt|`` for disparity.
    """
    pred = np.asarray(pred, np.float64)
    gt = np.asarray(gt, np.float64)
    if pred.shape != gt.shape:
        raise ValueError(f"prediction shape {pred.shape} != ground-truth shape {gt.shape}")
    if pred.ndim == 3:
        return np.hypot(pred[..., 0] - gt[..., 0], pred[..., 1] - gt[..., 1])
    return np.abs(pred - gt)


def _magnitude(gt: np.ndarray) -> np.ndarray:
    gt = np.asarray(gt, np.float64)
    return np.hypot(gt[..., 0], gt[..., 1]) if gt.ndim == 3 else np.abs(gt)


def outliers(err: np.ndarray, gt_magnitude: np.ndarray, *, inclusive: bool = False) -> np.ndarray:
    """KITTI outlier map: ``err > 3 px`` and ``err > 5 % · |gt|`` (``>=`` both when ``inclusive``).

    Args:
      err: ``(H, W)`` end-point error, pixels.
      gt_magnitude: ``(H, W)`` ground-truth flow norm / disparity, pixels.
      inclusive: use ``>=`` (the monodepth-lineage script's ``d1_all``) instead of the devkit's ``>``.
    Returns:
      ``(H, W)`` bool.
    """
    if inclusive:
        return (err >= OUTLIER_PX) & (err >= OUTLIER_REL * gt_magnitude)
    return (err > OUTLIER_PX) & (err > OUTLIER_REL * gt_magnitude)


def _check_mask(mask: Optional[np.ndarray], shape: tuple[int, ...], name: str) -> Optional[np.ndarray]:
    if mask is None:
        return None
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"{name} mask shape {mask.shape} != map shape {shape}")
    return mask.astype(bool)


def _region_sums(prefix_epe: str, prefix_out: str, err: np.ndarray, out: np.ndarray, mask: np.ndarray,
                 suffix: str) -> Sums:
    n = int(mask.sum())
    return {f"{prefix_epe}_{suffix}": (float(err[mask].sum()), n),
            f"{prefix_out}_{suffix}": (100.0 * float(out[mask].sum()), n)}


def _all_noc_occ(epe_name: str, out_name: str, err: np.ndarray, out: np.ndarray, valid: np.ndarray,
                 noc: Optional[np.ndarray]) -> Sums:
    sums = _region_sums(epe_name, out_name, err, out, valid, "all")
    if noc is not None:
        noc = noc & valid  # a noc pixel is always an occ-valid pixel in KITTI; enforce it for hand-made GT
        sums.update(_region_sums(epe_name, out_name, err, out, noc, "noc"))
        sums.update(_region_sums(epe_name, out_name, err, out, valid & ~noc, "occ"))
    return sums


# --------------------------------------------------------------------------------------------------------------
# Per-image sums


def flow_sums(pred: np.ndarray, gt: np.ndarray, valid: np.ndarray, noc: Optional[np.ndarray] = None) -> Sums:
    """Optical-flow sums of one image.

    Args:
      pred: ``(H, W, 2)`` predicted flow, pixels of the GT resolution.
      gt: ``(H, W, 2)`` ground-truth flow (``flow_occ``), pixels.
      valid: ``(H, W)`` bool, valid pixels of ``flow_occ``.
      noc: optional ``(H, W)`` bool, valid pixels of ``flow_noc``; adds the ``*_noc`` and ``*_occ`` metrics.
    Returns:
      sums for ``epe_all``, ``fl_all`` (+ ``epe_noc``, ``fl_noc``, ``epe_occ``, ``fl_occ``).
    """
    err = endpoint_error(pred, gt)
    valid = _check_mask(valid, err.shape, "valid")
    noc = _check_mask(noc, err.shape, "noc")
    out = outliers(err, _magnitude(gt))
    return _all_noc_occ("epe", "fl", err, out, valid, noc)


def disparity_sums(pred: np.ndarray, gt: np.ndarray, valid: Optional[np.ndarray] = None,
                   noc: Optional[np.ndarray] = None, *, prefix: str = "d1") -> Sums:
    """Disparity sums of one image.

    Args:
      pred: ``(H, W)`` predicted disparity, pixels of the GT resolution (positive).
      gt: ``(H, W)`` ground-truth disparity (``disp_occ``), pixels; 0 = no ground truth.
      valid: ``(H, W)`` bool; default ``gt > 0``.
      noc: optional ``(H, W)`` bool, valid pixels of ``disp_noc``.
      prefix: outlier-rate name, ``"d1"`` for frame t, ``"d2"`` for frame t+1 (brought into frame t).
    Returns:
      sums for ``epe_all``, ``<prefix>_all``, ``<prefix>_all_paper`` (+ ``*_noc``, ``*_occ``,
      ``<prefix>_noc_paper``); EPE names carry the prefix too when it is not ``d1`` (``d2_epe_all``...).
      ``*_paper`` count ``>=`` outliers (the monodepth-lineage script): ``d1_all_paper`` on ``disp_occ`` is what
      upstream BridgeDepthFlow's ``evaluate_kitti.py`` computed (it reads ``disp_occ_0``), ``d1_noc_paper`` on
      ``disp_noc`` is the original Monodepth script's choice.
    """
    gt = np.asarray(gt, np.float64)
    err = endpoint_error(pred, gt)
    valid = gt > 0 if valid is None else _check_mask(valid, err.shape, "valid")
    noc = _check_mask(noc, err.shape, "noc")
    epe_name = "epe" if prefix == "d1" else f"{prefix}_epe"
    mag = np.abs(gt)
    sums = _all_noc_occ(epe_name, prefix, err, outliers(err, mag), valid, noc)
    paper = outliers(err, mag, inclusive=True)
    sums[f"{prefix}_all_paper"] = (100.0 * float(paper[valid].sum()), int(valid.sum()))
    if noc is not None:
        sums[f"{prefix}_noc_paper"] = (100.0 * float(paper[noc].sum()), int(noc.sum()))
    return sums


def scene_flow_sums(d1: tuple, d2: tuple, fl: tuple, *, suffix: str = "all") -> Sums:
    """Scene-flow outlier sums of one image (KITTI 2015 SF): a pixel is wrong if D1, D2 or Fl is wrong.

    Only pixels valid in all three ground truths count.

    Args:
      d1: ``(pred (H, W), gt (H, W), valid (H, W))`` disparity at t.
      d2: the same for the t+1 disparity brought into frame t (KITTI ``disp_*_1``).
      fl: ``(pred (H, W, 2), gt (H, W, 2), valid (H, W))`` flow.
      suffix: ``"all"`` for ``*_occ`` ground truth, ``"noc"`` for ``*_noc``.
    Returns:
      ``{"sf_<suffix>": (100 · outliers, count)}``.
    """
    bad, valid = None, None
    for pred, gt, v in (d1, d2, fl):
        err = endpoint_error(pred, gt)
        o = outliers(err, _magnitude(gt))
        v = _check_mask(v, err.shape, "valid")
        bad = o if bad is None else bad | o
        valid = v if valid is None else valid & v
    return {f"sf_{suffix}": (100.0 * float(bad[valid].sum()), int(valid.sum()))}


def disparity_to_depth(disp: np.ndarray, focal: float, baseline: float, *, clamp: bool = True,
                       zero_disparity_depth: float = float("inf")) -> np.ndarray:
    """Depth in metres from disparity in pixels: ``f · B / d``, as the paper's (monodepth-lineage) script.

    Args:
      disp: ``(H, W)`` disparity, pixels of the image whose focal length ``focal`` (pixels) is given.
      baseline: metres.
      clamp: clamp to ``[MIN_DEPTH, MAX_DEPTH]`` (the paper's protocol for predictions); a negative disparity
        gives a negative depth and so clamps to ``MIN_DEPTH``.
      zero_disparity_depth: depth given to ``d == 0`` before clamping: ``inf`` (→ 80 m; KITTI-split script) or
        ``0`` (→ 1e-3 m; the Eigen-split script sets infinite depths to 0 before clamping).
    """
    disp = np.asarray(disp, np.float64)
    zero = disp == 0
    with np.errstate(divide="ignore", invalid="ignore"):
        depth = np.where(zero, zero_disparity_depth, focal * baseline / np.where(zero, 1.0, disp))
    if clamp:
        depth = np.clip(depth, MIN_DEPTH, MAX_DEPTH)
    return depth


def depth_sums(pred_depth: np.ndarray, gt_depth: np.ndarray, mask: np.ndarray) -> Sums:
    """Monocular-depth sums of one image: abs_rel, sq_rel, rmse, rmse_log (natural log), a1..a3 (δ < 1.25^k).

    Args:
      pred_depth: ``(H, W)`` metres (already clamped, see :func:`disparity_to_depth`).
      gt_depth: ``(H, W)`` metres.
      mask: ``(H, W)`` bool, pixels to score (e.g. ``gt_disp > 0``; Eigen: ``1e-3 < gt < 80`` & Garg crop).
    """
    pred_depth = np.asarray(pred_depth, np.float64)
    gt_depth = np.asarray(gt_depth, np.float64)
    if pred_depth.shape != gt_depth.shape:
        raise ValueError(f"prediction shape {pred_depth.shape} != ground-truth shape {gt_depth.shape}")
    mask = _check_mask(mask, gt_depth.shape, "depth")
    g, p = gt_depth[mask], pred_depth[mask]
    n = int(g.size)
    ratio = np.maximum(g / p, p / g) if n else g
    d = g - p
    dl = np.log(g) - np.log(p) if n else g
    return {
        "abs_rel": (float(np.sum(np.abs(d) / g)), n),
        "sq_rel": (float(np.sum(d * d / g)), n),
        "rmse": (float(np.sum(d * d)), n),
        "rmse_log": (float(np.sum(dl * dl)), n),
        "a1": (float(np.sum(ratio < 1.25)), n),
        "a2": (float(np.sum(ratio < 1.25 ** 2)), n),
        "a3": (float(np.sum(ratio < 1.25 ** 3)), n),
    }


def garg_crop_mask(height: int, width: int) -> np.ndarray:
    """The Garg et al. (ECCV 2016) evaluation crop as a ``(H, W)`` bool mask (rows 40.8–99.2 %, cols 3.6–96.4 %)."""
    top, bottom = int(0.40810811 * height), int(0.99189189 * height)
    left, right = int(0.03594771 * width), int(0.96405229 * width)
    mask = np.zeros((height, width), bool)
    mask[top:bottom, left:right] = True
    return mask


# --------------------------------------------------------------------------------------------------------------
# Reductions


def finalize(sums: Mapping[str, tuple[float, int]]) -> dict[str, float]:
    """Turn one image's (or pooled) sums into values; a metric with no valid pixel is NaN."""
    out = {}
    for name, (s, n) in sums.items():
        v = s / n if n else float("nan")
        out[name] = float(np.sqrt(v)) if name in SQRT_METRICS and n else float(v)
    return out


class MetricAccumulator:
    """Collects per-image sums and reduces them both ways.

    ``add(sums)`` once per image (several groups of one image may be added in one call or several, as long as the
    names do not collide). ``per_image_mean()`` averages each metric over the images where it had at least one
    valid pixel; ``pooled()`` divides the total sum by the total count.
    """

    def __init__(self) -> None:
        self._per_image: dict[str, list[float]] = {}
        self._total: dict[str, list] = {}

    def add(self, sums: Mapping[str, tuple[float, int]]) -> None:
        for name, (s, n) in sums.items():
            tot = self._total.setdefault(name, [0.0, 0])
            tot[0] += float(s)
            tot[1] += int(n)
            if n:
                self._per_image.setdefault(name, []).append(finalize({name: (s, n)})[name])

    @property
    def names(self) -> list[str]:
        return list(self._total)

    def num_images(self, name: str) -> int:
        """How many images contributed to ``name`` (had at least one valid pixel)."""
        return len(self._per_image.get(name, []))

    def per_image_mean(self) -> dict[str, float]:
        return {name: (float(np.mean(np.asarray(self._per_image[name], np.float64)))
                       if name in self._per_image else float("nan")) for name in self._total}

    def pooled(self) -> dict[str, float]:
        return finalize({name: (s, n) for name, (s, n) in self._total.items()})

    def summary(self) -> dict:
        """``{"per_image_mean": {...}, "pooled": {...}, "num_images": {...}}``."""
        return {"per_image_mean": self.per_image_mean(), "pooled": self.pooled(),
                "num_images": {name: self.num_images(name) for name in self._total}}


# --------------------------------------------------------------------------------------------------------------
# One-image convenience wrappers


def flow_metrics(pred, gt, valid, noc=None) -> dict[str, float]:
    """:func:`flow_sums` reduced for one image (EPE px, Fl %)."""
    return finalize(flow_sums(pred, gt, valid, noc))


def disparity_metrics(pred, gt, valid=None, noc=None, *, prefix: str = "d1") -> dict[str, float]:
    """:func:`disparity_sums` reduced for one image (EPE px, D1 %)."""
    return finalize(disparity_sums(pred, gt, valid, noc, prefix=prefix))


def depth_metrics(pred_depth, gt_depth, mask) -> dict[str, float]:
    """:func:`depth_sums` reduced for one image."""
    return finalize(depth_sums(pred_depth, gt_depth, mask))


def scene_flow_metrics(d1, d2, fl, *, suffix: str = "all") -> dict[str, float]:
    """:func:`scene_flow_sums` reduced for one image (SF %)."""
    return finalize(scene_flow_sums(d1, d2, fl, suffix=suffix))


# --------------------------------------------------------------------------------------------------------------
# Sparsification: does a confidence map rank the errors?

SPARSIFICATION_FRACTIONS = tuple(i / 20 for i in range(20))
"""Fractions of the pixels removed, least confident first, at which a sparsification curve is read (0, 5 %, ...,
95 %)."""


def sparsification(errors: np.ndarray, confidence: np.ndarray, mask: Optional[np.ndarray] = None,
                   fractions=SPARSIFICATION_FRACTIONS) -> dict:
    """The sparsification curve of a confidence map (Ilg et al. 2018, "Uncertainty estimates and multi-hypotheses
    networks for optical flow"): the mean error of the pixels left after removing a fraction of them, the least
    confident first, beside the oracle's (the largest errors first).

    Args:
      errors: per-pixel errors (end-point error, or absolute disparity error), any shape.
      confidence: the same shape; higher = more trusted. Ties are broken by the pixel order (stable sort).
      mask: optional bool, the pixels with ground truth (default: all).
      fractions: removed fractions, each in [0, 1).
    Returns:
      {"fractions": list, "curve": list (mean error of what is left, at each fraction), "oracle": list,
       "mean": mean error of all pixels, "ause": area between the curve and the oracle's over the fractions
       (trapezoids, in the errors' unit), "ause_relative": the same with both curves divided by "mean",
       "top_half_ratio": mean error of the 50 % most confident pixels / "mean"}; NaN values when no pixel
       has ground truth.
    """
    err = np.asarray(errors, np.float64).reshape(-1)
    conf = np.asarray(confidence, np.float64).reshape(-1)
    if err.shape != conf.shape:
        raise ValueError(f"errors and confidence differ in size: {np.shape(errors)} and {np.shape(confidence)}")
    if mask is not None:
        keep = np.asarray(mask, bool).reshape(-1)
        err, conf = err[keep], conf[keep]
    fractions = [float(f) for f in fractions]
    n = err.size
    if n == 0:
        nan = float("nan")
        return {"fractions": fractions, "curve": [nan] * len(fractions), "oracle": [nan] * len(fractions),
                "mean": nan, "ause": nan, "ause_relative": nan, "top_half_ratio": nan}

    def kept_means(order: np.ndarray, at: list[float]) -> list[float]:
        # order: most trusted first; keep the first ceil((1 - f) * n) pixels (at least one)
        cums = np.cumsum(err[order])
        return [float(cums[max(1, int(np.ceil((1.0 - f) * n))) - 1] / max(1, int(np.ceil((1.0 - f) * n))))
                for f in at]

    by_conf = np.argsort(-conf, kind="stable")
    by_err = np.argsort(err, kind="stable")
    curve, oracle = kept_means(by_conf, fractions), kept_means(by_err, fractions)
    mean = float(err.mean())
    gap = np.asarray(curve) - np.asarray(oracle)
    ause = float(np.trapezoid(gap, fractions)) if len(fractions) > 1 else 0.0
    half = kept_means(by_conf, [0.5])[0]
    return {"fractions": fractions, "curve": curve, "oracle": oracle, "mean": mean, "ause": ause,
            "ause_relative": ause / mean if mean > 0 else float("nan"),
            "top_half_ratio": half / mean if mean > 0 else float("nan")}


def mask_scores(predicted: np.ndarray, truth: np.ndarray, valid: Optional[np.ndarray] = None) -> dict:
    """{"precision", "recall", "f1"} (fractions) of a predicted bool mask against a true one over `valid` pixels
    (default all); NaN where a ratio has no pixel to count."""
    pred = np.asarray(predicted, bool)
    true = np.asarray(truth, bool)
    if valid is not None:
        keep = np.asarray(valid, bool)
        pred, true = pred[keep], true[keep]
    tp = float(np.sum(pred & true))
    precision = tp / float(pred.sum()) if pred.sum() else float("nan")
    recall = tp / float(true.sum()) if true.sum() else float("nan")
    f1 = 2 * precision * recall / (precision + recall) if precision + recall > 0 else float("nan")
    return {"precision": precision, "recall": recall, "f1": f1}


# --------------------------------------------------------------------------------------------------------------
# Depth edges: where stereo methods fatten the foreground

DEPTH_EDGE_JUMP = 3.0
"""A depth edge lies between two neighbouring ground-truth pixels whose disparities differ by more than this many
pixels (the KITTI outlier threshold: a surface, however slanted, rarely changes by that much from one pixel to
the next)."""
DEPTH_EDGE_RADIUS = 5
"""Pixels within this Euclidean distance (px of the ground-truth resolution) of a depth edge form its band."""


def depth_edge_band(gt: np.ndarray, valid: Optional[np.ndarray] = None, *, jump: float = DEPTH_EDGE_JUMP,
                    radius: float = DEPTH_EDGE_RADIUS) -> np.ndarray:
    """``(H, W)`` bool: the pixels with ground truth within `radius` px of a depth edge of `gt`.

    An edge pixel is a valid pixel whose left, right, upper or lower neighbour is valid and differs from it by
    more than `jump` px; both sides of the jump are edge pixels. Pixels without ground truth neither make edges
    (the border of a hole is not a depth edge) nor belong to the band.

    Args:
      gt: ``(H, W)`` ground-truth disparity, pixels; 0 = no ground truth.
      valid: ``(H, W)`` bool; default ``gt > 0``.
    """
    from scipy import ndimage  # jax's own dependency; imported here so that metrics stays numpy-only at import

    gt = np.asarray(gt, np.float64)
    valid = gt > 0 if valid is None else _check_mask(valid, gt.shape, "valid")
    edge = np.zeros(gt.shape, bool)
    across = (np.abs(np.diff(gt, axis=1)) > jump) & valid[:, 1:] & valid[:, :-1]
    edge[:, 1:] |= across
    edge[:, :-1] |= across
    down = (np.abs(np.diff(gt, axis=0)) > jump) & valid[1:] & valid[:-1]
    edge[1:] |= down
    edge[:-1] |= down
    if not edge.any():
        return np.zeros(gt.shape, bool)
    return (ndimage.distance_transform_edt(~edge) <= radius) & valid


def disparity_edge_metrics(pred: np.ndarray, gt: np.ndarray, valid: Optional[np.ndarray] = None, *,
                           jump: float = DEPTH_EDGE_JUMP, radius: float = DEPTH_EDGE_RADIUS) -> dict[str, float]:
    """The disparity error near depth edges (`depth_edge_band`) of one image: {"epe_edge" px, "d1_edge" %
    (KITTI outliers among the band's pixels), "fat_edge" % (the band's pixels whose disparity is too *large* by an
    outlier's margin: a nearer surface bled over a farther one, the foreground fattening of window-based and
    coarse-to-fine stereo)}; NaN when the image has no depth edge.

    Args:
      pred: ``(H, W)`` predicted disparity, pixels of the ground-truth resolution.
      gt: ``(H, W)`` ground-truth disparity; 0 = no ground truth.
      valid: ``(H, W)`` bool; default ``gt > 0``.
    """
    gt = np.asarray(gt, np.float64)
    band = depth_edge_band(gt, valid, jump=jump, radius=radius)
    if not band.any():
        return {"epe_edge": float("nan"), "d1_edge": float("nan"), "fat_edge": float("nan")}
    pred = np.asarray(pred, np.float64)
    err = endpoint_error(pred, gt)
    bad = outliers(err, np.abs(gt))
    return {"epe_edge": float(err[band].mean()), "d1_edge": 100.0 * float(bad[band].mean()),
            "fat_edge": 100.0 * float((bad & (pred > gt))[band].mean())}


def out_of_view_mask(gt: np.ndarray, valid: Optional[np.ndarray] = None) -> np.ndarray:
    """The pixels of a left image that the right image cannot see because their match lies beyond its left
    border: ground truth at column x with x - d < 0 (the strip along the left edge, as wide as the disparity
    there). A stereo method has nothing to match there and can only extrapolate from the pixels beside it.

    Args:
      gt: ``(H, W)`` ground-truth disparity of the left image, pixels; 0 = no ground truth.
      valid: ``(H, W)`` bool; default ``gt > 0``.
    """
    gt = np.asarray(gt, np.float64)
    valid = gt > 0 if valid is None else _check_mask(valid, gt.shape, "valid")
    return valid & (np.arange(gt.shape[1])[None, :] - gt < 0)


def disparity_out_of_view_metrics(pred: np.ndarray, gt: np.ndarray,
                                  valid: Optional[np.ndarray] = None) -> dict[str, float]:
    """The disparity error where the right image cannot see the left one's pixels (`out_of_view_mask`):
    {"epe_outview" px, "d1_outview" % (KITTI outliers)}; NaN when there is no such pixel.

    Args:
      pred: ``(H, W)`` predicted disparity, pixels of the ground-truth resolution.
      gt: ``(H, W)`` ground-truth disparity; 0 = no ground truth.
      valid: ``(H, W)`` bool; default ``gt > 0``.
    """
    gt = np.asarray(gt, np.float64)
    strip = out_of_view_mask(gt, valid)
    if not strip.any():
        return {"epe_outview": float("nan"), "d1_outview": float("nan")}
    err = endpoint_error(np.asarray(pred, np.float64), gt)
    return {"epe_outview": float(err[strip].mean()),
            "d1_outview": 100.0 * float(outliers(err, np.abs(gt))[strip].mean())}
