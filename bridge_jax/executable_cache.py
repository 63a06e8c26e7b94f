"""Warm starts without tracing: compiled programs kept whole beside the compilation cache.

XLA's persistent compilation cache (`compile_cache`) keeps what XLA compiled, but a new process still has to
*trace* the function in Python and lower it to StableHLO before it can even look the executable up: on a 2-core
VM that is 3.4 s of tracing and 1.0 s of lowering for the demo's 128x256 train step, and about 1 s for the
`demo` predictor's forward pass, the larger part of a warm start. `cached_compile` keeps the compiled
executable itself (`jax.experimental.serialize_executable`) in the same folder, under a key computed without
tracing, so that the next run of the same code, config and shapes loads it and calls it: no tracing, no
lowering, no second lookup. Training keeps its train step this way (`bridge-train`), prediction its network
(`bridge-predict`, `bridge-evaluate`).

An entry is used only when everything that shapes the program is the same: the source of every bridge_jax
module (a hash of the files), the jax and jaxlib versions, the caller's config (everything the function closes
over: the run config, the model config), the tree structure, shapes, dtypes and shardings of the arguments, the
device kind, platform, CPU vector ISA (the convolution gradient rules depend on it), CPU model and feature
flags (XLA compiles for the host's exact CPU) and the XLA / JAX / bridge_jax environment variables. Anything else gives another key, and the function is compiled as before.
Entries are files named `<key>-exec-cache` in the compilation cache folder, trimmed with its other entries.

Single-device programs only: a function whose arguments live on several devices is returned as it is, and
so is one whose executable refers to this process (host callbacks, side effects). An executable that XLA
itself loaded from its cache is used but not kept again: XLA:CPU cannot serialise a deserialised executable
(the copy lacks its kernels and fails when run), so only a fresh compile writes an entry.
"""
from __future__ import annotations

import contextlib
import functools
import hashlib
import json
import os
import pickle
import warnings
from typing import Callable, Optional, Sequence

import jax
from jax.experimental import serialize_executable

from bridge_jax import compile_cache, files
from bridge_jax.models import layers

SUFFIX = "-exec-cache"
"""File name ending of an entry (the compilation cache's trimming keeps every `*-cache` file under its cap)."""
FORMAT = 1
"""Version of the entry layout; entries of another version are ignored (and overwritten)."""
ENV_PREFIXES = ("XLA_", "JAX_", "BRIDGE_JAX_")
"""Environment variables that can change the compiled program: they are part of the key."""


@functools.lru_cache(maxsize=1)
def source_fingerprint() -> str:
    """sha256 of every `.py` file of the bridge_jax package (path and contents) and the jax / jaxlib versions:
    any code change gives new keys, so an entry never outlives the code that compiled it."""
    root = os.path.dirname(os.path.abspath(__file__))
    h = hashlib.sha256(f"jax {jax.__version__} jaxlib {jax.lib.__version__}".encode())
    for folder, dirs, names in os.walk(root):
        dirs.sort()
        for name in sorted(names):
            if name.endswith(".py"):
                path = os.path.join(folder, name)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()


@functools.lru_cache(maxsize=1)
def cpu_signature() -> str:
    """The CPU's model name and feature flags (/proc/cpuinfo's first processor; "" where there is none). XLA:CPU
    compiles for the host's exact features, so an executable from another CPU model may use instructions this one
    lacks: a cache folder shared between machines (a network home) must not hand it over."""
    wanted, found = ("model name", "flags", "Features", "CPU part"), {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if not line.strip():
                    break  # the end of the first processor's block
                name, _, value = line.partition(":")
                if name.strip() in wanted:
                    found[name.strip()] = value.strip()
    except OSError:
        pass
    return json.dumps(found, sort_keys=True)


def _leaf_signature(x) -> str:
    if not hasattr(x, "shape"):
        return repr(x)  # a static argument (a tuple of flags, an int)
    return f"{tuple(x.shape)}:{x.dtype}:{getattr(x, 'sharding', None)}"


def entry_key(config: dict, args) -> str:
    """The entry key of a program: hex sha256 over the source fingerprint, `config`, the arguments' tree
    structure, shapes, dtypes and shardings (static arguments by value), the devices, the CPU model and features
    (`cpu_signature`), and the environment (`ENV_PREFIXES`)."""
    env = {k: v for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIXES)}
    parts = {"source": source_fingerprint(), "config": config, "env": env,
             "tree": str(jax.tree.structure(args)), "leaves": [_leaf_signature(x) for x in jax.tree.leaves(args)],
             "devices": [str(d.device_kind) for d in jax.devices()], "platform": jax.default_backend(),
             "isa": layers.cpu_vector_isa(), "cpu": cpu_signature()}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _devices(args) -> set:
    return {d for x in jax.tree.leaves(args) if hasattr(x, "sharding") for d in x.sharding.device_set}


