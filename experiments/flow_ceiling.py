"""What limits the demo's flow: priors, a supervised ceiling, and whether a trained net matches at all.

Three measurements on the built-in synthetic data at the demo's 64x128: training cycles are the demo's own
(base seed 0 = `config.seed`), held-out cycles come from base seed 1 (disjoint from training; the trainer's
periodic validation uses `config.eval.seed` = 1_000_003 instead, 16 cycles); every EPE is the per-image mean over GT-valid (or noc) pixels, as a ratio
of the zero-motion EPE. Results: experiments/results/train_bench.md (2026-11-30).

  # 1. what position-only guesses and oracles score (no network)
  python experiments/flow_ceiling.py priors
  # 2. the same network trained WITH ground truth (L2 endpoint error) for the demo's step budget
  python experiments/flow_ceiling.py supervised --rows flow --mask noc --steps 1500
  python experiments/flow_ceiling.py supervised --rows flow_stereo --mask noc --steps 1500 --lr 3e-4
  python experiments/flow_ceiling.py supervised --rows flow --model pwcnet --overrides '{"warp": "pixels"}'
  python experiments/flow_ceiling.py supervised --rows flow --model pwc_lite --overrides '{"coords": true}'
  # 3. a trained checkpoint: does it match, or predict from one image? (right image replaced by the left)
  python experiments/flow_ceiling.py matching --workdir work/demo/train
  # 4. model + unsupervised loss together: overfit ONE training cycle with the real train step (and the same
  #    with the flow pair's second frame replaced by its first: then nothing can be matched)
  python experiments/flow_ceiling.py overfit --model pwc_lite --loss '{"photometric": "census"}' --steps 300
  python experiments/flow_ceiling.py overfit --model pwc_lite --same-image

Each run prints JSON lines (one per evaluation) for experiments/results/raw/.
"""
from __future__ import annotations

import argparse
import json
import sys
import time

import numpy as np

from bridge_jax import metrics as M
from bridge_jax.data import synthetic

H, W = 64, 128
TRAIN_SEED, VAL_SEED = 0, 1  # demo config.seed = 0 (training); 1 = held out (not config.eval.seed)


def render(seed: int, n: int) -> list[dict]:
    return [synthetic.render_sample(synthetic.sample_seed(seed, i), H, W) for i in range(n)]


def mean_epe(samples, pred_fn, task: str = "flow", mask_key: str | None = None) -> float:
    """Per-image mean EPE of `pred_fn(sample)` (flow `(H, W, 2)` or disparity `(H, W)`, pixels) against the
    sample's GT, on `mask_key` pixels (default: GT-valid), computed by `bridge_jax.metrics` as in validation."""
    acc = M.MetricAccumulator()
    for s in samples:
        if task == "flow":
            acc.add(M.flow_sums(pred_fn(s), s["flow"], s[mask_key or "valid_flow"]))
        else:
            acc.add(M.disparity_sums(pred_fn(s), s["disp_t"], s[mask_key or "valid_disp_t"]))
    return acc.per_image_mean()["epe_all"]


def zero_map(s) -> np.ndarray:
    return np.zeros_like(s["flow"])


def zero_disparity(s) -> np.ndarray:
    return np.zeros_like(s["disp_t"])


def flow_ratio(samples, pred_fn, mask_key="valid_flow") -> float:
    """Per-image mean flow EPE of pred_fn / that of zero motion, on `mask_key` pixels."""
    return mean_epe(samples, pred_fn, "flow", mask_key) / mean_epe(samples, zero_map, "flow", mask_key)


def priors(args) -> None:
    train, val = render(TRAIN_SEED, args.train_samples), render(VAL_SEED, args.val_samples)
    flows = np.stack([s["flow"] for s in train])
    valid = np.stack([s["valid_flow"] for s in train])
    mean_field = (flows * valid[..., None]).sum(0) / np.maximum(valid.sum(0), 1)[..., None]
    median_field = np.nan_to_num(np.nanmedian(np.where(valid[..., None], flows, np.nan), axis=0))
    bh, bw = int(np.ceil(0.1 * H)), int(np.ceil(0.1 * W))
    inside = np.zeros((H, W), bool)
    inside[bh:-bh, bw:-bw] = True  # the loss's border band (LossConfig.border_ratio = 0.1) excluded
    rows = {
        "zero_epe_all_px": mean_epe(val, zero_map),
        "mean_field": flow_ratio(val, lambda s: mean_field),
        "median_field": flow_ratio(val, lambda s: median_field),
        "gt_on_noc_zero_elsewhere": flow_ratio(val, lambda s: np.where(s["noc_flow"][..., None], s["flow"], 0)),
        "gt_on_noc_inside_border_zero_elsewhere": flow_ratio(
            val, lambda s: np.where((s["noc_flow"] & inside)[..., None], s["flow"], 0)),
        "gt_on_noc_median_field_elsewhere": flow_ratio(
            val, lambda s: np.where(s["noc_flow"][..., None], s["flow"], median_field)),
        "noc_fraction_of_valid": float(np.mean([s["noc_flow"][s["valid_flow"]].mean() for s in val])),
    }
    print(json.dumps({"what": "flow_priors", "size": [H, W], "val_samples": len(val), **rows}))


