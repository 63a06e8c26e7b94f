"""Whether a working size can fit at all: a lower bound of the memory that training or prediction needs at a size,
compared with the memory of the device that would run it, before anything is allocated or written.

    needed = memory.prediction_bytes(height, width)
    memory.check_fits("--working-size", height, width, needed, "a prediction (one pair per call)")

refuses with one ValueError line naming the option, the size (height x width), the estimate and what the machine
has: "--working-size 100000x100000 (height x width): a prediction (one pair per call) needs at least 596.0 GiB at
this size, more than the 23.5 GiB of this machine's RAM". `setup.parse` checks training's working size this way,
`inference.load_predictor` prediction's.

The estimates are lower bounds on purpose: only a size that truly cannot fit is refused (one below them may still
run out of memory). Both are per pixel of the working size, measured with XLA's `memory_analysis` on XLA:CPU at
64x128 to 256x512 (the temporaries grow with the pixel count) and rounded well below the smallest measurement:

  training    `TRAIN_BYTES_PER_PIXEL` per pair-forward of a step on one device (2P rows per cycle: 8 for
              flow_stereo, 16 for the paper's batch of 2 cycles), plus `CYCLE_BYTES_PER_PIXEL` per cycle of the
              batch (4 frames x 3 channels of float32). Every form of the step (one jit, micro-batched) holds all
              maps of the batch and their loss at once, and the cycle loss's forward and gradient alone, whatever
              the network, took 443 (ssim_l1, finest scale only), 563 (ssim_l1, the paper's four scales) and 1480
              (census, finest scale) bytes per pixel and pair-forward; the network's activations come on top.
  prediction  `PREDICT_BYTES_PER_PIXEL` per pair of a call. The compiled network of the smallest model
              (resnet_md_tiny) took 96 bytes per pixel for one pair (its input alone is 24), pwc_lite 148,
              pwcnet 315, resnet_md 381.

The memory compared with (`memory_limit`): the device's own where the backend reports it (a GPU's or TPU's
`memory_stats()["bytes_limit"]`), else this machine's physical memory or the container's limit if lower. Not
what is free at the moment: that changes with other processes, and a size that fits once they end must not be
refused.
"""

from __future__ import annotations

import os
from typing import Any, Optional

TRAIN_BYTES_PER_PIXEL = 256
"""Lower bound of training's memory per pixel of the working size and pair-forward of a step (see above)."""
CYCLE_BYTES_PER_PIXEL = 4 * 3 * 4
"""A cycle of the batch: 4 frames of 3 float32 channels per pixel."""
PREDICT_BYTES_PER_PIXEL = 64
"""Lower bound of prediction's memory per pixel of the working size and pair of a call (see above)."""

# cgroup v2, then v1: a container's memory limit, where it is lower than the machine's
_CGROUP_LIMITS = ("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory/memory.limit_in_bytes")


def training_bytes(height: int, width: int, rows: int, cycles: int) -> int:
    """Lower bound of the memory (bytes) of a train step of `rows` pair-forwards on `cycles` cycles at
    `height x width` (see the module docstring)."""
    return int(height) * int(width) * (int(rows) * TRAIN_BYTES_PER_PIXEL + int(cycles) * CYCLE_BYTES_PER_PIXEL)


def prediction_bytes(height: int, width: int, pairs: int = 1) -> int:
    """Lower bound of the memory (bytes) of one predictor call on `pairs` pairs at `height x width`."""
    return int(height) * int(width) * int(pairs) * PREDICT_BYTES_PER_PIXEL


def _machine_bytes() -> Optional[int]:
    """This machine's physical memory, or the container's limit where that is lower; None if unknown."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):  # no sysconf names on this system
        return None
    for path in _CGROUP_LIMITS:
        try:
            with open(path) as f:
                text = f.read().strip()
        except OSError:
            continue
        if text.isdigit():  # "max" (v2) = no limit
            total = min(total, int(text))
    return total if total > 0 else None


def memory_limit(device: Any = None) -> tuple[Optional[int], str]:
    """(bytes, whose memory in words) that a computation on `device` (a jax device; None = this machine's host)
    can have: the device's own memory where its backend reports it, else the machine's (`_machine_bytes`);
    (None, ...) when neither is known."""
    if device is not None and getattr(device, "platform", "cpu") != "cpu":
        try:
            limit = (device.memory_stats() or {}).get("bytes_limit")
        except Exception:  # noqa: BLE001  (a backend without memory statistics: fall back to the host's)
            limit = None
        if limit:
            return int(limit), f"the {device.device_kind}'s memory"
    return _machine_bytes(), "this machine's RAM"


def gib(num_bytes: float) -> str:
    """`num_bytes` as "12.3 GiB"."""
    return f"{num_bytes / 2 ** 30:,.1f} GiB"


def check_fits(option: str, height: int, width: int, needed: int, what: str, device: Any = None) -> None:
    """Raises ValueError (one line naming `option` and the size, height x width) when `needed` bytes (an estimate
    of `what` at `height x width`) exceed the memory of `device` (`memory_limit`); nothing when that memory is
    unknown."""
    limit, where = memory_limit(device)
    if limit is not None and needed > limit:
        raise ValueError(f"{option} {height}x{width} (height x width): {what} needs at least {gib(needed)} at this "
                         f"size, more than the {gib(limit)} of {where}")
