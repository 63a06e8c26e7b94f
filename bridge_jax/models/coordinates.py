"""Coordinate channels: normalised pixel positions appended to a network's input (every model's `coords` switch).

Under ego-motion the flow of a pixel depends on where it is in the image (expansion away from the focus of
expansion, the ground plane's shear), and a convolution, being translation-equivariant, cannot see position;
two extra channels holding x and y let it.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp


def coordinate_channels(n: int, h: int, w: int, dtype=jnp.float32) -> jax.Array:
    """`(n, h, w, 2)` normalised pixel coordinates: ch0 = x, ch1 = y, -1 at the first pixel centre, +1 at the last
    (0 for a dimension of size 1)."""
    xs = jnp.linspace(-1.0, 1.0, w, dtype=dtype) if w > 1 else jnp.zeros((1,), dtype)
    ys = jnp.linspace(-1.0, 1.0, h, dtype=dtype) if h > 1 else jnp.zeros((1,), dtype)
    grid = jnp.stack(jnp.meshgrid(xs, ys, indexing="xy"), axis=-1)  # (h, w, 2)
    return jnp.broadcast_to(grid, (n, h, w, 2))


def with_coordinates(x: jax.Array) -> jax.Array:
    """`(N, H, W, C) -> (N, H, W, C + 2)`: x with `coordinate_channels` appended."""
    n, h, w, _ = x.shape
    return jnp.concatenate([x, coordinate_channels(n, h, w, x.dtype)], axis=-1)
