"""How well the predictor's confidence and occlusion maps rank its errors (`Predictor.predict(..., confidence=True)`),
how their settings were chosen, and what they cost.

Frames with exact ground truth:

* **selection** frames (`--selection`, the built-in synthetic video's "demo" scene at 256x512, a seed no check
  or training run draws from): the only place the settings of `bridge_jax.confidence` are chosen (`--sweep`);
* **held-out** synthetic frames (`real_checks.heldout_synthetic`, the real-image page's held-out check: other
  textures, camera and photometric changes) and Middlebury **Motorcycle** (disparity only, no occlusion ground
  truth): where the chosen settings are reported, never chosen.

For each model and each check mode (`confidence.CHECK_MODES`: the backward maps from a plain network call, or
from the prediction's own stages) and each task, pooled over the frames' pixels with ground truth: the
sparsification curve (`metrics.sparsification`), AUSE, the mean error of the 50 % most confident pixels over
that of all pixels, and the occlusion mask's precision and recall against the ground truth's occluded and
out-of-view pixels (valid pixels whose point is not visible in the other image). Also measured: the disparity
after filling the pixels the check flags with their background neighbours' (`eval.baselines.fill_invalid_disparity`,
the KITTI devkit's rule), the flow after giving them their nearest unflagged neighbour's, and the cost: seconds per frame with and without the confidence, warm, alternating on
one predictor.

    python experiments/confidence.py --models long --sweep --out experiments/results/raw/confidence.json
"""
from __future__ import annotations

import argparse
import datetime
import itertools
import json
import os
import platform
import sys
import time

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

import numpy as np  # noqa: E402
from scipy import ndimage  # noqa: E402

from bridge_jax import compile_cache, confidence, metrics  # noqa: E402
from bridge_jax.eval import real_checks  # noqa: E402
from bridge_jax.eval.baselines import fill_invalid_disparity  # noqa: E402
from bridge_jax.eval.datasets import synthetic_frames  # noqa: E402
from bridge_jax.inference import load_predictor  # noqa: E402

SELECTION_SEED = 91_000_003
"""Seed of the selection frames (the "demo" scene; no check and no training run draws from it)."""
EDGE_GRID = {"radius": (1, 2, 3, 5), "weight": (0.1, 0.3, 1.0, 3.0)}
"""The edge term's settings tried on the selection frames."""
THRESHOLD_GRID = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0)
"""The occlusion thresholds tried on the selection frames."""


def frame_jobs(frame) -> list[tuple[str, str, np.ndarray, np.ndarray]]:
    """(key, task, image a, image b) of a synthetic frame's two pairs."""
    im = frame.images
    return [("disparity", "stereo", im["left_t"], im["right_t"]), ("flow", "flow", im["left_t"], im["left_t1"])]


