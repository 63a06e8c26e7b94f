"""Model registry: pick a network by config name, with a functional boundary around the NNX modules.

    graphdef, params = models.init(jax.random.key(0), models.model_config("resnet_md"))
    maps = models.apply(graphdef, params, pair)          # pair (N, H, W, 6) float32 in [0, 1]
    maps["px"][0]    # (N, H, W, 2) pixels at full resolution (ch0 = x, ch1 = y)
    maps["frac"][3]  # (N, H/8, W/8, 2) fractions of that scale's width / height

`params` is a plain nested dict of float32 arrays (string keys), so optax, orbax and jax.tree work on it
directly; `graphdef` is the static NNX graph (hashable, cheap). Names:

- `resnet_md`: the paper's Monodepth ResNet-50 encoder-decoder (58,461,416 params).
- `resnet_md_tiny`: the same code with tiny widths/depths (tests, smoke runs).
- `pwcnet`: the PWC-Net variant of the paper's supplement (9,374,340 params with upstream's defaults).
- `pwc_lite`: a small correlation network (normalised-feature cost volume, coarse to fine, one shared
  estimator; beyond the paper), the demo's model: see `bridge_jax.models.pwc_lite`.

Every model takes `coords=True` (normalised x, y channels appended to its input; see
`models.coordinates`); the default, False, is the paper's network.
"""
from __future__ import annotations

import json
import math
from collections.abc import Mapping
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from bridge_jax.models import layers, pwc_lite, pwcnet, resnet_md
from bridge_jax.models.layers import init_params_like

_BUILDERS = {
    "resnet_md": (resnet_md.normalize_config, resnet_md.build),
    "resnet_md_tiny": (resnet_md.normalize_config, resnet_md.build),
    "pwcnet": (pwcnet.normalize_config, pwcnet.build),
    "pwc_lite": (pwc_lite.normalize_config, pwc_lite.build),
}
NAMES = tuple(_BUILDERS)

_HEAD_PREFIXES = {"resnet_md": resnet_md.HEAD_PREFIXES, "resnet_md_tiny": resnet_md.HEAD_PREFIXES,
                  "pwcnet": pwcnet.HEAD_PREFIXES, "pwc_lite": pwc_lite.HEAD_PREFIXES}

INPUT_MULTIPLE = {"resnet_md": resnet_md.MULTIPLE, "resnet_md_tiny": resnet_md.MULTIPLE, "pwcnet": pwcnet.MULTIPLE,
                  "pwc_lite": pwc_lite.MULTIPLE}
"""Working height and width must be multiples of this, per model name."""

NATIVE_MULTIPLE = {"resnet_md": resnet_md.MULTIPLE, "resnet_md_tiny": resnet_md.MULTIPLE, "pwcnet": pwcnet.MULTIPLE,
                   "pwc_lite": 2 ** len(pwc_lite.DEFAULT_CONFIG["pyramid"])}
"""The multiple the native working-size rule rounds to (`inference.native_working_size`): pwc_lite runs at any
multiple of 8, but at multiples of 64 its pyramid keeps all 6 levels (a search range of 4 x 64 pixels)."""


