"""Convert an upstream BridgeDepthFlow PyTorch checkpoint (`.pth`) into a bridge_jax params checkpoint.

Example:

    bridge-convert --from monodepth_ver_a.pth --out checkpoints/ver_a
    bridge-predict --checkpoint checkpoints/ver_a lt.png rt.png lt1.png rt1.png --out out/

Output: `OUT/model.json` (the model config) + `OUT/params/` (orbax), the params-only layout that evaluate,
predict, export and `config.init_from` read.

Accepts a bare `state_dict` (as `torch.save(net.state_dict())`) or an upstream epoch checkpoint (a dict with
`state_dict`, `optimizer`, `scheduler`, `epoch`), in PyTorch's zip format (torch >= 1.6) or its legacy
pickle stream (torch 1.0, which upstream used). The model (`resnet_md` / `pwcnet`) and, for resnet_md, its
widths and depths are read off the key names and shapes.

**Safety / no torch needed.** The file is read with a restricted unpickler written here: it rebuilds tensors
as numpy arrays and turns every other pickled global (e.g. the pickled LR scheduler object in training dicts)
into an inert placeholder, so no code from the file is executed and PyTorch need not be installed. What it
allocates is bounded: every storage's and tensor's byte size is computed from its header, shape and stride
before anything is read or allocated, and a tensor that is no plain view of its storage (reads past it,
negative strides, a stride 0 expanding one element, more elements than the storage) or a storage over 4 GiB is
one error line ("<file>: tensor <key> claims <N> GiB from a <M> B storage (...)"). All storages and tensors of
one file together may take at most 2 GiB (`MAX_FILE_BYTES`; the largest upstream epoch checkpoint, weights plus
Adam state, takes under 1 GiB). A zip file's directory is checked before any member is decompressed: members
declaring more than that in all, or one expanding more than 100:1 (`MAX_COMPRESSION_RATIO`; torch.save does not
compress at all), are refused ("<file>: zip member <name> expands <N> KiB to <M> GiB (...)").

Conversion is all-or-nothing: every expected tensor must be present with the right shape and no
unexpected tensor may remain; otherwise the missing / unexpected / mismatched keys are reported by name and
nothing is written. Weights holding NaN/Inf are refused the same way (the error names the first such
parameter). Conv weights go OIHW -> HWIO (permute 2, 3, 1, 0); transposed-conv weights
(in, out, kh, kw) -> (kh, kw, in, out).
"""
from __future__ import annotations

import io
import os
import pickle
import struct
import sys
import zipfile
import zlib
from collections import OrderedDict
from pathlib import Path
from typing import Any

import jax
import ml_dtypes
import numpy as np

from bridge_jax import checkpointing, cli, models

# --------------------------------------------------------------------------------------------------------
# Reading .pth files without torch (restricted unpickler)
# --------------------------------------------------------------------------------------------------------

_STORAGE_DTYPES = {
    "FloatStorage": np.float32, "DoubleStorage": np.float64, "HalfStorage": np.float16,
    "LongStorage": np.int64, "IntStorage": np.int32, "ShortStorage": np.int16, "CharStorage": np.int8,
    "ByteStorage": np.uint8, "BoolStorage": np.bool_, "UntypedStorage": np.uint8,
}
_LEGACY_MAGIC = 0x1950A86A20F9469CFC6C
_LEGACY_PROTOCOL = 1001


class CheckpointFormatError(ValueError):
    """The file is not a readable PyTorch checkpoint / not an upstream BridgeDepthFlow checkpoint."""


class _Opaque:
    """Inert stand-in for any pickled global we do not trust (scheduler objects, optimizers, ...)."""

    _qualname = "?"

    def __init__(self, *args, **kwargs):
        self._args = args

    def __setstate__(self, state):
        self._state = state

    def __setitem__(self, key, value):
        pass

    def append(self, value):
        pass

    def extend(self, values):
        pass

    def __repr__(self):
        return f"<unpickled placeholder for {self._qualname}>"


class _StorageType:
    def __init__(self, name: str):
        if name == "BFloat16Storage":
            self.dtype = np.dtype(ml_dtypes.bfloat16)
        else:
            self.dtype = np.dtype(_STORAGE_DTYPES[name])
        self.name = name