def _pair(a, b):
    return np.concatenate([a, b], axis=-1)


def supervised(args) -> None:
    import jax
    import jax.numpy as jnp
    import optax
    from bridge_jax import models

    mcfg = models_section(args.model)  # zero heads, as the demo
    mcfg.update(json.loads(args.overrides))
    graphdef, params = models.init(0, mcfg)
    train, val = render(TRAIN_SEED, args.train_samples), render(VAL_SEED, args.val_samples)
    with_stereo = args.rows == "flow_stereo"

    def rows(s):
        """Inputs (left_t, left_t1) [+ (left_t, right_t)], GT maps and masks (disparity map = (-d, 0))."""
        f = s["cycle"].astype(np.float32) / 255.0
        x, g, m = [_pair(f[0], f[2])], [s["flow"]], [s[f"{args.mask}_flow"]]
        if with_stereo:
            x.append(_pair(f[0], f[1]))
            g.append(np.stack([-s["disp_t"], np.zeros_like(s["disp_t"])], -1))
            m.append(s[f"{args.mask}_disp_t"])
        return np.stack(x), np.stack(g), np.stack(m).astype(np.float32)

    tx = optax.adam(args.lr)
    opt = tx.init(params)

    def loss_fn(p, x, g, m):
        px = models.apply(graphdef, p, x)["px"][0]
        epe = jnp.sqrt(jnp.sum((px - g) ** 2, -1) + 1e-6)
        return jnp.sum(epe * m) / jnp.sum(m)

    @jax.jit
    def step(p, o, x, g, m):
        loss, grads = jax.value_and_grad(loss_fn)(p, x, g, m)
        updates, o = tx.update(grads, o, p)
        return optax.apply_updates(p, updates), o, loss

    forward = jax.jit(lambda p, x: models.apply(graphdef, p, x)["px"][0])

    def evaluate(p, samples):
        flow = {}
        for s in samples:  # one forward per sample: (left_t, left_t1), (left_t, right_t), (left_t, left_t)
            f = s["cycle"].astype(np.float32) / 255.0
            flow[s["seed"]] = np.asarray(forward(p, np.stack([_pair(f[0], f[2]), _pair(f[0], f[1]), _pair(f[0], f[0])])))
        ratio = flow_ratio(samples, lambda s: flow[s["seed"]][0], f"{args.mask}_flow")
        disp = mean_epe(samples, lambda s: -flow[s["seed"]][1][..., 0], "disparity")
        disp_same = mean_epe(samples, lambda s: -flow[s["seed"]][2][..., 0], "disparity")
        return ratio, disp, disp_same

    rng = np.random.default_rng(0)
    t0 = time.time()
    for it in range(args.steps + 1):
        batch = [rows(train[i]) for i in rng.integers(0, len(train), args.batch)]
        x, g, m = (np.concatenate([b[k] for b in batch]) for k in range(3))
        if it % args.eval_every == 0:
            ratio, disp, disp_same = evaluate(params, val)
            train_ratio = evaluate(params, train[:32])[0]
            print(json.dumps({"what": "supervised", "model": args.model, "overrides": args.overrides, "rows": args.rows,
                              "mask": args.mask, "lr": args.lr, "step": it, f"val_flow_{args.mask}_vs_zero": round(ratio, 4),
                              f"train_flow_{args.mask}_vs_zero": round(train_ratio, 4), "val_disp_epe": round(disp, 4),
                              "val_disp_epe_right_replaced_by_left": round(disp_same, 4),
                              "seconds": round(time.time() - t0, 1)}), flush=True)
        params, opt, _ = step(params, opt, x, g, m)


def matching(args) -> None:
    from bridge_jax.inference import load_predictor

    pred = load_predictor(args.workdir, size=(H, W))
    val = render(VAL_SEED, args.val_samples)
    out = {}
    for name, replaced in (("real", False), ("b_replaced_by_a", True)):
        def image_b(s, k, replaced=replaced):  # frame k (1 = right_t, 2 = left_t1), or left_t again
            return s["cycle"][0 if replaced else k]

        out[f"disp_epe_{name}"] = mean_epe(
            val, lambda s: pred.predict_pair(s["cycle"][0], image_b(s, 1), task="stereo"), "disparity")
        out[f"flow_vs_zero_{name}"] = flow_ratio(val, lambda s: pred.predict_pair(s["cycle"][0], image_b(s, 2), task="flow"))
    out["zero_disp_epe"] = mean_epe(val, zero_disparity, "disparity")
    print(json.dumps({"what": "matching", "workdir": args.workdir, "val_samples": len(val), **out}))


