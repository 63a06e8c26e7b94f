r"""Does fine-tuning the shipped `long` model on a user's own stereo video help? Measured the way a user does it.

What: a stereo video with exact ground truth is made from a real photograph (scikit-image's "brick", 512x512 grey,
textured everywhere, one of `bridge_jax.data.photos.TRAIN_PHOTOS`, upscaled 2.25x with cv2; "rocket" is mostly
empty sky): a 256x512 (HxW) window pans across it with a known,
slowly changing velocity (vx_t, vy_t) (both components non-zero, a few px per frame), the left view is the window
and the right view the same window shifted right by a known, slowly changing disparity d_t (4-12 px); the right
camera has a different response (gain and gamma) and both get a little sensor noise. The two views are written as
left.mp4 / right.mp4 (cv2.VideoWriter, mp4v) and read back with the project's own `bridge-frames` command. The
first 80 % of the frames are the training folder, the last 20 % (where the window has moved on) the held-out
folder. Then:

  1. the shipped `long` is scored on the held-out pairs against the exact ground truth;
  2. `bridge-train --config=long:finetune --workdir=WORK --config.data.data_dir=TRAIN --config.data.val_dir=HELDOUT`
     runs (200 steps, as shipped; its output goes to WORK/../train.log; its validation lines at step 0 and every
     50 steps are collected);
  3. WORK (the recipe workdir, a checkpoint path) is scored the same way.

Why: the `long:finetune` stage promises that a user can continue the shipped model on their own video; this
checks, with ground truth the trainer never sees, whether 200 steps on such a video keep or improve its numbers,
with the card's test-time polish and without it.

Conventions (checked against bridge_jax): disparity d means left pixel x matches right pixel x - d (right content
at x = left content at x + d; bridge_jax/data/synthetic.py, "right-image match at x - d"); `predict_pair(L, R,
task="stereo")` returns -u of the left -> right map, i.e. d >= 0. A flow map (u, v) for (a, b) says pixel (x, y)
of a is found at (x + u, y + v) in b. The window moves by +v_t between frames t and t+1, so content moves by -v_t:
GT flow(left_t -> left_t+1) = -(vx_t, vy_t), uniform; GT disparity = d_t, uniform. Both signs are asserted on the
decoded frames (warping frame t+1 / the right view by the GT map must reproduce frame t / the left view far better
than the opposite sign does).

Scores per held-out pair (left_t, left_t+1) and (left_t, right_t), over interior pixels (a border of
ceil(max |motion|) + 4 px is left out, where content leaves the frame): flow EPE (px), Fl (%), disparity EPE (px),
D1 (%, > 3 px and > 5 %, `bridge_jax.metrics.outliers`); means over pairs. Each checkpoint is scored three ways:
"card" = `load_predictor(ckpt)` (the card's test-time settings: native working size, refine 1, symmetry flips,
polish photometric), "polish none" = the same with polish="none", and "raw" = refine 0, symmetry none, polish none
(the network's single pass).

Run (from the repository root; 45 min on a 2-core AVX2 CPU, 37 of them the fine-tune):

    .venv/bin/python experiments/finetune_video.py                 # 150 frames, 200 fine-tune steps
    .venv/bin/python experiments/finetune_video.py --quick         # smoke run: 16 frames, 4 steps (~6 min)
    .venv/bin/python experiments/finetune_video.py --steps 100     # another step count
    .venv/bin/python experiments/finetune_video.py --set stage_overrides.finetune.lr=1.25e-4 --name lr2x   # a variant

Work files go under --work (default /tmp/bridge_finetune_video[_quick], replaced on each run). The full run writes
experiments/results/finetune_video.md and experiments/results/raw/finetune_video_<date>.json (a --quick run writes
its JSON and report under --work only). A rerun rewrites the report: the hand-written "Reading" section that
follows the generated part has to be redone from the new numbers.
"""
from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import math
import os
import re
import shutil
import subprocess
import sys
import time

import cv2
import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, REPO)

from bridge_jax import metrics  # noqa: E402
from bridge_jax.data import photos  # noqa: E402

