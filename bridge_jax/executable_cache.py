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
import warnings
from typing import Callable, Optional, Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax._src import tree_util
from jax._src.interpreters import pxla
from jax._src.layout import Layout
from jax._src.lib import xla_client
from jax._src.linear_util import DebugInfo
from jax.sharding import AxisType, Mesh, NamedSharding, PartitionSpec, SingleDeviceSharding

from bridge_jax import compile_cache, files
from bridge_jax.models import layers

SUFFIX = "-exec-cache"
"""File name ending of an entry (the compilation cache's trimming keeps every `*-cache` file under its cap)."""
FORMAT = 2
"""Version of the entry layout (2: sealed JSON header and executable; 1 was a pickle); entries of another version
are removed and made again."""
ENV_PREFIXES = ("XLA_", "JAX_", "BRIDGE_JAX_")
"""Environment variables that can change the compiled program: they are part of the key."""
FOLDER_VARS = ("BRIDGE_JAX_CACHE_DIR", "JAX_COMPILATION_CACHE_DIR")
"""Environment variables naming a folder: their real path is in the key (`cache/` and `cache` are one folder)."""


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
    env = {k: (os.path.realpath(v) if k in FOLDER_VARS and v else v)  # the folder, not its spelling
           for k, v in sorted(os.environ.items()) if k.startswith(ENV_PREFIXES)}
    parts = {"source": source_fingerprint(), "config": config, "env": env,
             "tree": str(jax.tree.structure(args)), "leaves": [_leaf_signature(x) for x in jax.tree.leaves(args)],
             "devices": [str(d.device_kind) for d in jax.devices()], "platform": jax.default_backend(),
             "isa": layers.cpu_vector_isa(), "cpu": cpu_signature()}
    return hashlib.sha256(json.dumps(parts, sort_keys=True, default=str).encode()).hexdigest()


def _devices(args) -> set:
    return {d for x in jax.tree.leaves(args) if hasattr(x, "sharding") for d in x.sharding.device_set}


def _compile(fn: Callable, args, static_argnums: Sequence[int]):
    """Lower and compile `fn(*args)` the usual way (through XLA's persistent cache) -> (the compiled program,
    its entry body (`_describe`), or None when it must not be kept: see the module doc). Raises ValueError for an
    executable that refers to this process or that the entry format cannot describe."""
    with compile_cache.CompileClock() as clock:
        compiled = fn.lower(*args).compile()
    if clock.compiles != 1 or clock.cache_hits:
        return compiled, None  # loaded by XLA (from its cache or this process's): cannot be serialised again
    return compiled, _describe(compiled, _dynamic(args, static_argnums))


def _load(path: str, key: str, args, static_argnums: Sequence[int], device):
    """The compiled program kept at `path` for `key`, loaded onto `device`, or None when there is none or it
    cannot be used (`compile_cache.read_entry` checks its seal before anything reads it; an entry that fails to
    load after that is removed too)."""
    body = compile_cache.read_entry(path, key)
    if body is None:
        return None
    try:
        return _rebuild(body, _dynamic(args, static_argnums), device)
    except Exception as e:  # noqa: BLE001 - an entry that cannot be loaded is re-made, never a reason to fail
        compile_cache.discard_entry(path, f"cannot be loaded ({type(e).__name__}: {e})"[:300])
        return None


def _dynamic(args, static_argnums: Sequence[int]) -> tuple:
    static = frozenset(static_argnums)
    return tuple(x for i, x in enumerate(args) if i not in static)


# ----------------------------------------------------------------------------------------------------------
# The entry body: a JSON header describing the program's inputs and outputs, then XLA's serialised executable.
# What JAX's own `serialize_executable` writes is a pickle (unpickling runs whatever it names); this writes only
# data, and rebuilds JAX's objects from it with their constructors. Each entry is checked when written: the
# header is read back and must rebuild objects equal to the compiled program's, so a JAX release whose objects
# carry more than this format says gives "not kept" (compiled as usual), never a wrong program.
# ----------------------------------------------------------------------------------------------------------

