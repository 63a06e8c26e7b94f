"""Test set-up: fake 8 CPU devices so that sharded code is testable on any machine, and one compilation cache
folder for the session.

This must run before JAX initialises its backends (and before any test starts a subprocess), hence at conftest
import time.
"""
import ctypes
import ctypes.util
import gc
import os
import shutil
import tempfile

os.environ.setdefault("JAX_PLATFORMS", "cpu")
# The command-line entry points keep compiled executables in the user's cache folder (bridge_jax.compile_cache):
# the tests use one folder of their own instead, shared by the subprocesses they start, removed at the end.
_SESSION_CACHE = None
if "BRIDGE_JAX_CACHE_DIR" not in os.environ:
    _SESSION_CACHE = tempfile.mkdtemp(prefix="bridge_jax_test_xla_")
    os.environ["BRIDGE_JAX_CACHE_DIR"] = _SESSION_CACHE

import jax  # noqa: E402

jax.config.update("jax_num_cpu_devices", 8)
jax.config.update("jax_enable_x64", False)

# The session's folder is JAX's persistent compilation cache in the test processes too, turned on before their
# first compilation (JAX opens its cache once per process): tests build equal programs through different jitted
# functions (a fresh step, predictor or loss per test), which the in-memory cache cannot share and the persistent
# one does, across modules and across the two xdist workers.
from bridge_jax import compile_cache  # noqa: E402

compile_cache.enable("auto")
jax.config.update("jax_persistent_cache_min_compile_time_secs", 1.0)

import numpy as np  # noqa: E402
import pytest  # noqa: E402


try:
    _LIBC = ctypes.CDLL(ctypes.util.find_library("c") or "libc.so.6")
    _LIBC.malloc_trim  # glibc only
except (OSError, AttributeError):
    _LIBC = None


def _release():
    """Drop JAX's in-memory compiled programs and return the freed heap to the system."""
    jax.clear_caches()
    gc.collect()
    if _LIBC is not None:
        _LIBC.malloc_trim(0)  # hand the freed heap back: the worker's peak is its leftovers plus the next test


@pytest.fixture(scope="module", autouse=True)
def _release_compiled_programs():
    """After each test module, drop the compiled programs JAX keeps in memory: an xdist worker runs hundreds of
    tests, and their executables otherwise add up to several GB by the end of the session. A later module that
    needs one again loads it from the session's persistent compilation cache."""
    yield
    _release()


_RELEASE_ABOVE_BYTES = 1_500_000_000
"""`release_after_each_test` releases once the worker holds more than this (its tests then start from at most
this, plus their own ~1.2 GB at most): releasing after every test would recompile programs the next test reuses."""


def _resident_bytes() -> int:
    """The process's resident memory now (Linux), or a huge number where it cannot be read (then always release)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 1 << 62


@pytest.fixture
def release_after_each_test():
    """The same release after a test of a module that asks for it (`pytestmark =
    pytest.mark.usefixtures("release_after_each_test")`) once the worker holds more than `_RELEASE_ABOVE_BYTES`:
    in modules whose tests each build large programs (models of every kind, whole train steps) the leftovers
    otherwise reach 3.7 GB before the module ends."""
    yield
    if _resident_bytes() > _RELEASE_ABOVE_BYTES:
        _release()


@pytest.fixture
def rng():
    """A seeded numpy Generator; tests must be deterministic."""
    return np.random.default_rng(0)


@pytest.fixture(scope="session")
def tiny_checkpoint(tmp_path_factory):
    """A params-only checkpoint of `resnet_md_tiny` with random (not trained) weights of the right shapes.

    Built from `abstract_init` plus numpy draws: much cheaper than a real init on a loaded 2-core CPU.
    """
    from bridge_jax import checkpointing, models
    cfg = models.model_config("resnet_md_tiny")
    _, abstract = models.abstract_init(cfg)
    gen = np.random.default_rng(0)
    params = jax.tree.map(lambda s: (gen.standard_normal(s.shape) / np.sqrt(max(1, np.prod(s.shape[:-1]))))
                          .astype(np.float32), abstract)
    d = str(tmp_path_factory.mktemp("ckpt") / "tiny")
    checkpointing.save_params(d, params, cfg)
    return d


def pytest_sessionfinish(session, exitstatus):  # noqa: ARG001
    if _SESSION_CACHE is not None:
        shutil.rmtree(_SESSION_CACHE, ignore_errors=True)
