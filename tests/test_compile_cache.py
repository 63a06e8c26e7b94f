"""compile_cache: which folder, turning it on (or off, or without failing on a read-only home), trimming it,
the clocks of a first step, and the `--compilation-cache` option of the commands that compile."""

from __future__ import annotations

import os
import subprocess
import sys
import warnings

import jax
import jax.numpy as jnp
import pytest

from bridge_jax import compile_cache, evaluate, export, predict
from tests.train_helpers import REPO


@pytest.fixture
def recorded(monkeypatch):
    """jax.config.update calls, recorded instead of applied (the cache settings are process-global)."""
    calls = {}
    monkeypatch.setattr(compile_cache.jax.config, "update", lambda name, value: calls.__setitem__(name, value))
    monkeypatch.delenv("JAX_COMPILATION_CACHE_DIR", raising=False)
    return calls


def test_default_folder_is_the_env_variable_else_xdg_else_home(tmp_path, monkeypatch):
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "mine"))
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.default_cache_dir() == str(tmp_path / "mine")
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", "")
    assert compile_cache.default_cache_dir() is None  # set but empty: no cache
    monkeypatch.delenv("BRIDGE_JAX_CACHE_DIR")
    assert compile_cache.default_cache_dir() == str(tmp_path / "xdg" / "bridge_jax" / "xla")
    monkeypatch.delenv("XDG_CACHE_HOME")
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    assert compile_cache.default_cache_dir() == str(tmp_path / "home" / ".cache" / "bridge_jax" / "xla")


def test_enable_sets_the_folder_and_the_threshold(tmp_path, monkeypatch, recorded):
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", str(tmp_path / "c"))
    assert compile_cache.enable() == str(tmp_path / "c") and (tmp_path / "c").is_dir()
    assert recorded == {"jax_compilation_cache_dir": str(tmp_path / "c"),
                        "jax_persistent_cache_min_compile_time_secs": compile_cache.MIN_COMPILE_TIME_S}
    recorded.clear()
    monkeypatch.setenv("BRIDGE_JAX_CACHE_DIR", "")
    assert compile_cache.enable("auto") is None and not recorded
    with pytest.raises(ValueError, match=r"^--compilation-cache=workdir: only training has a workdir"):
        compile_cache.enable("workdir")


def test_an_unwritable_folder_warns_once_and_runs_without_cache(tmp_path, recorded):
    (tmp_path / "file").write_text("not a folder")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("default")
        for _ in range(3):
            assert compile_cache.enable(str(tmp_path / "file" / "xla")) is None
    assert not recorded
    assert len(caught) == 1 and caught[0].category is compile_cache.CacheWarning
    assert str(tmp_path / "file" / "xla") in str(caught[0].message) and "running without it" in str(caught[0].message)


@pytest.mark.skipif(os.name != "posix" or os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_existing_folder_is_not_used(tmp_path, recorded):
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        with pytest.warns(compile_cache.CacheWarning, match="running without it"):
            assert compile_cache.enable(str(ro)) is None
    finally:
        ro.chmod(0o755)
    assert not recorded


def test_trim_deletes_the_least_recently_used_entries_first(tmp_path):
    # four 100-byte entries used at times 1..4 (the oldest first) and one file that is not an entry
    for i, name in enumerate(["a-cache", "b-cache", "c-cache", "d-cache"], start=1):
        (tmp_path / name).write_bytes(b"x" * 100)
        os.utime(tmp_path / name, (1000 * i, 1000 * i))
    (tmp_path / "a-atime").write_bytes(b"x" * 500)
    assert compile_cache.trim(str(tmp_path), 250) == 2  # 400 -> 200 bytes: a and b go
    assert sorted(os.listdir(tmp_path)) == ["a-atime", "c-cache", "d-cache"]
    assert compile_cache.trim(str(tmp_path), 250) == 0
    assert compile_cache.trim(str(tmp_path / "missing"), 0) == 0


def test_process_age_counts_from_the_start_of_the_process_not_the_import():
    code = ("import time; time.sleep(1.5); from bridge_jax import compile_cache; "
            "print(compile_cache.process_age_s())")
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       env=dict(os.environ, PYTHONPATH=REPO))
    assert r.returncode == 0, r.stderr
    assert 1.5 <= float(r.stdout) < 30


def test_compile_clock_counts_only_compiles_while_active():
    f = jax.jit(lambda x: jnp.sin(x) * 3.0 + 1.25)
    x = jnp.arange(7.0)
    with compile_cache.CompileClock() as clock:
        f(x).block_until_ready()
    first = clock.seconds
    assert first > 0
    with compile_cache.CompileClock() as again:
        f(x).block_until_ready()  # compiled already: nothing to count
    assert again.seconds == 0 and clock.seconds == first


@pytest.mark.parametrize("module", [predict, evaluate, export])
def test_commands_have_the_option_and_refuse_workdir_naming_it(module, capsys):
    text = " ".join(module.build_parser().format_help().split())  # argparse wraps lines
    assert "--compilation-cache DIR" in text and "'' = off" in text and "(default: auto)" in text
    args = {predict: ["--checkpoint", "demo", "--out", "o", "a.png", "b.png"],
            evaluate: ["--dataset", "synthetic", "--data-dir", "d"],
            export: ["--checkpoint", "demo", "--out", "o"]}[module]
    assert module.main([*args, "--compilation-cache", "workdir"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: --compilation-cache=workdir: only training has a workdir; give a folder, 'auto' or '' (off)"]
