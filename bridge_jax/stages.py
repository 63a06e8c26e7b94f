"""The test-time stages of a predictor and their one composition (`predicted_maps`).

A `testtime.TestTime` record says which stages run; they run in this order:

1. the network's scale-0 pixel map, averaged over mirrored and transposed copies of each pair
   (`symmetric_maps`, `TestTime.symmetry`);
2. `TestTime.refine` passes of test-time iterative residual refinement (`refine_maps`), each pass's residual
   averaged the same way: the same network with no new weights, at K + 1 times the cost;
3. the photometric polish of the final maps against the images (`polish.polish_maps`, `TestTime.polish`, its
   parameters in a `polish.PolishConfig`): at the working size here; `Predictor` runs it on the images as given
   instead, after bringing the map to their size (`PolishConfig.resolution`, `Predictor.stage_maps`).

Stages 1-2 are the network program (`network_maps`), stage 3 the polish program (`polish_stage`);
`predicted_maps` composes the two. `Predictor` compiles them as two programs (`POLISH_APART`), `export` traces
both into one artifact; both call `predicted_maps`.

The map for (a, b) says where pixel (x, y) of `a` is found in `b`: at (x + u, y + v). `flow_rows (N,)` is
the task of each row as the stages use it (`flow_rows(tasks)`): 1.0 for a flow row, 0.0 for a rectified stereo
row (whose vertical component is dropped: a stereo match lies on the same row).
"""
from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Optional

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import geometry
from bridge_jax.cycle import check_task
from bridge_jax.network import Network
from bridge_jax.polish import DEFAULT_CONFIG, PolishConfig, component_mask, config_for_rows, polish_maps
from bridge_jax.testtime import TestTime

POLISH_APART = True
"""`Predictor` compiles the polish as a program of its own, at XLA's full optimisation whatever its compile
mode: the polish is all elementwise loops, which XLA:CPU's optimisation level 0 ("fast") leaves unvectorised,
while the network's convolutions (library calls) do not care. `export` fuses both into one artifact."""


def flow_rows(tasks: Sequence[str]) -> np.ndarray:
    """`(N,)` float32 of N tasks ("flow" / "stereo"): 1 for flow rows, 0 for stereo rows."""
    return np.array([0.0 if t == "stereo" else 1.0 for t in tasks], np.float32)


def refine_maps(network_maps: Callable, pairs: jax.Array, maps: jax.Array, flow_rows: jax.Array,
                passes: int) -> jax.Array:
    """Test-time iterative residual refinement of correspondence maps.

    Each pass backward-warps image b by the current map D (`geometry.warp`, bilinear, border clamp), so that
    what is left to find is a small residual R between a and warp(b, D), asks the network for it, and composes
    the two: pixel x of a is found at x + R(x) in warp(b, D), which is b at x + R(x) + D(x + R(x)), so
    D'(x) = R(x) + D(x + R(x)) (D sampled at the residual's end point, again by `geometry.warp`).

    Args:
      network_maps: pair inputs `(N, H, W, 6)` -> maps `(N, H, W, 2)` in working pixels (the network).
      pairs: `(N, H, W, 6)` = [image a, image b].
      maps: `(N, H, W, 2)`, the maps so far (the first network call's).
      flow_rows: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows, whose vertical component is
        dropped before each warp (a stereo match lies on the same row).
      passes: how many passes (static); one compiled copy of the network serves them all (`lax.fori_loop`).
    Returns:
      `(N, H, W, 2)` refined maps.
    """
    image_a, image_b = pairs[..., :3], pairs[..., 3:]
    mask = component_mask(flow_rows)

    def one_pass(_, d):
        d = d * mask
        residual = network_maps(jnp.concatenate([image_a, geometry.warp(image_b, d)], axis=-1)) * mask
        return residual + geometry.warp(d, residual)

    return jax.lax.fori_loop(0, passes, one_pass, maps)



def _flip(x: jax.Array, left_right: bool, up_down: bool) -> jax.Array:
    """`(N, H, W, C)` flipped along W and/or H (pixel x -> W - 1 - x: exact, no resampling)."""
    if left_right:
        x = x[:, :, ::-1]
    if up_down:
        x = x[:, ::-1]
    return x



