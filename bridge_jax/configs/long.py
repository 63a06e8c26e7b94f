r"""The `long` model's recipe: pwc_lite trained from random initialisation on the synthetic scenes that carry over to
real images, in stages, by one command (a recipe, `bridge_jax.recipe`).

    bridge-train --config=long --workdir=work/rebuilt             # the whole recipe, from nothing (resumable)
    bridge-train --status work/rebuilt                            # which stage, which step
    bridge-train --config=long:finetune --workdir=work/mine \
        --config.data.data_dir=MY_VIDEO --config.data.val_dir=MY_HELDOUT   # continue it on your own stereo video

Stages (`STAGES`; each starts from the previous stage's final params with fresh Adam moments, see
`bridge_jax.recipe`):

1. `coarse`: the demo's first stage on the `real_motion` scenes (photo textures, slanted and rotating objects,
   varied rigs, per-camera photometric differences, vertical motion): 10,000 steps at 64x128, one cycle per
   step, lr 1e-3 halving every 2,400 steps from step 3,200. At a quarter of the pixels of 128x256 a step costs
   about a quarter, and this is where most of the learning happens.
2. `main`: 1,500 steps at 128x256 (lr 2.5e-4, halved at 1,000) with the census photometric term (robust to the
   exposure and gain differences between real cameras), the self-supervision term at weight 1.0 (full-frame maps
   teach the maps of crops: the only teacher of the strip along the left edge that the right camera does not
   see), frames t+1 cut up to 8 % of the height away from t (vertical motion at the frame level), the stereo
   pairs' photometric terms masked by the forward-backward occlusion check as the flow pairs' are
   (`loss.stereo_occlusion`; the paper leaves them unmasked, which rewards giving background the right view cannot
   see the foreground's disparity), and the background fill of stereo pixels the occlusion check distrusts
   (`loss.occlusion_fill` 3.0, which pulls the disparity of background hidden in the right view towards its row's
   farther neighbour).
3. `hires`: 350 steps of the same at 256x512, so that one working pixel is 1-2 input pixels of a photograph (fine
   detail, object edges, sub-pixel shifts the smaller stages never saw), at lr 2.5e-4 halved at steps 180 and 315,
   with the params' moving average (`ema_decay` 0.99, about the last 100 steps) as the stage's model: at this lr
   the average beat the last step's params on nearly every real-image check. Its loss is `main`'s.

Both terms at these weights in the last stage only (candidate NF3 of `long_recipe.md`) gave a network that beat
the shipped `long` on every real-image check but Motorcycle; from `main` on (candidate NF3m) the out-of-view strip
on Motorcycle halved its error and the network alone beat it on every check (`long_recipe.md` §3g).

The same steps at half the last stage's lr, without the average and without the stereo mask (candidate J) took
1 h 56 min on a 2-core Intel Xeon VM (2026-12-06); neither the average nor the mask adds measurable step time (the
occlusion check runs for the flow pairs anyway). Which split and which last stage were
tried, and what each bought: `experiments/results/long_recipe.md`.

Arguments: `short` = every stage at toy scale (4 steps each at 64x128) for tests and smoke runs;
`finetune` = one stage with the last stage's settings from the shipped `long` weights, on your own stereo video
(`data.source=folder`; set `data.data_dir` and, to see whether it helps, `data.val_dir`), validating before its
first step, at half the lr the shipped weights' own last stage had (`FINETUNE_LR`), with the loss the shipped weights
were trained with (stereo pairs unmasked, self-supervision 0.3, no fill term), and with the last stage's moving average as the model (measured in
`experiments/results/finetune_video_ema.md` and `finetune_video_ema_half_lr.md`: each of the two changes improved
the held-out numbers); `legacy` = the five hand-chained stages the `long` shipped
until 2026-12-04 came from, as one recipe from random initialisation (about 5x the compute of the recipe above;
kept to measure against).
"""

from __future__ import annotations

import ml_collections

from bridge_jax.configs import demo

ARGS = ("short", "finetune", "legacy")

# Each stage's settings on top of the base (the demo's base config, `demo.base_config`), as dotted keys.
STAGES = (
    ("coarse", {
        "data.synthetic_scene": "real_motion", "data.augment_shift": 0.08,
        "loop.num_train_steps": 10000, "loop.steps_per_epoch": 800,  # lr 1e-3, halved at 3200, 5600, 8000
        "loop.checkpoint_every": 500, "loop.eval_every": 1000, "loop.image_every": 1000,
    }),
    ("main", {
        "height": 128, "width": 256, "lr": 2.5e-4,
        "data.synthetic_scene": "real_motion", "data.augment_shift": 0.08,
        "loss.photometric": "census", "loss.self_supervision": 1.0, "loss.stereo_occlusion": True,
        "loss.occlusion_fill": 3.0,
        "loop.num_train_steps": 1500, "loop.steps_per_epoch": 250,  # halved at 1000
        "loop.checkpoint_every": 250, "loop.eval_every": 500, "loop.image_every": 500, "eval.batch": 4,
    }),
    ("hires", {
        "height": 256, "width": 512, "lr": 2.5e-4, "ema_decay": 0.99,
        "data.synthetic_scene": "real_motion", "data.augment_shift": 0.08,
        "loss.photometric": "census", "loss.self_supervision": 1.0, "loss.stereo_occlusion": True,
        "loss.occlusion_fill": 3.0,
        "loop.num_train_steps": 350, "loop.steps_per_epoch": 45,  # halved at 180 and 315
        "loop.checkpoint_every": 125, "loop.eval_every": 350, "loop.image_every": 350, "eval.batch": 4,
    }),
)
"""The recipe's stages in order: (name, {dotted config key: value}), each on top of the base config."""

