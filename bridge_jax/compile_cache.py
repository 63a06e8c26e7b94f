"""Time to a first answer: the persistent XLA compilation cache the command-line entry points share, and the
clocks that say how long a first step took.

Compiling a network is most of the wait before a first prediction or train step (10-60 s on a CPU). JAX can
keep compiled executables on disk; `enable` turns that on in one folder per user, so that `bridge-predict`
after `bridge-train` (or a resumed run, or the second `bridge-evaluate`) loads what an earlier process compiled:

    BRIDGE_JAX_CACHE_DIR        if set: the folder ("" = no cache)
    $XDG_CACHE_HOME/bridge_jax/xla, else ~/.cache/bridge_jax/xla

JAX's own JAX_COMPILATION_CACHE_DIR, if set, wins. Training keeps its compiled train step and prediction its
compiled network whole in the same folder (`executable_cache`, `*-exec-cache` files), so that a warm start
neither traces nor lowers them. The folder is trimmed to `MAX_CACHE_BYTES` at start-up (least recently used
entries first). A folder that cannot be written (a read-only home) is one warning, and
the command runs without a cache. `bridge-bench` never calls `enable`: it measures compile times.

What a cache entry holds is machine code that the next process runs, so nothing is trusted as found:
- every entry (JAX's own and bridge_jax's `*-exec-cache`) is *sealed*: a header and a sha256 over the entry's
  key and bytes (`seal` / `unseal`), checked before anything is deserialised. An entry that fails (flipped bytes,
  a truncated write, an entry of another format, one renamed to another key) is removed, with one warning line,
  and the program compiled and written again. JAX's entries are sealed by a thin layer over JAX's own file
  cache (`_CheckedCache`), so a process that uses JAX's cache through bridge_jax only ever reads sealed entries.
- a folder that belongs to another user or that other users may write is refused (one line, the command runs
  without a cache: `folder_problem`), and an entry file that belongs to another user is never read: an entry
  planted there would run as the next user's code.
- nothing in the folder is unpickled: the compiled-program entries are a JSON header and XLA's serialised
  executable (`executable_cache`).
"""

from __future__ import annotations

import argparse
import contextlib
import hashlib
import hmac
import os
import stat
import tempfile
import time
import warnings

import jax

ENV = "BRIDGE_JAX_CACHE_DIR"
MIN_COMPILE_TIME_S = 0.05
"""Executables that compiled faster than this are not stored. The networks' forward passes take 10-20 s to
compile on 2 CPU cores and the train steps longer; resizes, casts and metrics compile in under 0.02 s and would
only fill the folder with entries that load about as slowly as they compile. Between the two, a training start
compiles a few programs of 0.05-0.25 s (the random initialisation: `_normal`, the state's `build`, the key
split): stored, they took a warm 128x256 first step from 5.4 to 5.1 s (2026-12-03, AVX-512 EPYC, three
alternating pairs, medians; 0.5 s was the threshold before)."""
MAX_CACHE_BYTES = 2 * 2**30
"""The folder is trimmed to this size at start-up. (JAX's own `jax_compilation_cache_max_size` evicts on every
write but needs the `filelock` package, which bridge_jax does not depend on.)"""
STALE_TEMP_S = 3600.0
"""A temporary entry file (`.NAME.tmp-*`, written then renamed) older than this belongs to a killed write and
is removed by `trim`."""
OPTION_HELP = ("persistent XLA compilation cache folder, so that a later run skips most of the compile: 'auto' = "
               f"${ENV} if set, else $XDG_CACHE_HOME/bridge_jax/xla, else ~/.cache/bridge_jax/xla; '' = off "
               "(JAX_COMPILATION_CACHE_DIR, if set, wins)")


class CacheWarning(UserWarning):
    """The cache folder cannot be used; the command runs without it (printed once, as one line)."""


def default_cache_dir() -> str | None:
    """The per-user cache folder ("auto"): $BRIDGE_JAX_CACHE_DIR if set ("" = None, no cache), else
    $XDG_CACHE_HOME/bridge_jax/xla, else ~/.cache/bridge_jax/xla."""
    if ENV in os.environ:
        return os.path.abspath(os.path.expanduser(os.environ[ENV])) if os.environ[ENV] else None
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return os.path.abspath(os.path.join(base, "bridge_jax", "xla"))