class _Storage:
    """A storage record from a persistent id; `data` (1-D numpy) is filled when the bytes are read. `budget`: the
    file's `_Budget`, charged for the bytes read and for each tensor materialised from this storage."""

    def __init__(self, dtype: np.dtype, numel: int, budget: _Budget):
        self.dtype, self.numel, self.data, self.budget = dtype, numel, None, budget
        self.base: _Storage | None = None
        self.base_offset = 0

    def array(self) -> np.ndarray:
        if self.base is not None:
            return self.base.array()[self.base_offset:self.base_offset + self.numel]
        if self.data is None:
            raise CheckpointFormatError("tensor storage data missing from the file")
        return self.data


# No tensor of an upstream checkpoint comes near this (the largest, a decoder conv, is ~9 MiB): a file claiming
# more is corrupt or crafted, and is refused before anything of that size is allocated.
MAX_TENSOR_BYTES = 4 * 2**30

# What reading one file may allocate for its storages and tensors together. The largest upstream file, a resnet_md
# epoch checkpoint, holds 234 MB of weights and twice that of Adam state, and reading it copies the weights once
# more (under 1 GiB in all); a bound per tensor alone would let eight 4 GiB storages ask for 32 GiB.
MAX_FILE_BYTES = 2 * 2**30

# torch.save writes its zip members uncompressed, and float weights re-zipped shrink by ~10%; deflating zeros
# reaches ~1000:1, so a few MB of file could otherwise make the reader inflate gigabytes before the size bounds
# see the result. Members of at most MAX_RATIO_FREE_BYTES are not held to the ratio: a small all-zero bias in a
# re-zipped file compresses as well and costs nothing.
MAX_COMPRESSION_RATIO = 100
MAX_RATIO_FREE_BYTES = 2**20

# Storage bytes are read in pieces of this size into one array of the declared size: zipfile's read() of a whole
# member concatenates bytes objects, holding the member two or three times over.
_READ_CHUNK = 16 * 2**20


def _size_text(nbytes: int) -> str:
    """`149 GiB`, `12.5 MiB`, `1020 KiB`, `400 B`."""
    for unit, scale in (("GiB", 2**30), ("MiB", 2**20), ("KiB", 2**10)):
        if nbytes >= scale:
            value = nbytes / scale
            return f"{value:.3g} {unit}" if value < 1000 else f"{value:.0f} {unit}"  # .3g: 1020 -> 1.02e+03
    return f"{nbytes} B"


class _Budget:
    """The bytes one file's storages and tensors have taken so far, bounded by `MAX_FILE_BYTES` (read at each
    charge, so that tests can lower it)."""

    def __init__(self):
        self.used = 0

    def charge(self, nbytes: int, what: str = "") -> None:
        """Count `nbytes` about to be allocated for `what` ("storage 3"; "" where the caller names it), or raise
        CheckpointFormatError when that would pass the bound (before anything is allocated)."""
        total = self.used + nbytes
        if total > MAX_FILE_BYTES:
            raise CheckpointFormatError(f"{what + ' ' if what else ''}takes {_size_text(nbytes)}, which brings the "
                                        f"file's storages and tensors to {_size_text(total)}, over the "
                                        f"{_size_text(MAX_FILE_BYTES)} limit of one file")
        self.used = total


