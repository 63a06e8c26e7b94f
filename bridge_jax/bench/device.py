"""The device measured on: its peak FLOP/s (for MFU) and its memory."""

from __future__ import annotations

import time

import jax
import jax.numpy as jnp

# Dense peak TFLOP/s per chip, (bf16, float32 as XLA runs it by default), matched by substring of the lower-cased
# `device_kind`, first match wins. float32: XLA:GPU uses TF32 tensor cores for f32 dots/convs at the default
# precision on Ampere+; XLA:TPU runs f32 matmuls as single-pass bf16 at the default precision.
PEAK_TFLOPS: tuple[tuple[str, float, float], ...] = (
    ("h200", 989.0, 494.7),
    ("h100 pcie", 756.0, 378.0),
    ("h100", 989.0, 494.7),  # SXM
    ("a100", 312.0, 156.0),
    ("tpu v6 lite", 918.0, 918.0),  # v6e
    ("tpu v6e", 918.0, 918.0),
    ("tpu v5 lite", 197.0, 197.0),  # v5e
    ("tpu v5e", 197.0, 197.0),
    ("tpu v5p", 459.0, 459.0),
    ("tpu v5", 459.0, 459.0),
    ("tpu v4", 275.0, 275.0),
)


# ---------------------------------------------------------------------------------------------------------
# Device: kind, peak FLOP/s, memory
# ---------------------------------------------------------------------------------------------------------

def known_peak_tflops(device_kind: str, dtype: str) -> float | None:
    """Dense peak TFLOP/s of a known accelerator (`PEAK_TFLOPS`), or None."""
    kind = device_kind.lower()
    for key, bf16, f32 in PEAK_TFLOPS:
        if key in kind:
            return bf16 if dtype == "bfloat16" else f32
    return None


def measured_matmul_tflops(dtype: str = "float32", n: int = 2048, repeats: int = 4) -> float:
    """Best-of-`repeats` TFLOP/s of one jitted (n, n) @ (n, n) matmul on the default device (the CPU 'peak')."""
    dt = jnp.bfloat16 if dtype == "bfloat16" else jnp.float32
    k1, k2 = jax.random.split(jax.random.key(0))
    a = jax.random.normal(k1, (n, n), dt)
    b = jax.random.normal(k2, (n, n), dt)
    f = jax.jit(lambda a, b: jnp.dot(a, b, preferred_element_type=dt))
    f(a, b).block_until_ready()
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        f(a, b).block_until_ready()
        best = min(best, time.perf_counter() - t0)
    return 2.0 * n**3 / best / 1e12


def device_peak(dtype: str, override_tflops: float | None = None) -> tuple[float, str]:
    """(peak TFLOP/s, where it came from) for the default device."""
    if override_tflops:
        return float(override_tflops), "--peak-tflops"
    dev = jax.devices()[0]
    peak = known_peak_tflops(dev.device_kind, dtype)
    if peak is not None:
        return peak, f"table:{dev.device_kind}"
    return measured_matmul_tflops(dtype), "measured 2048^2 matmul (best of 4)"


def device_memory_peak_bytes() -> int | None:
    stats = jax.devices()[0].memory_stats()
    if not stats:
        return None
    return int(stats.get("peak_bytes_in_use", stats.get("bytes_in_use", 0))) or None


def cost_flops(cost) -> float | None:
    if cost is None:
        return None
    if isinstance(cost, (list, tuple)):
        cost = cost[0] if cost else None
        if cost is None:
            return None
    f = cost.get("flops")
    return float(f) if f is not None and f >= 0 else None
