r"""README main job: a small, fast model on the built-in synthetic stereo video (~10 minutes on 2 CPU cores).

Same losses and training code as the paper configs, with a tiny ResNet-MD at 128x256 and a larger learning
rate, so that learning is visible within minutes: the held-out validation flow EPE falls well below the
zero-motion baseline (`val/flow_epe_vs_zero` in metrics.jsonl / TensorBoard).

  python -m bridge_jax.demo --workdir=work/demo          # train + evaluate + report (what `make demo` runs)
  python -m bridge_jax.train --config=bridge_jax/configs/demo.py --workdir=work/demo   # training only
"""

import ml_collections

from bridge_jax import models
from bridge_jax.configs import default


def get_config(arg=None):
    c = default.get_config(None)
    c.variant = "demo"
    c.model = default.model_section("resnet_md_tiny")
    c.height, c.width = 128, 256
    c.global_batch = 2
    c.micro_batch = 0  # a tiny model: one jitted step beats many small calls
    c.lr = 5e-4
    c.num_train_steps = 1500
    c.steps_per_epoch = 500  # lr halves at "epochs" 4, 7, ... = never within the demo's 1500 steps
    c.data.synthetic_num = 20_000
    c.data.num_workers = 0
    c.checkpoint_every = 250
    c.keep_checkpoints = 2
    c.log_every = 10
    c.image_every = 250
    c.eval_every = 250
    c.eval.num_samples = 16
    c.eval.batch = 8
    if arg == "short":  # a 1-minute smoke run of the same pipeline
        c.num_train_steps = 30
        c.checkpoint_every = c.eval_every = c.image_every = 15
        c.eval.num_samples = 4
    elif arg:
        raise ValueError(f"demo.py: unknown config argument {arg!r} (expected nothing or 'short')")
    return c
