"""Upstream .pth -> bridge_jax converter: file formats (written here without torch), key mapping, safety,
error reporting, and numerical parity with the upstream network (the fixture, see tests/fixture.py)."""

import io
import re
import struct
import zipfile

import jax
import numpy as np
import pytest

from bridge_jax import checkpointing, convert, models
from tests.fixture import fixture_file

# ---------------------------------------------------------------- a tiny torch.save writer (pickle protocol 2)


class _Global:
    def __init__(self, module, name):
        self.module, self.name = module, name


class _Call:
    """Pickles as GLOBAL fn + args tuple + REDUCE."""

    def __init__(self, fn, *args):
        self.fn, self.args = fn, args


class _Tensor:
    def __init__(self, key, array):
        self.key, self.array = key, np.ascontiguousarray(array, np.float32)


class _Writer:
    """Hand-written opcodes for the subset of pickle that torch.save emits for state dicts."""

    def __init__(self, legacy=False, storage_module="torch"):
        self.out = io.BytesIO()
        self.legacy = legacy
        self.storage_module = storage_module  # "torch.cuda" for checkpoints saved from GPU tensors

    def dump(self, obj):
        self.out.write(b"\x80\x02")
        self._save(obj)
        self.out.write(b".")
        return self.out.getvalue()

    def _save(self, obj):
        w = self.out.write
        if obj is None:
            w(b"N")
        elif obj is True or obj is False:
            w(b"\x88" if obj else b"\x89")
        elif isinstance(obj, int):
            if -2**31 <= obj < 2**31:
                w(b"J" + struct.pack("<i", obj))
            else:
                raw = obj.to_bytes((obj.bit_length() + 8) // 8, "little", signed=True)
                w(b"\x8a" + bytes([len(raw)]) + raw)
        elif isinstance(obj, float):
            w(b"G" + struct.pack(">d", obj))
        elif isinstance(obj, str):
            raw = obj.encode()
            w(b"X" + struct.pack("<I", len(raw)) + raw)
        elif isinstance(obj, tuple):
            w(b"(")
            for v in obj:
                self._save(v)
            w(b"t")
        elif isinstance(obj, list):
            w(b"]")
            if obj:
                w(b"(")
                for v in obj:
                    self._save(v)
                w(b"e")
        elif isinstance(obj, dict):
            self._save(_Call(_Global("collections", "OrderedDict")))
            if obj:
                w(b"(")
                for k, v in obj.items():
                    self._save(k)
                    self._save(v)
                w(b"u")
        elif isinstance(obj, _Global):
            w(f"c{obj.module}\n{obj.name}\n".encode())
        elif isinstance(obj, _Call):
            self._save(obj.fn)
            self._save(tuple(obj.args))
            w(b"R")
        elif isinstance(obj, _Tensor):
            a = obj.array
            shape, stride = getattr(obj, "layout", (tuple(a.shape), tuple(s // a.itemsize for s in a.strides)))
            location = "cuda:0" if self.storage_module == "torch.cuda" else "cpu"
            pid = ("storage", _Global(self.storage_module, "FloatStorage"), obj.key, location,
                   int(getattr(obj, "numel", a.size)))
            if self.legacy:
                pid = pid + (None,)
            self._save(_Global("torch._utils", "_rebuild_tensor_v2"))
            w(b"(")
            self._save(pid)
            w(b"Q")  # BINPERSID
            for v in (0, shape, stride, False):
                self._save(v)
            self._save(_Call(_Global("collections", "OrderedDict")))
            w(b"tR")
        else:
            raise TypeError(type(obj))


def write_pth(path, obj, tensors, legacy=False, compression=zipfile.ZIP_STORED, declare=None):
    """`obj` holds _Tensor leaves; `tensors` lists them (storage order). Zip files: `compression` for every
    member (torch.save stores them), `declare` {member: size} the uncompressed sizes their directory states."""
    if not legacy:
        with zipfile.ZipFile(path, "w", compression) as zf:
            zf.writestr("archive/data.pkl", _Writer().dump(obj))
            zf.writestr("archive/byteorder", "little")
            for t in tensors:
                zf.writestr(f"archive/data/{t.key}", t.array.tobytes())
            zf.writestr("archive/version", "3\n")
            for name, size in (declare or {}).items():
                zf.getinfo(name).file_size = size  # the central directory is written from these at close
        return
    with open(path, "wb") as f:
        f.write(_Writer().dump(0x1950A86A20F9469CFC6C))
        f.write(_Writer().dump(1001))
        f.write(_Writer().dump({"protocol_version": 1001, "little_endian": True}))
        f.write(_Writer(legacy=True, storage_module="torch.cuda").dump(obj))  # upstream: torch 1.0, GPU
        f.write(_Writer().dump([t.key for t in tensors]))
        for t in tensors:
            f.write(struct.pack("<q", t.array.size) + t.array.tobytes())


# ---------------------------------------------------------------- upstream key names, written out by hand


def upstream_shapes(stem, planes, blocks, decoder, exp=4):
    """{key: OIHW shape} of upstream MonodepthNet, from its published layer table (independent of convert.py)."""
    s = {"conv1.weight": (stem, 6, 7, 7), "conv1.bias": (stem,)}
    cin = stem
    for li, (p, n) in enumerate(zip(planes, blocks), start=1):
        for i in range(n):
            pre = f"layer{li}.{i}."
            s[pre + "conv1.weight"], s[pre + "conv1.bias"] = (p, cin, 1, 1), (p,)
            s[pre + "conv2.weight"], s[pre + "conv2.bias"] = (p, p, 3, 3), (p,)
            s[pre + "conv3.weight"], s[pre + "conv3.bias"] = (exp * p, p, 1, 1), (exp * p,)
            s[pre + "shortcut.0.weight"], s[pre + "shortcut.0.bias"] = (exp * p, cin, 1, 1), (exp * p,)
            cin = exp * p
    d6, d5, d4, d3, d2, d1 = decoder
    ups = {6: (cin, d6, d6 + exp * planes[2]), 5: (d6, d5, d5 + exp * planes[1]), 4: (d5, d4, d4 + exp * planes[0]),
           3: (d4, d3, d3 + stem + 2), 2: (d3, d2, d2 + stem + 2), 1: (d2, d1, d1 + 2)}
    for k, (i, o, mid) in ups.items():
        s[f"up{k}.conv1.weight"], s[f"up{k}.conv1.bias"] = (o, i, 3, 3), (o,)
        s[f"up{k}.conv2.weight"], s[f"up{k}.conv2.bias"] = (o, mid, 3, 3), (o,)
    for k, c in {4: d4, 3: d3, 2: d2, 1: d1}.items():
        s[f"get_disp{k}.conv1.weight"], s[f"get_disp{k}.conv1.bias"] = (2, c, 3, 3), (2,)
    return s


TINY = dict(stem=8, planes=[8, 16, 16, 32], blocks=[1, 2, 1, 1], decoder=[32, 16, 16, 8, 8, 8])


def test_full_size_key_table_matches_reference():
    want = upstream_shapes(64, [64, 128, 256, 512], [3, 4, 6, 3], [512, 256, 128, 64, 32, 16])
    assert len(want) == 162 and sum(int(np.prod(v)) for v in want.values()) == 58_461_416
    got = {k: v[1] for k, v in convert.expected_keys(models.model_config("resnet_md")).items()}
    assert got == want


def tiny_state_dict(rng):
    return {k: (rng.normal(size=shape) * 0.3).astype(np.float32) for k, shape in upstream_shapes(**TINY).items()}


def np_conv_nchw(x, w, b, stride=1):
    """Reference conv in PyTorch layout: x (N,C,H,W), w (O,I,k,k) OIHW, symmetric padding k//2."""
    k = w.shape[-1]
    p = k // 2
    xp = np.pad(x, ((0, 0), (0, 0), (p, p), (p, p)))
    ho = (x.shape[2] + 2 * p - k) // stride + 1
    wo = (x.shape[3] + 2 * p - k) // stride + 1
    out = np.zeros((x.shape[0], w.shape[0], ho, wo))
    for i in range(k):
        for j in range(k):
            patch = xp[:, :, i:i + stride * (ho - 1) + 1:stride, j:j + stride * (wo - 1) + 1:stride]
            out += np.einsum("nchw,oc->nohw", patch, w[:, :, i, j])
    return out + b[None, :, None, None]


@pytest.mark.parametrize("layout", ["zip", "legacy", "training_dict"])
def test_round_trip_first_layers_match_numpy(tmp_path, layout):
    rng = np.random.default_rng(0)
    sd = tiny_state_dict(rng)
    tensors = [_Tensor(str(i), v) for i, v in enumerate(sd.values())]
    obj = dict(zip(sd, tensors))
    marker = tmp_path / "pwned"
    if layout == "training_dict":  # upstream epoch checkpoint, with a pickled object that must not run
        evil = _Call(_Global("os", "system"), f"touch {marker}")
        obj = {"epoch": 3, "state_dict": obj, "optimizer": {"state": {}, "param_groups": [{"lr": 1e-4}]},
               "scheduler": evil}
    src = tmp_path / "up.pth"
    write_pth(src, obj, tensors, legacy=(layout != "zip"))  # upstream epoch files: torch 1.0 legacy format
    out = tmp_path / "converted"
    assert convert.main(["--from", str(src), "--out", str(out)]) == 0
    assert not marker.exists()
    cfg, params = checkpointing.read_params(out)
    assert cfg["name"] == "resnet_md_tiny"
    # bridge_jax forward (NHWC) vs numpy forward in PyTorch layout straight from the state dict
    x = rng.uniform(size=(1, 6, 64, 128))
    graphdef, _ = models.abstract_init(cfg)
    from flax import nnx
    model = nnx.merge(graphdef, nnx.State(params))
    skip1, skip2, skip3 = (np.asarray(a).transpose(0, 3, 1, 2)
                           for a in model.encode(x.transpose(0, 2, 3, 1).astype(np.float32))[:3])
    g = {k: v.astype(np.float64) for k, v in sd.items()}
    elu = lambda v: np.where(v > 0, v, np.expm1(np.minimum(v, 0)))  # noqa: E731
    r1 = elu(np_conv_nchw(x, g["conv1.weight"], g["conv1.bias"], 2))
    xp = np.pad(r1, ((0, 0), (0, 0), (1, 1), (1, 1)), constant_values=-np.inf)
    r2 = np.max([xp[:, :, i:i + 32:2, j:j + 64:2] for i in range(3) for j in range(3)], axis=0)
    y = elu(np_conv_nchw(r2, g["layer1.0.conv1.weight"], g["layer1.0.conv1.bias"]))
    y = elu(np_conv_nchw(y, g["layer1.0.conv2.weight"], g["layer1.0.conv2.bias"], 2))
    r3 = elu(np_conv_nchw(y, g["layer1.0.conv3.weight"], g["layer1.0.conv3.bias"])
             + np_conv_nchw(r2, g["layer1.0.shortcut.0.weight"], g["layer1.0.shortcut.0.bias"], 2))
    for got, ref in ((skip1, r1), (skip2, r2), (skip3, r3)):
        np.testing.assert_allclose(got, ref, rtol=1e-4, atol=1e-4)
    head = np.asarray(params["get_disp1"]["conv1"]["kernel"])
    np.testing.assert_array_equal(head, sd["get_disp1.conv1.weight"].transpose(2, 3, 1, 0))


def test_torch_saved_file_if_torch_installed(tmp_path):
    torch = pytest.importorskip("torch", reason="torch not installed (optional extra); pure-python files tested")
    sd = tiny_state_dict(np.random.default_rng(1))
    torch.save({k: torch.from_numpy(v) for k, v in sd.items()}, tmp_path / "t.pth")
    got = convert.load_state_dict(tmp_path / "t.pth")
    assert set(got) == set(sd) and all(np.array_equal(got[k], sd[k]) for k in sd)


def test_mismatches_reported_by_name_and_nothing_written(tmp_path, capsys):
    sd = tiny_state_dict(np.random.default_rng(2))
    sd.pop("up3.conv2.bias")
    sd["layer2.1.conv2.weight"] = np.zeros((16, 16, 5, 5), np.float32)
    sd["extra.weight"] = np.zeros((1,), np.float32)
    tensors = [_Tensor(str(i), v) for i, v in enumerate(sd.values())]
    src = tmp_path / "bad.pth"
    write_pth(src, dict(zip(sd, tensors)), tensors)
    out = tmp_path / "out"
    assert convert.main(["--from", str(src), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert "up3.conv2.bias" in err and "extra.weight" in err and "layer2.1.conv2.weight" in err
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())


@pytest.mark.parametrize("kind", ["text", "list", "dict_without_tensors", "npz"])
def test_not_an_upstream_checkpoint(tmp_path, capsys, kind):
    src = tmp_path / "x.pth"
    if kind == "text":
        src.write_text("hello")
    elif kind == "npz":
        np.savez(src.with_suffix(".npz"), a=np.zeros(3))
        src = src.with_suffix(".npz")
    else:
        obj = [1, 2] if kind == "list" else {"epoch": 3, "lr": 5}
        write_pth(src, obj, [])
    assert convert.main(["--from", str(src), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and err.startswith("error:")
    assert not (tmp_path / "o").exists()


def test_non_finite_weights_refused_by_name_and_nothing_written(tmp_path, capsys):
    sd = tiny_state_dict(np.random.default_rng(3))
    sd["up3.conv2.weight"][0, 0, 0, :3] = [np.nan, np.inf, -np.inf]  # OIHW: 3 bad values in one kernel
    sd["up2.conv1.weight"][1, 1, 1, 1] = np.nan  # bad too and first in tree order (up2 < up3): the one named
    tensors = [_Tensor(str(i), v) for i, v in enumerate(sd.values())]
    src = tmp_path / "nan.pth"
    write_pth(src, dict(zip(sd, tensors)), tensors)
    out = tmp_path / "out"
    assert convert.main(["--from", str(src), "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert err == f"error: {src}: parameter up2/conv1/kernel has 1 non-finite values (NaN/Inf); these weights are " \
                  "unusable (the run that wrote them diverged, or the file is corrupt)\n"
    assert not out.exists() and not any(p.name.startswith(".out") for p in tmp_path.iterdir())
    sd["up2.conv1.weight"][1, 1, 1, 1] = 0.0
    tensors = [_Tensor(str(i), v) for i, v in enumerate(sd.values())]
    write_pth(src, dict(zip(sd, tensors)), tensors)
    with pytest.raises(ValueError, match=r"^" + re.escape(f"{src}: parameter up3/conv2/kernel has 3 non-finite")):
        convert.convert(src, out)  # the library call refuses it too, naming the file
    assert not out.exists()


def test_cli_help_has_an_example_and_every_option_a_help_text(capsys):
    with pytest.raises(SystemExit) as e:
        convert.main(["--help"])
    assert e.value.code == 0
    text = capsys.readouterr().out
    assert text.startswith("usage: bridge-convert ")
    assert "\n    bridge-convert --from monodepth_ver_a.pth --out checkpoints/ver_a\n" in text
    actions = [a for a in convert.build_parser()._actions if a.option_strings]
    assert {a.dest for a in actions} == {"help", "src", "out", "model", "overwrite", "debug"}
    assert [a.dest for a in actions if not a.help] == []  # argparse keeps None where help= was left out


def test_cli_debug_shows_the_traceback(tmp_path, capsys):
    src = tmp_path / "x.pth"
    src.write_text("hello")
    assert convert.main(["--from", str(src), "--out", str(tmp_path / "o"), "--debug"]) == 2
    err = capsys.readouterr().err
    assert "Traceback (most recent call last)" in err
    assert err.strip().splitlines()[-1] == f"error: {src}: not a PyTorch checkpoint (starts with bytes b'hell')"


# ---------------------------------------------------------------- parity with upstream PyTorch (fixture)

def test_parity_with_upstream_fixture():
    """Seed-0 upstream MonodepthNet, converted: every scale's fraction and pixel maps within 1e-4.

    Runs whenever the fixture folder (tests/fixture.py) holds weights.pth, which does not ship with it."""
    weights = fixture_file("weights.pth", required_in_ci=False)
    sd = convert.load_state_dict(weights)
    cfg, params = convert.convert_state_dict(sd)
    assert cfg["name"] == "resnet_md" and models.param_count(params) == 58_461_416
    ref = np.load(fixture_file("reference.npz"))
    x = ref["net_input"].transpose(0, 2, 3, 1)
    graphdef, _ = models.abstract_init(cfg)
    from flax import nnx

    def fwd(p, x):
        return nnx.merge(graphdef, nnx.State(p)).forward_with_activations(x)

    maps, acts = jax.jit(fwd)(jax.tree.map(np.asarray, params), x)
    report = {}
    for name in ("conv1", "pool1", "layer1", "layer2", "layer3", "layer4", "up6", "up5", "up4", "up3", "up2", "up1"):
        want = ref[f"act_{name}"].transpose(0, 2, 3, 1)
        report[name] = float(np.abs(np.asarray(acts[name]) - want).max() / max(1.0, np.abs(want).max()))
    errors = {}
    for s in range(4):
        for kind, key in (("frac", "disp_frac"), ("px", "disp_px")):
            errors[f"{kind}{s}"] = float(np.abs(np.asarray(maps[kind][s]) - ref[f"{key}_{s}"].transpose(0, 2, 3, 1)).max())
    print("parity max abs error per scale:", errors, "\nactivation rel. errors:", report)
    assert all(v < 1e-4 for v in report.values()), f"first mismatch in activations: {report}"
    assert all(v < 1e-4 for v in errors.values()), errors


# ---------------------------------------------------------------- crafted files claiming huge tensors


class _Claim(_Tensor):
    """A tensor whose pickled shape / stride claim more than its (tiny) storage holds."""

    def __init__(self, key, storage, shape, stride, numel=None):
        super().__init__(key, storage)
        self.layout = (tuple(shape), tuple(stride))
        self.numel = numel if numel is not None else storage.size


@pytest.mark.parametrize("legacy", [False, True])
@pytest.mark.parametrize("shape, stride, storage, why", [
    ((200000, 200000), (0, 0), 1, "stride 0"),  # 0.3 KB asking for 149 GiB
    ((200000, 200000), (1, 200000), 1, "past the end"),
    ((4, 4), (-4, 1), 16, "negative"),
    ((70000, 70000), (70000, 1), 70000 * 70000, None),  # 18 GiB storage: refused before it is read
])
def test_a_tensor_claiming_more_than_its_storage_is_one_line_before_any_allocation(tmp_path, capsys, legacy, shape,
                                                                                    stride, storage, why):
    src = tmp_path / "bomb.pth"
    if storage > 1000:  # a storage claiming 18 GiB, written without its bytes
        t = _Claim("0", np.zeros(1, np.float32), shape, stride, numel=storage)
        write_pth(src, {"conv1.weight": t}, [t], legacy=legacy)
        if legacy:  # the storage header (numel) before the bytes claims the 18 GiB there
            src.write_bytes(src.read_bytes()[:-12] + struct.pack("<q", storage))
        expect = r"storage 0 claims 18.3 GiB"
    else:
        t = _Claim("0", np.arange(storage, dtype=np.float32), shape, stride)
        write_pth(src, {"conv1.weight": t}, [t], legacy=legacy)
        expect = rf"tensor conv1.weight claims [0-9.]+ (GiB|B) from a {storage * 4} B storage \(.*{why}"
    assert src.stat().st_size < 2000
    err, peak = _refused(src, tmp_path, capsys)
    assert err.startswith(f"error: {src}: ") and re.search(expect, err), err
    assert peak < 200 * 2**20


def test_the_stride_zero_bomb_names_its_size_in_gib(tmp_path):
    src = tmp_path / "bomb.pth"
    t = _Claim("0", np.zeros(1, np.float32), (200000, 200000), (0, 0))
    write_pth(src, {"w": t}, [t])
    with pytest.raises(convert.CheckpointFormatError, match=r"bomb.pth: tensor w claims 149 GiB from a 4 B storage"):
        convert.load_state_dict(src)


# ---------------------------------------------------------------- bounds over a whole file (zip directory, total)


@pytest.fixture
def zip_opens(monkeypatch):
    """Counts the members opened (decompressed) from any zip file; ZipFile.read goes through ZipFile.open."""
    opened = []
    real_open = zipfile.ZipFile.open

    def counting_open(self, name, mode="r", *args, **kwargs):
        if mode == "r":  # not the members a test writes
            opened.append(getattr(name, "filename", name))
        return real_open(self, name, mode, *args, **kwargs)

    monkeypatch.setattr(zipfile.ZipFile, "open", counting_open)
    return opened


def _refused(src, tmp_path, capsys):
    """`bridge-convert` on `src`: (its one error line, peak traced bytes); checks exit code 2 and nothing written."""
    import tracemalloc
    tracemalloc.start()
    try:
        code = convert.main(["--from", str(src), "--out", str(tmp_path / "out")])
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "out").exists()
    return err, peak


def test_a_deflate_bomb_member_is_refused_from_the_zip_directory(tmp_path, capsys, zip_opens):
    # 32 MiB of zeros deflate to 32 KB (1029:1): refused by its ratio before a byte of it is inflated
    t = _Tensor("0", np.zeros(8 * 2**20, np.float32))
    src = tmp_path / "bomb.pth"
    write_pth(src, {"conv1.weight": t}, [t], compression=zipfile.ZIP_DEFLATED)
    assert src.stat().st_size < 40_000
    err, peak = _refused(src, tmp_path, capsys)
    assert re.fullmatch(rf"error: {re.escape(str(src))}: zip member archive/data/0 expands 31.\d KiB to 32 MiB "
                        r"\(10[23]\d:1, over the 100:1 limit of the compression ratio of a member\)\n", err), err
    assert zip_opens == [] and peak < 2**20


def test_a_member_declaring_a_huge_size_is_refused_before_reading(tmp_path, capsys, zip_opens):
    # a 40-byte storage whose directory entry declares 3.5 GiB (the local header keeps the true size)
    t = _Tensor("0", np.arange(10, dtype=np.float32))
    src = tmp_path / "claims.pth"
    write_pth(src, {"conv1.weight": t}, [t], declare={"archive/data/0": 7 * 2**29})
    err, peak = _refused(src, tmp_path, capsys)
    assert err == (f"error: {src}: zip member archive/data/0 expands 40 B to 3.5 GiB (93952410:1, over the 100:1 "
                   "limit of the compression ratio of a member)\n")
    assert zip_opens == [] and peak < 2**20


def test_members_declaring_more_than_the_file_bound_are_refused_before_reading(tmp_path, capsys, zip_opens,
                                                                               monkeypatch):
    # eight 4 KiB storages, each a plain stored member (ratio 1:1), 32 KiB (+ data.pkl) against a bound of 16 KiB
    monkeypatch.setattr(convert, "MAX_FILE_BYTES", 16 * 2**10)
    tensors = [_Tensor(str(i), np.full(1024, i, np.float32)) for i in range(8)]
    src = tmp_path / "many.pth"
    write_pth(src, {f"w{i}": t for i, t in enumerate(tensors)}, tensors)
    err, _ = _refused(src, tmp_path, capsys)
    assert re.fullmatch(rf"error: {re.escape(str(src))}: zip members declare 3[23].\d KiB in all, over the 16 KiB "
                        r"limit of one file\n", err), err
    assert zip_opens == []


@pytest.mark.parametrize("legacy", [False, True])
def test_storages_read_count_against_the_file_bound(tmp_path, capsys, monkeypatch, legacy):
    # a legacy file has no directory: its storages are charged as they are read, and the third one passes the bound
    monkeypatch.setattr(convert, "MAX_FILE_BYTES", 10 * 2**10)
    monkeypatch.setattr(convert, "_check_zip_directory", lambda zf: None)  # the zip case: the same bound, later
    tensors = [_Tensor(str(i), np.full(1024, i, np.float32)) for i in range(8)]
    src = tmp_path / "many.pth"
    write_pth(src, {f"w{i}": t for i, t in enumerate(tensors)}, tensors, legacy=legacy)
    err, _ = _refused(src, tmp_path, capsys)
    assert err == (f"error: {src}: storage 2 takes 4 KiB, which brings the file's storages and tensors to 12 KiB, "
                   "over the 10 KiB limit of one file\n")


@pytest.mark.parametrize("legacy", [False, True])
def test_tensors_sharing_one_storage_count_against_the_file_bound(tmp_path, capsys, monkeypatch, legacy):
    # one 4 KiB storage viewed whole by eight tensors: each tensor is a 4 KiB copy, so the file asks for 36 KiB
    monkeypatch.setattr(convert, "MAX_FILE_BYTES", 10 * 2**10)
    storage = np.arange(1024, dtype=np.float32)
    tensors = [_Claim("0", storage, (32, 32), (32, 1)) for _ in range(8)]
    src = tmp_path / "shared.pth"
    write_pth(src, {f"w{i}": t for i, t in enumerate(tensors)}, tensors[:1], legacy=legacy)
    with pytest.raises(convert.CheckpointFormatError) as e:
        convert.load_state_dict(src)
    assert str(e.value) == (f"{src}: tensor w1 takes 4 KiB, which brings the file's storages and tensors to "
                            "12 KiB, over the 10 KiB limit of one file")
    monkeypatch.setattr(convert, "MAX_FILE_BYTES", 36 * 2**10)  # exactly enough: every tensor is the storage
    got = convert.load_state_dict(src)
    assert list(got) == [f"w{i}" for i in range(8)]
    assert all(np.array_equal(v, storage.reshape(32, 32)) for v in got.values())


def test_a_deflated_checkpoint_still_converts(tmp_path, zip_opens):
    # re-zipped weights shrink by ~10%, far from the ratio bound; every member is read once
    sd = tiny_state_dict(np.random.default_rng(4))
    tensors = [_Tensor(str(i), v) for i, v in enumerate(sd.values())]
    src = tmp_path / "deflated.pth"
    write_pth(src, dict(zip(sd, tensors)), tensors, compression=zipfile.ZIP_DEFLATED)
    out = tmp_path / "converted"
    assert convert.main(["--from", str(src), "--out", str(out)]) == 0
    assert sorted(zip_opens) == sorted(["archive/data.pkl", "archive/byteorder"]
                                       + [f"archive/data/{t.key}" for t in tensors])
    _, params = checkpointing.read_params(out)
    np.testing.assert_array_equal(np.asarray(params["up3"]["conv2"]["kernel"]),
                                  sd["up3.conv2.weight"].transpose(2, 3, 1, 0))


def test_the_file_bound_fits_the_largest_upstream_checkpoint():
    # resnet_md's weights (58,461,416 float32, test_full_size_key_table_matches_reference) and Adam's two moments
    # in an epoch checkpoint, plus the copy of the weights that reading makes
    assert convert.MAX_FILE_BYTES >= 4 * 4 * 58_461_416
    assert convert.MAX_FILE_BYTES < 8 * convert.MAX_TENSOR_BYTES


def test_sizes_in_messages_are_plain_numbers():
    # 1020 KiB, a 1 GiB deflate bomb's compressed size, came out as "1.02e+03 KiB"
    assert [convert._size_text(n) for n in (400, 1020 * 2**10, 7 * 2**29, 5000 * 2**30)] == \
        ["400 B", "1020 KiB", "3.5 GiB", "5000 GiB"]


def test_a_corrupt_deflate_stream_is_one_line(tmp_path, capsys):
    t = _Tensor("0", np.zeros(4096, np.float32))
    src = tmp_path / "corrupt.pth"
    write_pth(src, {"conv1.weight": t}, [t], compression=zipfile.ZIP_DEFLATED)
    with zipfile.ZipFile(src) as zf:
        info = zf.getinfo("archive/data/0")
    data = bytearray(src.read_bytes())
    start = info.header_offset + 30 + len(info.filename.encode()) + len(info.extra)  # after the local header
    data[start:start + 4] = b"\xff\xff\xff\xff"  # a deflate block type that does not exist
    src.write_bytes(bytes(data))
    err, _ = _refused(src, tmp_path, capsys)
    assert err.startswith(f"error: {src}: corrupt or unsupported torch file (error: Error -3 while decompressing"), err
