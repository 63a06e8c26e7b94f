"""The compilation caches cannot crash a run or run planted code: every entry is sealed (a checksum over its
key and bytes, checked before anything is deserialised), nothing is unpickled, and a folder or entry that
another user could have written is not used.

Damage is done to real entries (a compiled program kept by `executable_cache`, and JAX's own entries written by
a separate process) at several offsets; the planted entry is a pickle that would create a file when unpickled."""
from __future__ import annotations

import os
import pickle
import stat
import subprocess
import sys
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import compile_cache, executable_cache
from tests.train_helpers import REPO


def _program(x, y):
    return {"sum": jnp.sum(x * y), "prod": (x @ y.T, [y * 2.0, None])}


ARGS = (jnp.arange(12.0).reshape(3, 4), jnp.ones((3, 4)))
EXPECTED = {"sum": 66.0, "prod0": np.arange(12.0).reshape(3, 4) @ np.ones((4, 3))}


def _check(out):
    assert float(out["sum"]) == EXPECTED["sum"]
    np.testing.assert_array_equal(np.asarray(out["prod"][0]), EXPECTED["prod0"])
    np.testing.assert_array_equal(np.asarray(out["prod"][1][0]), np.full((3, 4), 2.0))
    assert out["prod"][1][1] is None


def _kept(folder, stats=None):
    jax.clear_caches()
    stats = {} if stats is None else stats
    fn = executable_cache.cached_compile(jax.jit(_program), ARGS, config={"test": "integrity"}, folder=str(folder),
                                         stats=stats)
    return fn, stats


class Planted:
    """Unpickling this creates the file `path`: an entry that would run code if anything unpickled it."""

    def __init__(self, path):
        self.path = str(path)

    def __reduce__(self):
        return (open, (self.path, "w"))


@pytest.fixture
def no_xla_cache():
    """XLA's persistent cache off, so that `cached_compile` compiles (and keeps) what it is asked for."""
    from jax.experimental.compilation_cache import compilation_cache as cc
    before = jax.config.jax_enable_compilation_cache
    jax.config.update("jax_enable_compilation_cache", False)
    cc.reset_cache()
    yield
    jax.config.update("jax_enable_compilation_cache", before)
    cc.reset_cache()


