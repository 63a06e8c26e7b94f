"""bridge_jax.bench: the CLI's JSON, the recompilation detector, bf16 on CPU, micro-batched == plain step.

Tiny ResNet-MD at 128x256 (64x128 hits XLA:CPU's slow small-conv path, see the performance note). The plain vs
micro-batched *numerics* are tested at the step level by tests/test_train.py::test_micro_batched_step_equals_plain_step;
here the same comparison runs through the bench's own builder (`bench.build_train_step`), marked slow because
compiling the cycle loss twice costs tens of seconds on 2 cores.
"""

from __future__ import annotations

import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import bench
from bridge_jax.models import layers
from tests.train_helpers import REPO, enable_compilation_cache, plain_loss_and_grads, subprocess_env


@pytest.fixture(scope="module", autouse=True)
def _cache():
    restore = enable_compilation_cache()
    yield
    restore()


def _cli(*argv, timeout=600):
    env = subprocess_env()
    return subprocess.run([sys.executable, "-m", "bridge_jax.bench", *argv], cwd=REPO, env=env,
                          capture_output=True, text=True, timeout=timeout)


def test_cli_inference_json_has_every_field(tmp_path):
    out = tmp_path / "r.jsonl"
    p = _cli("--what", "inference", "--config", "default:local", "--repeats", "2", "--warmup", "1",
             "--pairs", "2", "--json", str(out))
    assert p.returncode == 0, p.stderr[-2000:]
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert len(lines) == 1
    r = lines[0]
    missing = [k for k in bench.REQUIRED_FIELDS if k not in r]
    assert not missing, missing
    assert r["what"] == "inference" and r["height"] == 128 and r["width"] == 256 and r["dtype"] == "float32"
    assert r["model"] == "resnet_md_tiny" and r["pairs_per_call"] == 2
    assert r["min_s"] <= r["median_s"] <= r["max_s"] and len(r["times_s"]) == 2
    assert r["flops"] > 1e8 and r["achieved_tflops"] > 0 and 0 < r["mfu"] < 5
    assert r["recompiled"] is False and r["traces_timed"] == 0 and r["compiles_timed"] == 0
    assert r["peak_rss_gib"] > 0.05 and r["jax_version"] == jax.__version__ and r["date"].endswith("Z")
    # stdout: the table, then the same record as one JSON line
    json_lines = [json.loads(line) for line in p.stdout.splitlines() if line.startswith("{")]
    assert json_lines and json_lines[0]["median_s"] == r["median_s"]
    assert "| inference |" in p.stdout
    # --json appends (a second run adds a line, nothing lost)
    p2 = _cli("--what", "inference", "--config", "default:local", "--repeats", "1", "--warmup", "1",
              "--dtype", "bfloat16", "--no-peak", "--json", str(out))
    assert p2.returncode == 0, p2.stderr[-2000:]
    lines = [json.loads(line) for line in out.read_text().splitlines()]
    assert [x["dtype"] for x in lines] == ["float32", "bfloat16"]
    assert lines[1]["mfu"] is None and lines[1]["peak_tflops"] is None


def test_cli_bad_input_one_line_error(tmp_path):
    p = _cli("--what", "inference", "--config", "no_such_config")
    assert p.returncode == 2 and "unknown config 'no_such_config'" in p.stderr
    assert "Traceback" not in p.stderr and len(p.stderr.strip().splitlines()) == 1
    p = _cli("--what", "inference", "--config", "default:local", "--height", "100")
    assert p.returncode == 2 and "multiples of 64" in p.stderr and "Traceback" not in p.stderr
    p = _cli("--what", "inference", "--config", "default:local", "--set", "loss.nope=1")
    assert p.returncode == 2 and "no field 'loss.nope'" in p.stderr


