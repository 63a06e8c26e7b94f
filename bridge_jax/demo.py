r"""README main job: train the `demo` config on the built-in synthetic stereo video, then evaluate it.

    bridge-demo --workdir=work/demo        # what `make demo` runs (9-18 min on 2 CPU cores)

Steps:
  1. train the demo recipe (bridge_jax/configs/demo.py) into WORKDIR/train: its `coarse` stage (64x128) in
     WORKDIR/train/stages/coarse, then its `finish` stage (the same at 128x256, from the first stage's weights)
     in WORKDIR/train/stages/finish, whose model is the demo model (resumes if interrupted: run the command
     again),
  2. write a held-out synthetic validation set in the KITTI 2015 layout to WORKDIR/val_data (the data module's
     writer; the same samples the trainer validates on),
  3. evaluate the trained model and the zero-motion / OpenCV baselines on it (bridge_jax.evaluate) into
     WORKDIR/eval (results.md, results.json, pictures/), run as the shipped `demo` model answers by default
     (its card's test-time stages: `zoo.card_test_time`),
  4. print where the metrics, TensorBoard logs and pictures are, and whether the model learned (validation
     flow EPE vs the zero-motion baseline, from one network pass as training validates), with what the
     evaluation of step 3 measured next to it.
"""

from __future__ import annotations

import json
import os
import sys
import time

from bridge_jax import cli, compile_cache, console, evaluate, inference, recipe, train, zoo
from bridge_jax.configs import demo as demo_config
from bridge_jax.data import synthetic

