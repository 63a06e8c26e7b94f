"""Real-image checks: the models against OpenCV on real photographs with exact ground truth.

The checks themselves (data, scoring) are `bridge_jax.eval.real_checks`, which `bridge-zoo compare` also runs;
this script runs them for several models and OpenCV and writes the tables, pictures and card entries. Six
checks, each run for every model (`--models`, shipped names or checkpoint paths) at every working size
(`--sizes`: `trained` = the size the model was trained at, `native` = each input at its own resolution, or HxW),
next to OpenCV on the same inputs at full resolution:

1. **Middlebury "Motorcycle"** (scikit-image's stereo pair with its ground-truth disparity, 741x500): disparity
   EPE and D1 (KITTI outliers: > 3 px and > 5 %) over the pixels with ground truth, against SGBM in its
   standard form with its holes filled (`eval.baselines.sgbm_disparity`), searching the range Middlebury states
   for the pair (`real_checks.stated_max_disparity`).
2. **Real photos under known motion** (`real_checks.homography_pair`): a held-out photo
   (`data.photos.HELDOUT_PHOTOS`, never used in training) seen through a random homography, with 2-3
   independently moving pasted patches (affine motion) cut from another held-out photo, and a camera-response
   change plus noise between the frames. The flow is exact by construction and so is the occlusion mask: flow
   EPE-all / EPE-noc and Fl-all.
3. **Held-out synthetic frames** (`synthetic.SCENE_PRESETS["heldout"]`: held-out photos as textures, a focal
   length and baseline no training preset draws, stronger photometric differences), 256x512: flow EPE-all,
   EPE-noc and disparity EPE / D1 (SGBM searching the generator's stated range), and zero motion for scale.
4. **Pure shifts** (`real_checks.shift_set`): each held-out photo moved by 4 and 8 px, horizontally and
   vertically, with a camera-response change: EPE and the gain along the motion, per direction. It shows a
   direction the training scenes never moved in (the vertical, before `real_motion`).
5. **Pure zooms** (`real_checks.zoom_set`): each held-out photo zoomed by +4 % and -4 % about its centre, with a
   camera-response change: EPE and the gain (least-squares scale of the predicted flow), per direction. It shows
   whether a model reads expansion and contraction at their size (`long` before stage 6 read them 3-5 % short).
6. **Kept out** (`real_checks.kept_out`): held-out synthetic frames drawn with another seed, and 12 homography
   pairs of six other photos. No choice is made on it (`real_checks.SELECTION_CHECKS` are the five above: the
   working size a card recommends, its refine / symmetry / polish, the polish's parameters, a recipe); it reports
   how each choice fares on data the choice did not see. Near-edge disparity numbers (Motorcycle and both
   synthetic sets: EPE and D1 within 5 px of a depth edge, and the share of those pixels fattened by a nearer
   surface, `metrics.disparity_edge_metrics`) show the foreground fattening apart from the rest.

Every check runs zero motion and three OpenCV baselines, each SGBM for disparity with one optical flow:
DIS (medium preset), DIS down to the finest scale (`setFinestScale(0)`) and DeepFlow (`eval.baselines.FLOWS`;
DeepFlow needs `opencv-contrib-python-headless`, the `experiments` extra). Each table names the strongest
baseline of its check (`strongest_baseline`).

    python experiments/real_images.py --models demo,long --sizes trained,native \\
        --out experiments/results/real_images.md --pictures experiments/results/real_images

`--baselines-only --models-from FILE.json` runs only zero motion and the baselines, and takes the models' rows
from an earlier run's JSON (the models are not rerun; nor are pictures or cards written).

Writes the markdown table (machine and date in its header), a JSON file beside it with every number, picture
panels (input | ground truth | OpenCV | each model; half-size JPEGs) under `--pictures`, and with `--card` the
first model's numbers for its zoo card (`bridge-zoo build NAME --from WORKDIR --card FILE`; at the first
`--refine`, `--symmetry` and `--polish` values, which the card then recommends; with `--polish photometric,none`
also the same settings' numbers without the polish, the card's `real_images_polish_none`). `--refine 0,2` scores each
model without and with two test-time refinement passes (`inference.refine_maps`), `--symmetry none,flips`
without and with test-time symmetry averaging (`inference.symmetric_maps`), `--polish none,photometric`
without and with the test-time photometric polish (`bridge_jax.polish`); the default of all three, `card`, runs
each model as its card says.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import sys
import time
from typing import Optional

import cv2

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO not in sys.path:
    sys.path.insert(0, REPO)

from bridge_jax import inference, polish, testtime, visualize, zoo  # noqa: E402
from bridge_jax.bench import timing  # noqa: E402
from bridge_jax.eval import real_checks  # noqa: E402

PICTURES = {"motorcycle": lambda d: visualize.disparity_to_color(d, vmax=64.0),
            "homography": lambda f: visualize.flow_to_color(f, max_flow=20.0),
            "heldout_synthetic": lambda f: visualize.flow_to_color(f, max_flow=30.0)}
"""The checks with a picture panel, and how each colours a map."""


def run_checks(methods: dict, *, per_photo: int = 3, synthetic_num: int = 16, pictures: str | None = None,
               checks: tuple = tuple(real_checks.CHECKS)) -> dict:
    """methods: name -> method (`real_checks`: a predictor, `ZeroMotion`, `OpenCV`). Returns {check: {method:
    metrics}} for each of `checks` (default every check of `real_checks.CHECKS`), plus {"seconds": {method: s}};
    with `pictures`, writes a panel per check of `PICTURES` (input | ground truth | each method's first map)
    into that folder."""
    results: dict[str, dict] = {check: {} for check in checks}
    seconds: dict[str, float] = {}
    data = {check: real_checks.build(check, per_photo=per_photo, synthetic_num=synthetic_num) for check in checks}
    panels: dict[str, list] = {check: [] for check in PICTURES if check in checks}
    for name, method in methods.items():
        t0 = time.perf_counter()
        for check in checks:
            results[check][name], first = real_checks.score(method, check, data[check])
            if check in panels:
                panels[check].append((name, PICTURES[check](first)))
        seconds[name] = time.perf_counter() - t0
        print(f"{name}: {seconds[name]:.1f} s", file=sys.stderr, flush=True)
    if pictures:
        os.makedirs(pictures, exist_ok=True)
        gt_images = {"motorcycle": lambda d: (d["left"], PICTURES["motorcycle"](d["disp"])),
                     "homography": lambda d: (d[0]["frame_t"], PICTURES["homography"](d[0]["flow"])),
                     "heldout_synthetic": lambda d: (d[0].images["left_t"],
                                                     PICTURES["heldout_synthetic"](d[0].gt["flow_occ"]))}
        for check, items in panels.items():
            image, gt = gt_images[check](data[check])
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


BASELINES = tuple(f"OpenCV SGBM / {flow}" for flow in ("DIS medium", "DIS fine", "DeepFlow"))
"""The names of the OpenCV baselines' rows: SGBM (standard form, the check's stated range) with each flow."""
ZERO = "zero motion"

STRONGEST_BY = {"motorcycle": ("d1_all", "epe_all"), "homography": ("epe_all",),
                "heldout_synthetic": ("flow_epe_all",), "shifts": ("epe_horizontal", "epe_vertical"),
                "zooms": ("epe_expand", "epe_contract"), "kept_out": ("flow_epe_all", "photo_epe_all")}
"""What makes a baseline the strongest of a check: the lowest mean of these numbers (every baseline's stereo is
the same SGBM, so on the held-out synthetic set the flow decides)."""


def is_baseline(name: str) -> bool:
    """Whether a row of the results is zero motion or an OpenCV baseline (of this version or an earlier one)."""
    return name == ZERO or name.startswith("OpenCV")


def strongest_baseline(results: dict, check: str) -> Optional[str]:
    """The name of the OpenCV row of `results[check]` with the lowest mean of `STRONGEST_BY[check]` (the first
    of a tie); None when the check has none."""
    rows = {n: m for n, m in results.get(check, {}).items() if n.startswith("OpenCV")}
    if not rows:
        return None
    return min(rows, key=lambda n: sum(rows[n][k] for k in STRONGEST_BY[check]) / len(STRONGEST_BY[check]))


COLUMNS = {"motorcycle": [("epe_all", "disp EPE px"), ("d1_all", "D1 %"), ("epe_edge", "EPE near edges px"),
                          ("d1_edge", "D1 near edges %"), ("fat_edge", "fattened near edges %"),
                          ("epe_outview", "EPE out of view px"), ("d1_outview", "D1 out of view %")],
           "homography": [("epe_all", "flow EPE-all px"), ("epe_noc", "EPE-noc px"), ("fl_all", "Fl-all %")],
           "heldout_synthetic": [("flow_epe_all", "flow EPE-all"), ("flow_epe_noc", "EPE-noc"), ("fl_all", "Fl %"),
                                 ("disp_epe_all", "disp EPE"), ("d1_all", "D1 %"), ("disp_epe_edge", "EPE near edges"),
                                 ("d1_edge", "D1 near edges %"), ("fat_edge", "fattened %")],
           "shifts": [("epe_horizontal", "EPE horizontal px"), ("epe_vertical", "EPE vertical px"),
                      ("gain_horizontal", "gain horizontal"), ("gain_vertical", "gain vertical")],
           "zooms": [("epe_expand", "EPE expanding px"), ("epe_contract", "EPE contracting px"),
                     ("gain_expand", "gain expanding"), ("gain_contract", "gain contracting")],
           "kept_out": [("flow_epe_all", "synthetic flow EPE-all"), ("flow_epe_noc", "EPE-noc"),
                        ("disp_epe_all", "disp EPE"), ("d1_all", "D1 %"), ("d1_edge", "D1 near edges %"),
                        ("photo_epe_all", "photo flow EPE-all"), ("photo_epe_noc", "photo EPE-noc")]}
TITLES = {"motorcycle": "Middlebury Motorcycle (741x500, disparity)",
          "homography": "Held-out photos under homographies + moving patches (flow)",
          "heldout_synthetic": "Held-out synthetic scenes, 256x512 (flow and disparity)",
          "shifts": "Held-out photos shifted by 4 and 8 px, horizontally and vertically (flow; gain 1 = exact)",
          "zooms": "Held-out photos zoomed by +4 % and -4 % about their centre (flow; gain 1 = exact)",
          "kept_out": ("Kept out of every choice: held-out synthetic scenes of another seed (256x512) and 12 "
                       "homography pairs of six other photos")}


STEREO_ONLY, FLOW_ONLY = ("motorcycle",), ("homography", "shifts", "zooms")


def baseline_label(check: str, name: str) -> str:
    """How `check`'s table names the baseline row `name` ("OpenCV SGBM / DeepFlow"): by the half of it the check
    uses ("OpenCV SGBM" on Motorcycle, "OpenCV DeepFlow" on a flow-only check); other rows as they are."""
    if not name.startswith("OpenCV SGBM / "):
        return name
    if check in STEREO_ONLY:
        return "OpenCV SGBM"
    if check in FLOW_ONLY:
        return "OpenCV " + name.split(" / ", 1)[1]
    return name


def _number(key: str, value: float) -> str:
    return f"{value:.3f}" if key.startswith(("epe", "flow_epe", "disp_epe", "photo_epe", "gain")) else f"{value:.1f}"


def markdown(results: dict, header: str) -> str:
    lines = [header, ""]
    for check, cs in COLUMNS.items():
        if check not in results:  # results of an earlier version of the script
            continue
        best = strongest_baseline(results, check)
        lines += [f"### {TITLES[check]}", "", "| method | " + " | ".join(c[1] for c in cs) + " |",
                  "|---" * (len(cs) + 1) + "|"]
        shown = set()
        for name, m in results[check].items():
            label = baseline_label(check, name)
            if label in shown:  # the same SGBM under another flow: one row
                continue
            shown.add(label)
            label = f"**{label}** (strongest baseline)" if name == best else label
            lines.append(f"| {label} | " + " | ".join(_number(c[0], m[c[0]]) if c[0] in m else "–" for c in cs)
                         + " |")
        lines.append("")
        if best:
            lines += [f"Strongest baseline: {baseline_label(check, best)} (lowest {' / '.join(STRONGEST_BY[check])}).",
                      ""]
    return "\n".join(lines)


def merge_model_rows(results: dict, earlier: dict) -> dict:
    """`results` (baselines only, as `run_checks` returns them) with the model rows of an `earlier` run's JSON
    after them, per check; its baseline rows (zero motion, any OpenCV) are left out. {"seconds"} keeps only
    this run's."""
    merged = {}
    for check in real_checks.CHECKS:
        merged[check] = dict(results.get(check, {}))
        for name, m in (earlier.get(check) or {}).items():
            if not is_baseline(name):
                merged[check][name] = m
    merged["seconds"] = results.get("seconds", {})
    return merged