def test_seal_detects_any_change_of_bytes_or_key():
    body = bytes(range(256)) * 4
    sealed = compile_cache.seal("k1", body)
    assert compile_cache.unseal("k1", sealed) == body
    for offset in (0, 10, len(compile_cache.ENTRY_MAGIC) + 3, len(sealed) // 2, len(sealed) - 1):
        damaged = bytearray(sealed)
        damaged[offset] ^= 0x01
        with pytest.raises(compile_cache.CacheEntryError):
            compile_cache.unseal("k1", bytes(damaged))
    with pytest.raises(compile_cache.CacheEntryError, match="checksum"):
        compile_cache.unseal("k2", sealed)  # renamed to another key
    with pytest.raises(compile_cache.CacheEntryError, match="checksum"):
        compile_cache.unseal("k1", sealed[:-7])  # a write cut short
    with pytest.raises(compile_cache.CacheEntryError, match="not a sealed"):
        compile_cache.unseal("k1", pickle.dumps({"format": 1}))


def test_a_kept_program_damaged_anywhere_is_removed_and_made_again(tmp_path, no_xla_cache):
    fn, stats = _kept(tmp_path)
    _check(fn(*ARGS))
    key = stats["cache_key"]
    path = tmp_path / (key + executable_cache.SUFFIX)
    good = path.read_bytes()
    assert b"pickle" not in good[:200] and good.startswith(compile_cache.ENTRY_MAGIC)
    header = len(compile_cache.ENTRY_MAGIC) + 32
    for offset in (1, header + 2, header + 40, len(good) // 2, len(good) - 3):
        damaged = bytearray(good)
        for i in range(4):
            damaged[min(offset + i, len(good) - 1)] ^= 0xA5
        path.write_bytes(bytes(damaged))
        with pytest.warns(compile_cache.CacheWarning, match="removed, compiling instead") as caught:
            fn, stats = _kept(tmp_path)
        assert len([w for w in caught if issubclass(w.category, compile_cache.CacheWarning)]) == 1
        assert stats["cache"] == "written", offset
        compile_cache.unseal(key, path.read_bytes())
        _check(fn(*ARGS))
    _, stats = _kept(tmp_path)
    assert stats["cache"] == "hit"


@pytest.mark.parametrize("sealed", [False, True])
def test_a_planted_pickle_is_never_unpickled(tmp_path, no_xla_cache, sealed):
    marker = tmp_path / "ran"
    folder = tmp_path / "cache"
    folder.mkdir()
    key = executable_cache.entry_key({"test": "integrity"}, ARGS)
    payload = pickle.dumps({"format": 1, "executable": Planted(marker), "in_tree": None, "out_tree": None})
    if sealed:  # even with a valid seal (someone who knows the format) the body is data, never a pickle
        payload = compile_cache.seal(key, len(payload).to_bytes(8, "little") + payload)
    (folder / (key + executable_cache.SUFFIX)).write_bytes(payload)
    with pytest.warns(compile_cache.CacheWarning, match="removed, compiling instead"):
        fn, stats = _kept(folder)
    assert not marker.exists()
    assert stats["cache"] == "written"
    _check(fn(*ARGS))


_JAX_CHILD = """
import sys, warnings
import jax, jax.numpy as jnp
import bridge_jax.compile_cache as cc
folder = cc.enable(sys.argv[1])
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
x = jnp.arange(64.0).reshape(8, 8)
print("RESULT", float(jax.jit(lambda a: jnp.sum(jnp.tanh(a @ a.T) * 3.0))(x)))
"""


def _child(folder):
    env = dict(os.environ, PYTHONPATH=REPO, JAX_PLATFORMS="cpu")
    env.pop("JAX_COMPILATION_CACHE_DIR", None)
    return subprocess.run([sys.executable, "-c", _JAX_CHILD, str(folder)], capture_output=True, text=True,
                          env=env, timeout=300, cwd=REPO)


def test_jax_entries_damaged_or_planted_are_replaced_in_a_new_process(tmp_path):
    folder = tmp_path / "xla"
    first = _child(folder)
    assert first.returncode == 0, first.stderr
    result = first.stdout.split("RESULT")[1].strip()
    entries = sorted(p for p in folder.iterdir() if p.name.endswith("-cache"))
    assert entries and all(p.read_bytes().startswith(compile_cache.ENTRY_MAGIC) for p in entries)
    marker = tmp_path / "ran"
    for how in ("flip", "truncate", "pickle"):
        for p in entries:
            good = p.read_bytes()
            if how == "flip":
                damaged = bytearray(good)
                for offset in (len(good) // 3, len(good) - 2):
                    damaged[offset] ^= 0xFF
                p.write_bytes(bytes(damaged))
            elif how == "truncate":
                p.write_bytes(good[: len(good) // 2])
            else:
                p.write_bytes(pickle.dumps(Planted(marker)))
        again = _child(folder)
        assert again.returncode == 0, (how, again.stderr[-2000:])
        assert again.stdout.split("RESULT")[1].strip() == result
        assert again.stderr.count("removed, compiling instead") == len(entries), (how, again.stderr)
        assert "Traceback" not in again.stderr
        for p in entries:  # replaced by a sound entry
            assert p.exists() and p.read_bytes().startswith(compile_cache.ENTRY_MAGIC), how
    assert not marker.exists()
    quiet = _child(folder)
    assert quiet.returncode == 0 and "removed" not in quiet.stderr


def test_a_folder_others_can_write_is_refused_in_one_line(tmp_path):
    folder = tmp_path / "shared"
    folder.mkdir()
    folder.chmod(0o777)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert compile_cache.enable(str(folder)) is None
    messages = [str(w.message) for w in caught if issubclass(w.category, compile_cache.CacheWarning)]
    assert len(messages) == 1 and "users other than its owner may write it (mode 777" in messages[0]
    assert "\n" not in messages[0]
    folder.chmod(0o755)
    assert compile_cache.folder_problem(str(folder)) is None


def test_a_folder_or_entry_of_another_user_is_not_used(tmp_path, monkeypatch, no_xla_cache):
    folder = tmp_path / "theirs"
    folder.mkdir(mode=0o700)
    fn, stats = _kept(folder)  # an entry made by "them" (this process, before pretending to be another user)
    entry = folder / (stats["cache_key"] + executable_cache.SUFFIX)
    me = os.geteuid()
    monkeypatch.setattr(os, "geteuid", lambda: me + 4242)
    assert "belongs to another user" in compile_cache.folder_problem(str(folder))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert compile_cache.enable(str(folder)) is None
    assert [str(w.message) for w in caught if "belongs to another user" in str(w.message)]
    with pytest.warns(compile_cache.CacheWarning, match="belongs to another user.*not reading it"):
        assert compile_cache.read_entry(str(entry), stats["cache_key"]) is None
    assert entry.exists()  # someone else's file: left alone


def test_the_key_names_the_folder_not_its_spelling(tmp_path, monkeypatch):
    (tmp_path / "c").mkdir()
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "c"))
    key = executable_cache.entry_key({}, ARGS)
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "c") + "/")
    assert executable_cache.entry_key({}, ARGS) == key
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "c" / ".." / "c"))
    assert executable_cache.entry_key({}, ARGS) == key
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "d"))
    assert executable_cache.entry_key({}, ARGS) != key


def test_trim_removes_the_temporary_files_of_killed_writes(tmp_path):
    old = tmp_path / ".abc-exec-cache.tmp-x1y2"
    fresh = tmp_path / ".def-exec-cache.tmp-z3"
    for p in (old, fresh):
        p.write_bytes(b"partial")
    past = time.time() - compile_cache.STALE_TEMP_S - 60
    os.utime(old, (past, past))
    compile_cache.trim(str(tmp_path), 2**30)
    assert not old.exists() and fresh.exists()  # a write in flight is left to finish