def _compile(fn: Callable, args):
    """Lower and compile `fn(*args)` the usual way (through XLA's persistent cache) -> (the compiled program,
    its entry bytes, or None when it must not be kept: see the module doc). Raises ValueError for an
    executable that refers to this process."""
    with compile_cache.CompileClock() as clock:
        compiled = fn.lower(*args).compile()
    if clock.compiles != 1 or clock.cache_hits:
        return compiled, None  # loaded by XLA (from its cache or this process's): cannot be serialised again
    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if unloaded is None:
        raise ValueError("this compiled program has no serialisable executable")
    if unloaded.host_callbacks or unloaded.keepalive or unloaded.ordered_effects or unloaded.unordered_effects:
        raise ValueError("the program has host callbacks or side effects, which refer to this process")
    payload, in_tree, out_tree = serialize_executable.serialize(compiled)
    return compiled, pickle.dumps({"format": FORMAT, "executable": payload, "in_tree": in_tree,
                                   "out_tree": out_tree})


def _load(path: str, device):
    """The compiled program kept at `path`, loaded onto `device`, or None when it is missing, of another format
    or unreadable."""
    try:
        with open(path, "rb") as f:
            entry = pickle.load(f)
        if entry.get("format") != FORMAT:
            return None
        return serialize_executable.deserialize_and_load(entry["executable"], entry["in_tree"], entry["out_tree"],
                                                         execution_devices=[device])
    except FileNotFoundError:
        return None
    except Exception as e:  # noqa: BLE001 - a damaged entry is removed (and re-made), never a reason to fail
        warnings.warn(f"ignoring an unreadable compiled-program cache entry {path} ({type(e).__name__}: {e}); "
                      "compiling instead", stacklevel=3)
        with contextlib.suppress(OSError):
            os.remove(path)  # warn once: when XLA's own cache answers the compile, nothing is written over it
        return None


def cached_compile(fn: Callable, args: Sequence, *, config: dict, folder: Optional[str],
                   stats: Optional[dict] = None, static_argnums: Sequence[int] = (),
                   announce: Optional[Callable[[bool], None]] = None) -> Callable:
    """`fn` (a jitted function) compiled for `args`, loaded from `folder` when it holds the entry (`entry_key`
    of `config` and `args`), else compiled and written there.

    `config` must name everything `fn` closes over that shapes its program (its args' shapes are in the key
    already). `static_argnums`: positions of `fn`'s static arguments (part of the key by value).
    Returns a function of the same arguments as `fn` (static ones included, and ignored: they are the ones
    compiled for), or `fn` itself when `folder` is None, when the arguments live on more than one device, when
    `fn` is not jitted, or when its executable cannot be kept. `stats`, if given, gets "cache" = "hit",
    "written" or "off", "cache_key", and "cache_error" saying why a compiled program was not kept.
    `announce`, if given, is called once before anything is loaded or compiled, with True when an entry is
    there to load (a caller's "loading ..." / "compiling ..." line).
    """
    stats = {} if stats is None else stats
    devices = _devices(args)
    if folder is None or not hasattr(fn, "lower") or len(devices) != 1:
        stats["cache"] = "off"
        if announce:
            announce(False)
        return fn
    key = entry_key(config, args)
    path = os.path.join(folder, key + SUFFIX)
    stats["cache_key"] = key
    if announce:
        announce(os.path.exists(path))
    compiled = _load(path, next(iter(devices)))
    if compiled is not None:
        stats["cache"] = "hit"
    else:
        try:
            compiled, entry = _compile(fn, args)
        except Exception as e:  # noqa: BLE001 - a program whose executable cannot be kept is jitted as before
            stats.update(cache="off", cache_error=f"{type(e).__name__}: {e}"[:500])
            return fn
        if entry is None:
            stats.update(cache="off", cache_error="XLA loaded this program from its own cache; not kept again")
        else:
            try:
                files.write_bytes(path, entry)
                stats["cache"] = "written"
            except OSError as e:  # a full or read-only folder: this run still uses what it just compiled
                warnings.warn(f"could not write the compiled-program cache entry {path}: {e}", stacklevel=2)
                stats["cache"] = "off"
    if not static_argnums:
        return compiled
    static = frozenset(static_argnums)
    return lambda *a: compiled(*(x for i, x in enumerate(a) if i not in static))


__all__ = ["cached_compile", "entry_key", "source_fingerprint", "SUFFIX"]