def _spec_json(spec) -> list:
    return [list(p) if isinstance(p, tuple) else p for p in spec]


def _spec(d: list) -> PartitionSpec:
    return PartitionSpec(*(tuple(p) if isinstance(p, list) else p for p in d))


def _mesh_json(mesh) -> dict:
    return {"names": list(mesh.axis_names), "sizes": [int(n) for n in mesh.axis_sizes],
            "types": [t.name for t in mesh.axis_types]}


def _mesh(d: dict, device) -> Mesh:
    """The one-device mesh `d` describes, on `device`."""
    return Mesh(np.array([device], dtype=object).reshape(d["sizes"]), tuple(d["names"]),
                axis_types=tuple(AxisType[t] for t in d["types"]))


def _sharding_json(sharding) -> dict:
    if isinstance(sharding, SingleDeviceSharding):
        return {"memory_kind": sharding.memory_kind}
    if isinstance(sharding, NamedSharding) and sharding.mesh.devices.size == 1:  # a one-device training mesh
        return {"memory_kind": sharding.memory_kind, "mesh": _mesh_json(sharding.mesh),
                "spec": _spec_json(sharding.spec)}
    raise ValueError(f"a {type(sharding).__name__} this entry format does not describe")


def _sharding(d: dict, device):
    if "mesh" not in d:
        return SingleDeviceSharding(device, memory_kind=d["memory_kind"])
    return NamedSharding(_mesh(d["mesh"], device), _spec(d["spec"]), memory_kind=d["memory_kind"])


def _aval_json(aval) -> dict:
    d = {"shape": [int(n) for n in aval.shape], "dtype": str(aval.dtype), "weak_type": bool(aval.weak_type)}
    mesh = aval.sharding.mesh
    if mesh.axis_names:  # a sharding in the type (explicit mesh axes); else the default, not written
        d.update(mesh=_mesh_json(mesh), spec=_spec_json(aval.sharding.spec))
    return d


def _aval(d: dict, device):
    sharding = {}
    if "mesh" in d:
        sharding["sharding"] = NamedSharding(_mesh(d["mesh"], device).abstract_mesh, _spec(d["spec"]))
    return jax.core.ShapedArray(tuple(d["shape"]), jnp.dtype(d["dtype"]), weak_type=d["weak_type"], **sharding)


def _layout_json(layout):
    if layout is None:
        return None
    return {"major_to_minor": list(layout.major_to_minor), "tiling": [list(t) for t in layout.tiling],
            "sub_byte_element_size_in_bits": int(layout.sub_byte_element_size_in_bits)}


def _layout(d):
    if d is None:
        return None
    return Layout(tuple(d["major_to_minor"]), tiling=tuple(tuple(t) for t in d["tiling"]),
                  sub_byte_element_size_in_bits=d["sub_byte_element_size_in_bits"])


def _strings(value):
    return list(value) if isinstance(value, (tuple, list)) and all(isinstance(v, str) for v in value) else None


def _node_table(tree) -> list:
    """The (type, aux data) of every inner node of `tree`, in pre-order: what an output node may refer to."""
    table = []

    def walk(t):
        if jax.tree_util.treedef_is_leaf(t) and t.num_leaves == 1:
            return
        table.append(t.node_data())
        for child in t.children():
            walk(child)

    walk(tree)
    return table


def _same_node(a, b) -> bool:
    try:
        return a[0] is b[0] and bool(a[1] == b[1])
    except Exception:  # noqa: BLE001 - aux data without a plain equality: not the same node
        return False


