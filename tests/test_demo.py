"""The README main job (`python -m bridge_jax.demo`), end to end in a subprocess, with its short config."""

from __future__ import annotations

import json
import os
import subprocess
import sys

from tests.train_helpers import REPO


def test_demo_short_runs_end_to_end_and_keeps_a_compile_cache(tmp_path):
    wd = tmp_path / "demo"
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    env.pop("JAX_COMPILATION_CACHE_DIR", None)  # the per-user cache folder must be used
    env["BRIDGE_JAX_CACHE_DIR"] = str(tmp_path / "user_cache")
    env.pop("JAX_NUM_CPU_DEVICES", None)
    r = subprocess.run([sys.executable, "-m", "bridge_jax.demo", "--short", f"--workdir={wd}"], env=env, cwd=REPO,
                       capture_output=True, text=True, timeout=900)
    assert r.returncode == 0, r.stderr[-3000:]
    summary = json.loads((wd / "demo_summary.json").read_text())
    assert summary["steps"] == 30 and not summary["interrupted"]
    # The validation numbers are real EPEs against a positive zero-motion baseline, not placeholders.
    assert summary["zero_flow_epe"] > 0.5 and summary["zero_disp_epe"] > 0.5
    assert 0.2 < summary["val_flow_epe_vs_zero"] < 5.0
    assert (wd / "eval" / "results.md").is_file() and os.listdir(wd / "eval" / "pictures")
    results = (wd / "eval" / "results.md").read_text()
    assert "zero" in results.lower() and "sgbm" in results.lower()
    cache = tmp_path / "user_cache"
    assert cache.is_dir() and os.listdir(cache), "the demo should keep its compiled functions in the user's cache"
    assert not (wd / "xla_cache").exists()
    assert "Where things are" in r.stdout
