"""The prepared accelerator run (experiments/gpu/run.py) in its CPU dry-run mode: the records it writes carry the
numbers the GPU run must report, consistent with each other."""
import json
import os
import shutil
import subprocess
import sys

import pytest

from tests.train_helpers import REPO

SCRIPT = os.path.join(REPO, "experiments", "gpu", "run.py")


def _run(tmp_path, *extra, timeout=900):
    out = tmp_path / "gpu.jsonl"
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_NUM_CPU_DEVICES", None)
    r = subprocess.run([sys.executable, SCRIPT, "--dry-run", "--out", str(out), *extra], env=env, cwd=REPO,
                       capture_output=True, text=True, timeout=timeout)
    assert r.returncode == 0, r.stderr[-3000:]
    return [json.loads(line) for line in out.read_text().splitlines()], r.stdout


def _check_measurement(rec):
    assert rec["compile_s"] > 0 and rec["median_s"] > 0 and rec["flops"] > 0
    assert rec["recompiled"] is False and rec["traces_timed"] == 0
    # achieved TFLOP/s is the XLA FLOP count over the measured time (recomputed here, not read back)
    assert rec["achieved_tflops"] == pytest.approx(rec["flops"] / rec["median_s"] / 1e12, rel=2e-2, abs=1e-5)
    assert (rec["height"], rec["width"]) == (64, 128)


@pytest.mark.slow
def test_dry_run_train_step_and_inference_records(tmp_path):
    recs, stdout = _run(tmp_path, "--only", "train_step_f32,inference_f32")
    assert [r["label"] for r in recs] == ["train_step float32, 2 cycles", "inference float32, 1 pair"]
    for r in recs:
        _check_measurement(r)
    assert recs[0]["cycles"] == 2 and recs[0]["dtype"] == "float32" and recs[0]["what"] == "train_step"
    assert recs[1]["pairs_per_call"] == 1
    assert "| train_step float32, 2 cycles |" in stdout


def test_upstream_without_a_harness_is_recorded_as_skipped(tmp_path):
    recs, _ = _run(tmp_path, "--only", "peer")
    assert [r["what"] for r in recs] == ["peer_train", "peer_train", "peer_infer"]
    assert all(r["skipped"] == "no --peer-dir" for r in recs)


@pytest.mark.slow
def test_whole_dry_run_with_upstream_on_cpu(tmp_path):
    """Every measurement; upstream too where a PyTorch interpreter and the harness are set up
    (BRIDGE_JAX_PEER_PYTHON, BRIDGE_JAX_PEER_DIR, BDF_SRC as for `bench --peer`)."""
    py, peer_dir = os.environ.get("BRIDGE_JAX_PEER_PYTHON"), os.environ.get("BRIDGE_JAX_PEER_DIR")
    extra = ["--peer-dir", peer_dir, "--peer-python", py] if py and peer_dir and shutil.which(py) else []
    recs, stdout = _run(tmp_path, *extra)
    jax_recs = [r for r in recs if not r["what"].startswith("peer")]
    assert len(jax_recs) == 5
    for r in jax_recs:
        _check_measurement(r)
    assert {r["dtype"] for r in jax_recs} == {"float32", "bfloat16"}
    if extra:
        peers = [r for r in recs if r["what"].startswith("peer")]
        assert all(r.get("median_s", 0) > 0 for r in peers), peers
        assert "bf16 train step throughput vs upstream AMP" in stdout