def truth(frame, key: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(ground truth, valid, occluded) of a synthetic frame's map `key`."""
    gt = frame.gt
    if key == "flow":
        valid = gt["flow_occ_valid"]
        return gt["flow_occ"], valid, valid & ~gt["flow_noc_valid"]
    valid = gt["disp_occ_0"] > 0
    return gt["disp_occ_0"], valid, valid & ~(gt["disp_noc_0"] > 0)


def collect(pred, frames, modes) -> list[dict]:
    """Per pair: its key, task, ground truth, the forward map (`Predictor.stage_maps`) and the backward map of
    each mode."""
    own = pred.test_time
    items = []
    for fr in frames:
        jobs = [(task, a, b) for _, task, a, b in frame_jobs(fr)]
        forward = pred.stage_maps(jobs, len(jobs))
        backward = {}
        for mode in modes:
            pred.check = confidence.check_record(mode, own)
            backward[mode] = pred.backward_maps(jobs, len(jobs))
        pred.check = None
        for j, (key, task, a, _) in enumerate(frame_jobs(fr)):
            gt, valid, occ = truth(fr, key)
            items.append({"key": key, "task": task, "gt": gt, "valid": valid, "occ": occ, "forward": forward[j],
                          "backward": {m: backward[m][j] for m in modes}})
    return items


def motorcycle_items(pred, modes) -> list[dict]:
    moto = real_checks.motorcycle()
    jobs = [("stereo", moto["left"], moto["right"])]
    forward = pred.stage_maps(jobs, 1)[0]
    backward = {}
    for mode in modes:
        pred.check = confidence.check_record(mode, pred.test_time)
        backward[mode] = pred.backward_maps(jobs, 1)[0]
    pred.check = None
    return [{"key": "disparity", "task": "stereo", "gt": moto["disp"], "valid": moto["valid"], "occ": None,
             "forward": forward, "backward": backward}]


def scored(item: dict, mode: str, radius: int, weight: float, threshold: float) -> dict:
    """The prediction, its error, confidence and occlusion at the ground truth's resolution."""
    task = item["task"]
    pred, conf, occ = confidence.checked_map(task, item["forward"], item["backward"][mode], *item["gt"].shape[:2],
                                             threshold, radius=radius, edge_weight=weight)
    err = np.sqrt(np.sum((pred - item["gt"]) ** 2, -1)) if task == "flow" else np.abs(pred - item["gt"])
    return {"pred": pred, "err": err, "conf": conf, "occ": occ}


def nearest_fill(flow: np.ndarray, flagged: np.ndarray) -> np.ndarray:
    """`flow (H, W, 2)` with each flagged pixel given the flow of the nearest unflagged one (Euclidean)."""
    if not flagged.any() or flagged.all():
        return flow
    _, (iy, ix) = ndimage.distance_transform_edt(flagged, return_indices=True)
    return flow[iy, ix]


def pooled(items: list[dict], mode: str, radius: int = confidence.EDGE_RADIUS,
           weight: float = confidence.EDGE_WEIGHT, threshold: float | None = None, fill: bool = False) -> dict:
    """Per key: sparsification numbers and occlusion scores pooled over `items`' valid pixels (and with `fill`,
    the disparity metrics before and after filling the flagged pixels, averaged over pairs)."""
    threshold = confidence.OCCLUSION_THRESHOLD[mode] if threshold is None else threshold
    parts: dict[str, dict[str, list]] = {}
    for item in items:
        s = scored(item, mode, radius, weight, threshold)
        v = item["valid"]
        p = parts.setdefault(item["key"], {"err": [], "conf": [], "occ": [], "true": [], "fill": []})
        p["err"].append(s["err"][v])
        p["conf"].append(s["conf"][v])
        p["occ"].append(s["occ"][v])
        if item["occ"] is not None:
            p["true"].append(item["occ"][v])
        if fill and item["key"] == "disparity":
            before = metrics.disparity_metrics(s["pred"], item["gt"])
            after = metrics.disparity_metrics(fill_invalid_disparity(s["pred"], ~s["occ"]), item["gt"])
            p["fill"].append((before["epe_all"], before["d1_all"], after["epe_all"], after["d1_all"]))
        if fill and item["key"] == "flow":
            noc = v & ~item["occ"]
            before = metrics.flow_metrics(s["pred"], item["gt"], v, noc)
            after = metrics.flow_metrics(nearest_fill(s["pred"], s["occ"]), item["gt"], v, noc)
            p["fill"].append((before["epe_all"], before["epe_noc"], after["epe_all"], after["epe_noc"]))
    out = {}
    for key, p in parts.items():
        sp = metrics.sparsification(np.concatenate(p["err"]), np.concatenate(p["conf"]))
        row = {k: sp[k] for k in ("mean", "ause", "ause_relative", "top_half_ratio", "curve", "oracle")}
        row["occluded_predicted"] = float(np.concatenate(p["occ"]).mean())
        if p["true"]:
            true = np.concatenate(p["true"])
            row.update({f"occ_{k}": v for k, v in metrics.mask_scores(np.concatenate(p["occ"]), true).items()})
            row["occluded_true"] = float(true.mean())
        if p["fill"]:
            f = np.mean(np.asarray(p["fill"]), axis=0)
            second = "d1" if key == "disparity" else "epe_noc"
            row["fill"] = {"epe": f[0], second: f[1], "epe_filled": f[2], f"{second}_filled": f[3]}
        out[key] = row
    return out


def sweep(items: list[dict], modes) -> dict:
    """The selection frames' grids: (radius, weight) of the edge term by summed relative AUSE (flow +
    disparity), the occlusion threshold per mode by summed F1; and the picks by the rules of
    `bridge_jax.confidence` (the smallest radius, then weight, within 0.005 of the best AUSE; the smallest
    threshold within 0.02 of the best F1)."""
    default = confidence.DEFAULT_CHECK
    edge_rows = []
    for radius, weight in itertools.product(EDGE_GRID["radius"], EDGE_GRID["weight"]):
        r = pooled(items, default, radius, weight)
        edge_rows.append({"radius": radius, "weight": weight, "disparity": r["disparity"]["ause_relative"],
                          "flow": r["flow"]["ause_relative"],
                          "sum": r["disparity"]["ause_relative"] + r["flow"]["ause_relative"]})
    best = min(row["sum"] for row in edge_rows)
    edge_pick = min((row for row in edge_rows if row["sum"] <= best + 0.005), key=lambda r: (r["radius"], r["weight"]))
    thresholds = {}
    for mode in modes:
        rows = []
        for thr in THRESHOLD_GRID:
            r = pooled(items, mode, threshold=thr)
            rows.append({"threshold": thr, "disparity_f1": r["disparity"]["occ_f1"], "flow_f1": r["flow"]["occ_f1"],
                         "sum": r["disparity"]["occ_f1"] + r["flow"]["occ_f1"]})
        top = max(row["sum"] for row in rows)
        thresholds[mode] = {"rows": rows, "pick": min(row["threshold"] for row in rows if row["sum"] >= top - 0.02)}
    return {"edge": {"rows": edge_rows, "pick": {"radius": edge_pick["radius"], "weight": edge_pick["weight"]}},
            "threshold": thresholds,
            "shipped": {"radius": confidence.EDGE_RADIUS, "weight": confidence.EDGE_WEIGHT,
                        "threshold": dict(confidence.OCCLUSION_THRESHOLD)}}


def timing(pred, frames, modes, repeats: int = 2) -> dict:
    """Warm seconds per frame (its two pairs as one call), without and with the confidence of each mode,
    alternating on one predictor (medians)."""
    jobs = [[(task, a, b) for _, task, a, b in frame_jobs(fr)] for fr in frames]
    own = pred.test_time
    checks = {m: confidence.check_record(m, own) for m in modes}
    pred.predict(jobs[0], 2)
    for m in modes:  # compile what each check needs
        pred.check = checks[m]
        pred.predict(jobs[0], 2, confidence=True)
    seconds: dict[str, list] = {"plain": [], **{m: [] for m in modes}}
    for _ in range(repeats):
        for j in jobs:
            pred.check = None
            t = time.perf_counter()
            pred.predict(j, 2)
            seconds["plain"].append(time.perf_counter() - t)
            for m in modes:
                pred.check = checks[m]
                t = time.perf_counter()
                pred.predict(j, 2, confidence=True)
                seconds[m].append(time.perf_counter() - t)
    pred.check = None
    med = {k: float(np.median(v)) for k, v in seconds.items()}
    return {"seconds_per_frame": med, "ratio": {m: med[m] / med["plain"] for m in modes}}


def summary_lines(result: dict) -> list[str]:
    lines = []
    for model, entry in result["models"].items():
        lines.append(f"{model} ({entry['working_size']}, {entry['test_time']})")
        for mode, sets in entry["modes"].items():
            for name, rows in sets.items():
                for key, r in rows.items():
                    occ = (f" occ P {r['occ_precision']:.2f} R {r['occ_recall']:.2f}" if "occ_precision" in r else "")
                    fill = ""
                    if "fill" in r:
                        f = r["fill"]
                        fill = (f" fill D1 {f['d1']:.2f} -> {f['d1_filled']:.2f} %" if "d1" in f else
                                f" fill EPE {f['epe']:.3f} -> {f['epe_filled']:.3f}, noc {f['epe_noc']:.3f} -> "
                                f"{f['epe_noc_filled']:.3f}")
                    lines.append(f"  {mode:8s} {name:18s} {key:9s} mean {r['mean']:.3f} top-50% ratio "
                                 f"{r['top_half_ratio']:.3f} AUSE {r['ause']:.3f} ({r['ause_relative']:.3f}){occ}{fill}")
        if "timing" in entry:
            lines.append(f"  timing {entry['timing']}")
    return lines


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--models", default="long", help="comma list of shipped names or checkpoints")
    p.add_argument("--selection", type=int, default=8, help="selection frames")
    p.add_argument("--heldout", type=int, default=16, help="held-out synthetic frames")
    p.add_argument("--sweep", action="store_true", help="also run the selection grids (first model only)")
    p.add_argument("--timing-frames", type=int, default=3)
    p.add_argument("--out", required=True, help="JSON file")
    args = p.parse_args(argv)
    compile_cache.enable("auto")
    modes = confidence.CHECK_MODES
    selection = synthetic_frames(args.selection, SELECTION_SEED, 256, 512, scene="demo")
    heldout = real_checks.heldout_synthetic(args.heldout)
    result = {"date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
              "machine": f"{os.cpu_count()} CPUs, {platform.processor() or platform.machine()}",
              "selection_seed": SELECTION_SEED, "models": {}}
    for n, model in enumerate(args.models.split(",")):
        t0 = time.perf_counter()
        pred = load_predictor(model)
        entry = result["models"][model] = {"test_time": pred.test_time.to_dict(), "working_size": str(pred.size),
                                           "modes": {}}
        sel_items = collect(pred, selection, modes)
        held_items = collect(pred, heldout, modes)
        moto_items = motorcycle_items(pred, modes)
        if args.sweep and n == 0:
            entry["sweep"] = sweep(sel_items, modes)
            print(json.dumps({k: v["pick"] if "pick" in v else v for k, v in entry["sweep"].items()}), flush=True)
        for mode in modes:
            entry["modes"][mode] = {"selection": pooled(sel_items, mode),
                                    "heldout_synthetic": pooled(held_items, mode, fill=True),
                                    "motorcycle": pooled(moto_items, mode, fill=True)}
        entry["timing"] = timing(pred, heldout[:args.timing_frames], modes)
        entry["seconds"] = time.perf_counter() - t0
        print("\n".join(summary_lines({"models": {model: entry}})), flush=True)
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