def resolve(path: str, workdir: str | None = None, option: str = "--compilation-cache") -> str | None:
    """The folder `path` stands for: "auto" = `default_cache_dir()`, "workdir" = `<workdir>/xla_cache` (a
    training run's own cache, as before the per-user one), "" = None (off), anything else a folder. ValueError
    naming `option` for "workdir" without a workdir."""
    if not path:
        return None
    if path == "auto":
        return default_cache_dir()
    if path == "workdir":
        if not workdir:
            raise ValueError(f"{option}=workdir: only training has a workdir; give a folder, 'auto' or '' (off)")
        return os.path.join(os.path.abspath(workdir), "xla_cache")
    return os.path.abspath(os.path.expanduser(path))


def enable(path: str = "auto", workdir: str | None = None, option: str = "--compilation-cache") -> str | None:
    """Turns on JAX's persistent compilation cache for this process in the folder `path` stands for (see
    `resolve`); returns that folder, or None when off. JAX_COMPILATION_CACHE_DIR, if set, wins (returned as is).

    Call it before the first compilation: JAX opens the cache once, at the process's first compile that has a
    cache folder, and keeps it. A folder that cannot be created or written warns once and leaves the cache off.
    """
    install_entry_checks()
    if os.environ.get("JAX_COMPILATION_CACHE_DIR"):
        folder = os.environ["JAX_COMPILATION_CACHE_DIR"]
        problem = folder_problem(folder) if os.path.isdir(folder) else None
        if problem:
            jax.config.update("jax_compilation_cache_dir", None)
            warnings.warn(f"compilation cache {folder} (JAX_COMPILATION_CACHE_DIR): {problem}; running without it",
                          CacheWarning, stacklevel=2)
            return None
        return folder
    folder = resolve(path, workdir, option)
    if folder is None:
        return None
    try:
        os.makedirs(folder, mode=0o700, exist_ok=True)
        problem = folder_problem(folder)
        if not problem:
            with tempfile.TemporaryFile(dir=folder):  # writable? (a read-only home passes makedirs of an old dir)
                pass
    except OSError as e:
        problem = e.strerror or str(e)
    if problem:
        warnings.warn(f"compilation cache {folder}: {problem}; running without it (set {option}='' or "
                      f"{ENV}='' to silence this)", CacheWarning, stacklevel=2)
        return None
    trim(folder, MAX_CACHE_BYTES)
    jax.config.update("jax_compilation_cache_dir", folder)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", MIN_COMPILE_TIME_S)
    return folder


def folder_problem(folder: str) -> str | None:
    """Why `folder` must not hold a cache, or None: it belongs to another user, or users other than its owner may
    write it (an entry planted there would run as code in the next process that loads it). OSError when it
    cannot be read."""
    st = os.stat(folder)
    if hasattr(os, "geteuid") and st.st_uid != os.geteuid():
        return f"it belongs to another user (uid {st.st_uid}; you are uid {os.geteuid()})"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return (f"users other than its owner may write it (mode {stat.S_IMODE(st.st_mode):o}; "
                f"`chmod go-w {folder}` makes it usable)")
    return None


def _owned_by_another_user(st: os.stat_result) -> bool:
    return hasattr(os, "geteuid") and st.st_uid != os.geteuid()


# ----------------------------------------------------------------------------------------------------------
# Sealed entries: a header and a checksum of key and bytes, checked before anything is deserialised
# ----------------------------------------------------------------------------------------------------------

ENTRY_MAGIC = b"bridge_jax cache entry v1\n"
"""The first bytes of every sealed entry; a file without them (another format, JAX's own unsealed entry,
garbage) is not an entry."""
_DIGEST_BYTES = 32


class CacheEntryError(ValueError):
    """A cache entry that must not be used: not sealed, damaged, or sealed for another key."""


def _digest(key: str, body: bytes) -> bytes:
    h = hashlib.sha256(b"key\0" + key.encode() + b"\0")
    h.update(body)
    return h.digest()


def seal(key: str, body: bytes) -> bytes:
    """The bytes of a cache entry for `key` holding `body`: `ENTRY_MAGIC`, sha256 over the key and the body,
    the body."""
    return ENTRY_MAGIC + _digest(key, body) + body


