r"""README main job: a small correlation network on the built-in synthetic stereo video (7-15 minutes on 2 CPU
cores).

Same cycle of four pairs, one network shared by stereo and flow, the paper's occlusion, smoothness, left-right
losses, at 64x128. Two things go beyond the paper, chosen by an ablation of the training switches (1,000-step
runs of each):

* the model is `pwc_lite` (a cost volume on normalised features, coarse to fine, one shared estimator), because
  the paper's encoder-decoder hardly learns flow on this data even when trained with ground truth;
* gradient clipping (`clip_grad_norm=1.0`); every other training switch of `losses.LossConfig` stays at the
  paper's setting, because none of them lowered the flow error in the ablation.

Watch `val/flow_epe_vs_zero` and `val/disp_epe_all` (metrics.jsonl / TensorBoard); the README's "The two
commands" says what a run reaches.

  bridge-demo --workdir=work/demo                        # train + evaluate + report (what `make demo` runs)
  bridge-train --config=demo --workdir=work/demo         # training only

Arguments (comma-separated, e.g. `demo:resnet_md_tiny,paper_loss`): `short` = a 1-minute smoke run;
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
256x512, initialised from stage 4's workdir `work/long4`);
`long` = a longer recipe (128x256, 6,000 steps: under 2 h
on 2 CPU cores; resumable, so it can be stopped and continued).
"""

from bridge_jax.configs import default

ARGS = ("short", "resnet_md_tiny", "paper_loss", "long", "real", "selfsup", "motion", "census", "hires")


def get_config(arg=None):
    opts = [a for a in (arg or "").split(",") if a]
    unknown = sorted(set(opts) - set(ARGS))
    if unknown:
        raise ValueError(f"demo.py: unknown config argument(s) {unknown} (expected a comma-separated subset of "
                         f"{list(ARGS)})")
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
    c.loop.num_train_steps = 2500
    # The paper's step schedule, compressed: 250-step "epochs", so the lr halves at the starts of epochs 4 and 7
    # (steps 1000 and 1750).
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
    if "long" in opts:  # the same recipe at 4x the pixels and 2.4x the steps, two cycles per step
        c.height, c.width = 128, 256
        c.global_batch = 2
        c.loop.update(num_train_steps=6000, steps_per_epoch=600,  # lr halves at steps 2400 and 4200
                      checkpoint_every=500, eval_every=500, image_every=500)
        c.eval.batch = 4
    if "real" in opts:  # the synthetic scenes that carry over to real images (data.synthetic_scene)
        c.data.synthetic_scene = "real"
        if "long" in opts:  # the shipped `long` model: the demo model fine-tuned on them at 128x256
            c.init_from = "demo"
            c.lr = 5e-4
            c.loop.update(num_train_steps=4000, steps_per_epoch=500, checkpoint_every=250)  # lr halves at 2000
            if "selfsup" in opts:  # stage 2 of the shipped `long`: self-supervision on top of the finished stage 1
                # (the loss's teacher term: full-frame maps, gradient stopped, supervise the maps of crops), at
                # stage 1's last lr, from stage 1's workdir (--config.init_from=DIR if it lives elsewhere).
                c.init_from = "work/long"
                c.lr = 1.25e-4
                c.loss.self_supervision = 0.3
                c.loop.update(num_train_steps=1000, steps_per_epoch=1000, eval_every=250)
                if "motion" in opts:  # stage 3: vertical motion (a rig that pitches, rolls and moves up and down,
                    # objects that move vertically, frames t+1 cut up to 8 % of the height away from t), which
                    # the scenes before it lacked, on top of the finished stage 2 (its workdir `work/long2`)
                    c.init_from = "work/long2"
                    c.lr = 2.5e-4
                    c.data.synthetic_scene = "real_motion"
                    c.data.augment_shift = 0.08
                    c.loop.update(num_train_steps=1500, steps_per_epoch=250, eval_every=250)  # lr halves at 1000
                    if "census" in opts:  # stage 4: the census photometric term (robust to the exposure and
                        # gain differences between real cameras, which SSIM + L1 only partly absorbs), at stage
                        # 2's lr, on top of the finished stage 3 (its workdir `work/long3`)
                        c.init_from = "work/long3"
                        c.lr = 1.25e-4
                        c.loss.photometric = "census"
                        c.loop.update(num_train_steps=1000, steps_per_epoch=1000)  # constant lr
                        if "hires" in opts:  # stage 5: the same at 256x512, so that one working pixel is 1-2
                            # input pixels of a photograph (fine detail, object edges, sub-pixel shifts the
                            # 128x256 stages never saw), on top of the finished stage 4 (its workdir `work/long4`)
                            c.init_from = "work/long4"
                            c.height, c.width = 256, 512
                            c.loop.update(num_train_steps=250, checkpoint_every=125)
    if "short" in opts:  # a 1-minute smoke run of the same pipeline
        c.loop.update(num_train_steps=30, checkpoint_every=15, eval_every=15, image_every=15)
        c.eval.num_samples = 4
    return c
