r"""README main job: a small correlation network on the built-in synthetic stereo video (9-18 minutes on 2 CPU
cores).

Same cycle of four pairs, one network shared by stereo and flow, the paper's occlusion, smoothness, left-right
losses, in two phases: 1,750 steps at 64x128, then 300 at 128x256 from those weights (`demo:finish`); the model
of the second phase is the demo model. Two things go beyond the paper, chosen by an ablation of the training
switches (1,000-step runs of each):

* the model is `pwc_lite` (a cost volume on normalised features, coarse to fine, one shared estimator), because
  the paper's encoder-decoder hardly learns flow on this data even when trained with ground truth;
* gradient clipping (`clip_grad_norm=1.0`); every other training switch of `losses.LossConfig` stays at the
  paper's setting, because none of them lowered the flow error in the ablation.

Watch `val/flow_epe_vs_zero` and `val/disp_epe_all` (metrics.jsonl / TensorBoard); the README's "The two
commands" says what a run reaches.

  bridge-demo --workdir=work/demo                        # both phases + evaluate + report (what `make demo` runs)
  bridge-train --config=demo --workdir=work/demo/train_64x128          # training only: the first phase,
  bridge-train --config=demo:finish --workdir=work/demo/train          # then the second

Why two phases: a model that only ever saw 64x128 frames is lost on real photographs, at 64x128 (one working
pixel is 4-6 of the photo's) and at larger sizes alike (finer texture, larger motions); 300 steps at 128x256 on
top of it, in about the time of the 750 steps at 64x128 they replace, cut its Middlebury Motorcycle D1 from
61.6 % to 34.1 % and its photo flow error from 6.40 to 4.25 px (experiments/results/real_images.md,
2026-12-03), at the same flow error on its own validation frames (0.49x zero motion).

Arguments (comma-separated, e.g. `demo:resnet_md_tiny,paper_loss`): `short` = a 1-minute smoke run; `finish` = the
second phase (from `work/demo/train_64x128`; `--config.init_from=DIR` if it lives elsewhere);
`resnet_md_tiny` = the paper's network (tiny widths) instead of pwc_lite; `paper_loss` = every training switch
at the paper's setting; `real` = the synthetic scenes that carry over to real images (photo textures, slanted and
rotating objects, varied rigs, per-camera photometric differences: `data.synthetic_scene=real`), and with `long`
stage 1 of the shipped `long` model (the demo model fine-tuned on them at 128x256, 4,000 steps, lr 5e-4);
`long,real,selfsup` = its stage 2 (1,000 steps with the self-supervision term, lr 1.25e-4, initialised from
stage 1's workdir `work/long`);
`long,real,selfsup,motion` = its stage 3 (1,500 steps with vertical motion: `data.synthetic_scene=real_motion` and
`data.augment_shift=0.08`, lr 2.5e-4 halved at 1,000, initialised from stage 2's workdir `work/long2`);
`long,real,selfsup,motion,census` = its stage 4 (1,000 steps with the census photometric term,
`loss.photometric=census`, at a constant lr 1.25e-4, initialised from stage 3's workdir `work/long3`);
`long,real,selfsup,motion,census,hires` = its stage 5, the shipped `long` (250 steps of stage 4's recipe at
256x512, initialised from stage 4's workdir `work/long4`). Each stage needs the arguments of the stages before it
(`LONG_STAGES`);
`long` = a longer recipe (128x256, 6,000 steps: under 2 h
on 2 CPU cores; resumable, so it can be stopped and continued).
"""

from bridge_jax.configs import default

ARGS = ("short", "resnet_md_tiny", "paper_loss", "finish", "long", "real", "selfsup", "motion", "census", "hires")


def get_config(arg=None):
    opts = [a for a in (arg or "").split(",") if a]
    unknown = sorted(set(opts) - set(ARGS))
    if unknown:
        raise ValueError(f"demo.py: unknown config argument(s) {unknown} (expected a comma-separated subset of "
                         f"{list(ARGS)})")
    chain = ["long"] + [arg for arg, _ in LONG_STAGES]
    for i, arg in enumerate(chain[2:], 2):  # a stage of `long` needs every stage before it
        missing = [a for a in chain[:i] if a not in opts]
        if arg in opts and missing:
            raise ValueError(f"demo.py: config argument {arg!r} is a stage of the `long` model and needs "
                             f"{missing} too (e.g. demo:{','.join(chain[:i + 1])})")
    c = default.get_config(None)
    if "resnet_md_tiny" in opts:
        c.model = default.model_section("resnet_md_tiny")
        c.model.head_init = "zeros"  # every map starts at zero motion (see models.init)
    else:
        c.model = default.model_section("pwc_lite")  # zero output heads by default
    # 64x128: the loss, not the small network, dominates a step, so 4x fewer pixels than 128x256 buy 4x the steps.
    c.height, c.width = 64, 128
    # One cycle (8 pair-forwards) per step: 2,500 steps of it reach the same flow error as about 1,500 steps of two
    # cycles, in half the compute of the 2,500 two-cycle steps used before (the demo recipe rows of
    # experiments/results/perf.md, 2026-12-02), which is what fits the demo in ~12 minutes on 2 cores.
    c.global_batch = 1
    c.micro_batch = 0  # a small model: one jitted step beats many small calls
    c.lr = 1e-3
    # The first of the demo's two phases (`bridge-demo` runs both): 1,750 steps here, then `demo:finish` (300
    # steps at 128x256) from these weights, in about the time 2,500 steps here took alone.
    c.loop.num_train_steps = 1750
    # The paper's step schedule, compressed: 250-step "epochs", so the lr halves at the start of epoch 4 (step
    # 1000); the second phase runs at the lr of the next halving (epoch 7, step 1750).
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
    if "finish" in opts:  # the demo's second phase: the same at 128x256, from the first phase's weights
        if "long" in opts:
            raise ValueError("demo.py: config argument 'finish' is the demo's second phase; it does not combine "
                             "with 'long'")
        _finish(c)
    if "long" in opts:  # the same recipe at 4x the pixels and 2.4x the steps, two cycles per step
        c.height, c.width = 128, 256
        c.global_batch = 2
        c.loop.update(num_train_steps=6000, steps_per_epoch=600,  # lr halves at steps 2400 and 4200
                      checkpoint_every=500, eval_every=500, image_every=500)
        c.eval.batch = 4
    if "real" in opts:  # the synthetic scenes that carry over to real images (data.synthetic_scene)
        c.data.synthetic_scene = "real"
    if "long" in opts and "real" in opts:  # the stages of the shipped `long` model, each on top of the one before
        for arg, stage in LONG_STAGES:
            if arg not in opts:
                break
            stage(c)
    return _short(c, "finish" in opts) if "short" in opts else c


