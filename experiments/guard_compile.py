"""Compile and step time of the full2 train step (2 cycles, 512x256, plain) with the committed non-finite guard
or the previous one (loss + per-leaf isfinite of the gradients, as of commit c9c35a2), one variant per run.

    .venv/bin/python experiments/guard_compile.py current     # then: ... previous  (results/perf.md, 2026-12-01)
"""
import importlib.util
import os
import resource
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp

from bridge_jax import configs, network, train_step
from bridge_jax.bench import measure

variant = sys.argv[1] if len(sys.argv) > 1 else "current"
if variant not in ("current", "previous"):
    raise SystemExit("usage: guard_compile.py current|previous")
cfg = configs.load("full2")
cfg.global_batch, cfg.micro_batch = 2, 0
run = measure.bench_run(cfg)
graphdef, params = network.init_params(jax.random.key(0), run.model.config, run.model.separate)
net = run.model.network(graphdef)
tx, schedule = train_step.make_optimizer(run.optimizer, 1000)
state = train_step.create_train_state(params, tx, jax.random.key_data(jax.random.key(1)))
cycles = jnp.zeros((2, 4, run.height, run.width, 3), jnp.float32)
if variant == "previous":  # train_step() looks apply_gradients up in its module: swap in the old one
    repo = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    src = subprocess.run(["git", "show", "c9c35a2:bridge_jax/train_step.py"], cwd=repo, capture_output=True,
                         text=True, check=True).stdout
    with tempfile.NamedTemporaryFile("w", suffix=".py", delete=False) as f:
        f.write(src)
    spec = importlib.util.spec_from_file_location("train_step_previous", f.name)
    old = importlib.util.module_from_spec(spec)
    sys.modules["train_step_previous"] = old
    spec.loader.exec_module(old)
    train_step.apply_gradients = old.apply_gradients
step = train_step.make_train_step(net, run.loss, tx, schedule)
t0 = time.perf_counter()
lowered = step.lower(state, cycles)
t1 = time.perf_counter()
compiled = lowered.compile()
t2 = time.perf_counter()
print(f"{variant}: lower {t1 - t0:.1f} s, compile {t2 - t1:.1f} s", flush=True)
for i in range(3):
    t0 = time.perf_counter()
    state, metrics = compiled(state, cycles)
    jax.block_until_ready(metrics["loss"])
    print(f"{variant}: step {i} {time.perf_counter() - t0:.2f} s", flush=True)
print(f"{variant}: peak RSS {resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20:.2f} GiB")
