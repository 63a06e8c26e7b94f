"""ONNX export of the inference function: `bridge-export --format onnx` (optional extra: `pip install
'bridge-jax[onnx]'`).

The model is the function the StableHLO export writes (`stages.inference_function`): `pairs (B, H, W, 6)`
float32 in [0, 1] -> `px0`, `frac0`, each `(B, H, W, 2)` float32, the predictor's refinement passes, symmetry
averaging and polish included, the weights baked in as initializers. It is converted by jax2onnx, a maintained
JAX -> ONNX converter (no graph is written by hand here), and runs under onnxruntime, OpenCV's dnn module or
TensorRT without JAX:

    import onnxruntime as ort
    sess = ort.InferenceSession("model.onnx")
    px, frac = sess.run(None, {"pairs": pairs})

How: the function is first traced to a jaxpr (`jax.make_jaxpr`), and jax2onnx converts that jaxpr's primitives.
Converting the Python function directly would route `lax.fori_loop` through jax2onnx's own fori_loop shim, which
cannot take a loop body that reads values computed before the loop (the refinement's and the polish's loops
all do); traced first, the loops reach the converter as `scan`, which it converts to an ONNX `Loop` with those
values as loop inputs.
"""
from __future__ import annotations

import importlib.metadata
import logging
import os
import re
from pathlib import Path

import jax
import jax.numpy as jnp

from bridge_jax import files, inference, stages

OPSET = 17
"""ONNX opset of the exported model: 17 is read by onnxruntime >= 1.13, TensorRT 8.6 and OpenCV's dnn module."""
INPUT_NAME = "pairs"
OUTPUT_NAMES = ("px0", "frac0")
CONVERTER = "jax2onnx>=0.17.1,<0.18"
"""The converter release this export is checked with. jax2onnx declares orbax-checkpoint<0.11.37, which this
package's checkpoints cannot use (>=0.12), though it never imports orbax: so it is installed without its
declared dependencies, after the `onnx` extra has installed those it imports (`INSTALL_HINT`)."""
INSTALL_HINT = f"pip install 'bridge-jax[onnx]' && pip install --no-deps '{CONVERTER}'"
MIN_CONVERTER = (0, 17, 1)


class MissingExtra(ImportError):
    """The ONNX converter (jax2onnx, onnx) is not installed."""


class UnsupportedStage(ValueError):
    """A stage of the inference function has a JAX primitive the converter cannot express in ONNX."""


def require_converter():
    """`(jax2onnx, onnx)` modules, or MissingExtra with one line telling how to install them."""
    try:
        import jax2onnx
        import onnx
    except ImportError as e:
        raise MissingExtra(f"--format onnx needs the ONNX converter ({e.name or e} is not installed): "
                           f"{INSTALL_HINT}") from None
    version = converter_version()
    numbers = tuple(int(v) for v in re.findall(r"\d+", version)[:3])
    if numbers and numbers < MIN_CONVERTER:
        raise MissingExtra(f"--format onnx needs jax2onnx >= {'.'.join(map(str, MIN_CONVERTER))}, found {version}: "
                           f"pip install --no-deps '{CONVERTER}'")
    return jax2onnx, onnx


def converter_version() -> str:
    try:
        return importlib.metadata.version("jax2onnx")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


def _primitives(closed_jaxpr) -> set[str]:
    """Names of every primitive in a closed jaxpr, its sub-jaxprs (loops, jit calls) included."""
    from jax.extend import core as jex

    names: set[str] = set()
    todo = [closed_jaxpr.jaxpr]
    while todo:
        jaxpr = todo.pop()
        for eqn in jaxpr.eqns:
            names.add(eqn.primitive.name)
            todo.extend(sub.jaxpr if hasattr(sub, "jaxpr") else sub for sub in jex.jaxprs_in_params(eqn.params))
    return names