def test_trace_counter_detects_shape_change():
    f = jax.jit(lambda x: jnp.sin(x) * 2.0)
    xs = {0: jnp.ones((8,)), 1: jnp.ones((8,)), 2: jnp.ones((8,)), 3: jnp.ones((9,))}  # call 3 changes shape
    steady = bench.time_calls(lambda i: f(xs[min(i, 2)]), repeats=3, warmup=1)
    assert steady["recompiled"] is False and steady["traces_timed"] == 0 and steady["compiles_timed"] == 0
    changed = bench.time_calls(lambda i: f(xs[i]), repeats=3, warmup=1)
    assert changed["recompiled"] is True and changed["traces_timed"] >= 1 and changed["compiles_timed"] >= 1
    with pytest.raises(bench.RecompilationError):
        bench.time_calls(lambda i: f(jnp.ones((20 + i,))), repeats=2, warmup=1, strict=True)


def test_known_peaks_and_table():
    assert bench.known_peak_tflops("NVIDIA H100 80GB HBM3", "bfloat16") == 989.0
    assert bench.known_peak_tflops("NVIDIA H100 PCIe", "bfloat16") == 756.0
    assert bench.known_peak_tflops("NVIDIA H200", "float32") == 494.7
    assert bench.known_peak_tflops("NVIDIA A100-SXM4-40GB", "bfloat16") == 312.0
    assert bench.known_peak_tflops("TPU v4", "bfloat16") == 275.0
    assert bench.known_peak_tflops("TPU v5 lite", "bfloat16") == 197.0
    assert bench.known_peak_tflops("TPU v6 lite", "bfloat16") == 918.0
    assert bench.known_peak_tflops("cpu", "float32") is None
    rec = dict(what="loss", variant="forward", cycles=2, height=256, width=512, dtype="float32", compile_s=1.0,
               median_s=0.5, min_s=0.4, max_s=0.6, peak_rss_gib=1.0, flops=2e9, achieved_tflops=0.004, mfu=0.1,
               recompiled=False, other_procs_cpu_frac=0.0)
    t = bench.table([rec])
    assert "| loss | forward | 2x256x512 | float32 |" in t and "10.0%" in t


def test_random_maps_are_consistent():
    m = bench.random_maps(8, 128, 256)
    for s in range(4):
        h, w = 128 >> s, 256 >> s
        assert m["px"][s].shape == (8, h, w, 2)
        np.testing.assert_allclose(m["px"][s], m["frac"][s] * np.array([w, h], np.float32), rtol=1e-6)
        assert np.abs(m["frac"][s]).max() < 0.05


def _tiny_config(**kw):
    cfg = bench.load_config("default:local", [f"{k}={v}" for k, v in kw.items()])
    return cfg


@pytest.mark.slow
def test_bf16_train_step_runs_on_cpu():
    """The bf16 compute path (params / optimizer float32) through the bench's builder: finite, params stay f32."""
    cfg = _tiny_config(**{"loss.tasks": "stereo_only"})  # stereo pairs only: the cheapest loss to compile
    cfg.dtype = "bfloat16"
    cfg.global_batch = 1
    state, step, cycles, info, _, _ = bench.build_train_step(cfg, micro_batch=0)
    assert info["pairs_per_step"] == 4
    state, m = step(state, cycles)
    assert np.isfinite(float(m["loss"])) and int(m["nonfinite"]) == 0 and int(state["step"]) == 1
    assert {x.dtype for x in jax.tree.leaves(state["params"])} == {jnp.dtype(jnp.float32)}


