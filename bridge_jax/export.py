"""Export the inference network to a serialized StableHLO artifact (`jax.export`), weights baked in.

    bridge-export --checkpoint demo --out demo.stablehlo
    bridge-export --checkpoint demo --format onnx --out demo.onnx     # pip install 'bridge-jax[onnx]' first
    bridge-export --checkpoint CKPT --out model.stablehlo [--height 256 --width 512] [--batch 1]
                                [--dtype float32|bfloat16] [--task flow|stereo]

The exported function is the predictor's network (`bridge_jax.inference.Predictor`) at its working size: it maps
`pairs (B, H, W, 6)` float32 in [0, 1] (image_a RGB, image_b RGB at the working size) to a tuple `(px0, frac0)`,
each `(B, H, W, 2)` float32: the full-resolution map in pixels and as fractions of (W, H), after the
predictor's test-time refinement passes, symmetry averaging and polish (`--refine`, `--symmetry`, `--polish`;
default: what a shipped model's card recommends, as for predict; `stages.predicted_maps`, fused into one
program). The working size
`H x W` defaults to the size the checkpoint was trained at, else 256 x 512 (as for predict and evaluate); B is
`--batch`. Load and run it without bridge_jax's model code:

    from jax import export
    exp = export.deserialize(open("model.stablehlo", "rb").read())
    px, frac = exp.call(pairs)

`--format onnx` writes the same function as an ONNX model (`bridge_jax.onnx_export`: input "pairs", outputs "px0",
"frac0"), for onnxruntime, TensorRT or OpenCV's dnn module, which need no JAX (experiments/onnx_predict.py).

Input resizing and mapping back to the original resolution are not part of the artifact (see
`bridge_jax.inference.resize_images` / `flow_to_input_resolution` / `disparity_to_input_resolution`). So the
artifact polishes its maps at its own input size, the working size, where `Predictor` polishes them at the
images' own size after bringing them up (`polish.PolishConfig.resolution`): on inputs of another size its
polished maps are those of `PolishConfig(resolution="working")`, and equal to the predictor's for inputs of the
working size.
"""
from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

import jax
import jax.numpy as jnp

from bridge_jax import cli, compile_cache, files, inference, stages, testtime


inference_function = stages.inference_function  # the function both formats write (one composition, stages.py)


def export_network(predictor: inference.Predictor, *, batch: int = 1, task: str = "flow") -> jax.export.Exported:
    """`jax.export` of `pairs (batch, H, W, 6) -> (px0, frac0)` (`inference_function`) at the predictor's working
    size."""
    infer = inference_function(predictor, batch, task)
    spec = jax.ShapeDtypeStruct((batch, predictor.height, predictor.width, 6), jnp.float32)
    return jax.export.export(jax.jit(infer))(spec)


def serialize_to_file(exp: jax.export.Exported, out: str | os.PathLike) -> Path:
    """Write `exp.serialize()` to `out` atomically (temp file + rename)."""
    return Path(files.write_bytes(out, exp.serialize()))


def load_exported(path: str | os.PathLike) -> jax.export.Exported:
    """Deserialize an artifact written by this module."""
    return jax.export.deserialize(bytearray(Path(path).read_bytes()))