def _short(c, finish: bool = False):
    """A 1-minute smoke run of the same pipeline (10 steps of the second phase)."""
    steps = 10 if finish else 30
    c.loop.update(num_train_steps=steps, checkpoint_every=steps // 2, eval_every=steps // 2, image_every=steps // 2)
    c.eval.num_samples = 4
    return c


FINISH_SIZE = (128, 256)
"""The working size of the demo's second phase."""
FINISH_STEPS = 300
"""Steps of the demo's second phase."""
FINISH_LR = 2.5e-4
"""Learning rate of the demo's second phase (constant): where the first phase's schedule arrives at its last step
(its halving at step 1,750)."""
FINISH_INIT_FROM = "work/demo/train_64x128"
"""Where the second phase finds the first phase's weights (`bridge-demo` passes its own WORKDIR/train_64x128)."""


def _finish(c):
    """The demo's second phase: FINISH_STEPS steps at 128x256 (4x the pixels) at the first phase's last lr,
    from its weights. A model that only ever saw 64x128 frames reads a real photograph at that size, where one
    working pixel is 4-6 of the photo's (Motorcycle D1 61.6 %), and is lost at larger sizes, whose finer
    texture, larger motions and wider uniform regions it never saw (44-50 %); a short second phase at twice the
    size per side is what carries it over (the real-image checks of experiments/results/real_images.md)."""
    c.init_from = FINISH_INIT_FROM
    c.height, c.width = FINISH_SIZE
    c.lr = FINISH_LR
    c.loop.update(num_train_steps=FINISH_STEPS, steps_per_epoch=FINISH_STEPS,  # constant lr
                  checkpoint_every=FINISH_STEPS // 2, eval_every=FINISH_STEPS // 2, image_every=FINISH_STEPS // 2)
    c.eval.batch = 4


def _stage1_real(c):
    """Stage 1: the demo model fine-tuned on the `real` scenes at 128x256."""
    c.init_from = "demo"
    c.lr = 5e-4
    c.loop.update(num_train_steps=4000, steps_per_epoch=500, checkpoint_every=250)  # lr halves at 2000


def _stage2_selfsup(c):
    """Stage 2: self-supervision on top of the finished stage 1 (the loss's teacher term: full-frame maps, gradient
    stopped, supervise the maps of crops), at stage 1's last lr, from stage 1's workdir (--config.init_from=DIR if
    it lives elsewhere)."""
    c.init_from = "work/long"
    c.lr = 1.25e-4
    c.loss.self_supervision = 0.3
    c.loop.update(num_train_steps=1000, steps_per_epoch=1000, eval_every=250)


def _stage3_motion(c):
    """Stage 3: vertical motion (a rig that pitches, rolls and moves up and down, objects that move vertically,
    frames t+1 cut up to 8 % of the height away from t), which the scenes before it lacked."""
    c.init_from = "work/long2"
    c.lr = 2.5e-4
    c.data.synthetic_scene = "real_motion"
    c.data.augment_shift = 0.08
    c.loop.update(num_train_steps=1500, steps_per_epoch=250, eval_every=250)  # lr halves at 1000


def _stage4_census(c):
    """Stage 4: the census photometric term (robust to the exposure and gain differences between real cameras,
    which SSIM + L1 only partly absorbs), at stage 2's lr."""
    c.init_from = "work/long3"
    c.lr = 1.25e-4
    c.loss.photometric = "census"
    c.loop.update(num_train_steps=1000, steps_per_epoch=1000)  # constant lr


def _stage5_hires(c):
    """Stage 5: the same at 256x512, so that one working pixel is 1-2 input pixels of a photograph (fine detail,
    object edges, sub-pixel shifts the 128x256 stages never saw)."""
    c.init_from = "work/long4"
    c.height, c.width = 256, 512
    c.loop.update(num_train_steps=250, checkpoint_every=125)


LONG_STAGES = (("real", _stage1_real), ("selfsup", _stage2_selfsup), ("motion", _stage3_motion),
               ("census", _stage4_census), ("hires", _stage5_hires))
"""The stages of the shipped `long` model, in order: with `long`, each argument applies its stage on top of the
stages before it, and needs all of them (`demo:long,real,selfsup` is stage 2)."""
