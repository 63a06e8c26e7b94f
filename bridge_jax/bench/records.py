"""Benchmark records: the fields every measurement carries, the table, and the JSON-lines file."""

from __future__ import annotations

import datetime
import json
import os
import platform
from typing import Sequence

import jax
import jaxlib

from bridge_jax import files
from bridge_jax.bench.device import device_memory_peak_bytes
from bridge_jax.bench.timing import cpu_isa, cpu_model, loadavg, machine, peak_rss_gib

REQUIRED_FIELDS = ("what", "variant", "config", "height", "width", "cycles", "dtype", "repeats", "warmup",
                   "compile_s", "median_s", "min_s", "max_s", "peak_rss_gib", "device_memory_peak_bytes", "flops",
                   "achieved_tflops", "peak_tflops", "peak_source", "mfu", "traces_timed", "compiles_timed",
                   "recompiled", "device_kind", "platform", "num_devices", "jax_version", "jaxlib_version",
                   "date", "cpu_model", "loadavg", "other_procs_cpu_frac")


def host_environment() -> dict:
    """The fields that describe the machine, the software and the date."""
    dev = jax.devices()[0]
    return dict(device_kind=dev.device_kind, platform=dev.platform, num_devices=jax.device_count(),
                jax_version=jax.__version__, jaxlib_version=jaxlib.__version__, python=platform.python_version(),
                machine=machine(), cpu_model=cpu_model(), cpu_isa=cpu_isa(), cpu_count=os.cpu_count(),
                xla_flags=os.environ.get("XLA_FLAGS", ""),
                date=datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))


def environment(run, args) -> dict:
    """The fields that describe the machine and the measured configuration (`run` = a one-device `setup.Run`)."""
    return dict(config=args.config, overrides=list(args.set or []), height=run.height, width=run.width,
                cycles=run.global_batch, dtype=run.model.dtype, repeats=args.repeats, warmup=args.warmup,
                **host_environment())


def finish(rec: dict, env: dict, peak: tuple[float, str] | None) -> dict:
    out = dict(env)
    out.update(rec)
    out["peak_rss_gib"] = rec.get("peak_rss_gib") or round(peak_rss_gib(), 3)
    if "device_memory_peak_bytes" not in rec:
        out["device_memory_peak_bytes"] = device_memory_peak_bytes() if not rec["what"].startswith("peer") else None
    flops, med = out.get("flops"), out.get("median_s")
    out["achieved_tflops"] = round(flops / med / 1e12, 5) if flops and med else None
    if peak is not None and out["achieved_tflops"] is not None:
        out["peak_tflops"], out["peak_source"] = round(peak[0], 4), peak[1]
        out["mfu"] = round(out["achieved_tflops"] / peak[0], 4)
    else:
        out["peak_tflops"] = round(peak[0], 4) if peak else None
        out["peak_source"] = peak[1] if peak else None
        out["mfu"] = None
    out["loadavg"] = loadavg()
    return out


def finish_process(rec: dict) -> dict:
    """A fresh-process record (`bench.first`): the machine's fields, the record, the load average. Called after
    the children ran, so that this process set up no JAX backend before them."""
    out = host_environment()
    out.update(rec)
    out["loadavg"] = loadavg()
    return out


def _fmt(v, spec=".3g"):
    return "-" if v is None else format(v, spec) if isinstance(v, (int, float)) and not isinstance(v, bool) else str(v)


def table(records: Sequence[dict]) -> str:
    """The in-process measurements as one table, then the fresh-process ones (`cold_s`, ...) as another."""
    timed = [r for r in records if "cold_s" not in r]
    fresh = [r for r in records if "cold_s" in r]
    parts = [_timed_table(timed)] if timed or not fresh else []
    if fresh:
        parts.append(_fresh_table(fresh))
    return "\n\n".join(parts)


def _shape(r: dict) -> str:
    return "x".join(str(r[k]) for k in ("cycles", "height", "width") if r.get(k) is not None)


def _fresh_table(records: Sequence[dict]) -> str:
    head = ("what", "variant", "shape", "cold s", "warm s", "off s", "first step cold s", "first step warm s",
            "children's peak RSS GiB", "others' CPU")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        row = (r["what"], r["variant"], _shape(r), *(_fmt(r.get(k), ".4g") for k in (
            "cold_s", "warm_s", "off_s", "first_step_cold_s", "first_step_warm_s")),
               _fmt(r.get("children_peak_rss_gib")), _fmt(r.get("other_procs_cpu_frac")))
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def _timed_table(records: Sequence[dict]) -> str:
    head = ("what", "variant", "shape", "dtype", "compile s", "median s", "min s", "max s", "peak RSS GiB",
            "GFLOP", "TFLOP/s", "MFU", "retraced", "others' CPU")
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for r in records:
        row = (r["what"], r["variant"], _shape(r), r.get("dtype"), _fmt(r.get("compile_s")),
               _fmt(r.get("median_s"), ".4g"),
               _fmt(r.get("min_s"), ".4g"), _fmt(r.get("max_s"), ".4g"), _fmt(r.get("peak_rss_gib")),
               _fmt(r["flops"] / 1e9 if r.get("flops") else None, ".5g"), _fmt(r.get("achieved_tflops"), ".4g"),
               _fmt(r.get("mfu"), ".1%") if r.get("mfu") is not None else "-", _fmt(r.get("recompiled")),
               _fmt(r.get("other_procs_cpu_frac")))
        lines.append("| " + " | ".join(row) + " |")
    return "\n".join(lines)


def append_jsonl(path: str, records: Sequence[dict]) -> None:
    """Appends records to a JSON-lines file atomically (the old lines and the new ones written together)."""
    old = ""
    if os.path.exists(path):
        with open(path) as f:
            old = f.read()
        if old and not old.endswith("\n"):
            old += "\n"
    files.write_text(path, old + "".join(json.dumps(r, sort_keys=True) + "\n" for r in records))