def build_parser() -> argparse.ArgumentParser:
    ap = cli.make_parser("bridge_jax.export", __doc__)
    ap.add_argument("--checkpoint", required=True,
                    help="the model: a params dir, a training workdir, a step dir, or a shipped model name such as "
                         "demo")
    ap.add_argument("--out", required=True, help="output file (serialized StableHLO, or the ONNX model), written "
                                                 "atomically")
    ap.add_argument("--format", choices=["stablehlo", "onnx"], default="stablehlo",
                    help="stablehlo: jax.export's artifact, run by JAX; onnx: an ONNX model (opset "
                         "17), run by onnxruntime and others without JAX (needs pip install 'bridge-jax[onnx]')")
    ap.add_argument("--height", type=int, default=None,
                    help="working height, a multiple of the model's input multiple (64 for resnet_md and pwcnet, "
                         "8 for pwc_lite); default: the height the checkpoint was trained at, else 256")
    ap.add_argument("--width", type=int, default=None,
                    help="working width, the same multiple; default: the width the checkpoint was trained at, "
                         "else 512")
    ap.add_argument("--batch", type=int, default=1,
                    help="number of pairs B the exported function takes per call (its input is fixed at "
                         "(B, H, W, 6))")
    ap.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32",
                    help="compute dtype baked into the artifact (weights stay float32)")
    ap.add_argument("--task", choices=list(inference.TASKS), default="flow",
                    help="which network of a separate-networks checkpoint to export (flow: consecutive frames, "
                         "stereo: left/right pairs); a shared network is the same for both")
    cli.add_test_time_options(ap)
    compile_cache.add_option(ap)
    cli.add_debug_flag(ap)
    return ap


def _working_size(args) -> tuple[int, int] | None:
    """(H, W) of --height/--width, a side not given being the trained size's; None when neither is given (the
    size the card recommends, else the trained size)."""
    if args.height is None and args.width is None:
        return None
    trained = inference.resolve_working_size(args.checkpoint, inference.TRAINED)
    return (trained.height if args.height is None else args.height, trained.width if args.width is None else args.width)


def without_fill(test_time: testtime.TestTime, given: str | None) -> testtime.TestTime:
    """The test-time record an artifact can hold: the polish's fill step runs on the host after the network (it
    predicts each pair's reverse pair too, `Predictor.fill_maps`), so it cannot be part of one program.
    When the fill came from a card's recommendation it is dropped with a notice on stderr; when the user asked
    for it (`given`, their --polish), a ValueError naming --polish."""
    rest = test_time.photometric_part
    if given is not None:
        raise ValueError(f"--polish {given}: the fill step runs on the host after the network (it predicts the reverse "
                         f"pair too) and cannot be exported; use --polish {rest.polish} and fill the artifact's "
                         f"disparities with bridge_jax.confidence.left_right_fill, its flows with "
                         f"bridge_jax.confidence.forward_backward_fill")
    print(f"bridge-export: the card's polish {test_time.polish} runs its fill step on the host; the artifact "
          f"holds --polish {rest.polish}", file=sys.stderr)
    return rest


@cli.entry_point
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        compile_cache.enable(args.compilation_cache)
        if args.batch < 1:   # checked before the (slow) checkpoint load
            raise ValueError(f"--batch must be >= 1, got {args.batch}")
        if args.format == "onnx":
            from bridge_jax import onnx_export
            onnx_export.require_converter()  # the missing extra is told before the checkpoint load too
        predictor = inference.load_predictor(args.checkpoint, size=_working_size(args), dtype=args.dtype,
                                             size_option="--height/--width",
                                             test_time=cli.given_test_time(args), options=testtime.OPTIONS)
        if predictor.test_time.fill:
            predictor.test_time = without_fill(predictor.test_time, args.polish)
        if args.format == "onnx":
            out = onnx_export.save_model(onnx_export.export_onnx(predictor, batch=args.batch, task=args.task),
                                         args.out)
        else:
            out = serialize_to_file(export_network(predictor, batch=args.batch, task=args.task), args.out)
    except ImportError as e:  # jax.export serialization needs the `flatbuffers` package
        if args.format == "onnx" and isinstance(e, onnx_export.MissingExtra):
            return cli.report_error(e, debug=args.debug)
        return cli.report_error(ImportError(f"{e} (pip install flatbuffers)"), debug=args.debug)
    except (ValueError, OSError) as e:
        return cli.report_error(e, debug=args.debug)
    shape = [args.batch, predictor.height, predictor.width]
    print(json.dumps({"out": str(out), "format": args.format, "bytes": out.stat().st_size,
                      "model": predictor.model_cfg["name"],
                      "input": shape + [6], "output": f"(px0, frac0) each {shape + [2]}", "dtype": args.dtype,
                      **predictor.test_time.to_dict()}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