def suggest_working_size(name: str, height: int, width: int) -> tuple[int, int] | None:
    """The valid working size of model `name` closest to ``height x width`` (sum of the differences): the
    nearest multiples of its input multiple (halves round up), grown where the model needs more (pwc_lite's
    pyramid); None when no size within 16 multiples fits."""
    multiple = INPUT_MULTIPLE[name]

    def nearest(v):
        return max(multiple, (max(int(v), 0) + multiple // 2) // multiple * multiple)

    def fits(h, w):
        try:
            _check_size(name, h, w, "")
            return True
        except ValueError:
            return False

    steps = [k * multiple for k in range(16)]
    found = [(abs(h - height) + abs(w - width), h, w) for h in (nearest(height) + d for d in steps)
             for w in (nearest(width) + d for d in steps) if fits(h, w)]
    return min(found)[1:] if found else None


def _check_size(name: str, height: Any, width: Any, what: str) -> None:
    multiple = INPUT_MULTIPLE[name]
    ints = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (height, width))
    if not ints or height <= 0 or width <= 0 or height % multiple or width % multiple:
        raise ValueError(f"{what} {height}x{width}: height and width must be multiples of {multiple} for model "
                         f"{name}")
    if name == "pwc_lite":
        try:
            pwc_lite.pyramid_levels(int(height), int(width), pwc_lite.MIN_LEVELS)
        except ValueError as e:
            raise ValueError(f"{what} {height}x{width}: {e}") from None


def check_working_size(name: str, height: Any, width: Any, what: str = "working size") -> None:
    """Raises ValueError unless height and width are positive integer multiples of `INPUT_MULTIPLE[name]`
    (and, for pwc_lite, large enough for its 3-level minimum pyramid); the message names `what` (the option,
    e.g. "config.height/config.width", "--working-size"), the size given and the nearest size that fits:
    "--working-size 100x200: height and width must be multiples of 64 for model resnet_md (try 128x192)".
    """
    try:
        _check_size(name, height, width, what)
    except ValueError as e:
        ints = all(isinstance(v, (int, np.integer)) and not isinstance(v, bool) for v in (height, width))
        near = suggest_working_size(name, int(height), int(width)) if ints else None
        raise ValueError(str(e) + (f" (try {near[0]}x{near[1]})" if near else "")) from None


def _as_dict(config: Any) -> dict:
    if isinstance(config, str):
        return {"name": config}
    if hasattr(config, "to_dict"):  # ml_collections.ConfigDict
        config = config.to_dict()
    if not isinstance(config, Mapping):
        raise ValueError(f"model config must be a name or a mapping with 'name', got {type(config).__name__}")
    return dict(config)


def model_config(name: str | Mapping, **overrides) -> dict:
    """The full, JSON-serialisable description of a model (enough to rebuild it).

    Args:
      name: one of `NAMES`, or a (partial) config mapping with a "name" key.
      overrides: model-specific keys, e.g. `blocks=[1, 1, 1, 1]`, `dtype="bfloat16"` (default compute dtype).
    Raises:
      ValueError: unknown name or unknown keys.
    """
    cfg = _as_dict(name)
    cfg.update(overrides)
    model_name = cfg.get("name")
    if model_name not in _BUILDERS:
        raise ValueError(f"unknown model name {model_name!r}; expected one of {list(NAMES)}")
    return _BUILDERS[model_name][0](cfg)


def _module(config: Any, rngs: nnx.Rngs) -> nnx.Module:
    cfg = model_config(config)
    return _BUILDERS[cfg["name"]][1](cfg, rngs)


def _abstract_module(cfg: dict) -> nnx.Module:
    """The model with `jax.ShapeDtypeStruct` params (no initializer traced: `layers.shapes_only`). No `nnx.Rngs`
    either: the layers draw no key under `shapes_only`, and creating one is the process's first eager jax op
    (~0.1 s)."""
    with layers.shapes_only():
        return _module(cfg, None)


def init(rng: jax.Array | int, config: Any) -> tuple[nnx.GraphDef, dict]:
    """Build the model and return `(graphdef, params)`; params are float32 with upstream's init laws
    (resnet_md: PyTorch default uniform; pwcnet: kaiming-normal, zero bias), except that the output convs
    are zero when the config says `head_init="zeros"` (all maps start at 0).

    Runs eagerly (draws two flat random vectors, see `layers.init_params_like`), so it is not traceable under
    `jax.jit` / `jax.eval_shape`: use `abstract_init` for shapes.

    Args:
      rng: a `jax.random.key` (or an int seed).
      config: a model name or config mapping (see `model_config`).
    """
    if isinstance(rng, int):
        rng = jax.random.key(rng)
    cfg = model_config(config)
    abstract_model = _abstract_module(cfg)
    graphdef, state = nnx.split(abstract_model, nnx.Param)
    params = init_params_like(abstract_model, nnx.to_pure_dict(state), rng)
    if cfg.get("head_init") == "zeros":
        # Zero output convs: the maps start at the zero-motion solution instead of a random field of
        # several pixels (0.3 tanh of a random conv), from which the photometric gradient, a local
        # signal, cannot find its way back (measured on the synthetic video). The layers below
        # still get gradients once the head weights move away from zero.
        heads = _HEAD_PREFIXES[cfg["name"]]
        params = {k: (jax.tree.map(np.zeros_like, v) if k.startswith(heads) else v) for k, v in params.items()}
    # one device_put of the tree: jnp.asarray on a numpy leaf compiles a small XLA program per leaf shape
    return graphdef, jax.device_put(params)


_ABSTRACT: dict[str, tuple[nnx.GraphDef, dict]] = {}


def abstract_init(config: Any) -> tuple[nnx.GraphDef, dict]:
    """Like `init` but without allocating: params are `jax.ShapeDtypeStruct`s (shapes for counts/converters).

    Memoised per normalised config: building the module abstractly takes ~0.3 s for pwc_lite, and loading a
    model for prediction asks twice (the shape check of the weights, then the predictor). The results are
    immutable (a GraphDef and ShapeDtypeStructs), so sharing them is safe; callers get a fresh dict."""
    cfg = model_config(config)
    key = json.dumps(cfg, sort_keys=True, default=repr)
    if key not in _ABSTRACT:
        graphdef, state = nnx.split(_abstract_module(cfg), nnx.Param)
        _ABSTRACT[key] = graphdef, jax.tree.map(lambda v: jax.ShapeDtypeStruct(v.shape, v.dtype),
                                                nnx.to_pure_dict(state))
    graphdef, params = _ABSTRACT[key]
    return graphdef, jax.tree.map(lambda a: a, params)


def apply(graphdef: nnx.GraphDef, params: dict, pair: jax.Array, *, dtype: Any = None) -> dict:
    """Run the network on image pairs.

    Args:
      graphdef, params: from `init` / a checkpoint (params stay float32).
      pair: `(N, H, W, 6)` = concat(image_a, image_b) in [0, 1]; H, W multiples of `INPUT_MULTIPLE[name]`.
      dtype: compute dtype (e.g. `jnp.bfloat16`); None = float32. Outputs are always float32.
    Returns:
      `{"px": (s0, s1, s2, s3), "frac": (s0, s1, s2, s3)}`, finest first, each `(N, H/2^s, W/2^s, 2)`:
      where pixel (x, y) of image_a is found in image_b, at (x + D_x, y + D_y); px in pixels of scale s,
      frac as fractions of (W_s, H_s).
    """
    dtype = jnp.dtype(dtype) if dtype is not None else jnp.float32
    if dtype != jnp.float32:
        params = jax.tree.map(lambda p: p.astype(dtype), params)
    model = nnx.merge(graphdef, nnx.State(params))
    maps = model(jnp.asarray(pair).astype(dtype))
    return {k: tuple(m.astype(jnp.float32) for m in v) for k, v in maps.items()}


def param_count(params: Any) -> int:
    """Total number of scalars in a params pytree (arrays or ShapeDtypeStructs)."""
    return int(sum(math.prod(p.shape) for p in jax.tree.leaves(params)))


__all__ = ["NAMES", "INPUT_MULTIPLE", "NATIVE_MULTIPLE", "check_working_size", "model_config", "init", "abstract_init", "apply", "param_count"]
