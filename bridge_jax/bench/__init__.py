"""Benchmarks (`bridge-bench`, documented in `bridge_jax.bench.cli`).

  timing   time_calls: blocked wall times, traces/compiles during the timed calls, host RSS and load
  device   peak FLOP/s (MFU) and device memory
  measure  train step, inference, loss, conv backward, input pipeline
  peer     the upstream PyTorch code beside it (--peer)
  first    time to a first answer: fresh predict / train processes, cold and warm compilation cache
  records  record fields, the table, the JSON-lines file
  cli      the command line
"""

from bridge_jax.bench.cli import PROCESS_WHATS, WHATS, load_config, main, run
from bridge_jax.bench.device import PEAK_TFLOPS, known_peak_tflops
from bridge_jax.bench.measure import (CONV_LAYERS, bench_run, build_train_step, measure_conv_backward,
                                      random_maps)
from bridge_jax.bench.records import REQUIRED_FIELDS, table
from bridge_jax.bench.timing import BenchError, RecompilationError, time_calls

__all__ = ["PROCESS_WHATS", "WHATS", "load_config", "main", "run", "PEAK_TFLOPS", "known_peak_tflops", "CONV_LAYERS",
           "bench_run", "build_train_step", "measure_conv_backward", "random_maps", "REQUIRED_FIELDS", "table",
           "BenchError", "RecompilationError", "time_calls"]