class _LazyTensor:
    """A tensor to be materialised from its storage (after legacy files have read their storage bytes)."""

    def __init__(self, storage: _Storage, offset: int, size: tuple, stride: tuple):
        self.storage, self.offset, self.size, self.stride = storage, int(offset), tuple(size), tuple(stride)

    def _refusal(self, base: np.ndarray) -> str:
        """Why the tensor cannot be a view of its storage `base` (without allocating anything), or "". Its
        byte size is computed from the shape alone; each dimension's stride, the offset and the storage's size
        must make it an in-bounds view that repeats no element (a stride 0 on a dimension > 1 would expand a
        tiny storage into the shape's full size)."""
        size, stride = self.size, self.stride
        if len(stride) != len(size) or any(not isinstance(v, int) for v in (*size, *stride)):
            return "a shape and stride that do not match"
        if any(n < 0 for n in size):
            return "a negative dimension"
        numel = int(np.prod(size, dtype=object)) if size else 1
        nbytes = numel * base.itemsize
        why = ""
        if numel == 0:
            return ""
        if self.offset < 0 or any(s < 0 for n, s in zip(size, stride) if n > 1):
            why = "a negative offset or stride"
        elif any(s == 0 for n, s in zip(size, stride) if n > 1):
            why = "a stride 0 that repeats one element over a dimension"
        elif self.offset + sum((n - 1) * s for n, s in zip(size, stride)) >= base.size:
            why = "reads past the end of its storage"
        elif numel > base.size:
            why = "more elements than its storage holds"
        elif nbytes > MAX_TENSOR_BYTES:
            why = f"over the {_size_text(MAX_TENSOR_BYTES)} limit of one tensor"
        if why:
            return f"claims {_size_text(nbytes)} from a {_size_text(base.size * base.itemsize)} storage ({why})"
        return ""

    def numpy(self) -> np.ndarray:
        base = self.storage.array()
        why = self._refusal(base)
        if why:
            raise CheckpointFormatError(why)
        if any(n == 0 for n in self.size):
            return np.zeros(self.size, base.dtype)
        if not self.size:
            return np.array(base[self.offset])
        # each tensor is a copy: many tensors viewing one large storage would otherwise multiply it unbounded
        self.storage.budget.charge(int(np.prod(self.size, dtype=object)) * base.itemsize)
        item = base.itemsize
        view = np.lib.stride_tricks.as_strided(base[self.offset:], shape=self.size,
                                               strides=tuple(s * item for s in self.stride))
        return np.array(view)


def _rebuild_tensor(storage, storage_offset, size, stride, *unused):
    if not isinstance(storage, _Storage):
        raise CheckpointFormatError("tensor without a storage")
    return _LazyTensor(storage, storage_offset, size, stride)


def _rebuild_parameter(data, *unused):
    return data


def _rebuild_from_type_v2(func, new_type, args, state):
    if func not in (_rebuild_tensor, _rebuild_parameter):
        return _Opaque()
    return func(*args)


_SAFE_GLOBALS = {
    ("collections", "OrderedDict"): OrderedDict,
    ("torch._utils", "_rebuild_tensor_v2"): _rebuild_tensor,
    ("torch._utils", "_rebuild_tensor"): _rebuild_tensor,
    ("torch._utils", "_rebuild_parameter"): _rebuild_parameter,
    ("torch._utils", "_rebuild_parameter_with_state"): _rebuild_parameter,
    ("torch._tensor", "_rebuild_from_type_v2"): _rebuild_from_type_v2,
    ("builtins", "set"): set, ("builtins", "frozenset"): frozenset, ("builtins", "slice"): slice,
    ("builtins", "complex"): complex,
    ("__builtin__", "set"): set,
}


class _RestrictedUnpickler(pickle.Unpickler):
    def __init__(self, file, persistent_load):
        super().__init__(file)
        self._persistent = persistent_load

    def find_class(self, module, name):
        if (module, name) in _SAFE_GLOBALS:
            return _SAFE_GLOBALS[(module, name)]
        # GPU-saved checkpoints (upstream trained on CUDA) name their storages torch.cuda.FloatStorage etc.
        if module in ("torch", "torch.storage", "torch.cuda") and (name in _STORAGE_DTYPES or name == "BFloat16Storage"):
            return _StorageType(name)
        return type(name, (_Opaque,), {"_qualname": f"{module}.{name}"})

    def persistent_load(self, pid):
        return self._persistent(pid)


def _storage_from_pid(pid, storages: dict, budget: _Budget) -> _Storage:
    if not isinstance(pid, tuple) or len(pid) < 5 or pid[0] != "storage":
        raise CheckpointFormatError(f"unsupported persistent id {pid!r:.80}")
    stype, key, numel = pid[1], str(pid[2]), int(pid[4])
    if not isinstance(stype, _StorageType):
        raise CheckpointFormatError(f"unsupported storage type {stype!r:.80}")
    if key not in storages:
        storages[key] = _Storage(stype.dtype, numel, budget)
    root = storages[key]
    view = pid[5] if len(pid) > 5 else None
    if view is not None:  # legacy views: (view_key, offset, size) into the root storage
        vkey, offset, vsize = view
        if vkey not in storages:
            s = _Storage(stype.dtype, int(vsize), budget)
            s.base, s.base_offset = root, int(offset)
            storages[vkey] = s
        return storages[vkey]
    return root


