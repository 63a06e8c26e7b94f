"""Timing the same way every time: wall time of blocked calls, traces and compiles, host RSS and load.

`time_calls(call, repeats, warmup)` times `call(i)` after warm-up calls, blocking on its result, and records the
jaxpr traces and XLA compiles that happened during the timed calls (from `jax.monitoring` events): a non-zero
count means the function recompiled (a shape changed), which the record says and the CLI turns into exit code 3.
"""

from __future__ import annotations

import os
import resource
import statistics
import threading
import time
from typing import Any, Callable

import jax

from bridge_jax import compile_cache
from bridge_jax.host import cpu_isa, cpu_model, machine  # noqa: F401 - re-exported for the records


class BenchError(Exception):
    """Bad input or a failed measurement; the CLI prints it as one line and exits 2."""


class RecompilationError(BenchError):
    """A trace or XLA compile happened during the timed calls."""


# ---------------------------------------------------------------------------------------------------------
# Trace / compile counter: training's clock (jax.monitoring events), which counts traces and compiles too
# ---------------------------------------------------------------------------------------------------------

CompileCounter = compile_cache.CompileClock


# ---------------------------------------------------------------------------------------------------------
# Host measurements: RSS, load, other processes' CPU share
# ---------------------------------------------------------------------------------------------------------

def peak_rss_gib() -> float:
    """Peak resident set size of this process so far (ru_maxrss, KiB on Linux) in GiB."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20


def current_rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError, IndexError):
        return 0


def _busy_jiffies() -> int | None:
    try:
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return v[0] + v[1] + v[2] + v[5] + v[6] + (v[7] if len(v) > 7 else 0)  # user nice system irq softirq steal
    except (OSError, ValueError, IndexError):
        return None


class HostMonitor:
    """During a block: peak sampled RSS and the share of all CPUs used by other processes (0 = quiet host)."""

    def __init__(self, interval: float = 0.05):
        self.interval, self.peak_rss = interval, 0
        self.other_cpu_frac: float | None = None
        self._stop = threading.Event()

    def _run(self):
        while not self._stop.wait(self.interval):
            self.peak_rss = max(self.peak_rss, current_rss_bytes())

    def __enter__(self):
        self.peak_rss = current_rss_bytes()
        self._j0, self._t0 = _busy_jiffies(), time.perf_counter()
        ru = resource.getrusage(resource.RUSAGE_SELF)
        self._c0 = ru.ru_utime + ru.ru_stime
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()
        return self

    def __exit__(self, *exc):
        self._stop.set()
        self._thread.join()
        self.peak_rss = max(self.peak_rss, current_rss_bytes())
        j1, wall = _busy_jiffies(), time.perf_counter() - self._t0
        ru = resource.getrusage(resource.RUSAGE_SELF)
        own = ru.ru_utime + ru.ru_stime - self._c0
        if j1 is not None and self._j0 is not None and wall > 0:
            busy = (j1 - self._j0) / os.sysconf("SC_CLK_TCK")
            self.other_cpu_frac = max(0.0, (busy - own) / (wall * (os.cpu_count() or 1)))
        return False


def loadavg() -> list[float] | None:
    try:
        return [round(x, 2) for x in os.getloadavg()]
    except OSError:
        return None


# ---------------------------------------------------------------------------------------------------------
# Timing core
# ---------------------------------------------------------------------------------------------------------

def _block(tree):
    return jax.block_until_ready(tree)


def time_calls(call: Callable[[int], Any], *, repeats: int, warmup: int, strict: bool = False) -> dict:
    """Times `call(i)` (its result is blocked on): `warmup` untimed calls, then `repeats` timed ones.

    Returns {"first_call_s", "times_s", "median_s", "min_s", "max_s", "traces_timed", "compiles_timed",
    "recompiled", "rss_timed_peak_gib", "other_procs_cpu_frac", "compile_s_first", "trace_s_first"}.
    A trace or compile during the timed calls sets "recompiled" (and raises RecompilationError if `strict`).
    """
    if repeats < 1 or warmup < 0:
        raise BenchError(f"--repeats must be >= 1 and --warmup >= 0, got {repeats} and {warmup}")
    first = None
    with CompileCounter() as warm:
        for i in range(warmup):
            t0 = time.perf_counter()
            _block(call(i))
            if first is None:
                first = time.perf_counter() - t0
    times = []
    with CompileCounter() as timed, HostMonitor() as mon:
        for i in range(repeats):
            t0 = time.perf_counter()
            _block(call(warmup + i))
            times.append(time.perf_counter() - t0)
    out = {
        "first_call_s": round(first if first is not None else times[0], 4),
        "times_s": [round(t, 4) for t in times],
        "median_s": round(statistics.median(times), 4),
        "min_s": round(min(times), 4),
        "max_s": round(max(times), 4),
        "traces_timed": timed.traces,
        "compiles_timed": timed.compiles,
        "recompiled": bool(timed.traces or timed.compiles),
        "rss_timed_peak_gib": round(mon.peak_rss / 2**30, 3),
        "other_procs_cpu_frac": None if mon.other_cpu_frac is None else round(mon.other_cpu_frac, 3),
        "warmup_traces": warm.traces,
        "warmup_compile_s": round(warm.compile_s, 3),
        "warmup_trace_s": round(warm.trace_s, 3),
    }
    if strict and out["recompiled"]:
        raise RecompilationError(f"{timed.traces} trace(s) / {timed.compiles} compile(s) during the timed calls")
    return out
