"""Ablation of the training switches on the demo's data, seeds and budget (experiments/results/ablation.md).

Each variant is the demo config (`bridge_jax/configs/demo.py`, with the `paper_loss` argument as the base:
every switch at the paper's setting) plus `KEY=VALUE` overrides, trained for `--steps` steps; the trainer's own
held-out validation (16 synthetic cycles, `config.eval.seed`) gives the numbers. One JSON line per variant:

  python experiments/ablation.py --steps 1000 --out experiments/results/raw/ablation.jsonl \
      base= census=loss.photometric=census finest=loss.scales=finest \
      'census+finest=loss.photometric=census,loss.scales=finest'
  python experiments/ablation.py --model resnet_md_tiny --steps 1000 ...

  python experiments/ablation.py --table experiments/results/raw/ablation.jsonl   # the markdown table

A variant is NAME=OVERRIDES, OVERRIDES a comma-separated list of KEY=VALUE (configs.override syntax); the
workdir of each run is kept under --workdir (a long run can be resumed by running it again with more steps).
"""
from __future__ import annotations

import argparse
import json
import os
import re
import sys
import time

from bridge_jax import configs, recipe, setup, train


def parse_variant(text: str) -> tuple[str, list[str]]:
    name, eq, rest = text.partition("=")
    if not eq or not name:
        raise SystemExit(f"variant {text!r}: expected NAME=KEY=VALUE[,KEY=VALUE...] or NAME= (no override)")
    items = [i for i in re.split(r",(?=[a-z_.]+=)", rest) if i]
    return name, items


def step_seconds(metrics_path: str) -> float | None:
    """Median of the logged per-step wall times (the trainer's `step_time_s`) after the first logs."""
    times = []
    with open(metrics_path) as f:
        for line in f:
            rec = json.loads(line)
            if "step_time_s" in rec and rec.get("step", 0) > 50:
                times.append(rec["step_time_s"])
    return sorted(times)[len(times) // 2] if times else None


def table(path: str) -> str:
    """Markdown table of a results file: one row per (model, variant, steps), grouped by model in order of first
    appearance, variants in file order (the last record of a row wins)."""
    rows = {}
    with open(path) as f:
        for line in f:
            r = json.loads(line)
            rows[(r["model"], r["variant"], r["steps"])] = r
    fmt = lambda v, d=3: "–" if v is None else f"{v:.{d}f}"
    out = ["| model | variant | overrides | steps | flow EPE-all / zero | flow EPE-noc / zero | disp EPE px | D1-all % "
           "| s/step |", "|---|---|---|---|---|---|---|---|---|"]
    models = list(dict.fromkeys(k[0] for k in rows))
    for (model, variant, steps), r in sorted(rows.items(), key=lambda kv: models.index(kv[0][0])):
        out.append(f"| {model} | {variant} | {' '.join(r['overrides']) or '(paper loss)'} | {steps} | "
                   f"{fmt(r['flow_epe_vs_zero'])} | {fmt(r['flow_noc_vs_zero'])} | {fmt(r['disp_epe_all'])} | "
                   f"{fmt(r['disp_d1_all'], 2)} | {fmt(r['s_per_step'], 2)} |")
    return "\n".join(out)


def main(argv=None) -> int:
    if argv is None:
        argv = sys.argv[1:]
    if argv[:1] == ["--table"] and len(argv) == 2:
        print(table(argv[1]))
        return 0
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--model", default="pwc_lite", choices=("pwc_lite", "resnet_md_tiny"))
    ap.add_argument("--steps", type=int, default=1000)
    ap.add_argument("--workdir", default="work/ablation")
    ap.add_argument("--out", required=True, help="JSON lines file to append to")
    ap.add_argument("--base", default="paper_loss", help="demo config argument(s) the variants start from")
    ap.add_argument("variants", nargs="+")
    args = ap.parse_args(argv)
    for text in args.variants:
        name, items = parse_variant(text)
        base = ",".join(a for a in (args.base, "resnet_md_tiny" if args.model == "resnet_md_tiny" else "") if a)
        config = recipe.single_run(configs.load(f"demo:{base}"))  # the demo recipe's first stage
        configs.override(config, items + [f"loop.num_train_steps={args.steps}", f"loop.eval_every={args.steps}",
                                          "loop.image_every=-1", f"loop.checkpoint_every={args.steps}", "loop.progress_bar=False"])
        run = setup.parse(config)
        workdir = os.path.join(args.workdir, f"{args.model}_{name}_{args.steps}")
        t0 = time.time()
        result = train.train_and_evaluate(run, workdir)
        val = result.get("validation", {})
        rec = {"model": args.model, "variant": name, "overrides": items, "steps": result["step"],
               "flow_epe_vs_zero": val.get("flow_epe_vs_zero"),
               "flow_noc_vs_zero": val.get("flow_noc_vs_zero"), "flow_epe_all": val.get("flow_epe_all"),
               "flow_epe_noc": val.get("flow_epe_noc"), "zero_flow_epe_all": val.get("zero_flow_epe_all"),
               "disp_epe_all": val.get("disp_epe_all"), "disp_d1_all": val.get("disp_d1_all"),
               "s_per_step": step_seconds(os.path.join(workdir, "metrics.jsonl")),
               "wall_s": round(time.time() - t0, 1), "workdir": workdir,
               "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())}
        with open(args.out, "a") as f:
            f.write(json.dumps(rec) + "\n")
        print(json.dumps(rec), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