def _read_storage_bytes(f, nbytes: int, dtype: np.dtype, little: bool, key: str) -> np.ndarray:
    """At most `nbytes` from the binary file `f` as a 1-D array of `dtype` stored with the given byte order,
    allocated once at `nbytes` (the caller has bounded and charged it) and filled in `_READ_CHUNK` pieces; fewer
    bytes when the file ends sooner."""
    buf = np.empty(nbytes, np.uint8)
    pos = 0
    while pos < nbytes:
        chunk = f.read(min(_READ_CHUNK, nbytes - pos))
        if not chunk:
            break
        buf[pos:pos + len(chunk)] = np.frombuffer(chunk, np.uint8)
        pos += len(chunk)
    buf = buf[:pos]
    if pos % dtype.itemsize:
        raise CheckpointFormatError(f"storage {key} holds {pos} B, not a whole number of {dtype.itemsize}-byte "
                                    f"elements")
    stored = dtype.newbyteorder("<" if little else ">")
    data = buf.view(stored)
    if not stored.isnative:  # swapped in place: no second copy of the storage
        data = data.byteswap(inplace=True).view(stored.newbyteorder())
    return data.view(dtype)


def _check_zip_directory(zf: zipfile.ZipFile) -> None:
    """Refuse an archive from its directory alone, before any member is decompressed: a member expanding more
    than `MAX_COMPRESSION_RATIO` (and to more than `MAX_RATIO_FREE_BYTES`), or members declaring more than
    `MAX_FILE_BYTES` in all. The declared size is what zipfile decompresses a member to at most."""
    total = 0
    for info in zf.infolist():
        total += info.file_size
        if info.file_size > max(MAX_RATIO_FREE_BYTES, MAX_COMPRESSION_RATIO * info.compress_size):
            raise CheckpointFormatError(
                f"zip member {info.filename} expands {_size_text(info.compress_size)} to "
                f"{_size_text(info.file_size)} ({info.file_size / max(info.compress_size, 1):.0f}:1, over the "
                f"{MAX_COMPRESSION_RATIO}:1 limit of the compression ratio of a member)")
    if total > MAX_FILE_BYTES:
        raise CheckpointFormatError(f"zip members declare {_size_text(total)} in all, over the "
                                    f"{_size_text(MAX_FILE_BYTES)} limit of one file")


def _load_zip(path: Path) -> Any:
    with zipfile.ZipFile(path) as zf:
        _check_zip_directory(zf)
        names = zf.namelist()
        pkl = [n for n in names if n.endswith("data.pkl") and n.count("/") == 1]
        if not pkl:
            what = "a TorchScript archive" if any(n.endswith("constants.pkl") for n in names) else "a zip file"
            raise CheckpointFormatError(f"{what} without data.pkl, not a torch.save() checkpoint")
        prefix = pkl[0][: -len("data.pkl")]
        order = "little"
        if prefix + "byteorder" in names:
            order = zf.read(prefix + "byteorder").decode().strip()
        storages: dict[str, _Storage] = {}
        budget = _Budget()

        def persistent_load(pid):
            st = _storage_from_pid(pid, storages, budget)
            if st.data is None and st.base is None:
                key = str(pid[2])
                try:
                    info = zf.getinfo(f"{prefix}data/{key}")
                except KeyError as e:
                    raise CheckpointFormatError(f"storage {key} missing from the archive") from e
                claim = max(info.file_size, st.numel * st.dtype.itemsize)
                if claim > MAX_TENSOR_BYTES:  # checked before decompressing anything
                    raise CheckpointFormatError(f"storage {key} claims {_size_text(claim)} (over the "
                                                f"{_size_text(MAX_TENSOR_BYTES)} limit of one tensor)")
                budget.charge(info.file_size, f"storage {key}")
                with zf.open(info) as f:
                    st.data = _read_storage_bytes(f, info.file_size, st.dtype, order == "little", key)
            return st

        return _RestrictedUnpickler(io.BytesIO(zf.read(pkl[0])), persistent_load).load()