def _stage_functions(predictor: inference.Predictor, batch: int, task: str) -> list[tuple[str, object, tuple]]:
    """(stage as the user asks for it, function, example arguments) of each stage the exported function runs,
    to tell which one holds a primitive the converter cannot express."""
    from bridge_jax import polish, stages as test_time_stages

    params = jax.tree.map(jnp.asarray, predictor.params)
    tasks = predictor.net.static_tasks((task,) * batch)
    flow_rows = jnp.asarray(test_time_stages.flow_rows([task] * batch))
    pairs = jax.ShapeDtypeStruct((batch, predictor.height, predictor.width, 6), jnp.float32)
    maps = jax.ShapeDtypeStruct((batch, predictor.height, predictor.width, 2), jnp.float32)
    net = lambda x: predictor.net(params, x, tasks * (x.shape[0] // batch))["px"][0]
    test_time = predictor.test_time
    stages = [("the network", lambda x: predictor.net(params, x, tasks), (pairs,))]
    if test_time.symmetry != "none":
        stages.append((f"--symmetry {test_time.symmetry}",
                       lambda x: test_time_stages.symmetric_maps(net, x, test_time.symmetry, flow_rows), (pairs,)))
    if test_time.refine:
        stages.append((f"--refine {test_time.refine}",
                       lambda x, m: test_time_stages.refine_maps(net, x, m, flow_rows, test_time.refine),
                       (pairs, maps)))
    if test_time.polish != "none":
        stages.append((f"--polish {test_time.polish}",
                       lambda x, m: polish.polish_maps(x, m, flow_rows, predictor.polish_config), (pairs, maps)))
    return stages


def _unsupported_stage(predictor, batch, task, primitive: str) -> str | None:
    """The first stage (`_stage_functions`) whose jaxpr has `primitive`, or None."""
    for stage, fn, args in _stage_functions(predictor, batch, task):
        if primitive in _primitives(jax.make_jaxpr(fn)(*args)):
            return stage
    return None


def convert(fn, specs, *, name: str = "bridge_jax", input_names=None, output_names=None, opset: int = OPSET):
    """`fn(*arrays)` at `specs` (`jax.ShapeDtypeStruct`s) as an `onnx.ModelProto`: traced to a jaxpr, whose
    primitives jax2onnx converts (see the module docstring). NotImplementedError from the converter for a
    primitive it has no ONNX form of."""
    jax2onnx, _ = require_converter()
    from jax.extend.core import jaxpr_as_fun

    closed = jax.make_jaxpr(fn)(*specs)
    quiet = logging.getLogger("onnx_ir")  # "value type ... is not known ... Skipping serialization" of shape notes
    level = quiet.level
    quiet.setLevel(logging.ERROR)
    try:
        return jax2onnx.to_onnx(jaxpr_as_fun(closed), list(specs), model_name=name, opset=opset,
                                input_names=input_names, output_names=output_names)
    finally:
        quiet.setLevel(level)


def export_onnx(predictor: inference.Predictor, *, batch: int = 1, task: str = "flow", opset: int = OPSET):
    """The ONNX model (`onnx.ModelProto`) of `stages.inference_function(predictor, batch, task)`: input
    `pairs (batch, H, W, 6)`, outputs `px0`, `frac0` `(batch, H, W, 2)`.

    Raises MissingExtra without the converter, ValueError for a bad batch or task or a bfloat16 predictor, and
    UnsupportedStage (one line naming the stage's option) when a stage cannot be expressed in ONNX."""
    require_converter()
    if predictor.dtype is not None and jnp.dtype(predictor.dtype) != jnp.float32:
        raise ValueError(f"--dtype {jnp.dtype(predictor.dtype).name}: the ONNX export computes in float32 "
                         "(--dtype float32)")
    infer = stages.inference_function(predictor, batch, task)
    spec = jax.ShapeDtypeStruct((batch, predictor.height, predictor.width, 6), jnp.float32)
    try:
        model = convert(infer, [spec], name=predictor.model_name, input_names=[INPUT_NAME],
                        output_names=list(OUTPUT_NAMES), opset=opset)
    except NotImplementedError as e:
        found = re.search(r"primitive '([^']+)'", str(e))
        primitive = found.group(1) if found else None
        stage = _unsupported_stage(predictor, batch, task, primitive) if primitive else None
        what = f"primitive {primitive!r}" if primitive else str(e).strip().splitlines()[0]
        raise UnsupportedStage(f"--format onnx: {stage or 'the model'} uses {what}, which jax2onnx "
                               f"{converter_version()} cannot express in ONNX (--format stablehlo can)") from e
    except Exception as e:  # a converter failure of another kind: still one line (the traceback with --debug)
        first = str(e).strip().splitlines()[0] if str(e).strip() else ""
        raise UnsupportedStage(f"--format onnx: jax2onnx {converter_version()} failed to convert the model "
                               f"({type(e).__name__}: {first})") from e
    meta = {"bridge_jax.model": predictor.model_name, "bridge_jax.height": predictor.height,
            "bridge_jax.width": predictor.width, "bridge_jax.refine": predictor.refine,
            "bridge_jax.symmetry": predictor.symmetry, "bridge_jax.polish": predictor.polish,
            "bridge_jax.task": task, "bridge_jax.outputs": "px0: map in working pixels; frac0: px0 / (W, H)",
            "bridge_jax.converter": f"jax2onnx {converter_version()}"}
    for key, value in meta.items():
        entry = model.metadata_props.add()
        entry.key, entry.value = key, str(value)
    model.producer_name = "bridge_jax"
    check_loads(model)
    return model


def check_loads(model) -> None:
    """onnxruntime (when installed) builds a session of `model`: a graph the converter got wrong is refused here,
    before anything is written, instead of where the model is deployed. UnsupportedStage otherwise."""
    try:
        import onnxruntime as ort
    except ImportError:
        return
    options = ort.SessionOptions()
    options.log_severity_level = 3  # the converter's loose shape notes are warnings only
    try:
        ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])
    except Exception as e:  # onnxruntime's own exception types
        first = str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__
        raise UnsupportedStage(f"--format onnx: onnxruntime cannot load the converted model ({first})") from e


def save_model(model, out: str | os.PathLike) -> Path:
    """Write an ONNX model to `out` atomically (temp file + rename), weights inside the one file."""
    return Path(files.write_bytes(out, model.SerializeToString()))


__all__ = ["export_onnx", "convert", "check_loads", "save_model", "require_converter", "MissingExtra", "UnsupportedStage", "OPSET",
           "INPUT_NAME", "OUTPUT_NAMES", "INSTALL_HINT"]
