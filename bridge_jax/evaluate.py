"""Evaluation on KITTI 2015 / 2012, the Eigen split, the built-in synthetic set or any KITTI-layout folder.

    bridge-evaluate --checkpoint CKPT --dataset kitti2015 --data-dir ~/data/data_scene_flow
    # the shipped demo model (or your own `make demo` run: --checkpoint work/demo/train) on the synthetic set
    bridge-evaluate --checkpoint demo --dataset synthetic --data-dir work/demo/val_data --out eval/
    # the baselines alone, on the first 20 frames
    bridge-evaluate --dataset kitti2015 --data-dir ~/data/data_scene_flow --max-frames 20

The model runs on each frame at the working size (default: the size a training workdir was trained at, else
256×512 = H×W like the paper), one compiled function per working size and batch, and its maps are brought to the
ground-truth resolution as the paper's scripts did (`bridge_jax.inference`):

* flow: the full-resolution pixel map is resized to the GT size with bilinear ``align_corners=True``, then
  ``u·W/w`` and ``v·H/h``;
* disparity: ``-channel 0`` as a fraction of the width, resized with OpenCV ``INTER_LINEAR`` and multiplied by
  the GT width; depth = f·B/d clamped to [1e-3, 80] m;
* the t+1 disparity is brought into frame t along the predicted flow (KITTI ``disp_1``) for D2 and SF.

Metrics (see `bridge_jax.metrics`) are reported as per-image means (paper) and pooled over pixels (KITTI
devkit), next to two baselines run on the same frames at full resolution: zero motion and OpenCV (StereoSGBM for
disparity, DIS for optical flow). Results are printed and written as JSON + Markdown (+ a few picture panels):

    OUT/
      results.json             every metric, per method and task, with timing
      results.md               the same as Markdown tables
      pictures/<frame id>.png  input | flow | flow GT | flow error, then disparity | GT | error; the colour bar at
                               the right reads the error maps' colours in px (log scale, 0 to 12 px and above)
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from collections.abc import Callable, Sequence
from typing import Any, Optional

import numpy as np
from tqdm import tqdm

from bridge_jax import cli, compile_cache, console, files, inference, testtime
from bridge_jax.eval.baselines import opencv_method, zero_method
from bridge_jax.eval.datasets import DATASETS, EvaluationError, Frame, list_frames, load_frame
from bridge_jax.eval.methods import ModelMethod
from bridge_jax.eval.report import markdown_table, write_outputs
from bridge_jax.eval.scoring import score_methods


def evaluate(predictor, dataset: str, data_dir: str, *, split: Optional[str] = None, baselines: bool = True,
             garg_crop: bool = True, batch: int = 1, max_frames: Optional[int] = None,
             out_dir: Optional[str] = None, num_pictures: int = 4, overwrite: bool = False,
             progress: bool = True, extra_info: Optional[dict] = None) -> dict:
    """Evaluate a predictor (and the baselines) on a dataset.

    Args:
      predictor: a `bridge_jax.inference.Predictor` (or None to run the baselines only).
      dataset: one of `DATASETS`; data_dir / split: see `bridge_jax.eval.datasets.list_frames`.
      baselines: also run zero motion and OpenCV SGBM / DIS on the same frames.
      garg_crop: Eigen only: apply the Garg crop (the papers' protocol).
      batch: frames per inference call (a fixed shape: the pairs of `batch` frames).
      max_frames: evaluate only the first frames (smoke runs).
      out_dir: if given, write ``results.json``, ``results.md`` and ``pictures/*.png`` there (refused if it
        exists and is not empty, unless ``overwrite``; written to a temporary folder, then renamed).
    Returns:
      ``{"dataset", "data_dir", "split", "num_frames", "methods": {method: {task: {"per_image_mean": {...},
      "pooled": {...}, "num_images": {...}}}}, "timing": {...}, "markdown": str}``.
    """
    if dataset not in DATASETS:
        raise EvaluationError(f"unknown dataset {dataset!r}; expected one of {', '.join(DATASETS)}")
    if out_dir is not None:
        files.check_output_dir(out_dir, overwrite)
    specs = list_frames(dataset, data_dir, split)
    if max_frames is not None:
        specs = specs[:max_frames]
    methods: dict[str, Callable] = {}
    model = None
    if predictor is not None:
        model = methods["model"] = ModelMethod(predictor, batch)
    if baselines:
        methods["zero"] = zero_method
        methods["opencv"] = opencv_method
    if not methods:
        raise EvaluationError("nothing to evaluate: no predictor and --no-baselines")
    step = max(1, int(batch))
    batches = ([load_frame(s, dataset, garg_crop=garg_crop) for s in specs[i:i + step]]
               for i in range(0, len(specs), step))
    t_start = time.perf_counter()
    with tqdm(total=len(specs), desc=f"evaluate {dataset}", unit="frame", file=sys.stderr,
              disable=not progress) as bar:
        scored = score_methods(batches, methods, num_pictures=num_pictures if out_dir is not None else 0,
                               picture_method="model" if model is not None else "opencv", bar=bar)
    total_s = time.perf_counter() - t_start
    results: dict[str, Any] = {
        "dataset": dataset, "data_dir": os.path.abspath(data_dir), "split": split, "num_frames": len(specs),
        "garg_crop": garg_crop if dataset == "eigen" else None,
        "methods": scored.scores.summary(),
        "units": "EPE in GT pixels; Fl/D1/D2/SF in %; depth errors in m; a1..a3 fractions",
    }
    method_s = scored.method_s
    timing = {"total_s": total_s, "load_s": scored.load_s, "frames_per_s": len(specs) / total_s if total_s else None}
    for m, s in method_s.items():
        timing[f"{m}_s"] = s
    if model is not None:
        timing["model_inference_s"] = model.inference_s
        timing["model_frames_per_s"] = len(specs) / method_s["model"] if method_s["model"] else None
        timing["model_inference_share"] = model.inference_s / method_s["model"] if method_s["model"] else None
    results["timing"] = timing
    if extra_info:
        results.update(extra_info)
    results["markdown"] = markdown_table(results)
    if out_dir is not None:
        write_outputs(out_dir, results, scored.pictures, overwrite)
    return results


# --------------------------------------------------------------------------------------------------------------
# Command line


DATASET_HELP = ("kitti2015 / kitti2012: the KITTI stereo+flow benchmarks (training split has GT); eigen: the "
                "Eigen depth split of KITTI raw; synthetic: the built-in synthetic set (bridge_jax.data.synthetic); "
                "folder: any KITTI 2015 layout folder, GT optional")


def build_parser() -> argparse.ArgumentParser:
    p = cli.make_parser("bridge_jax.evaluate", __doc__)
    p.add_argument("--checkpoint",
                   help="the model: a params dir, a training workdir, a step dir, or a shipped model name such as "
                        "demo (omit: baselines only)")
    p.add_argument("--dataset", required=True, choices=DATASETS, help=DATASET_HELP)
    p.add_argument("--data-dir", required=True, help="dataset root (KITTI layout folder, or KITTI raw for eigen)")
    p.add_argument("--split", default=None,
                   help="KITTI: sub-folder (default: training); eigen: a list file (default: the bundled 697 frames)")
    p.add_argument("--out", default=None, help="write results.json / results.md / pictures/ here")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out folder")
    p.add_argument("--working-size", type=cli.parse_working_size, default=None, metavar="HxW|native|trained",
                   help=cli.WORKING_SIZE_HELP + "; default: what a shipped model's card recommends "
                        f"(long: native), else {inference.DEFAULT_WORKING_SIZE}")
    cli.add_test_time_options(p)
    p.add_argument("--batch", type=int, default=1, help="frames per inference call (one compiled shape)")
    p.add_argument("--max-frames", type=int, default=None,
                   help="evaluate only the first N frames (a quick check; default: all)")
    p.add_argument("--pictures", type=int, default=4,
                   help="number of picture panels (input | prediction | GT | error, with the error colour bar) "
                        "written to --out/pictures/")
    # flags are store_true (never store_false): the help would otherwise show a misleading "(default: True)"
    p.add_argument("--no-garg-crop", action="store_true", help="eigen: evaluate without the Garg crop")
    p.add_argument("--no-baselines", action="store_true",
                   help="skip the baselines (zero motion, OpenCV SGBM / DIS), which run by default")
    p.add_argument("--baselines", dest="no_baselines", action="store_false", default=False,
                   help="run the baselines (the default; undoes an earlier --no-baselines)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    compile_cache.add_option(p)
    cli.add_debug_flag(p)
    return p


@cli.entry_point
def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    console.install(enabled=not cli.debug_enabled(args))  # XLA's slow-compile banner stays out of the console
    try:
        compile_cache.enable(args.compilation_cache)
        if args.batch < 1:
            raise EvaluationError(f"--batch must be >= 1, got {args.batch}")
        if args.max_frames is not None and args.max_frames < 1:
            raise EvaluationError(f"--max-frames must be >= 1, got {args.max_frames}")
        if args.out is not None:
            files.check_output_dir(args.out, args.overwrite)
        test_time = cli.given_test_time(args)
        predictor = (inference.load_predictor(args.checkpoint, size=args.working_size, size_option="--working-size",
                                              test_time=test_time, options=testtime.OPTIONS,
                                              executable_cache=compile_cache.active_dir())
                     if args.checkpoint else None)
        asked = [f for f, v in test_time.items() if v not in (None, 0, "none")]
        if predictor is None and asked:
            raise EvaluationError(f"{testtime.OPTIONS[asked[0]]} needs --checkpoint (the baselines have no network "
                                  "maps to run test-time stages on)")
        results = evaluate(predictor, args.dataset, args.data_dir, split=args.split, baselines=not args.no_baselines,
                           garg_crop=not args.no_garg_crop, batch=args.batch, max_frames=args.max_frames,
                           out_dir=args.out, num_pictures=args.pictures, overwrite=args.overwrite,
                           progress=not args.no_progress,
                           extra_info={"checkpoint": args.checkpoint,
                                       **(predictor.test_time.to_dict() if predictor else dict.fromkeys(test_time))})
    except (ValueError, OSError) as e:  # EvaluationError, CorruptImageError...: one line naming the path
        return cli.report_error(e, debug=args.debug)
    print(results["markdown"])
    if args.out:
        print(f"wrote {os.path.join(args.out, 'results.json')} and results.md")
    return 0


if __name__ == "__main__":
    sys.exit(main())