def _load_legacy(path: Path) -> Any:
    storages: dict[str, _Storage] = {}
    budget = _Budget()
    size = path.stat().st_size
    with open(path, "rb") as f:
        def plain():
            return _RestrictedUnpickler(f, lambda pid: None).load()

        if plain() != _LEGACY_MAGIC:
            raise CheckpointFormatError("a pickle file that is not a torch.save() checkpoint (no magic number)")
        if plain() != _LEGACY_PROTOCOL:
            raise CheckpointFormatError("unsupported legacy torch protocol version")
        sys_info = plain()
        little = not isinstance(sys_info, dict) or sys_info.get("little_endian", True)
        result = _RestrictedUnpickler(f, lambda pid: _storage_from_pid(pid, storages, budget)).load()
        keys = plain()
        for key in keys:
            st = storages.get(str(key))
            if st is None:
                raise CheckpointFormatError(f"storage {key} listed but never referenced")
            head = f.read(8)
            if len(head) != 8:
                raise CheckpointFormatError("file truncated in the tensor data")
            (numel,) = struct.unpack("<q" if little else ">q", head)
            nbytes = numel * st.dtype.itemsize
            if numel < 0 or nbytes > min(MAX_TENSOR_BYTES, size - f.tell()):  # before reading (allocating) it
                raise CheckpointFormatError(f"storage {key} claims {_size_text(max(nbytes, 0))}, more than "
                                            + ("the rest of the file holds" if nbytes <= MAX_TENSOR_BYTES else
                                               f"the {_size_text(MAX_TENSOR_BYTES)} limit of one tensor"))
            budget.charge(nbytes, f"storage {key}")
            st.data = _read_storage_bytes(f, nbytes, st.dtype, little, str(key))
            if st.data.size != numel:
                raise CheckpointFormatError("file truncated in the tensor data")
            st.numel = numel
    return result


def read_torch_file(path: str | Path) -> Any:
    """Unpickle a `torch.save` file safely; tensors come back as `_LazyTensor` (see `materialize`).

    Raises CheckpointFormatError, its message starting with the file name."""
    name = os.fspath(path)
    path = Path(path)
    if not path.is_file():
        raise CheckpointFormatError(f"{name}: no such file")
    with open(path, "rb") as f:
        head = f.read(4)
    try:
        if head[:2] == b"PK":
            return _load_zip(path)
        if head[:1] == b"\x80":
            return _load_legacy(path)
    except CheckpointFormatError as e:
        raise CheckpointFormatError(f"{name}: {e}") from e
    except (pickle.UnpicklingError, EOFError, zipfile.BadZipFile, zlib.error, ValueError, TypeError, KeyError) as e:
        raise CheckpointFormatError(f"{name}: corrupt or unsupported torch file ({type(e).__name__}: {e})") from e
    raise CheckpointFormatError(f"{name}: not a PyTorch checkpoint (starts with bytes {head!r})")