def overfit_cycle(model_cfg: dict, loss_cfg: dict, *, steps: int, lr: float = 1e-3, seed: int = 1,
                  same_image: bool = False, eval_every: int = 50, clip_grad_norm: float = 0.0):
    """Train on ONE synthetic cycle with the real training step (`train_step.train_step`: network on the 8 pair
    inputs, the cycle loss, Adam), yielding (step, flow EPE / zero-motion EPE of its left flow on GT-valid pixels,
    disparity EPE in px) every `eval_every` steps. `same_image`: the left t+1 frame is replaced by the left t frame
    (flow pairs then show no motion, so nothing can be matched; the GT is still the real flow)."""
    import jax
    import jax.numpy as jnp
    from bridge_jax import losses, network, train_step

    s = synthetic.render_sample(seed, H, W)
    frames = s["cycle"].astype(np.float32) / 255.0
    if same_image:
        frames = frames.copy()
        frames[2] = frames[0]
    cycles = jnp.asarray(frames)[None]
    graphdef, params = network.init_params(jax.random.key(0), model_cfg)
    net = network.Network(graphdef)
    lcfg = losses.LossConfig.from_dict(loss_cfg)
    tx, schedule = train_step.make_optimizer(train_step.OptimizerConfig(lr=lr, lr_milestones=(), clip_grad_norm=clip_grad_norm), 1)
    state = train_step.create_train_state(params, tx, jax.random.PRNGKey(0))
    step = jax.jit(lambda st, c: train_step.train_step(st, c, net=net, loss_cfg=lcfg, tx=tx, schedule=schedule))
    forward = jax.jit(lambda p, x: net(p, x)["px"][0])
    x = np.stack([_pair(frames[0], frames[2]), _pair(frames[0], frames[1])])
    zero = mean_epe([s], zero_map)
    for it in range(steps + 1):
        if it % eval_every == 0 or it == steps:
            out = np.asarray(forward(state["params"], x))
            flow_epe = mean_epe([s], lambda _: out[0])
            disp_epe = mean_epe([s], lambda _: -out[1][..., 0], "disparity")
            yield it, flow_epe / zero, disp_epe
        if it < steps:
            state, _ = step(state, cycles)


def overfit(args) -> None:
    model_cfg = dict(models_section(args.model), **json.loads(args.overrides))
    t0 = time.time()
    for it, ratio, disp in overfit_cycle(model_cfg, json.loads(args.loss), steps=args.steps, lr=args.lr,
                                         same_image=args.same_image, eval_every=args.eval_every,
                                         clip_grad_norm=args.clip):
        print(json.dumps({"what": "overfit", "model": args.model, "overrides": args.overrides, "loss": args.loss,
                          "same_image": args.same_image, "step": it, "flow_vs_zero": round(ratio, 4),
                          "disp_epe": round(disp, 4), "seconds": round(time.time() - t0, 1)}), flush=True)


def models_section(name: str) -> dict:
    """The model's full config with zero output heads, as the demo starts."""
    from bridge_jax.configs import default
    return dict(default.model_section(name), head_init="zeros")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    for name in ("priors", "supervised", "matching"):
        p = sub.add_parser(name)
        p.add_argument("--val-samples", type=int, default=32)
        p.add_argument("--train-samples", type=int, default=512)
    s = sub.choices["supervised"]
    s.add_argument("--model", default="resnet_md_tiny")
    s.add_argument("--overrides", default="{}", help="JSON of model config keys")
    s.add_argument("--rows", choices=("flow", "flow_stereo"), default="flow")
    s.add_argument("--mask", choices=("valid", "noc"), default="noc")
    s.add_argument("--lr", type=float, default=1e-3)
    s.add_argument("--steps", type=int, default=1500)
    s.add_argument("--batch", type=int, default=2)
    s.add_argument("--eval-every", type=int, default=250)
    sub.choices["matching"].add_argument("--workdir", required=True)
    o = sub.add_parser("overfit")
    o.add_argument("--model", default="pwc_lite")
    o.add_argument("--overrides", default="{}", help="JSON of model config keys")
    o.add_argument("--loss", default="{}", help="JSON of loss config fields")
    o.add_argument("--lr", type=float, default=1e-3)
    o.add_argument("--clip", type=float, default=0.0, help="gradient clipping (global norm; 0 = off)")
    o.add_argument("--steps", type=int, default=300)
    o.add_argument("--eval-every", type=int, default=50)
    o.add_argument("--same-image", action="store_true")
    args = ap.parse_args(argv)
    {"priors": priors, "supervised": supervised, "matching": matching, "overfit": overfit}[args.cmd](args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