def _tree_json(tree, table: list):
    """`tree` (a PyTreeDef) as JSON: "*" for a leaf, tuples / lists / dicts with string keys / None spelled out,
    any other node (a registered class: optax states, flax's State) as a reference to the same node of the
    input tree `table` (`_node_table`). ValueError for a node found in neither."""
    if jax.tree_util.treedef_is_leaf(tree) and tree.num_leaves == 1:
        return "*"
    typ, aux = tree.node_data()
    children = [_tree_json(c, table) for c in tree.children()]
    if typ in (tuple, list) and aux is None:
        return {"t": typ.__name__, "c": children}
    if typ is type(None):
        return {"t": "none"}
    if typ is dict and all(isinstance(k, str) for k in aux):
        return {"t": "dict", "k": list(aux), "c": children}
    for i, node in enumerate(table):
        if _same_node(node, (typ, aux)):
            return {"r": i, "c": children}
    raise ValueError(f"the output tree has a {typ.__name__} node that is not among the inputs")


def _tree(d, table: list):
    if d == "*":
        return jax.tree.structure(0)
    children = [_tree(c, table) for c in d.get("c", [])]
    if "r" in d:
        node = table[d["r"]]
    else:
        node = {"tuple": (tuple, None), "list": (list, None), "none": (type(None), None)}.get(d["t"])
        if d["t"] == "dict":
            node = (dict, list(d["k"]))
    return jax.tree_util.PyTreeDef.from_node_data_and_children(tree_util.default_registry, node, children)


def _describe(compiled, dyn_args) -> bytes:
    """The entry body of `compiled` (see above); ValueError when the format cannot describe it exactly."""
    unloaded = getattr(compiled._executable, "_unloaded_executable", None)
    if unloaded is None:
        raise ValueError("this compiled program has no serialisable executable")
    if unloaded.host_callbacks or unloaded.keepalive or unloaded.ordered_effects or unloaded.unordered_effects:
        raise ValueError("the program has host callbacks or side effects, which refer to this process")
    if (getattr(unloaded, "mut", None) is not None or getattr(unloaded, "pgle_profiler", None) is not None
            or compiled._params.const_args or len(unloaded.device_list) != 1):
        raise ValueError("the program carries state this entry format does not describe")
    args_info_flat, in_tree = jax.tree_util.tree_flatten(compiled.args_info)
    if in_tree != jax.tree.structure((dyn_args, {})):
        raise ValueError("the compiled program's inputs are not its arguments' tree")
    info = unloaded.all_args_info
    header = {
        "format": FORMAT, "name": unloaded.name, "committed": bool(unloaded.committed),
        "kept_var_idx": sorted(int(i) for i in unloaded.kept_var_idx),
        "input_avals": [_aval_json(a) for a in unloaded.input_avals],
        "output_avals": [_aval_json(a) for a in unloaded.output_avals],
        "input_shardings": [_sharding_json(x) for x in unloaded.input_shardings],
        "output_shardings": [_sharding_json(x) for x in unloaded.output_shardings],
        "xla_in_layouts": [_layout_json(x) for x in unloaded.xla_in_layouts],
        "dispatch_in_layouts": [_layout_json(x) for x in unloaded.dispatch_in_layouts],
        "xla_out_layouts": [_layout_json(x) for x in unloaded.xla_out_layouts],
        "all_args_info": None if info is None else {
            "in_avals": [_aval_json(a) for a in info.in_avals],
            "traced_for": info.debug_info.traced_for, "func_src_info": info.debug_info.func_src_info,
            "arg_names": _strings(info.debug_info.arg_names),
            "result_paths": _strings(info.debug_info.result_paths)},
        "args_info": [[_aval_json(a._aval), bool(a.donated)] for a in args_info_flat],
        "no_kwargs": bool(compiled._no_kwargs),
        "out_tree": _tree_json(compiled.out_tree, _node_table(in_tree)),
    }
    text = json.dumps(header, sort_keys=True).encode()
    executable = unloaded.xla_executable
    code = (executable.client.serialize_executable(executable) if hasattr(executable, "client")
            else executable.serialize())
    body = len(text).to_bytes(8, "little") + text + code
    # Read it back now: what this format cannot say must not come back as a different program next time.
    device = next(iter(unloaded.device_list))
    fields, args_info, out_tree = _fields(header, in_tree, device)
    for name, value in fields.items():
        if name != "all_args_info" and value != getattr(unloaded, name):
            raise ValueError(f"the entry format does not reproduce the program's {name}")
    if args_info != args_info_flat or out_tree != compiled.out_tree:
        raise ValueError("the entry format does not reproduce the program's argument or output trees")
    return body