def materialize(obj: Any) -> Any:
    """Replace every lazy tensor in nested dicts / lists / tuples with a numpy array."""
    if isinstance(obj, _LazyTensor):
        return obj.numpy()
    if isinstance(obj, dict):
        return {k: materialize(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return type(obj)(materialize(v) for v in obj)
    return obj


def load_state_dict(path: str | Path) -> dict[str, np.ndarray]:
    """Read an upstream checkpoint and return its state dict as `{torch key: numpy array}`.

    Accepts a bare state dict or a training dict with a `state_dict` entry (other entries, e.g. the pickled
    scheduler, are never materialised). A DataParallel `module.` prefix is stripped.
    Raises CheckpointFormatError (a ValueError) describing what was found otherwise.
    """
    obj = read_torch_file(path)
    if not isinstance(obj, dict):
        raise CheckpointFormatError(f"{path}: top-level object is {type(obj).__name__}, expected a state dict "
                                    f"or a training dict with 'state_dict'")
    if "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    tensors = {k: v for k, v in obj.items() if isinstance(v, _LazyTensor)}
    if not tensors or len(tensors) != len(obj) or not all(isinstance(k, str) for k in obj):
        keys = ", ".join(repr(k) for k in list(obj)[:8])
        raise CheckpointFormatError(f"{path}: a dict with keys [{keys}{', ...' if len(obj) > 8 else ''}] is not "
                                    f"a state dict of tensors (nor a training dict with 'state_dict')")
    if all(k.startswith("module.") for k in tensors):
        tensors = {k[len("module."):]: v for k, v in tensors.items()}
    arrays = {}
    for k, v in tensors.items():
        try:
            arrays[k] = v.numpy()
        except CheckpointFormatError as e:
            raise CheckpointFormatError(f"{path}: tensor {k} {e}") from None
    return arrays


# --------------------------------------------------------------------------------------------------------
# Upstream key names <-> bridge_jax params
# --------------------------------------------------------------------------------------------------------

class ConversionError(ValueError):
    """Keys missing / unexpected / mis-shaped: nothing is written."""


def detect_model(state_dict: dict) -> str:
    if "conv1.weight" in state_dict and "up1.conv1.weight" in state_dict:
        return "resnet_md"
    if "conv1a.0.weight" in state_dict:
        return "pwcnet"
    keys = ", ".join(list(state_dict)[:6])
    raise ConversionError(f"not an upstream BridgeDepthFlow model: no MonodepthNet or PWCDCNet keys (found {keys}, ...)")


def infer_model_config(state_dict: dict, name: str | None = None) -> dict:
    """The bridge_jax model config whose shapes an upstream state dict has (resnet_md widths/depths read off)."""

    name = name or detect_model(state_dict)
    if name not in ("resnet_md", "resnet_md_tiny"):
        return models.model_config(name)
    try:
        planes = [int(state_dict[f"layer{s}.0.conv1.weight"].shape[0]) for s in range(1, 5)]
        blocks = []
        for s in range(1, 5):
            idx = {int(k.split(".")[1]) for k in state_dict if k.startswith(f"layer{s}.") and k.split(".")[1].isdigit()}
            blocks.append(max(idx) + 1)
        cfg = dict(stem=int(state_dict["conv1.weight"].shape[0]), planes=planes, blocks=blocks,
                   expansion=int(state_dict["layer1.0.conv3.weight"].shape[0]) // planes[0],
                   decoder=[int(state_dict[f"up{k}.conv1.weight"].shape[0]) for k in range(6, 0, -1)])
    except (KeyError, IndexError, ValueError):
        return models.model_config("resnet_md")  # let the key check report what is missing
    for candidate in ("resnet_md", "resnet_md_tiny"):
        base = models.model_config(candidate)
        if all(base[k] == v for k, v in cfg.items()):
            return base
    return models.model_config("resnet_md", **cfg)


def _torch_key(path: tuple[str, ...]) -> str:
    parts = []
    for p in path:
        if p == "kernel":
            parts.append("weight")
        elif p == "shortcut":
            parts.append("shortcut.0")
        elif p == "conv":  # pwcnet `myconv` = Sequential(conv, LeakyReLU): the conv is child "0"
            parts.append("0")
        else:
            parts.append(p)
    return ".".join(parts)


def expected_keys(model_cfg: dict) -> dict[str, tuple[tuple[str, ...], tuple[int, ...], str]]:
    """`{torch key: (params path, torch shape, kind)}` for a model config; kind in {"conv", "deconv", "bias"}."""

    _, abstract = models.abstract_init(model_cfg)
    out = {}
    for kp, leaf in jax.tree_util.tree_flatten_with_path(abstract)[0]:
        path = tuple(str(k.key) for k in kp)
        shape = tuple(leaf.shape)
        if path[-1] == "bias":
            kind, tshape = "bias", shape
        elif path[0].startswith(("deconv", "upfeat")):
            kind, tshape = "deconv", (shape[2], shape[3], shape[0], shape[1])
        else:
            kind, tshape = "conv", (shape[3], shape[2], shape[0], shape[1])
        out[_torch_key(path)] = (path, tshape, kind)
    return out


def convert_state_dict(state_dict: dict[str, np.ndarray], model_cfg: dict | None = None) -> tuple[dict, dict]:
    """Map an upstream state dict onto bridge_jax params.

    Returns:
      `(model_cfg, params)`: params a nested dict of float32 numpy arrays (HWIO kernels).
    Raises:
      ConversionError listing missing, unexpected and shape-mismatched keys by name.
    """
    if model_cfg is None:
        model_cfg = infer_model_config(state_dict)
    expect = expected_keys(model_cfg)
    missing = [k for k in expect if k not in state_dict]
    unexpected = [k for k in state_dict if k not in expect]
    mismatched = [f"{k}: file {tuple(state_dict[k].shape)} vs model {expect[k][1]}"
                  for k in expect if k in state_dict and tuple(state_dict[k].shape) != expect[k][1]]
    if missing or unexpected or mismatched:
        def show(title, items):
            if not items:
                return ""
            more = f" (+{len(items) - 20} more)" if len(items) > 20 else ""
            return f"{title} ({len(items)}): " + ", ".join(items[:20]) + more

        parts = [show("missing", missing), show("unexpected", unexpected), show("shape mismatch", mismatched)]
        raise ConversionError(f"checkpoint does not match model {model_cfg['name']} (nothing written): "
                              + "; ".join(p for p in parts if p))
    params: dict = {}
    for key, (path, _, kind) in expect.items():
        v = np.asarray(state_dict[key], dtype=np.float32)
        if kind == "conv":
            v = v.transpose(2, 3, 1, 0)
        elif kind == "deconv":
            v = v.transpose(2, 3, 0, 1)
        node = params
        for p in path[:-1]:
            node = node.setdefault(p, {})
        node[path[-1]] = np.ascontiguousarray(v)
    return model_cfg, params


def convert(src: str | Path, out: str | Path, *, model: str | None = None, overwrite: bool = False) -> dict:
    """Read `src` (.pth), convert, and write a params checkpoint to `out`. Returns a summary dict.

    All-or-nothing: unreadable files, key / shape mismatches and non-finite weights raise a ValueError
    naming `src` (and the keys or the parameter) before anything is written.
    """
    try:
        sd = load_state_dict(src)
        cfg = infer_model_config(sd, model)
        cfg, params = convert_state_dict(sd, cfg)
        # NaN/Inf upstream weights would only turn every prediction and every fine-tuning step into NaN
        checkpointing.check_finite_params(params, str(src))
    except ValueError as e:
        if str(src) in str(e):
            raise
        cls = type(e) if isinstance(e, (CheckpointFormatError, ConversionError)) else ValueError
        raise cls(f"{src}: {e}") from e  # every error line names the file it is about
    checkpointing.save_params(out, params, cfg, overwrite=overwrite)
    return {"model": cfg["name"], "tensors": len(sd), "params": models.param_count(params), "out": str(out)}


def build_parser():
    """The `bridge-convert` argument parser (help epilog: this module's docstring)."""
    ap = cli.make_parser("bridge_jax.convert", __doc__)
    ap.add_argument("--from", dest="src", required=True, metavar="PTH",
                    help="upstream .pth checkpoint: a bare state dict or an upstream epoch dict with 'state_dict'")
    ap.add_argument("--out", required=True, metavar="DIR",
                    help="output bridge_jax params checkpoint directory (model.json + params/); must not exist "
                         "unless --overwrite")
    ap.add_argument("--model", choices=["resnet_md", "pwcnet"], default=None,
                    help="model type; when omitted it is detected from the key names (resnet_md widths and depths "
                         "are read off the shapes either way)")
    ap.add_argument("--overwrite", action="store_true",
                    help="replace --out if it exists (the old directory is replaced only once the new one is complete)")
    cli.add_debug_flag(ap)
    return ap


@cli.entry_point
def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        summary = convert(args.src, args.out, model=args.model, overwrite=args.overwrite)
    except (ValueError, OSError) as e:  # FileExistsError is an OSError; files.OutputExistsError a ValueError
        return cli.report_error(e, debug=args.debug)
    print(f"converted {summary['tensors']} tensors ({summary['params']:,} params, model {summary['model']}) "
          f"-> {summary['out']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