def run(workdir: str, *, config_arg: str | None = None, overrides: dict | None = None,
        enable_cache: bool = False) -> dict:
    """The recipe's two stages + validation set + evaluation; returns a summary dict (paths and headline numbers).

    `config_arg`: the demo config's argument ("short" for the smoke run). `overrides`: {"dotted.key": value}
    applied to the base and every stage that sets the key (`recipe.override_everywhere`). `enable_cache`: turn on
    the persistent compilation cache of `config.compilation_cache_dir` (`compile_cache.enable`; what the command
    line does; JAX keeps the first cache folder of a process, so library callers leave it off)."""
    workdir = os.path.abspath(workdir)
    train_dir = os.path.join(workdir, "train")
    config = demo_config.get_config(config_arg)
    recipe.override_everywhere(config, [f"{k}={v}" if isinstance(v, str) else f"{k}={v!r}"
                                        for k, v in (overrides or {}).items()])
    runs = train._recipe_runs(config, train_dir)  # every stage checked before anything is written
    train._check_recipe_workdir(train_dir, list(runs))
    first_run, second_run = runs["coarse"], runs["finish"]
    if enable_cache:  # the demo's config is fixed and checked above: one cache serves training and evaluation
        compile_cache.enable(first_run.compilation_cache_dir, workdir, option="config.compilation_cache_dir")
    val_dir = os.path.join(workdir, "val_data")
    eval_dir = os.path.join(workdir, "eval")

    t0 = time.time()
    print(f"[1/3] Training the demo recipe: {first_run.loop.num_train_steps} steps at {first_run.height}x"
          f"{first_run.width}, then {second_run.loop.num_train_steps} at {second_run.height}x{second_run.width} "
          f"({first_run.model.config['name']}) in {train_dir}", flush=True)
    result = train.run_recipe(config, train_dir, config_name="demo")
    train_s = time.time() - t0
    if result["interrupted"]:
        print(f"Training interrupted at step {result['step']} (stage {result['stage']}); run the same command again "
              "to resume.")
        return {"interrupted": True, "train_dir": train_dir}

    print(f"[2/3] Writing {second_run.eval.num_samples} held-out synthetic validation cycles to {val_dir}", flush=True)
    if not os.path.isdir(val_dir):
        synthetic.write_kitti_layout(val_dir, second_run.eval.num_samples, seed=second_run.eval.seed,
                                     height=second_run.height, width=second_run.width)

    # Step 3 runs the model as `--checkpoint demo` answers a user by default (the shipped card's refinement
    # passes and polish); the headline ratio stays training's single-pass validation, so both are reported.
    test_time = zoo.card_test_time("demo")
    print(f"[3/3] Evaluating the trained model (refine {test_time.refine}, symmetry {test_time.symmetry}, polish "
          f"{test_time.polish}: the shipped demo's defaults) and the baselines on it into {eval_dir}", flush=True)
    predictor = inference.load_predictor(train_dir, size=(second_run.height, second_run.width), test_time=test_time)
    results = evaluate.evaluate(predictor, "synthetic", val_dir, out_dir=eval_dir, overwrite=True,
                                batch=second_run.eval.batch, progress=False,
                                extra_info={"checkpoint": train_dir, **predictor.test_time.to_dict()})
    val = result.get("validation", {})
    model = results["methods"]["model"]
    eval_flow, eval_disp = model["flow"]["per_image_mean"], model["disparity"]["per_image_mean"]
    zero_flow = val.get("zero_flow_epe_all")
    summary = {
        "interrupted": False, "train_dir": train_dir, "eval_dir": eval_dir,
        "val_data": val_dir, "train_seconds": round(train_s, 1), "steps": result["step"],
        "stage_steps": {stage["name"]: stage["steps"] for stage in result["stages"]},
        "val_flow_epe": val.get("flow_epe_all"), "zero_flow_epe": val.get("zero_flow_epe_all"),
        "val_flow_epe_vs_zero": val.get("flow_epe_vs_zero"), "val_flow_noc_vs_zero": val.get("flow_noc_vs_zero"),
        "val_disp_epe": val.get("disp_epe_all"),
        "zero_disp_epe": val.get("zero_disp_epe_all"), "val_d1_all": val.get("disp_d1_all"),
        "eval_refine": test_time.refine, "eval_polish": test_time.polish, "eval_flow_epe": eval_flow["epe_all"],
        "eval_flow_epe_vs_zero": eval_flow["epe_all"] / zero_flow if zero_flow else None,
        "eval_disp_epe": eval_disp["epe_all"], "eval_d1_all": eval_disp["d1_all"],
    }
    with open(os.path.join(workdir, "demo_summary.json"), "w") as f:
        json.dump(summary, f, indent=2)
    print()
    print(results.get("markdown", ""))
    print("Where things are:")
    print(f"  training metrics (JSON lines):  {os.path.join(train_dir, 'metrics.jsonl')}")
    print(f"  TensorBoard:                    tensorboard --logdir {os.path.join(train_dir, 'tensorboard')}")
    print(f"  training-time pictures:         {os.path.join(train_dir, 'images')}")
    print(f"  checkpoints:                    {os.path.join(train_dir, 'checkpoints')}")
    print(f"  evaluation tables:              {os.path.join(eval_dir, 'results.md')} (and results.json)")
    print(f"  evaluation pictures:            {os.path.join(eval_dir, 'pictures')}")
    if summary["val_flow_epe_vs_zero"] is not None:
        ratio = summary["val_flow_epe_vs_zero"]
        print(f"Validation flow EPE {summary['val_flow_epe']:.3f} px vs zero-motion {summary['zero_flow_epe']:.3f} px "
              f"(ratio {ratio:.2f}; {'learned' if ratio <= 0.5 else 'target <= 0.5 not reached'}); disparity EPE "
              f"{summary['val_disp_epe']:.3f} px vs zero {summary['zero_disp_epe']:.3f} px (one network pass, as "
              f"training validates). Training took {train_s / 60:.1f} min.")
        if summary["eval_flow_epe_vs_zero"] is not None:
            print(f"As `--checkpoint demo` answers by default (refine {test_time.refine}, polish {test_time.polish}; "
                  "step 3's tables): "
                  f"flow EPE {summary['eval_flow_epe']:.3f} px (ratio {summary['eval_flow_epe_vs_zero']:.2f}), "
                  f"disparity EPE {summary['eval_disp_epe']:.3f} px, D1 {summary['eval_d1_all']:.1f} %.")
    return summary


def build_parser():
    parser = cli.make_parser("bridge_jax.demo", __doc__)
    parser.add_argument("--workdir", default="work/demo", help="output folder (resumed if it exists)")
    parser.add_argument("--short", action="store_true", help="a 1-minute smoke run (the config demo:short)")
    cli.add_debug_flag(parser)
    return parser


@cli.entry_point
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    # XLA's "Very slow compile?" banner goes to the training workdir's xla.log, not into the progress bar
    console.install(os.path.join(os.path.abspath(args.workdir), "train", train.XLA_LOG),
                    enabled=not cli.debug_enabled(args))
    try:
        summary = run(args.workdir, config_arg="short" if args.short else None, enable_cache=True)
    except train.TrainingDiverged as e:
        return cli.report_error(e, code=train.EXIT_DIVERGED, debug=args.debug)
    except (ValueError, OSError) as e:  # ConfigError, EvaluationError, a taken output folder...: one line
        return cli.report_error(e, debug=args.debug)
    return train.EXIT_INTERRUPTED if summary.get("interrupted") else 0


if __name__ == "__main__":
    sys.exit(main())