def _fields(header: dict, in_tree, device):
    """The UnloadedMeshExecutable fields (without the executable), the flat ArgInfo list and the output tree
    that `header` describes for inputs of tree `in_tree` on `device`."""
    info = header["all_args_info"]
    all_args_info = None
    if info is not None:
        debug = DebugInfo(info["traced_for"], info["func_src_info"],
                          None if info["arg_names"] is None else tuple(info["arg_names"]),
                          None if info["result_paths"] is None else tuple(info["result_paths"]))
        all_args_info = pxla.AllArgsInfo([_aval(a, device) for a in info["in_avals"]], debug)
    fields = dict(
        name=header["name"], committed=header["committed"], kept_var_idx=set(header["kept_var_idx"]),
        input_avals=[_aval(a, device) for a in header["input_avals"]],
        output_avals=[_aval(a, device) for a in header["output_avals"]],
        input_shardings=[_sharding(x, device) for x in header["input_shardings"]],
        output_shardings=[_sharding(x, device) for x in header["output_shardings"]],
        xla_in_layouts=[_layout(x) for x in header["xla_in_layouts"]],
        dispatch_in_layouts=[_layout(x) for x in header["dispatch_in_layouts"]],
        xla_out_layouts=[_layout(x) for x in header["xla_out_layouts"]],
        unordered_effects=[], ordered_effects=[], keepalive=[], host_callbacks=[], mut=None, pgle_profiler=None,
        all_args_info=all_args_info)
    args_info = [jax.stages.ArgInfo(_aval(a, device), donated) for a, donated in header["args_info"]]
    out_tree = _tree(header["out_tree"], _node_table(in_tree))
    return fields, args_info, out_tree


def _rebuild(body: bytes, dyn_args, device):
    """The `jax.stages.Compiled` an entry body describes, for arguments `dyn_args` on `device`."""
    size = int.from_bytes(body[:8], "little")
    header = json.loads(body[8:8 + size])
    if header.get("format") != FORMAT:
        raise ValueError(f"an entry of format {header.get('format')}, not {FORMAT}")
    in_tree = jax.tree.structure((dyn_args, {}))
    fields, args_info, out_tree = _fields(header, in_tree, device)
    backend = device.client
    devices = xla_client.DeviceList((device,))
    executable = backend.deserialize_executable(body[8 + size:], executable_devices=devices)
    unloaded = pxla.UnloadedMeshExecutable(xla_executable=executable, device_list=devices, backend=backend,
                                           **fields)
    return jax.stages.Compiled(unloaded.load(), [], in_tree.unflatten(args_info), out_tree,
                               no_kwargs=header["no_kwargs"])


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
    compiled = _load(path, key, args, static_argnums, next(iter(devices)))
    if compiled is not None:
        stats["cache"] = "hit"
    else:
        try:
            compiled, entry = _compile(fn, args, static_argnums)
        except Exception as e:  # noqa: BLE001 - a program whose executable cannot be kept is jitted as before
            stats.update(cache="off", cache_error=f"{type(e).__name__}: {e}"[:500])
            return fn
        if entry is None:
            stats.update(cache="off", cache_error="XLA loaded this program from its own cache; not kept again")
        else:
            try:
                files.write_bytes(path, compile_cache.seal(key, entry))
                stats["cache"] = "written"
            except OSError as e:  # a full or read-only folder: this run still uses what it just compiled
                warnings.warn(f"could not write the compiled-program cache entry {path}: {e.strerror or e}",
                              compile_cache.CacheWarning, stacklevel=2)
                stats["cache"] = "off"
    if not static_argnums:
        return compiled
    static = frozenset(static_argnums)
    return lambda *a: compiled(*(x for i, x in enumerate(a) if i not in static))


__all__ = ["cached_compile", "entry_key", "source_fingerprint", "SUFFIX"]
