"""Real-image checks: the models against OpenCV on real photographs with exact ground truth.

The checks themselves (data, scoring) are `bridge_jax.eval.real_checks`, which `bridge-zoo compare` also runs;
this script runs all five for several models and OpenCV and writes the tables, pictures and card entries. Five
checks, each run for every model (`--models`, shipped names or checkpoint paths) at every working size
(`--sizes`: `trained` = the size the model was trained at, `native` = each input at its own resolution, or HxW),
next to OpenCV on the same inputs at full resolution:

1. **Middlebury "Motorcycle"** (scikit-image's stereo pair with its ground-truth disparity, 741x500): disparity
   EPE and D1 (KITTI outliers: > 3 px and > 5 %) over the pixels with ground truth, against SGBM with its holes
   filled (`eval.baselines.sgbm_disparity`).
2. **Real photos under known motion** (`real_checks.homography_pair`): a held-out photo
   (`data.photos.HELDOUT_PHOTOS`, never used in training) seen through a random homography, with 2-3
   independently moving pasted patches (affine motion) cut from another held-out photo, and a camera-response
   change plus noise between the frames. The flow is exact by construction and so is the occlusion mask: flow
   EPE-all / EPE-noc and Fl-all against DIS (medium).
3. **Held-out synthetic frames** (`synthetic.SCENE_PRESETS["heldout"]`: held-out photos as textures, a focal
   length and baseline no training preset draws, stronger photometric differences), 256x512: flow EPE-all,
   EPE-noc and disparity EPE / D1 against DIS and SGBM, and zero motion for scale.
4. **Pure shifts** (`real_checks.shift_set`): each held-out photo moved by 4 and 8 px, horizontally and
   vertically, with a camera-response change: EPE and the gain along the motion, per direction. It shows a
   direction the training scenes never moved in (the vertical, before `real_motion`).
5. **Pure zooms** (`real_checks.zoom_set`): each held-out photo zoomed by +4 % and -4 % about its centre, with a
   camera-response change: EPE and the gain (least-squares scale of the predicted flow), per direction. It shows
   whether a model reads expansion and contraction at their size (`long` before stage 6 read them 3-5 % short).

    python experiments/real_images.py --models demo,long --sizes trained,native \\
        --out experiments/results/real_images.md --pictures experiments/results/real_images

Writes the markdown table (machine and date in its header), a JSON file beside it with every number, picture
panels (input | ground truth | OpenCV | each model; half-size JPEGs) under `--pictures`, and with `--card` the
first model's numbers for its zoo card (`bridge-zoo build NAME --from WORKDIR --card FILE`; at the first
`--refine`, `--symmetry` and `--polish` values, which the card then recommends). `--refine 0,2` scores each
model without and with two test-time refinement passes (`inference.refine_maps`), `--symmetry none,flips`
without and with test-time symmetry averaging (`inference.symmetric_maps`), `--polish none,photometric`
without and with the test-time photometric polish (`bridge_jax.polish`); the default of all three, `card`, runs
each model as its card says.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time

import cv2

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO not in sys.path:
    sys.path.insert(0, REPO)

from bridge_jax import inference, testtime, visualize  # noqa: E402
from bridge_jax.bench import timing  # noqa: E402
from bridge_jax.eval import real_checks  # noqa: E402

PICTURES = {"motorcycle": lambda d: visualize.disparity_to_color(d, vmax=64.0),
            "homography": lambda f: visualize.flow_to_color(f, max_flow=20.0),
            "heldout_synthetic": lambda f: visualize.flow_to_color(f, max_flow=30.0)}
"""The checks with a picture panel, and how each colours a map."""


def run_checks(methods: dict, *, per_photo: int = 3, synthetic_num: int = 16, pictures: str | None = None) -> dict:
    """methods: name -> method (`real_checks`: a predictor, `ZeroMotion`, `OpenCV`). Returns {check: {method:
    metrics}} for every check of `real_checks.CHECKS`, plus {"seconds": {method: s}}; with `pictures`, writes a
    panel per check of `PICTURES` (input | ground truth | each method's first map) into that folder."""
    results: dict[str, dict] = {check: {} for check in real_checks.CHECKS}
    seconds: dict[str, float] = {}
    data = {check: real_checks.build(check, per_photo=per_photo, synthetic_num=synthetic_num)
            for check in real_checks.CHECKS}
    panels: dict[str, list] = {check: [] for check in PICTURES}
    for name, method in methods.items():
        t0 = time.perf_counter()
        for check in real_checks.CHECKS:
            results[check][name], first = real_checks.score(method, check, data[check])
            if check in PICTURES:
                panels[check].append((name, PICTURES[check](first)))
        seconds[name] = time.perf_counter() - t0
        print(f"{name}: {seconds[name]:.1f} s", file=sys.stderr, flush=True)
    if pictures:
        os.makedirs(pictures, exist_ok=True)
        moto, hom, syn = data["motorcycle"], data["homography"][0], data["heldout_synthetic"][0]
        gt_images = {"motorcycle": (moto["left"], PICTURES["motorcycle"](moto["disp"])),
                     "homography": (hom["frame_t"], PICTURES["homography"](hom["flow"])),
                     "heldout_synthetic": (syn.images["left_t"], PICTURES["heldout_synthetic"](syn.gt["flow_occ"]))}
        for check, items in panels.items():
            image, gt = gt_images[check]
            tiles = [image, gt] + [t for _, t in items]
            labels = ["input", "ground truth"] + [n for n, _ in items]
            picture = visualize.panel(tiles, labels, ncols=3)
            picture = cv2.resize(picture, (picture.shape[1] // 2, picture.shape[0] // 2), interpolation=cv2.INTER_AREA)
            visualize.write_image(os.path.join(pictures, f"{check}.jpg"), picture)  # half size: small files
    results["seconds"] = seconds
    return results


HEADLINE = (("motorcycle", "d1_all"), ("motorcycle", "epe_all"), ("homography", "epe_all"),
            ("heldout_synthetic", "flow_epe_all"), ("heldout_synthetic", "disp_epe_all"))
"""The numbers that choose a model's default working size (lower is better)."""


def pick_working_size(card: dict) -> str:
    """The working size a model's card recommends (and `--working-size` defaults to): the measured size that
    beats every other measured size, one against one, on more of the `HEADLINE` numbers than it loses ("trained",
    "native" or "HxW", as `--sizes` named it); "trained" when no size beats all the others. A tie on a number (a
    check whose images are the trained size, so two sizes run the same) counts for neither."""
    sizes = list(dict.fromkeys(s for c, _ in HEADLINE for s in card.get(c, {}) if s != "opencv"))

    def beats(a: str, b: str) -> bool:
        pairs = [(card[c][a][k], card[c][b][k]) for c, k in HEADLINE if a in card.get(c, {}) and b in card.get(c, {})]
        return sum(x < y for x, y in pairs) > sum(y < x for x, y in pairs)

    winners = [a for a in sizes if all(beats(a, b) for b in sizes if b != a)]
    return winners[0] if winners else "trained"


def markdown(results: dict, header: str) -> str:
    lines = [header, ""]
    cols = {"motorcycle": [("epe_all", "disp EPE px"), ("d1_all", "D1 %")],
            "homography": [("epe_all", "flow EPE-all px"), ("epe_noc", "EPE-noc px"), ("fl_all", "Fl-all %")],
            "heldout_synthetic": [("flow_epe_all", "flow EPE-all"), ("flow_epe_noc", "EPE-noc"), ("fl_all", "Fl %"),
                                  ("disp_epe_all", "disp EPE"), ("d1_all", "D1 %")],
            "shifts": [("epe_horizontal", "EPE horizontal px"), ("epe_vertical", "EPE vertical px"),
                       ("gain_horizontal", "gain horizontal"), ("gain_vertical", "gain vertical")],
            "zooms": [("epe_expand", "EPE expanding px"), ("epe_contract", "EPE contracting px"),
                      ("gain_expand", "gain expanding"), ("gain_contract", "gain contracting")]}
    titles = {"motorcycle": "Middlebury Motorcycle (741x500, disparity)",
              "homography": "Held-out photos under homographies + moving patches (flow)",
              "heldout_synthetic": "Held-out synthetic scenes, 256x512 (flow and disparity)",
              "shifts": "Held-out photos shifted by 4 and 8 px, horizontally and vertically (flow; gain 1 = exact)",
              "zooms": "Held-out photos zoomed by +4 % and -4 % about their centre (flow; gain 1 = exact)"}
    for check, cs in cols.items():
        if check not in results:  # results of an earlier version of the script
            continue
        lines += [f"### {titles[check]}", "", "| method | " + " | ".join(c[1] for c in cs) + " |",
                  "|---" * (len(cs) + 1) + "|"]
        for name, m in results[check].items():
            lines.append(f"| {name} | " + " | ".join(f"{m[c[0]]:.3f}" if c[0].startswith(("epe", "flow_epe",
                                                                                             "disp_epe", "gain"))
                                                      else f"{m[c[0]]:.1f}" for c in cs) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="demo", help="comma list of shipped model names or checkpoint paths")
    p.add_argument("--sizes", default="trained,native", help="comma list: trained, native, or HxW")
    p.add_argument("--refine", default="card",
                   help="comma list of test-time refinement passes to score (each a method), or 'card' = what "
                        "each model's card recommends (0 for a checkpoint path)")
    p.add_argument("--symmetry", default="card",
                   help="comma list of test-time symmetry averagings to score (none, flips, dihedral; each a "
                        "method), or 'card' = what each model's card recommends (none for a checkpoint path)")
    p.add_argument("--polish", default="card",
                   help="comma list of test-time polishes to score (none, photometric; each a method), or 'card' = "
                        "what each model's card recommends (none for a checkpoint path)")
    p.add_argument("--per-photo", type=int, default=3, help="homography pairs per held-out photo")
    p.add_argument("--synthetic-num", type=int, default=16, help="held-out synthetic frames")
    p.add_argument("--out", default=None, help="markdown file (a .json with every number is written beside it)")
    p.add_argument("--pictures", default=None, help="folder for the picture panels")
    p.add_argument("--card", default=None,
                   help="write the first model's numbers (per check and size, with OpenCV's) as a model-card JSON "
                        "for `bridge-zoo build NAME --from WORKDIR --card FILE`")
    args = p.parse_args(argv)
    opencv = "OpenCV (SGBM filled / DIS medium)"
    methods: dict = {"zero motion": real_checks.ZeroMotion(), opencv: real_checks.OpenCV()}
    card_labels = {}
    for i, model in enumerate(m for m in args.models.split(",") if m):
        passes = [None] if args.refine == "card" else [int(v) for v in args.refine.split(",") if v]
        symmetries = [None] if args.symmetry == "card" else [v for v in args.symmetry.split(",") if v]
        polishes = [None] if args.polish == "card" else [v for v in args.polish.split(",") if v]
        for size in [s for s in args.sizes.split(",") if s]:
            ws = size if size in ("trained", "native") else tuple(int(v) for v in size.lower().split("x"))
            variants = [(r, y, q) for r in passes for y in symmetries for q in polishes]
            for k, (refine, symmetry, polish) in enumerate(variants):
                pred = inference.load_predictor(model, size=ws, options=testtime.OPTIONS,
                                                test_time={"refine": refine, "symmetry": symmetry, "polish": polish})
                label = f"{os.path.basename(model.rstrip('/'))} @ {size}"
                if size == "trained":
                    label += f" ({pred.height}x{pred.width})"
                if pred.refine:
                    label += f", refine {pred.refine}"
                if pred.symmetry != "none":
                    label += f", {pred.symmetry}"
                if pred.polish != "none":
                    label += f", {pred.polish} polish"
                methods[label] = pred
                if i == 0 and k == 0:
                    card_labels[size] = label
    results = run_checks(methods, per_photo=args.per_photo, synthetic_num=args.synthetic_num,
                         pictures=args.pictures)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = f"## Real-image checks, {stamp}, {timing.machine()}"
    text = markdown(results, header)
    print(text)
    print("seconds per method:", {k: round(v, 1) for k, v in results["seconds"].items()})
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
        with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
            json.dump({"date": stamp, "machine": timing.machine(), **results}, f, indent=1)
    if args.card:
        checks = ("motorcycle", "homography", "heldout_synthetic")
        card = {check: {**{size: results[check][label] for size, label in card_labels.items()},
                        "opencv": results[check][opencv]} for check in checks}
        with open(args.card, "w") as f:
            first = methods[next(iter(card_labels.values()))]  # numbers at the first --refine/--symmetry/--polish
            json.dump({"real_images": card, "real_images_measured": f"{stamp}, {timing.machine()}",
                       "default_working_size": pick_working_size(card), "default_refine": first.refine,
                       "default_symmetry": first.symmetry, "default_polish": first.polish}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