def parse_polish_settings(parser: argparse.ArgumentParser, text: Optional[str]) -> dict:
    """`--polish-settings`: {PolishConfig field: value} (an error naming the option for anything else)."""
    if text is None:
        return {}
    try:
        settings = json.loads(text)
    except ValueError as e:
        parser.error(f"--polish-settings {text!r}: not JSON ({e}); expected an object such as "
                     '\'{"variational_sigma": 4.5}\'')
    if not isinstance(settings, dict):
        parser.error(f"--polish-settings {text!r}: expected a JSON object of polish.PolishConfig fields")
    fields = {f.name for f in dataclasses.fields(polish.PolishConfig)}
    unknown = sorted(set(settings) - fields)
    if unknown:
        parser.error(f"--polish-settings: polish.PolishConfig has no field {', '.join(unknown)} (it has "
                     f"{', '.join(sorted(fields))})")
    try:
        dataclasses.replace(polish.DEFAULT_CONFIG, **settings)
    except (TypeError, ValueError) as e:
        parser.error(f"--polish-settings {text!r}: {e}")
    return settings


def model_polish_config(model: str, settings: dict) -> Optional[polish.PolishConfig]:
    """The polish parameters `model` is scored with: its card's (None: `load_predictor` reads them) with
    `settings` on top."""
    if not settings:
        return None
    return zoo.card_polish_config(model, **settings)


