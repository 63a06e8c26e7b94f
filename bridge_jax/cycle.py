"""How a stereo-video *cycle* becomes ordered image pairs, and which output map is which task.

A cycle is the four frames of a rectified stereo video at two consecutive times,

    FRAMES = (left_t, right_t, left_t1, right_t1)     # float32 (4, H, W, 3) in [0, 1]

(the order of upstream's cycle list files). The paper's network P(I_a, I_b) is applied to four
*ordered pairs* (former -> latter), each in both directions (paper eqs. 1-3). The pair order is the row order
of upstream's training batch, so per-pair tensors line up with the upstream parity fixture:

    pair 0  stereo_t1   left_t1 -> right_t1     stereo matching at t+1
    pair 1  flow_left   left_t  -> left_t1      optical flow, left camera
    pair 2  flow_right  right_t -> right_t1     optical flow, right camera
    pair 3  stereo_t    left_t  -> right_t      stereo matching at t

For one cycle the network input has 8 rows: rows 0..3 are the *forward* inputs concat(former, latter)
of the active pairs, rows 4..7 the *backward* inputs concat(latter, former). The forward map D says
where a pixel of `former` is found in `latter` (warp(latter, D) ~ former); the backward map D' is the
reverse. With a task subset (stereo-only, flow-only) only the active pairs are present, so a cycle has
2 * len(pairs) rows, forward rows first.

This module is the single place that knows this layout: the loss, the trainer and the evaluator use it.
"""

from __future__ import annotations

from typing import Any, NamedTuple, Sequence

import jax.numpy as jnp

FRAMES = ("left_t", "right_t", "left_t1", "right_t1")
LEFT_T, RIGHT_T, LEFT_T1, RIGHT_T1 = range(4)


TASKS = ("flow", "stereo")
"""What a pair is, its task: consecutive frames ("flow") or a rectified left -> right pair ("stereo")."""


def check_task(task: Any, option: str = "task") -> str:
    """`task` if it is one of `TASKS`, else a ValueError naming `option`."""
    if task not in TASKS:
        raise ValueError(f"{option} must be one of {TASKS}, got {task!r}")
    return task


class Pair(NamedTuple):
    name: str
    former: int  # index into FRAMES
    latter: int  # index into FRAMES
    task: str  # one of TASKS


PAIRS = (
    Pair("stereo_t1", LEFT_T1, RIGHT_T1, "stereo"),
    Pair("flow_left", LEFT_T, LEFT_T1, "flow"),
    Pair("flow_right", RIGHT_T, RIGHT_T1, "flow"),
    Pair("stereo_t", LEFT_T, RIGHT_T, "stereo"),
)
STEREO_T1, FLOW_LEFT, FLOW_RIGHT, STEREO_T = range(4)

TASK_SETS = ("flow_stereo", "stereo_only", "flow_only")
_TASK_PAIRS = {
    "flow_stereo": (STEREO_T1, FLOW_LEFT, FLOW_RIGHT, STEREO_T),
    "stereo_only": (STEREO_T1, STEREO_T),
    "flow_only": (FLOW_LEFT, FLOW_RIGHT),
}


def pairs_for_tasks(tasks: str) -> tuple[int, ...]:
    """Indices into PAIRS of the pairs a training variant uses (paper: stereo-only, flow-only, flow+stereo)."""
    if tasks not in _TASK_PAIRS:
        raise ValueError(f"tasks must be one of {TASK_SETS}, got {tasks!r}")
    return _TASK_PAIRS[tasks]


def rows_per_cycle(pairs: Sequence[int] = tuple(range(4))) -> int:
    """Number of network inputs per cycle: each pair in both directions."""
    return 2 * len(pairs)


def row_tasks(pairs: Sequence[int], num_rows: int, offset: int = 0) -> tuple[str, ...]:
    """The task ("stereo" / "flow") of each of `num_rows` consecutive pair-input rows, starting at row `offset`
    of the batch.

    Rows follow `batch_pair_inputs`: per cycle 2P rows, the P forward rows of `pairs`, then the P backward rows.
    The answer is static (it decides which network a row goes through when stereo and flow do not share one).
    """
    p = len(pairs)
    return tuple(PAIRS[pairs[(offset + i) % (2 * p) % p]].task for i in range(num_rows))


def _check_cycle(cycle, name: str, batched: bool):
    rank = 5 if batched else 4
    shape = "(B, 4, H, W, 3)" if batched else "(4, H, W, 3)"
    if cycle.ndim != rank or cycle.shape[-4] != 4 or cycle.shape[-1] != 3:
        raise ValueError(f"{name} must have shape {shape} (frames {FRAMES}), got {tuple(cycle.shape)}")


def pair_images(cycle, pairs: Sequence[int] = tuple(range(4))):
    """Split a cycle into the former and latter images of the given pairs.

    Args:
      cycle: (4, H, W, C) frames in FRAMES order.
      pairs: indices into PAIRS.
    Returns:
      (former, latter), each (P, H, W, C).
    """
    former = jnp.stack([cycle[PAIRS[k].former] for k in pairs])
    latter = jnp.stack([cycle[PAIRS[k].latter] for k in pairs])
    return former, latter


def pair_inputs(cycle, pairs: Sequence[int] = tuple(range(4))):
    """Network inputs of one cycle: (2P, H, W, 6); forward concat(former, latter) rows first, then backward."""
    _check_cycle(cycle, "cycle", batched=False)
    former, latter = pair_images(cycle, pairs)
    fwd = jnp.concatenate([former, latter], axis=-1)
    bwd = jnp.concatenate([latter, former], axis=-1)
    return jnp.concatenate([fwd, bwd], axis=0)


def batch_pair_inputs(cycles, pairs: Sequence[int] = tuple(range(4))):
    """Network inputs of a batch of cycles (B, 4, H, W, 3) -> (B * 2P, H, W, 6), cycle-major."""
    _check_cycle(cycles, "cycles", batched=True)
    b, _, h, w, _ = cycles.shape
    former = cycles[:, [PAIRS[k].former for k in pairs]]  # (B, P, H, W, 3)
    latter = cycles[:, [PAIRS[k].latter for k in pairs]]
    fwd = jnp.concatenate([former, latter], axis=-1)
    bwd = jnp.concatenate([latter, former], axis=-1)
    return jnp.concatenate([fwd, bwd], axis=1).reshape(b * 2 * len(pairs), h, w, 6)


def split_directions(x, num_pairs: int):
    """Split per-cycle rows (2P, ...) into (forward (P, ...), backward (P, ...))."""
    if x.shape[0] != 2 * num_pairs:
        raise ValueError(f"expected {2 * num_pairs} rows (forward and backward of {num_pairs} pairs), got {x.shape[0]}")
    return x[:num_pairs], x[num_pairs:]


def unbatch_maps(maps, num_cycles: int):
    """Reshape network maps of (B * 2P, h, w, 2) per scale into (B, 2P, h, w, 2) for vmapping over cycles."""
    return {k: tuple(m.reshape((num_cycles, -1) + m.shape[1:]) for m in v) for k, v in maps.items()}


def disparity_from_stereo_map(d_px):
    """Disparity (positive, pixels) from a left->right stereo map (..., 2): d = -D_x."""
    return -d_px[..., 0]
