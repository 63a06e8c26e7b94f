"""Time per pair: the ONNX export under onnxruntime against the JAX predictor, side by side in one process.

    python experiments/onnx_timing.py [--models demo,long] [--repeats 5]

For each model, at its card's working size (long: its trained 256x512, the size bridge-export uses), with the
card's test-time stages (refine, symmetry, polish) and with none: converts the inference function to ONNX
(`bridge_jax.onnx_export`, the time taken is reported), opens it in onnxruntime (CPU), builds the JAX predictor
at the same settings (`inference.load_predictor`, compiled before timing), and times both on the same real photo
pairs (a held-out photo under a homography, Middlebury Motorcycle), alternating, `--repeats` calls each; the
median seconds per pair is reported, with the largest |ONNX - StableHLO artifact| difference of the maps
(working pixels), the share of pixels within 0.05 px of it (worst pair), and the largest |StableHLO artifact -
JAX predictor| difference (the predictor runs the polish as a program of its own, so XLA may round differently).
Prints one Markdown table row per setting; the results are kept in experiments/results/onnx.md.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--models", default="demo,long")
    ap.add_argument("--repeats", type=int, default=5)
    args = ap.parse_args()

    import onnxruntime as ort

    from bridge_jax import export, inference, onnx_export
    from bridge_jax.data import photos
    from bridge_jax.eval import real_checks

    pair = real_checks.homography_pair(photos.load_photo("astronaut"), photos.load_photo("coffee"),
                                       np.random.default_rng(0))
    moto = real_checks.motorcycle()
    images = [(pair["frame_t"], pair["frame_t1"]), (moto["left"], moto["right"])]
    print("| model | working size | refine / symmetry / polish | ONNX conversion s | onnxruntime s/pair | "
          "JAX predictor s/pair | max abs ONNX - StableHLO px | pixels within 0.05 px | max abs StableHLO - "
          "predictor px |")
    print("|---|---|---|---|---|---|---|---|---|")
    for name in args.models.split(","):
        card = inference.load_predictor(name, executable_cache=None)
        height, width = card.height, card.width
        for stages in ((card.refine, card.symmetry, card.polish), (0, "none", "none")):
            refine, symmetry, polish = stages
            pred = inference.load_predictor(name, size=(height, width), executable_cache=None,
                                            test_time={"refine": refine, "symmetry": symmetry, "polish": polish})
            start = time.perf_counter()
            model = onnx_export.export_onnx(pred)
            convert_s = time.perf_counter() - start
            options = ort.SessionOptions()
            options.log_severity_level = 3
            sess = ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
            exp = export.export_network(pred)
            inputs = [pred.prepare([a], [b])[0] for a, b in images]
            ort_s, jax_s, worst, within, hlo_vs_pred = [], [], 0.0, 1.0, 0.0
            for x in inputs:  # warm-up: compiles the predictor, lets onnxruntime allocate
                got, ref, mine = sess.run(None, {"pairs": x})[0], np.asarray(exp.call(x)[0]), pred.run_network(x)
                worst = max(worst, float(np.abs(got - ref).max()))
                within = min(within, float((np.abs(got - ref) <= 0.05).mean()))
                hlo_vs_pred = max(hlo_vs_pred, float(np.abs(ref - mine).max()))
            for _ in range(args.repeats):
                for x in inputs:
                    t = time.perf_counter()
                    sess.run(None, {"pairs": x})
                    ort_s.append(time.perf_counter() - t)
                    t = time.perf_counter()
                    pred.run_network(x)
                    jax_s.append(time.perf_counter() - t)
            row = {"model": name, "size": f"{height}x{width}", "stages": f"{refine} / {symmetry} / {polish}",
                   "convert_s": round(convert_s, 1), "onnxruntime_s": round(statistics.median(ort_s), 3),
                   "jax_s": round(statistics.median(jax_s), 3), "onnx_vs_stablehlo_px": round(worst, 5),
                   "within_0.05": round(100 * within, 3), "stablehlo_vs_predictor_px": round(hlo_vs_pred, 5)}
            print(f"| {name} | {row['size']} | {row['stages']} | {row['convert_s']} | {row['onnxruntime_s']} | "
                  f"{row['jax_s']} | {row['onnx_vs_stablehlo_px']} | {row['within_0.05']} % | "
                  f"{row['stablehlo_vs_predictor_px']} |", flush=True)
            print(json.dumps(row), flush=True)
    import jax
    print(f"onnxruntime {ort.__version__}, jax2onnx {onnx_export.converter_version()}, jax {jax.__version__}")


if __name__ == "__main__":
    main()