@pytest.mark.slow
def test_micro_batched_equals_plain_through_bench_builder():
    """bench.build_train_step(micro_batch=2) gives the plain step's loss and gradients.

    Loss and every loss term agree to <= 1e-5 (measured: identical to 7 digits). Gradients: the micro-batched
    forward runs the convolutions at batch 2 instead of 8, so the maps differ by float32 rounding; the loss has
    |.| kinks (L1, second-order smoothness of near-constant random-init maps) where such rounding flips a sign,
    which moves single gradient entries of the finest head by ~1e-4 (measured 2026-11-23 at 128x256: max abs
    diff 1.0e-4 on get_disp1.conv1.bias of magnitude 0.45, global relative L2 difference 4.8e-5). So gradients
    are compared by global relative L2 difference (<= 1e-4) and per-leaf max abs diff (<= 1e-3 * the leaf's max).
    Stereo-only loss: its masks do not depend on the maps, so no occlusion-threshold flips add to that;
    tests/test_train.py::test_micro_batched_step_equals_plain_step covers the flow+stereo loss on 8 devices.
    """
    cfg = _tiny_config(**{"loss.tasks": "stereo_only"})
    cfg.global_batch = 2
    state0, plain, cycles, _, run, net = bench.build_train_step(cfg, 0)
    _, micro, _, _, _, _ = bench.build_train_step(cfg, 2)
    params = state0["params"]
    (l1, t1), g1 = plain_loss_and_grads(net, run.loss)(params, cycles)
    (l2, t2), g2 = micro.loss_and_grads(params, cycles)
    assert abs(float(l1) - float(l2)) <= 1e-5
    for k in t1:
        assert abs(float(t1[k]) - float(t2[k])) <= 1e-5, k
    la, lb = jax.tree.leaves(g1), jax.tree.leaves(g2)
    num = sum(float(jnp.sum((a - b) ** 2)) for a, b in zip(la, lb)) ** 0.5
    den = sum(float(jnp.sum(a ** 2)) for a in la) ** 0.5
    assert num / den <= 1e-4
    for a, b in zip(la, lb):
        assert float(jnp.max(jnp.abs(a - b))) <= 1e-3 * max(float(jnp.max(jnp.abs(a))), 1e-6)
    # the full steps as the bench times them: same loss metric, both update
    s1, m1 = plain(jax.tree.map(jnp.copy, state0), cycles)
    s2, m2 = micro(jax.tree.map(jnp.copy, state0), cycles)
    assert abs(float(m1["loss"]) - float(m2["loss"])) <= 1e-5
    assert int(s1["step"]) == int(s2["step"]) == 1 and int(m2["nonfinite"]) == 0


def test_conv_backward_records_every_weight_gradient_method(monkeypatch):
    """--what conv_backward: per layer shape one record per weight-gradient method (XLA's, shifted dy, shifted
    x, XLA's in batch chunks, XLA's in NCHW), the same weight gradient (checked inside against XLA's), the time
    ratio and what "auto" picks; two small layers keep it quick."""
    import argparse
    monkeypatch.setattr(layers, "cpu_vector_isa", lambda: "AVX-512")  # "auto" differs without AVX-512
    monkeypatch.setattr(bench.measure, "CONV_LAYERS", ((4, 8, 16, 1, 3, ((1, 1), (1, 1))),
                                                       (4, 64, 8, 2, 2, ((1, 0), (1, 0)))))
    config = bench.load_config("default:local")
    recs = bench.measure_conv_backward(config, argparse.Namespace(repeats=2, warmup=1, conv_batch=3))
    assert [r["weight_grad"] for r in recs] == ["xla", "shift_dy", "shift_x", "xla_chunks", "xla_nchw"] * 2
    assert [r["layer"] for r in recs[::5]] == [[3, 32, 64, 8, 16, 1], [3, 32, 64, 64, 8, 2]]
    assert [r["kernel"] for r in recs[::5]] == [3, 2] and recs[5]["padding"] == [[1, 0], [1, 0]]
    assert {r["auto_picks"] for r in recs} == {"xla"}  # 8 channels; stride 2
    for r in recs:
        assert r["what"] == "conv_backward" and r["min_s"] <= r["median_s"] <= r["max_s"] and not r["recompiled"]
        assert r["flops"] > 0 and r["dw_rel_diff_vs_xla"] < 1e-5
    assert recs[1]["min_time_vs_xla"] == pytest.approx(recs[1]["min_s"] / recs[0]["min_s"], rel=1e-2)
