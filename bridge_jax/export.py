"""Export the inference network to a serialized StableHLO artifact (`jax.export`), weights baked in.

    python -m bridge_jax.export --checkpoint CKPT --out model.stablehlo [--height 256 --width 512 --batch 1
                                [--dtype float32|bfloat16]]

The exported function maps `pairs (B, H, W, 6)` float32 in [0, 1] (image_a RGB, image_b RGB at the working
size) to a tuple `(px0, frac0)`, each `(B, H, W, 2)` float32: the full-resolution map in pixels and as
fractions of (W, H). Load and run it without bridge_jax's model code:

    from jax import export
    exp = export.deserialize(open("model.stablehlo", "rb").read())
    px, frac = exp.call(pairs)

Input resizing and mapping back to the original resolution are not part of the artifact (see
`bridge_jax.inference.resize_images` / `maps_to_input_resolution`).
"""
from __future__ import annotations

import argparse
import json
import os
import sys
import uuid
from pathlib import Path
from typing import Any

import jax
import jax.numpy as jnp

from bridge_jax import models


def export_network(graphdef, params, *, height: int, width: int, batch: int = 1, dtype: Any = None,
                   model_cfg: dict | None = None) -> jax.export.Exported:
    """`jax.export` of `pairs (batch, height, width, 6) -> (px0, frac0)` with params as constants."""
    from bridge_jax.inference import _parse_dtype

    name = (model_cfg or {}).get("name", "resnet_md")
    multiple = models.INPUT_MULTIPLE.get(name, 64)
    if height <= 0 or width <= 0 or height % multiple or width % multiple:
        raise ValueError(f"--height/--width must be positive multiples of {multiple}, got {height}x{width}")
    if batch < 1:
        raise ValueError(f"--batch must be >= 1, got {batch}")
    compute = _parse_dtype(dtype)
    params = jax.tree.map(jnp.asarray, params)

    def infer(pairs):
        maps = models.apply(graphdef, params, pairs, dtype=compute)
        return maps["px"][0], maps["frac"][0]

    spec = jax.ShapeDtypeStruct((batch, height, width, 6), jnp.float32)
    return jax.export.export(jax.jit(infer))(spec)


def serialize_to_file(exp: jax.export.Exported, out: str | os.PathLike) -> Path:
    """Write `exp.serialize()` to `out` atomically (temp file + rename)."""
    out = Path(out).absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.parent / f".{out.name}.tmp-{uuid.uuid4().hex[:8]}"
    try:
        tmp.write_bytes(exp.serialize())
        os.replace(tmp, out)
    finally:
        if tmp.exists():
            tmp.unlink()
    return out


def load_exported(path: str | os.PathLike) -> jax.export.Exported:
    """Deserialize an artifact written by this module."""
    return jax.export.deserialize(bytearray(Path(path).read_bytes()))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m bridge_jax.export", description=__doc__.split("\n\n")[0])
    ap.add_argument("--checkpoint", required=True, help="params dir, training workdir or step dir")
    ap.add_argument("--out", required=True, help="output file (serialized StableHLO)")
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--width", type=int, default=512)
    ap.add_argument("--batch", type=int, default=1)
    ap.add_argument("--dtype", choices=["float32", "bfloat16"], default="float32", help="compute dtype")
    ap.add_argument("--task", choices=["stereo", "flow"], default="flow",
                    help="which network of a separate-networks checkpoint to export")
    args = ap.parse_args(argv)
    from bridge_jax import checkpointing

    try:
        cfg, params = checkpointing.load_params(args.checkpoint)
        if cfg.pop("separate_networks", False):
            params = params[args.task]
        graphdef, _ = models.abstract_init(cfg)
        exp = export_network(graphdef, params, height=args.height, width=args.width, batch=args.batch,
                             dtype=args.dtype, model_cfg=cfg)
        out = serialize_to_file(exp, args.out)
    except ImportError as e:  # jax.export serialization needs the `flatbuffers` package
        print(f"error: {e} (pip install flatbuffers)", file=sys.stderr)
        return 2
    except (ValueError, OSError) as e:
        print(f"error: {str(e).splitlines()[0] if str(e) else type(e).__name__}", file=sys.stderr)
        return 2
    print(json.dumps({"out": str(out), "bytes": out.stat().st_size, "model": cfg["name"],
                      "input": [args.batch, args.height, args.width, 6], "output": "(px0, frac0) each "
                      f"[{args.batch}, {args.height}, {args.width}, 2]", "dtype": args.dtype}))
    return 0


if __name__ == "__main__":
    sys.exit(main())