# The chain the `long` shipped until 2026-12-04 was made by (five `bridge-train` runs by hand, each
# `--config.init_from` the previous one's workdir, the first from the one-phase demo model of 2026-12-02), as
# one recipe. Each of its stages kept every setting of the stages before it.
_LEGACY_STEPS = (
    ("demo", {"loop.num_train_steps": 2500}),  # the one-phase demo: 2,500 steps at 64x128
    ("real", {"height": 128, "width": 256, "global_batch": 2, "lr": 5e-4, "data.synthetic_scene": "real",
              "loop.num_train_steps": 4000, "loop.steps_per_epoch": 500, "loop.checkpoint_every": 250,
              "loop.eval_every": 500, "loop.image_every": 500, "eval.batch": 4}),
    ("selfsup", {"lr": 1.25e-4, "loss.self_supervision": 0.3, "loop.num_train_steps": 1000,
                 "loop.steps_per_epoch": 1000, "loop.eval_every": 250}),
    ("motion", {"lr": 2.5e-4, "data.synthetic_scene": "real_motion", "data.augment_shift": 0.08,
                "loop.num_train_steps": 1500, "loop.steps_per_epoch": 250}),
    ("census", {"lr": 1.25e-4, "loss.photometric": "census", "loop.num_train_steps": 1000,
                "loop.steps_per_epoch": 1000}),
    ("hires", {"height": 256, "width": 512, "loop.num_train_steps": 250, "loop.checkpoint_every": 125}),
)


def _cumulative(steps):
    """Stages that keep every setting of the stages before them (the legacy chain's way)."""
    out, acc = [], {}
    for name, settings in steps:
        acc = {**acc, **settings}
        out.append((name, dict(acc)))
    return tuple(out)


LEGACY_STAGES = _cumulative(_LEGACY_STEPS)
"""The legacy chain's stages, each with every setting it inherited spelt out."""


def _nested(settings: dict) -> ml_collections.ConfigDict:
    """{"a.b": v} -> ConfigDict {a: {b: v}}."""
    out = ml_collections.ConfigDict()
    for key, value in settings.items():
        *path, last = key.split(".")
        node = out
        for part in path:
            if part not in node:
                node[part] = ml_collections.ConfigDict()
            node = node[part]
        node[last] = value
    return out


def recipe_config(stages, base=None) -> ml_collections.ConfigDict:
    """A recipe config from (name, {dotted key: value}) stages on top of `base` (default: the demo's base)."""
    c = demo.base_config() if base is None else base
    c.stages = tuple(name for name, _ in stages)
    c.stage_overrides = ml_collections.ConfigDict({name: _nested(settings) for name, settings in stages})
    return c


FINETUNE_STEPS = 200
FINETUNE_LR = 6.25e-5  # half the shipped `long`'s last stage's lr (finetune_video_ema_half_lr.md)


def finetune_stage() -> tuple[str, dict]:
    """One stage with the recipe's last stage's settings, from the shipped `long` weights, on a folder of the
    user's own stereo video, validating before its first step."""
    name, last = STAGES[-1]
    settings = dict(last, **{
        "init_from": "long", "data.source": "folder", "lr": FINETUNE_LR,
        # the loss the shipped weights' last stage ran (and fine-tuning was measured with): stereo pairs unmasked,
        # self-supervision 0.3, no fill term
        "loss.stereo_occlusion": False, "loss.self_supervision": 0.3, "loss.occlusion_fill": 0.0,
        "loop.num_train_steps": FINETUNE_STEPS,
        "loop.steps_per_epoch": FINETUNE_STEPS, "loop.checkpoint_every": 50, "loop.eval_every": 50,
        "loop.image_every": 50, "loop.eval_at_start": True})
    return ("finetune", settings)


def _short(stages):
    """Every stage at toy scale: 4 steps at 64x128 and the base lr, 2 validation cycles. Stages that differ only in
    what a toy run cannot show (size, lr) then compile to the same program, which XLA's cache compiles once: the
    whole chain runs in about 2 minutes on 2 cores, most of it compiling."""
    out = []
    for name, settings in stages:
        small = {k: v for k, v in settings.items() if k != "lr"}
        small.update({"height": 64, "width": 128, "global_batch": 1, "loop.num_train_steps": 4,
                      "loop.steps_per_epoch": 4, "loop.checkpoint_every": 2, "loop.eval_every": 0,
                      "loop.image_every": 0, "loop.log_every": 1, "eval.num_samples": 2, "eval.batch": 2,
                      "loss.self_supervision_crop": 16})
        out.append((name, small))
    return tuple(out)


def get_config(arg=None):
    opts = [a for a in (arg or "").split(",") if a]
    unknown = sorted(set(opts) - set(ARGS))
    if unknown:
        raise ValueError(f"long.py: unknown config argument(s) {unknown} (expected a comma-separated subset of "
                         f"{list(ARGS)})")
    if "finetune" in opts and "legacy" in opts:
        raise ValueError("long.py: 'finetune' continues the shipped model; it does not combine with 'legacy'")
    stages = LEGACY_STAGES if "legacy" in opts else (finetune_stage(),) if "finetune" in opts else STAGES
    if "short" in opts:
        stages = _short(stages)
    return recipe_config(stages)
