"""A tiny exact stereo-video scene for tests: one smooth texture seen through pure translations.

    left_t(x, y)   = T(x, y)
    right_t(x, y)  = T(x + d, y)            D(L_t -> R_t)   = (-d, 0)
    left_t1(x, y)  = T(x - u, y - v)        F(L_t -> L_t1)  = (u, v)
    right_t1(x, y) = T(x + d - u, y - v)    F(R_t -> R_t1)  = (u, v),  D(L_t1 -> R_t1) = (-d, 0)

T is smooth and constant (0.5) within `margin` px of the image border, so border clamping of the warp
reproduces it exactly for shifts up to `margin`: integer shifts reconstruct every pixel exactly.
"""

import numpy as np

from bridge_jax import cycle as cyc


def texture(x, y, h, w, margin=8, seed=0):
    rng = np.random.default_rng(seed)
    t = np.zeros(np.broadcast(x, y).shape + (3,), np.float64)
    for _ in range(6):
        fx, fy = rng.uniform(0.04, 0.2, 2)
        ph = rng.uniform(0, 2 * np.pi, 3)
        amp = rng.uniform(0.05, 0.12, 3)
        t += amp * np.sin(fx * x[..., None] + fy * y[..., None] + ph)
    # smooth window: 0 at the border band, 1 inside
    def ramp(z, n):
        a = np.clip((z - margin) / 6.0, 0, 1) * np.clip((n - 1 - margin - z) / 6.0, 0, 1)
        return a * a * (3 - 2 * a)
    win = (ramp(x, w) * ramp(y, h))[..., None]
    return 0.5 + win * t


def translating_cycle(h=64, w=128, d=4.0, u=2.0, v=1.0, margin=8, seed=0):
    """Returns (cycle (4, H, W, 3) float32, gt_maps dict pair-name -> forward map (H, W, 2) in px)."""
    ys, xs = np.meshgrid(np.arange(h, dtype=np.float64), np.arange(w, dtype=np.float64), indexing="ij")
    frames = [texture(xs, ys, h, w, margin, seed), texture(xs + d, ys, h, w, margin, seed),
              texture(xs - u, ys - v, h, w, margin, seed), texture(xs + d - u, ys - v, h, w, margin, seed)]
    cycle = np.stack(frames).astype(np.float32)
    ones = np.ones((h, w, 1), np.float32)
    stereo = np.concatenate([-d * ones, 0 * ones], -1)
    flow = np.concatenate([u * ones, v * ones], -1)
    gt = {"stereo_t1": stereo, "flow_left": flow, "flow_right": flow, "stereo_t": stereo}
    return cycle, gt


def gt_maps(gt, h, w, num_scales=4, pairs=tuple(range(4))):
    """Exact multi-scale maps of a translating scene, rows as cycle.pair_inputs: fwd pairs, then bwd = -fwd."""
    px, frac = [], []
    for s in range(num_scales):
        hs, ws = h >> s, w >> s
        fwd = np.stack([gt[cyc.PAIRS[k].name][::2**s, ::2**s] / 2**s for k in pairs])
        m = np.concatenate([fwd, -fwd]).astype(np.float32)
        px.append(m)
        frac.append(m / np.array([ws, hs], np.float32))
    return {"px": tuple(px), "frac": tuple(frac)}


class KnownMaps:
    """Stands in for `Predictor.working_maps`: the exact working-size maps of hand-built scenes, found by the
    images of each job (so a reverse pair built the wrong way finds no map and fails). `calls`: the number of
    jobs of each call; `batches`: the `batch` each call asked for."""

    def __init__(self, entries):
        self.entries = entries   # [(task, image a, image b, map (H, W, 2))]
        self.calls = []
        self.batches = []

    def __call__(self, jobs, batch=None):
        self.calls.append(len(jobs))
        self.batches.append(batch)
        out = []
        for task, a, b in jobs:
            hits = [m for t, ea, eb, m in self.entries if t == task and np.array_equal(ea, a) and np.array_equal(eb, b)]
            assert hits, "a job whose images match no hand-built pair"
            out.append(hits[0])
        return out
