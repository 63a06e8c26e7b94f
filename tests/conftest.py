"""Test set-up: fake 8 CPU devices so that sharded code is testable on any machine.

This must run before JAX initialises its backends, hence at conftest import time.
"""
import os

os.environ.setdefault("JAX_PLATFORMS", "cpu")

import jax  # noqa: E402

jax.config.update("jax_num_cpu_devices", 8)
jax.config.update("jax_enable_x64", False)

import numpy as np  # noqa: E402
import pytest  # noqa: E402


@pytest.fixture
def rng():
    """A seeded numpy Generator; tests must be deterministic."""
    return np.random.default_rng(0)