BIN = os.path.dirname(sys.executable)  # the venv's console scripts (bridge-frames, bridge-train)
HEIGHT, WIDTH = 256, 512
PHOTO, UPSCALE = "brick", 2.25
FPS = 30
RIGHT_GAIN, RIGHT_GAMMA = 1.06, 0.9  # right camera: out = 255 * clip(gain * (in / 255)) ** gamma
NOISE_SIGMA = 1.0  # sensor noise, grey levels, both cameras
TRAIN_FRACTION = 0.8
BORDER_EXTRA = 4


# ----------------------------------------------------------------------------------------------------------
# The video and its ground truth
# ----------------------------------------------------------------------------------------------------------

def motion(n: int):
    """Per-frame window velocity (vx_t, vy_t) (frame t -> t+1, px) and disparity d_t (px), all slowly varying."""
    t = np.arange(n, dtype=np.float64)
    vx = 4.0 + 1.5 * np.sin(2 * np.pi * t / 150.0 + 0.3)       # 2.5 .. 5.5 px / frame
    vy = 2.5 + 1.0 * np.sin(2 * np.pi * t / 105.0 + 1.0)       # 1.5 .. 3.5 px / frame
    d = 8.0 + 4.0 * np.sin(2 * np.pi * t / 135.0 + 0.5)        # 4 .. 12 px
    return vx, vy, d


def render(n: int, seed: int = 0):
    """(left uint8 (n, H, W, 3) RGB, right likewise, info dict) for n frames."""
    photo = photos.load_photo(PHOTO)
    big = cv2.resize(photo, None, fx=UPSCALE, fy=UPSCALE, interpolation=cv2.INTER_CUBIC).astype(np.float32)
    bh, bw = big.shape[:2]
    vx, vy, d = motion(n)
    ox = np.concatenate([[0.0], np.cumsum(vx[:-1])]) + 8.0  # window origin of frame t
    oy = np.concatenate([[0.0], np.cumsum(vy[:-1])]) + 8.0
    if ox.max() + d.max() + WIDTH + 4 > bw or oy.max() + HEIGHT + 4 > bh:
        raise SystemExit(f"the pan does not fit the {bh}x{bw} photo")
    rng = np.random.default_rng(seed)

    def crop(x0, y0):  # window with top-left corner at sub-pixel (x0, y0): out(x, y) = big(x + x0, y + y0)
        m = np.array([[1, 0, x0], [0, 1, y0]], np.float64)
        return cv2.warpAffine(big, m, (WIDTH, HEIGHT), flags=cv2.INTER_CUBIC | cv2.WARP_INVERSE_MAP,
                              borderMode=cv2.BORDER_REFLECT)

    left, right = [], []
    for i in range(n):
        lv = crop(ox[i], oy[i])
        rv = crop(ox[i] + d[i], oy[i])  # right content at x = left content at x + d
        rv = 255.0 * np.clip(RIGHT_GAIN * rv / 255.0, 0, 1) ** RIGHT_GAMMA
        left.append(np.clip(lv + rng.normal(0, NOISE_SIGMA, lv.shape), 0, 255).round().astype(np.uint8))
        right.append(np.clip(rv + rng.normal(0, NOISE_SIGMA, rv.shape), 0, 255).round().astype(np.uint8))
    info = {"photo": PHOTO, "photo_size_hw": list(photo.shape[:2]), "upscale": UPSCALE,
            "upscaled_size_hw": [bh, bw], "frame_size_hw": [HEIGHT, WIDTH], "frames": n,
            "vx": vx.tolist(), "vy": vy.tolist(), "disparity": d.tolist(),
            "origin_x": ox.tolist(), "origin_y": oy.tolist(),
            "right_camera": {"gain": RIGHT_GAIN, "gamma": RIGHT_GAMMA}, "noise_sigma": NOISE_SIGMA}
    return np.stack(left), np.stack(right), info


def write_video(path: str, frames: np.ndarray) -> None:
    writer = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), FPS, (WIDTH, HEIGHT))
    if not writer.isOpened():
        raise SystemExit(f"cv2.VideoWriter could not open {path} with mp4v")
    for f in frames:
        writer.write(cv2.cvtColor(f, cv2.COLOR_RGB2BGR))
    writer.release()


