r"""README main job: a small correlation network on the built-in synthetic stereo video (9-18 minutes on 2 CPU
cores).

Same cycle of four pairs, one network shared by stereo and flow, the paper's occlusion, smoothness, left-right
losses, in two stages: 1,750 steps at 64x128, then 300 at 128x256 from those weights; the model of the second
stage is the demo model. Two things go beyond the paper, chosen by an ablation of the training
switches (1,000-step runs of each):

* the model is `pwc_lite` (a cost volume on normalised features, coarse to fine, one shared estimator), because
  the paper's encoder-decoder hardly learns flow on this data even when trained with ground truth;
* gradient clipping (`clip_grad_norm=1.0`); every other training switch of `losses.LossConfig` stays at the
  paper's setting, because none of them lowered the flow error in the ablation.

Watch `val/flow_epe_vs_zero` and `val/disp_epe_all` (metrics.jsonl / TensorBoard); the README's "The two
commands" says what a run reaches.

  bridge-demo --workdir=work/demo                        # the recipe + evaluate + report (what `make demo` runs)
  bridge-train --config=demo --workdir=work/demo/train   # training only: both stages (resumable)

The two phases are the two stages of one recipe (`bridge_jax.recipe`): `coarse`, 1,750 steps at 64x128 from
random initialisation, then `finish`, 300 steps at 128x256 from its final params; the demo model is the
`finish` stage's. Why two: a model that only ever saw 64x128 frames is lost on real photographs, at 64x128 (one
working pixel is 4-6 of the photo's) and at larger sizes alike (finer texture, larger motions); 300 steps at
128x256 on top of it, in about the time of the 750 steps at 64x128 they replace, is what carries it over to real
images at the same flow error on its own validation frames (0.49x zero motion).

Arguments (comma-separated, e.g. `demo:resnet_md_tiny,paper_loss`): `short` = a 1-minute smoke run of both
stages; `resnet_md_tiny` = the paper's network (tiny widths) instead of pwc_lite; `paper_loss` = every training
switch at the paper's setting; `real` = the synthetic scenes that carry over to real images (photo textures,
slanted and rotating objects, varied rigs, per-camera photometric differences: `data.synthetic_scene=real`).
The shipped `long` model has a recipe of its own: `--config=long` (bridge_jax/configs/long.py).
"""

import ml_collections

from bridge_jax.configs import default

ARGS = ("short", "resnet_md_tiny", "paper_loss", "real")
GONE = {"finish": "the demo's second phase is now the `finish` stage of the demo's recipe: --config=demo runs both "
                  "stages (--config.stage_overrides.finish.KEY=VALUE sets one of its fields)",
        **{a: "the stages of the shipped `long` model are the recipe --config=long (bridge_jax/configs/long.py)"
           for a in ("long", "selfsup", "motion", "census", "hires")}}


def get_config(arg=None):
    opts = [a for a in (arg or "").split(",") if a]
    gone = [a for a in opts if a in GONE]
    if gone:
        raise ValueError(f"demo.py: config argument {gone[0]!r} is gone: {GONE[gone[0]]}")
    unknown = sorted(set(opts) - set(ARGS))
    if unknown:
        raise ValueError(f"demo.py: unknown config argument(s) {unknown} (expected a comma-separated subset of "
                         f"{list(ARGS)})")
    c = base_config(opts)
    c.stages = ("coarse", "finish")
    c.stage_overrides = ml_collections.ConfigDict()
    c.stage_overrides.coarse = ml_collections.ConfigDict()  # the base as it is: 1,750 steps at 64x128
    c.stage_overrides.finish = finish_stage()
    return _short(c) if "short" in opts else c


def base_config(opts=()):
    """The demo's base config (its `coarse` stage), without stages: also the base of the `long` recipe."""
    c = default.get_config(None)
    if "resnet_md_tiny" in opts:
        c.model = default.model_section("resnet_md_tiny")
        c.model.head_init = "zeros"  # every map starts at zero motion (see models.init)
    else:
        c.model = default.model_section("pwc_lite")  # zero output heads by default
    # 64x128: the loss, not the small network, dominates a step, so 4x fewer pixels than 128x256 buy 4x the steps.
    c.height, c.width = 64, 128
    # One cycle (8 pair-forwards) per step: it reaches the flow error of fewer two-cycle steps in less compute,
    # which is what fits the demo in ~12 minutes on 2 cores.
    c.global_batch = 1
    c.micro_batch = 0  # a small model: one jitted step beats many small calls
    c.lr = 1e-3
    # The first of the demo's two stages: 1,750 steps here, then `finish` (300 steps at 128x256) from these
    # weights, in about the time 2,500 steps here took alone.
    c.loop.num_train_steps = 1750
    # The paper's step schedule, compressed: 250-step "epochs", so the lr halves at the start of epoch 4 (step
    # 1000); the second stage runs at the lr of the next halving (epoch 7, step 1750).
    c.loop.steps_per_epoch = 250
    if "paper_loss" not in opts:
        # The ablation's pick (1,000-step runs): every loss switch left at the
        # paper's setting (census, finest-only, 1st-order smoothness, a late occlusion start and coordinate
        # channels did not lower pwc_lite's flow error), plus global-norm gradient clipping, which matched the
        # paper loss on flow and lowered the disparity error.
        c.clip_grad_norm = 1.0
    c.data.synthetic_num = 20_000
    c.data.num_workers = 0
    c.loop.update(checkpoint_every=500, keep_checkpoints=2, log_every=25, image_every=250, eval_every=250)
    c.eval.num_samples = 16
    c.eval.batch = 8
    if "real" in opts:  # the synthetic scenes that carry over to real images (data.synthetic_scene)
        c.data.synthetic_scene = "real"
    return c


def _short(c):
    """A 1-minute smoke run of the same recipe: 30 steps of `coarse`, 10 of `finish`."""
    for name, steps in (("coarse", 30), ("finish", 10)):
        stage = c.stage_overrides[name]
        if "loop" not in stage:
            stage.loop = ml_collections.ConfigDict()
        stage.loop.update(num_train_steps=steps, checkpoint_every=steps // 2, eval_every=steps // 2,
                          image_every=steps // 2)
    c.eval.num_samples = 4
    return c


FINISH_SIZE = (128, 256)
"""The working size of the demo's second stage."""
FINISH_STEPS = 300
"""Steps of the demo's second stage."""
FINISH_LR = 2.5e-4
"""Learning rate of the demo's second stage (constant): where the first stage's schedule arrives at its last step
(its halving at step 1,750)."""


def finish_stage() -> ml_collections.ConfigDict:
    """The demo's second stage: FINISH_STEPS steps at 128x256 (4x the pixels) at the first stage's last lr,
    from its weights. A model that only ever saw 64x128 frames reads a real photograph at that size, where one
    working pixel is 4-6 of the photo's (Motorcycle D1 61.6 %), and is lost at larger sizes, whose finer
    texture, larger motions and wider uniform regions it never saw (44-50 %); a short second stage at twice the
    size per side is what carries it over."""
    return ml_collections.ConfigDict({
        "height": FINISH_SIZE[0], "width": FINISH_SIZE[1], "lr": FINISH_LR,
        "loop": {"num_train_steps": FINISH_STEPS, "steps_per_epoch": FINISH_STEPS,  # constant lr
                 "checkpoint_every": FINISH_STEPS // 2, "eval_every": FINISH_STEPS // 2,
                 "image_every": FINISH_STEPS // 2},
        "eval": {"batch": 4}})