def unseal(key: str, data: bytes) -> bytes:
    """The body of the sealed entry `data` of `key`; CacheEntryError saying what is wrong when it is not a
    sealed entry, is damaged or truncated, or was sealed for another key (a file renamed or copied)."""
    if not data.startswith(ENTRY_MAGIC):
        raise CacheEntryError("not a sealed bridge_jax cache entry (another format, or damaged at its start)")
    head = len(ENTRY_MAGIC)
    digest, body = data[head:head + _DIGEST_BYTES], data[head + _DIGEST_BYTES:]
    if len(digest) != _DIGEST_BYTES or not hmac.compare_digest(digest, _digest(key, body)):
        raise CacheEntryError("its checksum does not match its key and bytes (damaged, truncated or renamed)")
    return body


def read_entry(path: str, key: str) -> bytes | None:
    """The body of the sealed entry file `path` of `key`; None when there is none. An entry that fails its check
    is removed (so that the program is compiled and written again) with one warning line; a file that belongs
    to another user is left alone and not read (one warning line)."""
    try:
        with open(path, "rb") as f:
            st = os.fstat(f.fileno())
            if _owned_by_another_user(st):
                warnings.warn(f"compilation cache entry {path} belongs to another user (uid {st.st_uid}); not "
                              "reading it, compiling instead", CacheWarning, stacklevel=2)
                return None
            data = f.read()
    except FileNotFoundError:
        return None
    except OSError as e:
        warnings.warn(f"compilation cache entry {path}: {e.strerror or e}; compiling instead", CacheWarning,
                      stacklevel=2)
        return None
    try:
        return unseal(key, data)
    except CacheEntryError as e:
        discard_entry(path, str(e))
        return None


def discard_entry(path: str, why: str) -> None:
    """Removes the unusable entry `path` (one warning line saying `why`): the next compile writes it again."""
    warnings.warn(f"compilation cache entry {os.path.basename(path)}: {why}; removed, compiling instead",
                  CacheWarning, stacklevel=3)
    try:
        os.remove(path)
    except OSError:
        pass


class _CheckedCache:
    """JAX's file cache with sealed entries: `put` seals what JAX writes, `get` hands JAX only entries whose
    seal checks (`read_entry`), so XLA never deserialises damaged bytes, and an entry that fails is removed
    before JAX's `put` (which never overwrites an existing file) writes the new one."""

    def __init__(self, inner):
        self.inner = inner
        self.path = getattr(inner, "path", None)

    def _file(self, key: str) -> str:
        return os.path.join(str(self.path), f"{key}-cache")

    def get(self, key: str) -> bytes | None:
        if self.path is None:
            return None
        return read_entry(self._file(key), key)

    def put(self, key: str, value: bytes) -> None:
        self.inner.put(key, seal(key, value))

    def __getattr__(self, name):  # anything else JAX asks of its cache object
        return getattr(self.inner, name)


_CHECKS_INSTALLED = False


def install_entry_checks() -> None:
    """Seals JAX's own compilation-cache entries in this process (`_CheckedCache` over the file cache JAX opens
    at its first compile with a cache folder). Idempotent. Where JAX's internals differ from what this expects
    (another JAX release), nothing is changed and JAX's cache works as JAX made it."""
    global _CHECKS_INSTALLED
    if _CHECKS_INSTALLED:
        return
    try:
        from jax._src import compilation_cache as jax_cache
        opener = jax_cache.get_file_cache
    except (ImportError, AttributeError):
        return

    def checked_file_cache(path):
        got = opener(path)
        if got is None:
            return None
        cache, where = got
        return _CheckedCache(cache), where

    jax_cache.get_file_cache = checked_file_cache
    opened = getattr(jax_cache, "_cache", None)
    if opened is not None and not isinstance(opened, _CheckedCache):
        jax_cache._cache = _CheckedCache(opened)  # a cache JAX opened before bridge_jax was imported
    _CHECKS_INSTALLED = True


def trim(folder: str, max_bytes: int) -> int:
    """Deletes the least recently used cache entries (JAX's `*-cache` files) of `folder` until the rest holds
    at most `max_bytes`, and the temporary files of writes killed more than `STALE_TEMP_S` ago; returns how many
    entries were deleted. Errors (an entry another process just removed) are
    skipped: trimming is housekeeping, never a reason to fail."""
    entries, now = [], time.time()
    try:
        with os.scandir(folder) as it:
            for e in it:
                if e.name.startswith(".") and ".tmp-" in e.name and e.is_file(follow_symlinks=False):
                    # the temporary file of a write that was killed (a write in flight takes seconds)
                    with contextlib.suppress(OSError):
                        if now - e.stat(follow_symlinks=False).st_mtime > STALE_TEMP_S:
                            os.remove(e.path)
                    continue
                if e.name.endswith("-cache") and e.is_file(follow_symlinks=False):
                    st = e.stat(follow_symlinks=False)
                    entries.append((max(st.st_atime, st.st_mtime), st.st_size, e.path))
    except OSError:
        return 0
    total, deleted = sum(size for _, size, _ in entries), 0
    for _, size, path in sorted(entries):
        if total <= max_bytes:
            break
        try:
            os.remove(path)
        except OSError:
            continue
        total -= size
        deleted += 1
    return deleted