def symmetric_maps(network_maps: Callable, pairs: jax.Array, symmetry: str,
                       flow_rows: Optional[jax.Array] = None) -> jax.Array:
    """The network's map averaged over mirrored and transposed copies of each pair (test-time augmentation).

    A correspondence map commutes with the image's symmetries: if both images are flipped left-right, pixel
    (W - 1 - x, y) of the flipped `a` is found at (W - 1 - x - u, y + v) of the flipped `b`, so the flipped
    pair's map, flipped back, is (-u, v); upside-down flips negate v; a transposed pair's map, transposed back,
    has u and v swapped. The network does not know these symmetries exactly (it was trained on rigs that move
    forward, with mostly horizontal stereo), and its sub-pixel errors on the copies are partly independent, so
    their mean is more precise than any one of them; the monodepth family's flip post-processing is the
    one-flip case of the same idea. All flipped copies of one orientation run as one batch (one traced copy of
    the network per orientation).

    Args:
      network_maps: `(M, h, w, 6)` pair inputs -> `(M, h, w, 2)` maps in working pixels, for any M and any (h, w)
        the network accepts (a transposed pair is `(N, W, H, 6)`; working sizes are multiples of the model's
        input multiple both ways).
      pairs: `(N, H, W, 6)` = [image a, image b].
      symmetry: one of `testtime.SYMMETRY_MODES`.
      flow_rows: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows (as for `refine_maps`). A stereo
        row counts only its copies that are stereo pairs of the same kind: as given and flipped upside-down (a
        left-right flip turns a left -> right pair into one whose matches lie to the right, a transposition
        into a vertical one). None = all rows are flow.
    Returns:
      `(N, H, W, 2)` maps.
    """
    if symmetry == "none":
        return network_maps(pairs)
    n = pairs.shape[0]
    flips = ((False, False), (True, False), (False, True), (True, True))
    views = (False, True) if symmetry == "dihedral" else (False,)
    flow_rows = jnp.ones((n,), jnp.float32) if flow_rows is None else flow_rows.astype(jnp.float32)
    total = jnp.zeros(pairs.shape[:3] + (2,), jnp.float32)
    count = jnp.zeros((n,), jnp.float32)
    for transposed in views:
        view = jnp.swapaxes(pairs, 1, 2) if transposed else pairs
        maps = network_maps(jnp.concatenate([_flip(view, lr, ud) for lr, ud in flips])).astype(jnp.float32)
        for k, (lr, ud) in enumerate(flips):
            weight = flow_rows if (lr or transposed) else jnp.ones((n,), jnp.float32)
            m = _flip(maps[k * n:(k + 1) * n], lr, ud) * jnp.array([-1.0 if lr else 1.0, -1.0 if ud else 1.0])
            total = total + weight[:, None, None, None] * (jnp.swapaxes(m, 1, 2)[..., ::-1] if transposed else m)
            count = count + weight
    return total / count[:, None, None, None]


def network_maps(network: Network, params, pairs: jax.Array, tasks: tuple[str, ...], flow_rows: jax.Array,
                 test_time: TestTime) -> jax.Array:
    """Stages 1-2: the network's scale-0 pixel map of `pairs (N, H, W, 6)`, averaged over the `symmetry` copies
    (`symmetric_maps`), then `refine` passes (`refine_maps`). `network(params, x, tasks)`: a `Network` and its
    static tasks (`Network.static_tasks`, one per pair). Returns `(N, H, W, 2)`; the polish is not applied."""
    n = pairs.shape[0]
    # symmetric_maps stacks copies of the N pairs on the batch axis: separate networks need their tasks repeated
    net = lambda x: network(params, x, tasks * (x.shape[0] // n))["px"][0]
    averaged = lambda x: symmetric_maps(net, x, test_time.symmetry, flow_rows)
    maps = averaged(pairs)
    if test_time.refine:
        maps = refine_maps(averaged, pairs, maps, flow_rows, test_time.refine)
    return maps


def polish_stage(pairs: jax.Array, maps: jax.Array, flow_rows: jax.Array, test_time: TestTime,
                 config: PolishConfig = DEFAULT_CONFIG) -> jax.Array:
    """Stage 3: `maps` polished by the photometric step when `test_time.polish` has it (`polish.polish_maps`
    with `config`). The polish's "fill" step runs on the host at the input resolution (`Predictor.predict`)."""
    return polish_maps(pairs, maps, flow_rows, config) if test_time.photometric else maps


def predicted_maps(pairs, flow_rows, test_time: TestTime, network_program: Callable,
                   polish_program: Optional[Callable] = None):
    """What a predictor answers for `pairs`: `network_program(pairs)` (stages 1-2, `network_maps`), then, when
    `test_time`'s polish has its photometric step, `polish_program(pairs, maps, flow_rows)` (stage 3, `polish_stage`;
    default: traced into the caller's program). Both may be traced functions or compiled programs."""
    maps = network_program(pairs)
    if not test_time.photometric:
        return maps
    if polish_program is None:
        return polish_stage(pairs, maps, flow_rows, test_time)
    return polish_program(pairs, maps, flow_rows)


__all__ = ["refine_maps", "symmetric_maps", "network_maps", "polish_stage", "predicted_maps", "flow_rows", "inference_function",
           "POLISH_APART"]


def inference_function(predictor, batch: int = 1, task: str = "flow"):
    """The jittable function every export format writes: `infer(pairs (batch, H, W, 6)) -> (px0, frac0)` at the
    predictor's working size, params as constants, with the predictor's test-time stages (`predictor.test_time`,
    `predicted_maps`); `task` picks the network of a separate-networks model (and for "stereo" keeps the
    maps on image rows)."""
    if batch < 1:
        raise ValueError(f"--batch must be >= 1, got {batch}")
    check_task(task, "--task")
    params = jax.tree.map(jnp.asarray, predictor.params)
    tasks = predictor.net.static_tasks((task,) * batch)
    rows_flow = jnp.asarray(flow_rows([task] * batch))
    test_time = predictor.test_time

    def infer(pairs):
        if test_time == TestTime():
            maps = predictor.net(params, pairs, tasks)
            return maps["px"][0], maps["frac"][0]
        network_program = lambda x: network_maps(predictor.net, params, x, tasks, rows_flow,
                                                        test_time.network_part)
        config = config_for_rows(predictor.polish_config, flow_rows([task] * batch))
        polish_program = lambda x, maps, flows: polish_stage(x, maps, flows, test_time, config)
        px = predicted_maps(pairs, rows_flow, test_time, network_program, polish_program)
        return px, px / jnp.asarray([predictor.width, predictor.height], px.dtype)

    return infer