def card_polish_settings(config: polish.PolishConfig) -> dict:
    """The fields of `config` that differ from the polish's defaults: what a card records as its
    "default_polish_settings" (`zoo.card_polish_settings` reads them back)."""
    return {f.name: getattr(config, f.name) for f in dataclasses.fields(config)
            if getattr(config, f.name) != getattr(polish.DEFAULT_CONFIG, f.name)}


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
    p.add_argument("--polish-settings", default=None, metavar="JSON",
                   help="polish parameters for every model, as a JSON object of `polish.PolishConfig` fields (for "
                        "example '{\"variational_sigma\": 4.5}'), on top of what each model's card sets; --card "
                        "records the first model's as its default_polish_settings")
    p.add_argument("--checks", default=",".join(real_checks.CHECKS),
                   help="comma list of the checks to run (default all: %(default)s); `--checks kept_out` with "
                        "several --refine/--symmetry/--polish values reports each test-time choice on the check "
                        "no choice was made on")
    p.add_argument("--per-photo", type=int, default=3, help="homography pairs per held-out photo")
    p.add_argument("--synthetic-num", type=int, default=16, help="held-out synthetic frames")
    p.add_argument("--out", default=None, help="markdown file (a .json with every number is written beside it)")
    p.add_argument("--pictures", default=None, help="folder for the picture panels")
    p.add_argument("--card", default=None,
                   help="write the first model's numbers (per check and size, with the strongest OpenCV "
                        "baseline's) as a model-card JSON for `bridge-zoo build NAME --from WORKDIR --card FILE`")
    p.add_argument("--baselines-only", action="store_true",
                   help="run only zero motion and the OpenCV baselines; the models' rows come from --models-from")
    p.add_argument("--models-from", default=None,
                   help="with --baselines-only: an earlier run's JSON whose model rows the tables show")
    args = p.parse_args(argv)
    checks = tuple(c for c in args.checks.split(",") if c)
    unknown = [c for c in checks if c not in real_checks.CHECKS]
    if unknown or not checks:
        p.error(f"--checks {args.checks!r}: expected a comma list of {', '.join(real_checks.CHECKS)}")
    if args.card and set(checks) != set(real_checks.CHECKS):
        p.error("--card needs every check (its card lists them all): leave --checks out")
    if args.baselines_only != bool(args.models_from):
        p.error("--baselines-only and --models-from go together: the models' rows come from that JSON")
    if args.baselines_only and (args.card or args.pictures):
        p.error("--baselines-only writes no --card or --pictures: those need the models' maps")
    polish_settings = parse_polish_settings(p, args.polish_settings)
    earlier = None
    if args.models_from:
        try:
            with open(args.models_from) as f:
                earlier = json.load(f)
        except (OSError, ValueError) as e:
            p.error(f"--models-from {args.models_from}: cannot read a results JSON ({e})")
        if not isinstance(earlier, dict) or not any(isinstance(earlier.get(c), dict) for c in real_checks.CHECKS):
            p.error(f"--models-from {args.models_from}: no check results in it")
    from bridge_jax.eval import baselines
    if not baselines.has_contrib():
        p.error(f"DeepFlow: {baselines.CONTRIB_HINT}")
    methods: dict = {ZERO: real_checks.ZeroMotion()}
    methods.update({name: real_checks.OpenCV(flow=name.split(" / ")[1]) for name in BASELINES})
    card_labels, card_labels_none = {}, {}
    models = [] if args.baselines_only else [m for m in args.models.split(",") if m]
    for i, model in enumerate(models):
        passes = [None] if args.refine == "card" else [int(v) for v in args.refine.split(",") if v]
        symmetries = [None] if args.symmetry == "card" else [v for v in args.symmetry.split(",") if v]
        polishes = [None] if args.polish == "card" else [v for v in args.polish.split(",") if v]
        for size in [s for s in args.sizes.split(",") if s]:
            ws = size if size in ("trained", "native") else tuple(int(v) for v in size.lower().split("x"))
            variants = [(r, y, q) for r in passes for y in symmetries for q in polishes]
            for k, (refine, symmetry, finish) in enumerate(variants):
                pred = inference.load_predictor(model, size=ws, options=testtime.OPTIONS,
                                                test_time={"refine": refine, "symmetry": symmetry, "polish": finish},
                                                polish_config=model_polish_config(model, polish_settings))
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
                elif i == 0 and pred.polish == "none" and (refine, symmetry) == variants[0][:2]:
                    card_labels_none[size] = label  # the card's settings but the polish: the network's own maps
    results = run_checks(methods, per_photo=args.per_photo, synthetic_num=args.synthetic_num,
                         pictures=args.pictures, checks=checks)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = f"## Real-image checks, {stamp}, {timing.machine()}"
    extra = {}
    if earlier is not None:
        results = merge_model_rows(results, earlier)
        extra = {"models_from": {"file": args.models_from, "date": earlier.get("date"),
                                 "machine": earlier.get("machine")}}
        header += (f" (baselines; the models' rows from {os.path.basename(args.models_from)}, "
                   f"{earlier.get('date')}, {earlier.get('machine')})")
    ranges = {c: real_checks.stated_max_disparity(c, w) for c, w in (("motorcycle", 741), ("heldout_synthetic", 512))}
    header += ("\n\nSGBM searches each stereo pair's stated range: Motorcycle 0..%.1f px (Middlebury's ndisp), "
               "held-out synthetic 0..%.1f px (the generator's maximum)." % (ranges["motorcycle"],
                                                                           ranges["heldout_synthetic"]))
    text = markdown(results, header)
    print(text)
    print("seconds per method:", {k: round(v, 1) for k, v in results["seconds"].items()})
    strongest = {check: strongest_baseline(results, check) for check in real_checks.CHECKS}
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
        with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
            json.dump({"date": stamp, "machine": timing.machine(), **extra, "stated_max_disparity": ranges,
                       "strongest_baseline": strongest, **results}, f, indent=1)
    if args.card:
        checks = tuple(real_checks.CHECKS)
        card = {check: {**{size: results[check][label] for size, label in card_labels.items()},
                        "opencv": results[check][strongest[check]]} for check in checks}
        first = methods[next(iter(card_labels.values()))]  # numbers at the first --refine/--symmetry/--polish
        entries = {"real_images": card,
                   "real_images_opencv": {c: baseline_label(c, strongest[c]) for c in checks},
                   "real_images_measured": f"{stamp}, {timing.machine()}",
                   "default_working_size": pick_working_size(card), "default_refine": first.refine,
                   "default_symmetry": first.symmetry, "default_polish": first.polish}
        measured_with = card_polish_settings(first.polish_config) if first.polish != "none" else {}
        if measured_with:
            entries["default_polish_settings"] = measured_with
        if card_labels_none and first.polish != "none":  # `--polish P,none`: the network's own numbers beside
            entries[real_checks.CARD_KEY_POLISH_NONE] = {
                check: {size: results[check][label] for size, label in card_labels_none.items()} for check in checks}
        with open(args.card, "w") as f:
            json.dump(entries, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
