"""Where on Middlebury Motorcycle a model's disparity error lies: the error split by what the right view sees.

The real-image check's Motorcycle numbers (`experiments/real_images.py`) are means over every pixel with ground
truth. Recipes that differ by a few per cent there can differ in very different places, so this script splits
each model's error over disjoint regions of the left image, from the ground truth alone:

* ``out of view``: the strip along the left edge whose match lies beyond the right image's left border
  (`metrics.out_of_view_mask`: x - d < 0); nothing there can be matched, only extrapolated;
* ``occluded``: pixels the right view sees elsewhere but not here, because a nearer surface to their right lands
  on the same right-image column (`occluded_in_right`);
* ``visible``: the rest, split into ``visible near edges`` (within `metrics.DEPTH_EDGE_RADIUS` px of a depth edge,
  `metrics.depth_edge_band`) and ``visible elsewhere``.

For each region: its share of the ground-truth pixels, EPE, D1 (KITTI outliers), the mean signed error (bias,
px: > 0 = too near) and its **contribution** to the whole image's EPE (the region's error summed over the image's
pixel count: the contributions of the four disjoint regions add up to the EPE of the check). With
`--left-right`, also the share of each region's pixels that fail the left-right check (`left_right_flags`: the
model's right-view disparity from the mirrored pair, then the occlusion test of the paper's eq. 6), and of its
outliers: what a check-based fill can find.

    python experiments/motorcycle_regions.py --models long,W1,W2 --polish none,photometric \\
        --out experiments/results/raw/motorcycle_regions_DATE.json

Each model runs at the native resolution with one refinement pass and flip averaging (the settings of the
shipped `long`'s card) unless `--refine` / `--symmetry` say otherwise.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys

import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO not in sys.path:
    sys.path.insert(0, REPO)

from bridge_jax import metrics  # noqa: E402


def occluded_in_right(gt: np.ndarray, valid: np.ndarray, tolerance: float = 0.5) -> np.ndarray:
    """Left-image pixels hidden in the right view by a nearer surface: pixel x of a row is occluded when some
    pixel x' > x of the same row with ground truth lands at x' - d(x') <= x - d(x) + `tolerance` in the right
    image (the nearer surface's disparity is larger, so it overtakes x from the right). Out-of-view pixels are
    left to `metrics.out_of_view_mask`. (H, W) bool."""
    h, w = gt.shape
    target = np.where(valid, np.arange(w)[None, :] - gt, np.inf)
    # the smallest target among the pixels strictly to the right of each pixel
    right_min = np.minimum.accumulate(target[:, ::-1], axis=1)[:, ::-1]
    right_min = np.concatenate([right_min[:, 1:], np.full((h, 1), np.inf)], axis=1)
    return valid & (right_min <= target + tolerance) & ~metrics.out_of_view_mask(gt, valid)


def regions(gt: np.ndarray, valid: np.ndarray) -> dict[str, np.ndarray]:
    """The four disjoint regions of the module docstring, in the order the tables show them."""
    outview = metrics.out_of_view_mask(gt, valid)
    occluded = occluded_in_right(gt, valid)
    visible = valid & ~outview & ~occluded
    band = metrics.depth_edge_band(gt, valid)
    return {"out of view": outview, "occluded": occluded, "visible near edges": visible & band,
            "visible elsewhere": visible & ~band}


def region_numbers(pred: np.ndarray, gt: np.ndarray, masks: dict[str, np.ndarray]) -> dict[str, dict[str, float]]:
    """{region: {"share" %, "epe", "d1" %, "bias" px, "contribution" px}} of one disparity map over `masks`
    ({"all": the ground-truth pixels, **`regions`})."""
    err = metrics.endpoint_error(pred, gt)
    bad = metrics.outliers(err, np.abs(gt))
    n = int(masks["all"].sum())
    out = {}
    for name, mask in masks.items():
        k = int(mask.sum())
        out[name] = {"share": 100.0 * k / n, "epe": float(err[mask].mean()), "d1": 100.0 * float(bad[mask].mean()),
                     "bias": float((pred - gt)[mask].mean()), "contribution": float(err[mask].sum() / n)}
    return out


def left_right_flags(d_left: np.ndarray, d_right: np.ndarray, alpha1: float = 0.01,
                     alpha2: float = 0.5) -> np.ndarray:
    """Left-image pixels that fail the left-right check (paper eq. 6 on disparities,
    `geometry.forward_backward_occlusion`): pixel x with disparity d reads the right view's disparity d' at
    x - d (bilinear) and fails when (d - d')^2 > alpha1 (d^2 + d'^2) + alpha2, or when x - d lies left of the
    right image (out of view).

    Args:
      d_left: (H, W) the left view's disparity px (left x matches right x - d).
      d_right: (H, W) the right view's disparity px (right x matches left x + d').
    Returns:
      (H, W) bool, True = fails.
    """
    from bridge_jax import geometry  # imported here: the region split itself needs no jax

    zero = np.zeros_like(d_left)
    occluded, _ = geometry.forward_backward_occlusion(
        np.stack([-d_left, zero], -1).astype(np.float32), np.stack([d_right, zero], -1).astype(np.float32),
        alpha1=alpha1, alpha2=alpha2)
    return (np.asarray(occluded)[..., 0] > 0) | (np.arange(d_left.shape[1])[None, :] - d_left < 0)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", required=True, help="comma list of shipped model names or checkpoint paths")
    p.add_argument("--polish", default="none", help="comma list of test-time polishes: none, photometric, fill, photometric+fill")
    p.add_argument("--refine", type=int, default=1, help="test-time refinement passes (default 1)")
    p.add_argument("--symmetry", default="flips", help="test-time symmetry averaging (default flips)")
    p.add_argument("--left-right", action="store_true",
                   help="also report the share of each region failing the left-right check (one more prediction "
                        "per model: the mirrored pair)")
    p.add_argument("--out", default=None, help="JSON file for every number")
    args = p.parse_args(argv)
    from bridge_jax import confidence, inference, testtime
    from bridge_jax.bench import timing
    from bridge_jax.eval import real_checks
    moto = real_checks.motorcycle()
    gt, valid = moto["disp"].astype(np.float64), moto["valid"]
    masks = {"all": valid, **regions(gt, valid)}
    results = {}
    for model in [m for m in args.models.split(",") if m]:
        for polish in [q for q in args.polish.split(",") if q]:
            pred = inference.load_predictor(model, size="native", options=testtime.OPTIONS, test_time={
                "refine": args.refine, "symmetry": args.symmetry, "polish": polish})
            d = np.asarray(pred.predict_pair(moto["left"], moto["right"], "stereo"), np.float64)
            label = f"{os.path.basename(model.rstrip('/'))}, polish {polish}"
            results[label] = region_numbers(d, gt, masks)
            if args.left_right:
                # the mirrored pair (flipped right view as the left one) is a left -> right pair whose
                # disparity, flipped back, is the right view's
                mirrored = pred.predict([confidence.reverse_job("stereo", moto["left"], moto["right"])])[0]
                fails = left_right_flags(d, np.asarray(confidence.right_view_disparity(mirrored), np.float64))
                bad = metrics.outliers(metrics.endpoint_error(d, gt), np.abs(gt))
                for name, mask in masks.items():
                    results[label][name]["fails_left_right"] = 100.0 * float(fails[mask].mean())
                    results[label][name]["outliers_failing"] = 100.0 * float(fails[mask & bad].mean())
            lr_head = " fail LR check % | outliers failing % |" if args.left_right else ""
            print(f"\n{label}\n| region | share % | EPE px | D1 % | bias px | contribution px |{lr_head}\n"
                  + "|---" * (6 + 2 * args.left_right) + "|")
            for name, r in results[label].items():
                lr = (f" {r['fails_left_right']:.1f} | {r['outliers_failing']:.1f} |" if args.left_right else "")
                print(f"| {name} | {r['share']:.1f} | {r['epe']:.3f} | {r['d1']:.1f} | {r['bias']:+.3f} "
                      f"| {r['contribution']:.3f} |{lr}", flush=True)
    if args.out:
        stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
        with open(args.out, "w") as f:
            json.dump({"date": stamp, "machine": timing.machine(), "refine": args.refine,
                       "symmetry": args.symmetry, "results": results}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