def active_dir() -> str | None:
    """The cache folder JAX uses in this process (set by `enable`, JAX_COMPILATION_CACHE_DIR or a library
    caller), or None."""
    return jax.config.jax_compilation_cache_dir or None


def describe() -> str:
    """"cached in FOLDER" or "compilation cache off", for one-line messages before a long compile."""
    folder = active_dir()
    return f"cached in {folder}" if folder else "compilation cache off"


def add_option(parser: argparse.ArgumentParser) -> None:
    """`--compilation-cache DIR` (default auto) on a command that compiles a network."""
    parser.add_argument("--compilation-cache", default="auto", metavar="DIR", help=OPTION_HELP)


# ----------------------------------------------------------------------------------------------------------
# Clocks: since the process began, and the seconds spent tracing, lowering and compiling
# ----------------------------------------------------------------------------------------------------------

_IMPORTED = time.time()


def process_age_s() -> float:
    """Seconds since this process started: from /proc on Linux (interpreter start-up and imports included),
    elsewhere since this module was imported."""
    try:
        with open("/proc/self/stat") as f:
            # the command name (field 2) may hold spaces: count the fields after its closing parenthesis;
            # field 22 is the start time in clock ticks after boot
            start_ticks = int(f.read().rpartition(")")[2].split()[19])
        with open("/proc/uptime") as f:
            uptime = float(f.read().split()[0])
        return max(0.0, uptime - start_ticks / os.sysconf("SC_CLK_TCK"))
    except (OSError, ValueError, IndexError):
        return time.time() - _IMPORTED


_TRACE_EVENT = "/jax/core/compile/jaxpr_trace_duration"
_LOWER_EVENT = "/jax/core/compile/jaxpr_to_mlir_module_duration"
_BACKEND_EVENT = "/jax/core/compile/backend_compile_duration"
_CACHE_HIT_EVENT = "/jax/compilation_cache/cache_hits"
_CLOCKS: list["CompileClock"] = []
_listening = False


def _on_duration(event: str, duration: float, **_kw) -> None:
    if event not in (_TRACE_EVENT, _LOWER_EVENT, _BACKEND_EVENT):
        return
    for clock in _CLOCKS:
        clock.seconds += duration
        if event == _TRACE_EVENT:
            clock.traces += 1
            clock.trace_s += duration
        elif event == _BACKEND_EVENT:
            clock.compiles += 1
            clock.compile_s += duration


def _on_event(event: str, **_kw) -> None:
    if event == _CACHE_HIT_EVENT:
        for clock in _CLOCKS:
            clock.cache_hits += 1


class CompileClock:
    """Seconds JAX spent tracing, lowering and compiling (or loading from the cache) while active (`seconds`), and
    the jaxpr traces and XLA backend compiles among them (`traces`, `trace_s`, `compiles`, `compile_s`; a
    compile that loaded its program from the persistent cache counts in `compiles` and in `cache_hits`), from
    `jax.monitoring` events; a context manager. Training's first step and the bench's recompilation check both
    use it (process-wide listeners dispatch to the active clocks)."""

    def __init__(self):
        self.seconds = 0.0
        self.traces = self.compiles = self.cache_hits = 0
        self.trace_s = self.compile_s = 0.0

    def __enter__(self) -> "CompileClock":
        global _listening
        if not _listening:  # one pair of listeners for the process: jax.monitoring has no cheap way to remove one
            jax.monitoring.register_event_duration_secs_listener(_on_duration)
            jax.monitoring.register_event_listener(_on_event)
            _listening = True
        _CLOCKS.append(self)
        return self

    def __exit__(self, *exc) -> bool:
        _CLOCKS.remove(self)
        return False


# JAX's own entries are sealed in every process that imports bridge_jax (commands and library callers alike), so
# that no process of ours writes an entry another of ours would refuse.
install_entry_checks()