def read_png(path: str) -> np.ndarray:
    img = cv2.imread(path, cv2.IMREAD_COLOR)
    if img is None:
        raise SystemExit(f"could not read {path}")
    return cv2.cvtColor(img, cv2.COLOR_BGR2RGB)


def shift_sample(img: np.ndarray, u: float, v: float) -> np.ndarray:
    """out(x, y) = img(x + u, y + v) (bilinear), float32 grey."""
    g = cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32) if img.ndim == 3 else img.astype(np.float32)
    h, w = g.shape
    xs, ys = np.meshgrid(np.arange(w, dtype=np.float32) + np.float32(u), np.arange(h, dtype=np.float32) + np.float32(v))
    return cv2.remap(g, xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def grey(img: np.ndarray) -> np.ndarray:
    return cv2.cvtColor(img, cv2.COLOR_RGB2GRAY).astype(np.float32)


def check_signs(left: list, right: list, vx, vy, d, border: int) -> dict:
    """Warping with the GT map must reproduce the first image far better than the opposite sign (asserted).

    Flow: left_t(x) == left_t+1(x + u) with (u, v) = -(vx_t, vy_t). Stereo: left_t(x) == right_t(x - d) (compared
    after normalising each image's mean and contrast, as the right camera's response differs)."""
    s = (slice(border, -border), slice(border, -border))
    norm = lambda a: (a - a[s].mean()) / (a[s].std() + 1e-6)  # noqa: E731
    out = {"flow_gt_sign": [], "flow_opposite_sign": [], "stereo_gt_sign": [], "stereo_opposite_sign": []}
    for t in range(0, len(left) - 1, max(1, (len(left) - 1) // 5)):
        a = grey(left[t])
        for sign, key in ((1.0, "flow_gt_sign"), (-1.0, "flow_opposite_sign")):
            out[key].append(float(np.abs(shift_sample(left[t + 1], -sign * vx[t], -sign * vy[t]) - a)[s].mean()))
        for sign, key in ((1.0, "stereo_gt_sign"), (-1.0, "stereo_opposite_sign")):
            out[key].append(float(np.abs(norm(shift_sample(right[t], -sign * d[t], 0.0)) - norm(a))[s].mean()))
    res = {k: float(np.mean(v)) for k, v in out.items()}
    assert res["flow_gt_sign"] < 0.5 * res["flow_opposite_sign"], f"flow sign check failed: {res}"
    assert res["stereo_gt_sign"] < 0.5 * res["stereo_opposite_sign"], f"stereo sign check failed: {res}"
    return res


def novel_fraction(info: dict, train_frames: range, heldout_frames: range) -> float:
    """Fraction of the photo area seen by the held-out left views that no training left view saw."""
    bh, bw = info["upscaled_size_hw"]
    seen = np.zeros((bh, bw), bool)
    held = np.zeros((bh, bw), bool)
    for frames, mask in ((train_frames, seen), (heldout_frames, held)):
        for t in frames:
            x0, y0 = int(round(info["origin_x"][t])), int(round(info["origin_y"][t]))
            mask[y0:y0 + HEIGHT, x0:x0 + WIDTH] = True
    return float((held & ~seen).sum() / max(1, held.sum()))


# ----------------------------------------------------------------------------------------------------------
# Scoring a checkpoint
# ----------------------------------------------------------------------------------------------------------

def score(predictor, left: list, right: list, first: int, vx, vy, d, border: int) -> dict:
    """Mean over the held-out pairs (t, t+1) of flow EPE / Fl and disparity EPE / D1 over interior pixels."""
    s = (slice(border, -border), slice(border, -border))
    rows = []
    t0 = time.perf_counter()
    for i in range(len(left) - 1):
        t = first + i  # the global frame index (the GT arrays are indexed by it)
        flow = predictor.predict_pair(left[i], left[i + 1], task="flow")
        disp = predictor.predict_pair(left[i], right[i], task="stereo")
        assert flow.shape == (HEIGHT, WIDTH, 2) and disp.shape == (HEIGHT, WIDTH), (flow.shape, disp.shape)
        gt_flow = np.broadcast_to(np.array([-vx[t], -vy[t]], np.float32), flow.shape)
        gt_disp = np.full(disp.shape, d[t], np.float32)
        fe = metrics.endpoint_error(flow, gt_flow)[s]
        de = metrics.endpoint_error(disp, gt_disp)[s]
        rows.append({"frame": t, "flow_epe": float(fe.mean()),
                     "fl": 100.0 * float(metrics.outliers(fe, np.full_like(fe, np.hypot(vx[t], vy[t]))).mean()),
                     "disp_epe": float(de.mean()),
                     "d1": 100.0 * float(metrics.outliers(de, np.full_like(de, d[t])).mean()),
                     "flow_mean": [float(flow[s][..., 0].mean()), float(flow[s][..., 1].mean())],
                     "gt_flow": [float(-vx[t]), float(-vy[t])],
                     "disp_mean": float(disp[s].mean()), "gt_disp": float(d[t])})
    out = {k: float(np.mean([r[k] for r in rows])) for k in ("flow_epe", "fl", "disp_epe", "d1")}
    out.update(pairs=len(rows), seconds=round(time.perf_counter() - t0, 1), per_pair=rows)
    return out


def score_checkpoint(ckpt: str, left, right, first, vx, vy, d, border) -> dict:
    """The three ways of scoring a checkpoint (card defaults, polish none, raw network)."""
    from bridge_jax.inference import load_predictor
    p = load_predictor(ckpt)  # the card's (or the card it was fine-tuned from) test-time settings
    card = {"native": p.native, "refine": p.refine, "symmetry": p.symmetry, "polish": p.polish,
            "working_size": list(p.working_size(HEIGHT, WIDTH))}
    print(f"  {ckpt}: card settings {card}", flush=True)
    res = {"card_settings": card}
    variants = (("card", {}), ("polish none", {"polish": "none"}),
                ("raw", {"polish": "none", "refine": 0, "symmetry": "none"}))
    card_stages = p.test_time
    for name, attrs in variants:
        p.test_time = dataclasses.replace(card_stages, **attrs)  # TestTime is frozen: one record per variant
        res[name] = score(p, left, right, first, vx, vy, d, border)
        r = res[name]
        print(f"  {name:12s} flow EPE {r['flow_epe']:.3f} px, Fl {r['fl']:.2f} %, disparity EPE {r['disp_epe']:.3f} "
              f"px, D1 {r['d1']:.2f} % ({r['pairs']} pairs, {r['seconds']:.0f} s)", flush=True)
    return res


# ----------------------------------------------------------------------------------------------------------
# Main
# ----------------------------------------------------------------------------------------------------------

def run(cmd: list, log_path: str | None = None) -> tuple[int, float]:
    print("$ " + " ".join(cmd), flush=True)
    t0 = time.perf_counter()
    if log_path is None:
        rc = subprocess.run(cmd, cwd=REPO).returncode
    else:
        with open(log_path, "w") as f:
            rc = subprocess.run(cmd, cwd=REPO, stdout=f, stderr=subprocess.STDOUT).returncode
    return rc, time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--steps", type=int, default=200, help="fine-tune steps (default 200, the stage's own)")
    ap.add_argument("--quick", action="store_true", help="smoke run: 16 frames, 4 steps, nothing written to the repo")
    ap.add_argument("--frames", type=int, default=None, help="video length (default 150; 16 with --quick)")
    ap.add_argument("--work", default=None, help="work folder (replaced; default /tmp/bridge_finetune_video[_quick])")
    ap.add_argument("--set", action="append", default=[], metavar="KEY=VALUE",
                    help="a config override for the fine-tune (passed as --config.KEY=VALUE; repeatable), to measure "
                         "a variant of the stage; the report then goes to finetune_video_<--name>.md")
    ap.add_argument("--name", default=None, help="report name suffix for a variant (required with --set)")
    args = ap.parse_args()
    for item in args.set:
        if "=" not in item or item.startswith("="):
            ap.error(f"--set {item!r}: expected KEY=VALUE (a config key such as ema_decay=0.99)")
    if args.set and not args.name:
        ap.error("--set needs --name (the variant's report goes to experiments/results/finetune_video_<name>.md)")
    n = args.frames or (16 if args.quick else 150)
    steps = 4 if args.quick else args.steps
    work = args.work or ("/tmp/bridge_finetune_video_quick" if args.quick else "/tmp/bridge_finetune_video")
    if os.path.isdir(work):
        shutil.rmtree(work)
    os.makedirs(work)
    started = datetime.datetime.now(datetime.timezone.utc)
    t_all = time.perf_counter()

    # 1. the video
    left, right, info = render(n)
    vx, vy, d = (np.array(info[k]) for k in ("vx", "vy", "disparity"))
    lpath, rpath = os.path.join(work, "left.mp4"), os.path.join(work, "right.mp4")
    write_video(lpath, left)
    write_video(rpath, right)
    frames_dir = os.path.join(work, "frames")
    rc, _ = run([os.path.join(BIN, "bridge-frames"), lpath, rpath, "--out", frames_dir])
    if rc:
        raise SystemExit(f"bridge-frames exited with {rc}")
    names = sorted(os.listdir(os.path.join(frames_dir, "left")))
    assert len(names) == n, f"bridge-frames gave {len(names)} frames, wrote {n}"
    n_train = int(round(TRAIN_FRACTION * n))
    train_dir, heldout_dir = os.path.join(work, "train"), os.path.join(work, "heldout")
    for folder, sel in ((train_dir, names[:n_train]), (heldout_dir, names[n_train:])):
        for side in ("left", "right"):
            os.makedirs(os.path.join(folder, side))
            for name in sel:
                shutil.copy(os.path.join(frames_dir, side, name), os.path.join(folder, side, name))
    hl = [read_png(os.path.join(heldout_dir, "left", x)) for x in names[n_train:]]
    hr = [read_png(os.path.join(heldout_dir, "right", x)) for x in names[n_train:]]
    codec_err = float(np.abs(hl[0].astype(np.float32) - left[n_train]).mean())
    max_motion = max(float(np.hypot(vx, vy).max()), float(d.max()))
    border = int(math.ceil(max_motion)) + BORDER_EXTRA
    signs = check_signs(hl, hr, vx[n_train:], vy[n_train:], d[n_train:], border)
    novel = novel_fraction(info, range(n_train), range(n_train, n))
    heldout_range = {k: [float(a[n_train:n - 1].min()), float(a[n_train:n - 1].max())]
                     for k, a in (("vx", vx), ("vy", vy), ("disparity", d))}
    train_range = {k: [float(a[:n_train - 1].min()), float(a[:n_train - 1].max())]
                   for k, a in (("vx", vx), ("vy", vy), ("disparity", d))}
    print(f"video: {n} frames of {HEIGHT}x{WIDTH} from {PHOTO} x{UPSCALE}; train {n_train} frames, held out "
          f"{n - n_train}; held-out vx {heldout_range['vx']}, vy {heldout_range['vy']}, d {heldout_range['disparity']}; "
          f"border {border} px; mp4v round trip mean |err| {codec_err:.2f} grey levels; sign checks {signs}; "
          f"held-out area unseen in training {100 * novel:.1f} %", flush=True)

    # 2. the shipped model
    print("scoring long (shipped)", flush=True)
    before = score_checkpoint("long", hl, hr, n_train, vx, vy, d, border)

    # 3. the fine-tune, as a user runs it
    wdir = os.path.join(work, "finetuned")
    cmd = [os.path.join(BIN, "bridge-train"), "--config=long:finetune", f"--workdir={wdir}",
           f"--config.data.data_dir={train_dir}", f"--config.data.val_dir={heldout_dir}"]
    if steps != 200:
        cmd.append(f"--config.loop.num_train_steps={steps}")
    cmd += [f"--config.{item}" for item in args.set]
    log_path = os.path.join(work, "train.log")
    rc, train_s = run(cmd, log_path)
    with open(log_path, errors="replace") as f:
        log_text = f.read()
    lines = [ln.strip() for ln in re.split(r"[\r\n]+", log_text)]
    val_lines = [ln for ln in lines if re.search(r"step \d+ validation:", ln)]
    error_lines = [ln for ln in lines if re.match(r"(error|[A-Za-z]*Error)\b|Traceback|.*\brefus", ln)]
    print(f"bridge-train exited {rc} after {train_s:.0f} s; validation lines:", flush=True)
    for ln in val_lines:
        print("  " + ln, flush=True)
    if rc:
        print("\n".join(lines[-30:]))
        raise SystemExit(f"bridge-train exited with {rc} (log {log_path})")

    # 4. the fine-tuned model
    print(f"scoring {wdir} (fine-tuned)", flush=True)
    after = score_checkpoint(wdir, hl, hr, n_train, vx, vy, d, border)

    from bridge_jax.bench import timing
    total_s = time.perf_counter() - t_all
    result = {"date_utc": started.strftime("%Y-%m-%d %H:%M UTC"), "machine": timing.machine(),
              "quick": args.quick, "steps": steps, "train_command": " ".join(cmd), "train_rc": rc,
              "train_seconds": round(train_s, 1), "total_seconds": round(total_s, 1), "video": {
                  **{k: v for k, v in info.items() if k not in ("vx", "vy", "disparity", "origin_x", "origin_y")},
                  "codec": "mp4v (cv2.VideoWriter), 30 fps, read back by bridge-frames", "train_frames": n_train,
                  "heldout_frames": n - n_train, "heldout_pairs": n - n_train - 1, "train_range": train_range,
                  "heldout_range": heldout_range, "border_px": border, "codec_mean_abs_err": codec_err,
                  "sign_checks": signs, "heldout_area_unseen_in_training": novel,
                  "per_frame": {"vx": vx.tolist(), "vy": vy.tolist(), "disparity": d.tolist()}},
              "validation_lines": val_lines, "error_lines": error_lines, "before": before, "after": after}
    stamp = started.strftime("%Y-%m-%d")
    if args.quick:
        raw_path, md_path = os.path.join(work, "finetune_video.json"), os.path.join(work, "finetune_video.md")
    else:
        base = "finetune_video" + (f"_{args.name}" if args.name else "")
        raw_path = os.path.join(REPO, "experiments", "results", "raw", f"{base}_{stamp}.json")
        md_path = os.path.join(REPO, "experiments", "results", f"{base}.md")
    os.makedirs(os.path.dirname(raw_path), exist_ok=True)
    with open(raw_path, "w") as f:
        json.dump(result, f, indent=1)
    with open(md_path, "w") as f:
        f.write(report(result, os.path.relpath(raw_path, REPO) if not args.quick else raw_path))
    print(table(result))
    print(f"wrote {raw_path} and {md_path}")


def table(result: dict) -> str:
    lines = ["| model | test-time | flow EPE px | Fl % | disparity EPE px | D1 % |", "|---|---|---|---|---|---|"]
    for when, label in (("before", "long (shipped)"), ("after", f"long + {result['steps']}-step fine-tune")):
        for v in ("card", "polish none", "raw"):
            r = result[when][v]
            lines.append(f"| {label} | {v} | {r['flow_epe']:.3f} | {r['fl']:.2f} | {r['disp_epe']:.3f} | {r['d1']:.2f} |")
    return "\n".join(lines)


def comparison(result: dict) -> list[str]:
    """One line per test-time variant: each number before -> after and its change (lower is better)."""
    out = []
    for v in ("card", "polish none", "raw"):
        b, a = result["before"][v], result["after"][v]
        parts = []
        for key, label, unit in (("flow_epe", "flow EPE", " px"), ("fl", "Fl", " %"), ("disp_epe", "disparity EPE", " px"),
                                 ("d1", "D1", " %")):
            change = a[key] - b[key]
            rel = f", {100 * change / b[key]:+.0f} %" if b[key] > 1e-9 else ""
            verdict = "better" if change < -1e-9 else "worse" if change > 1e-9 else "same"
            parts.append(f"{label} {b[key]:.3f} -> {a[key]:.3f}{unit} ({change:+.3f}{rel}: {verdict})")
        out.append(f"- {v}: " + "; ".join(parts))
    return out


def report(result: dict, raw_path: str) -> str:
    v = result["video"]
    hr, tr = v["heldout_range"], v["train_range"]
    fmt = lambda r: f"{r[0]:.2f}-{r[1]:.2f}"  # noqa: E731
    val = "\n".join(result["validation_lines"]) or "(none printed)"
    cards = {w: result[w]["card_settings"] for w in ("before", "after")}
    return f"""# Fine-tuning `long` on a user's own stereo video (`long:finetune`)

Date: {result['date_utc']}. Machine: {result['machine']}. Script: `experiments/finetune_video.py`
(`.venv/bin/python experiments/finetune_video.py`); raw numbers: `{raw_path}`.

## Data

A {v['frame_size_hw'][0]}x{v['frame_size_hw'][1]} (HxW) window pans across scikit-image's `{v['photo']}`
({v['photo_size_hw'][0]}x{v['photo_size_hw'][1]}, one of `photos.TRAIN_PHOTOS`, upscaled x{v['upscale']} with cv2
INTER_CUBIC to {v['upscaled_size_hw'][0]}x{v['upscaled_size_hw'][1]}) for {v['frames']} frames (sub-pixel crops, cubic).
Window velocity per frame (vx_t, vy_t) = (4 + 1.5 sin(2 pi t/150 + 0.3), 2.5 + sin(2 pi t/105 + 1)) px, disparity
d_t = 8 + 4 sin(2 pi t/135 + 0.5) px: training frames vx {fmt(tr['vx'])}, vy {fmt(tr['vy'])}, d {fmt(tr['disparity'])};
held-out frames vx {fmt(hr['vx'])}, vy {fmt(hr['vy'])}, d {fmt(hr['disparity'])} px. Right view = the window shifted right
by d_t (left pixel x matches right pixel x - d, the project's convention), with a different camera response
(gain {v['right_camera']['gain']}, gamma {v['right_camera']['gamma']}); Gaussian noise sigma {v['noise_sigma']} grey
level on both. Codec: {v['codec']} (mean |decoded - rendered| {v['codec_mean_abs_err']:.2f} grey levels).
Split: the first {v['train_frames']} frames = `data_dir`, the last {v['heldout_frames']} = `val_dir` and the scored set
({v['heldout_pairs']} consecutive pairs); {100 * v['heldout_area_unseen_in_training']:.1f} % of the photo area the
held-out left views show was never in a training left view (the pan is continuous, so the held-out windows overlap
the last training windows).

Ground truth per held-out pair: disparity d_t (uniform), flow left_t -> left_t+1 = -(vx_t, vy_t) (uniform). Signs
asserted on the decoded frames (mean |difference| after warping by the GT map vs by the opposite sign): flow
{v['sign_checks']['flow_gt_sign']:.2f} vs {v['sign_checks']['flow_opposite_sign']:.2f} grey levels, stereo
(normalised) {v['sign_checks']['stereo_gt_sign']:.3f} vs {v['sign_checks']['stereo_opposite_sign']:.3f}. Scored over
interior pixels (a {v['border_px']} px border left out); EPE px; Fl / D1 = outliers > 3 px and > 5 %; means over pairs.

Test-time settings: "card" = `load_predictor(ckpt)` defaults (long: {cards['before']}; fine-tuned:
{cards['after']}); "polish none" = the same with polish="none"; "raw" = refine 0, symmetry none, polish none.

## Command

```
{result['train_command']}
```

Fine-tune wall time: {result['train_seconds']:.0f} s ({result['train_seconds'] / 60:.1f} min, {result['steps']} steps, whole
command incl. start-up, compilation and validations); the whole script {result['total_seconds'] / 60:.1f} min.

## Results (held-out pairs, lower is better)

{table(result)}

Changes (before -> after):

{chr(10).join(comparison(result))}

## The trainer's validation lines (photometric, on `val_dir`)

```
{val}
```
"""


if __name__ == "__main__":
    main()
