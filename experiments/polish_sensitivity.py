"""How far the photometric polish moves its output when its input map moves by 1e-4 px, and what it costs to
make it move less.

    python experiments/polish_sensitivity.py [--model long] [--noise 1e-4] [--configs card,soft0.01,...]

Two runtimes (onnxruntime and XLA) compute the network's map to within about 1e-4 px of each other
(`experiments/results/onnx.md`); the polish then decides, pixel by pixel, between candidate values whose costs
may be nearly tied, and a tiny change of its input can flip such a decision. This measures that directly, in
JAX alone: the model's working maps (its card's refine and symmetry, no polish) of three real pairs (Middlebury
Motorcycle, the first two homography pairs of the held-out photos), polished once as they are and once with
Gaussian noise of `--noise` px added, for each polish setting of `--configs`:

    card          the shipped polish (two rounds of hard candidate selection and the variational fit)
    softT         two rounds with `select_softness`=T (a softmin over the candidates instead of the cheapest)
    round1        one round, hard selection
    round1-softT  one round, `select_softness`=T
    select-hard, select-softT, fit
                  one stage alone on the network's map (candidate selection, or the variational fit)

For each it prints the largest change (working px), the number of pixels changed by more than 0.05 px, and the
accuracy at the input resolution (Motorcycle EPE and D1; flow EPE over all and non-occluded pixels).
"""
from __future__ import annotations

import argparse
import dataclasses
import time

import numpy as np

DEFAULT_CONFIGS = "card,soft0.003,soft0.01,soft0.03,round1,round1-soft0.003,round1-soft0.01,select-hard,select-soft0.01,fit"


def polish_function(name: str, rows, mask):
    """`f(pairs, maps) -> maps` for the setting `name` (see the module docstring)."""
    import jax

    from bridge_jax import polish

    base = polish.DEFAULT_CONFIG
    if name == "card":
        cfg = base
    elif name.startswith("soft"):
        cfg = dataclasses.replace(base, select_softness=float(name[4:]))
    elif name == "round1":
        cfg = dataclasses.replace(base, rounds=1)
    elif name.startswith("round1-soft"):
        cfg = dataclasses.replace(base, rounds=1, select_softness=float(name[len("round1-soft"):]))
    elif name.startswith("select-"):
        soft = 0.0 if name == "select-hard" else float(name[len("select-soft"):])
        cfg = dataclasses.replace(base, select_softness=soft)

        def select(pairs, maps):
            _, grey_b, norm_a = polish.grey_images(pairs, cfg)
            return polish.select_candidates(norm_a, grey_b, maps, mask, cfg)
        return jax.jit(select)
    elif name == "fit":
        def fit(pairs, maps):
            grey_a, grey_b, norm_a = polish.grey_images(pairs, base)
            return polish.variational_fit(norm_a, grey_a, grey_b, maps, rows, base)
        return jax.jit(fit)
    else:
        raise SystemExit(f"polish_sensitivity.py: unknown --configs entry {name!r} (see --help)")
    return jax.jit(lambda pairs, maps: polish.polish_maps(pairs, maps, rows, cfg))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__)
    ap.add_argument("--model", default="long")
    ap.add_argument("--noise", type=float, default=1e-4, help="standard deviation of the input change, px")
    ap.add_argument("--configs", default=DEFAULT_CONFIGS)
    args = ap.parse_args()

    import jax.numpy as jnp

    from bridge_jax import inference, metrics, polish
    from bridge_jax.eval import real_checks
    from bridge_jax.resizing import map_to_input_resolution

    pred = inference.load_predictor(args.model)
    test_time = pred.test_time = pred.test_time.network_part  # the card's refine and symmetry, no polish
    moto = real_checks.motorcycle()
    flows = real_checks.homography_set(per_photo=1, limit=2)
    cases = [("stereo", moto["left"], moto["right"], moto)] + [("flow", p["frame_t"], p["frame_t1"], p) for p in flows]
    maps = pred.working_maps([(task, a, b) for task, a, b, _ in cases])
    rng = np.random.default_rng(0)
    print(f"model {args.model}, network stages {test_time.to_dict()}, "
          f"input noise {args.noise:g} px")
    print("| pair | working size | setting | max change px | pixels > 0.05 px | accuracy | s |")
    print("|---|---|---|---|---|---|---|")
    for (task, a, b, truth), m in zip(cases, maps):
        pairs, full = pred.prepare([a], [b])
        pairs = jnp.asarray(pairs)
        rows = jnp.asarray([1.0 if task == "flow" else 0.0])
        mask = polish.component_mask(rows)
        m0 = jnp.asarray(m[None])
        noise = rng.normal(0.0, args.noise, m0.shape).astype(np.float32)
        if task == "stereo":
            noise[..., 1] = 0.0
        label = "Motorcycle" if task == "stereo" else truth["id"]
        for name in args.configs.split(","):
            f = polish_function(name, rows, mask)
            start = time.time()
            out = np.asarray(f(pairs, m0))
            seconds = time.time() - start
            change = np.abs(out - np.asarray(f(pairs, m0 + noise))).max(-1)[0]
            full_map = map_to_input_resolution(task, out[0], *full)
            if task == "stereo":
                r = metrics.disparity_metrics(full_map, truth["disp"], truth["valid"])
                acc = f"EPE {r['epe_all']:.3f}, D1 {r['d1_all']:.2f} %"
            else:
                r = metrics.flow_metrics(full_map, truth["flow"], truth["valid"], truth["noc"])
                acc = f"EPE all {r['epe_all']:.3f}, noc {r['epe_noc']:.3f}"
            print(f"| {label} | {out.shape[1]}x{out.shape[2]} | {name} | {change.max():.4f} | "
                  f"{int((change > 0.05).sum())} | {acc} | {seconds:.1f} |", flush=True)


if __name__ == "__main__":
    main()
