"""Real-image checks: the models against OpenCV on real photographs with exact ground truth.

Five checks, each run for every model (`--models`, shipped names or checkpoint paths) at every working size
(`--sizes`: `trained` = the size the model was trained at, `native` = each input at its own resolution, or HxW),
next to OpenCV on the same inputs at full resolution:

1. **Middlebury "Motorcycle"** (scikit-image's stereo pair with its ground-truth disparity, 741x500): disparity
   EPE and D1 (KITTI outliers: > 3 px and > 5 %) over the pixels with ground truth, against SGBM with its holes
   filled (`eval.baselines.sgbm_disparity`).
2. **Real photos under known motion** (`homography_pair`): a held-out photo (`data.photos.HELDOUT_PHOTOS`, never
   used in training) seen through a random homography, with 2-3 independently moving pasted patches (affine
   motion) cut from another held-out photo, and a camera-response change plus noise between the frames. The flow
   is exact by construction and so is the occlusion mask: flow EPE-all / EPE-noc and Fl-all against DIS (medium).
3. **Held-out synthetic frames** (`synthetic.SCENE_PRESETS["heldout"]`: held-out photos as textures, a focal
   length and baseline no training preset draws, stronger photometric differences), 256x512: flow EPE-all,
   EPE-noc and disparity EPE / D1 against DIS and SGBM, and zero motion for scale.
4. **Pure shifts** (`shift_set`): each held-out photo moved by 4 and 8 px, horizontally and vertically, with a
   camera-response change: EPE and the gain along the motion, per direction. It shows a direction the training
   scenes never moved in (the vertical, before `real_motion`).
5. **Pure zooms** (`zoom_set`): each held-out photo zoomed by +4 % and -4 % about its centre, with a
   camera-response change: EPE and the gain (least-squares scale of the predicted flow), per direction. It shows
   whether a model reads expansion and contraction at their size (`long` before stage 6 read them 3-5 % short).

    python experiments/real_images.py --models demo,long --sizes trained,native \\
        --out experiments/results/real_images.md --pictures experiments/results/real_images

Writes the markdown table (machine and date in its header), a JSON file beside it with every number, picture
panels (input | ground truth | OpenCV | each model; half-size JPEGs) under `--pictures`, and with `--card` the
first model's numbers for its zoo card (`bridge-zoo build NAME --from WORKDIR --card FILE`; at the first
`--refine`, `--symmetry` and `--polish` values, which the card then recommends). `--refine 0,2` scores each
model without and with two test-time refinement passes (`inference.refine_maps`), `--symmetry none,flips`
without and with test-time symmetry averaging (`inference.symmetric_estimate`), `--polish none,photometric`
without and with the test-time photometric polish (`bridge_jax.polish`); the default of all three, `card`, runs
each model as its card says.
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import sys
import time

import cv2
import numpy as np

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
if REPO not in sys.path:
    sys.path.insert(0, REPO)

from bridge_jax import inference, metrics, visualize  # noqa: E402
from bridge_jax.bench import timing  # noqa: E402
from bridge_jax.data import photos  # noqa: E402
from bridge_jax.eval import baselines  # noqa: E402
from bridge_jax.eval.datasets import synthetic_frames  # noqa: E402

HOMOGRAPHY_SEED = 20261202
HELDOUT_SYNTHETIC_SEED = 2_000_003  # disjoint from training (seed 0) and the validation seed (1,000,003)


# ----------------------------------------------------------------------------------------------------------
# Real photos under known motion
# ----------------------------------------------------------------------------------------------------------

def random_homography(rng: np.random.Generator, height: int, width: int, max_shift: float = 12.0) -> np.ndarray:
    """A 3x3 homography in pixel coordinates (x = column, y = row, centres at integers), frame t -> t+1: about
    the image centre a rotation (±3°), zoom (0.95-1.05), shear (±0.02) and perspective (±4e-5 / px), then a
    shift of up to `max_shift` px per axis."""
    cx, cy = (width - 1) / 2.0, (height - 1) / 2.0
    a, s = np.deg2rad(rng.uniform(-3, 3)), rng.uniform(0.95, 1.05)
    lin = s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]) @ np.array(
        [[1.0, rng.uniform(-0.02, 0.02)], [0.0, 1.0]])
    g = np.eye(3)
    g[:2, :2] = lin
    g[2, :2] = rng.uniform(-4e-5, 4e-5, 2)
    centre, back = np.eye(3), np.eye(3)
    centre[:2, 2] = (-cx, -cy)
    back[:2, 2] = (cx + rng.uniform(-max_shift, max_shift), cy + rng.uniform(-max_shift, max_shift))
    return back @ g @ centre


def apply_homography(h: np.ndarray, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Maps pixel coordinates `(x, y)` (any same-shape arrays) through `h`."""
    d = h[2, 0] * x + h[2, 1] * y + h[2, 2]
    return (h[0, 0] * x + h[0, 1] * y + h[0, 2]) / d, (h[1, 0] * x + h[1, 1] * y + h[1, 2]) / d


def _patch_ids(patches: list[dict], x: np.ndarray, y: np.ndarray, time: int) -> np.ndarray:
    """Topmost patch (1..K; 0 = background) covering each position `(x, y)` at `time` (0 = t, 1 = t+1)."""
    ids = np.zeros(x.shape, np.int32)
    for k, p in enumerate(patches, start=1):
        lx, ly = _patch_local(p, x, y, time)
        if p["ellipse"]:
            inside = (lx / p["half"][0]) ** 2 + (ly / p["half"][1]) ** 2 <= 1.0
        else:
            inside = (np.abs(lx) <= p["half"][0]) & (np.abs(ly) <= p["half"][1])
        ids[inside] = k
    return ids


def _patch_local(p: dict, x: np.ndarray, y: np.ndarray, time: int) -> tuple[np.ndarray, np.ndarray]:
    """Patch-local coordinates of positions `(x, y)`: r = p - c at t, r = M^-1 (q - c - v) at t+1."""
    dx, dy = x - p["centre"][0], y - p["centre"][1]
    if time == 0:
        return dx, dy
    dx, dy = dx - p["shift"][0], dy - p["shift"][1]
    inv = np.linalg.inv(p["affine"])
    return inv[0, 0] * dx + inv[0, 1] * dy, inv[1, 0] * dx + inv[1, 1] * dy


def camera_change(img: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """uint8 RGB -> uint8 RGB through another camera response: per-channel gain 0.9-1.1, offset ±3 %, gamma
    0.9-1.1 and noise of 1 % std."""
    x = img.astype(np.float32) / 255.0
    x = np.clip(x * rng.uniform(0.9, 1.1, 3) + rng.uniform(-0.03, 0.03, 3), 0, 1) ** rng.uniform(0.9, 1.1)
    x = x + rng.normal(0.0, 0.01, x.shape)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


MARGIN = 0.1
"""The share of a photo's height and width `homography_pair` crops from each side by default."""


def crop_margins(shape: tuple, margin: float = MARGIN) -> tuple[int, int]:
    """(rows, columns) `homography_pair` crops from each side of a photo of `shape` (h, w, ...)."""
    return int(round(margin * shape[0])), int(round(margin * shape[1]))


def homography_pair(photo: np.ndarray, patch_photo: np.ndarray, rng: np.random.Generator, *,
                    homography: np.ndarray | None = None, patches: list[dict] | None = None,
                    margin: float = MARGIN, photometric: bool = True) -> dict:
    """Two frames of a real photo under known motion, with exact flow and occlusion.

    Frame t is the photo cropped by `margin` on each side; frame t+1 sees the same plane through the homography
    `homography` (frame-t pixel -> frame-t+1 pixel; default `random_homography`). Patches of `patch_photo`
    (default 2-3 random rectangles and ellipses, 25-55 px half sizes) lie on top, each moving by its own affine
    map q = c + v + M (p - c). Frame t+1 gets `camera_change` when `photometric`.

    Returns {"frame_t", "frame_t1": uint8 (H, W, 3), "flow": float32 (H, W, 2) px t -> t+1, "valid": all True,
    "noc": bool (H, W) — the match lies inside frame t+1 and shows the same surface there}.
    """
    ph, pw = photo.shape[:2]
    my, mx = crop_margins(photo.shape, margin)
    height, width = ph - 2 * my, pw - 2 * mx
    g = random_homography(rng, height, width) if homography is None else np.asarray(homography, np.float64)
    if patches is None:
        patches = []
        for _ in range(int(rng.integers(2, 4))):
            a, s = np.deg2rad(rng.uniform(-5, 5)), rng.uniform(0.95, 1.05)
            patches.append({"centre": (rng.uniform(0.15, 0.85) * width, rng.uniform(0.15, 0.85) * height),
                            "half": (rng.uniform(25, 55), rng.uniform(25, 55)), "ellipse": bool(rng.uniform() < 0.5),
                            "shift": tuple(rng.uniform(-15, 15, 2)),
                            "affine": s * np.array([[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]),
                            "offset": (rng.uniform(60, patch_photo.shape[1] - 60),
                                       rng.uniform(60, patch_photo.shape[0] - 60))})
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))

    def render(time: int) -> tuple[np.ndarray, np.ndarray]:
        if time == 0:
            sx, sy = xs, ys
        else:
            sx, sy = apply_homography(np.linalg.inv(g), xs, ys)
        img = cv2.remap(photo, (sx + mx).astype(np.float32), (sy + my).astype(np.float32), cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_REFLECT_101)
        ids = _patch_ids(patches, xs, ys, time)
        for k, p in enumerate(patches, start=1):
            lx, ly = _patch_local(p, xs, ys, time)
            tex = cv2.remap(patch_photo, (lx + p["offset"][0]).astype(np.float32),
                            (ly + p["offset"][1]).astype(np.float32), cv2.INTER_LINEAR,
                            borderMode=cv2.BORDER_REFLECT_101)
            img[ids == k] = tex[ids == k]
        return img, ids

    frame_t, ids_t = render(0)
    frame_t1, _ = render(1)
    tx, ty = apply_homography(g, xs, ys)
    for k, p in enumerate(patches, start=1):
        sel = ids_t == k
        dx, dy = xs[sel] - p["centre"][0], ys[sel] - p["centre"][1]
        m = p["affine"]
        tx[sel] = p["centre"][0] + p["shift"][0] + m[0, 0] * dx + m[0, 1] * dy
        ty[sel] = p["centre"][1] + p["shift"][1] + m[1, 0] * dx + m[1, 1] * dy
    inside = (tx >= 0) & (tx <= width - 1) & (ty >= 0) & (ty <= height - 1)
    noc = inside & (_patch_ids(patches, tx, ty, 1) == ids_t)
    if photometric:
        frame_t1 = camera_change(frame_t1, rng)
    flow = np.stack([tx - xs, ty - ys], -1).astype(np.float32)
    return {"frame_t": frame_t, "frame_t1": frame_t1, "flow": flow, "valid": np.ones((height, width), bool),
            "noc": noc}


def homography_set(per_photo: int = 3, seed: int = HOMOGRAPHY_SEED) -> list[dict]:
    """`per_photo` pairs of each held-out photo; the patches come from the next held-out photo."""
    rng = np.random.default_rng(seed)
    names = photos.HELDOUT_PHOTOS
    images = {n: photos.load_photo(n) for n in names}
    out = []
    for i, name in enumerate(names):
        for j in range(per_photo):
            pair = homography_pair(images[name], images[names[(i + 1) % len(names)]], rng)
            pair["id"] = f"{name}-{j}"
            out.append(pair)
    return out


SHIFTS = ((4.0, 0.0), (-8.0, 0.0), (0.0, 4.0), (0.0, -8.0))
"""The translations (dx, dy) px of `shift_set`: two horizontal, then the same two turned vertical."""


def shift_set(seed: int = HOMOGRAPHY_SEED + 1) -> list[dict]:
    """Each held-out photo moved by each of `SHIFTS` (no patches, a camera-response change between the frames):
    the simplest motion there is, asked once horizontally and once vertically. A model that learned flow from
    scenes that hardly move vertically answers the vertical ones short (`shift_metrics`)."""
    rng = np.random.default_rng(seed)
    out = []
    for name in photos.HELDOUT_PHOTOS:
        image = photos.load_photo(name)
        for dx, dy in SHIFTS:
            g = np.array([[1.0, 0.0, dx], [0.0, 1.0, dy], [0.0, 0.0, 1.0]])
            pair = homography_pair(image, image, rng, homography=g, patches=[])
            pair.update(id=f"{name}-{dx:+.0f},{dy:+.0f}", shift=(dx, dy))
            out.append(pair)
    return out


ZOOMS = (1.04, 0.96)
"""The zooms of `zoom_set`: the scene expands by 4 % (the camera moves towards it), then contracts by 4 %."""


def zoom_set(seed: int = HOMOGRAPHY_SEED + 2) -> list[dict]:
    """Each held-out photo zoomed by each of `ZOOMS` about its centre (no patches, a camera-response change
    between the frames): flow s (p - c) - (p - c), from 0 at the centre to about 8 px at the corners. A model
    whose training scenes expand only one way (a rig driving forward), or only far from the horizon, reads the
    zoom short (`zoom_metrics`)."""
    rng = np.random.default_rng(seed)
    out = []
    for name in photos.HELDOUT_PHOTOS:
        image = photos.load_photo(name)
        my, mx = crop_margins(image.shape)
        cx, cy = (image.shape[1] - 2 * mx - 1) / 2.0, (image.shape[0] - 2 * my - 1) / 2.0  # centre of frame t
        for s in ZOOMS:
            g = np.array([[s, 0.0, (1 - s) * cx], [0.0, s, (1 - s) * cy], [0.0, 0.0, 1.0]])
            pair = homography_pair(image, image, rng, homography=g, patches=[])
            pair.update(id=f"{name}-x{s:.2f}", zoom=s)
            out.append(pair)
    return out


def zoom_metrics(flows: list[np.ndarray], pairs: list[dict]) -> dict:
    """EPE (noc pixels) of the expanding and of the contracting zooms of `zoom_set`, and the gain: the
    least-squares scale of the predicted flow against the true one over the noc pixels (sum f.g / sum g.g;
    1 = exact, < 1 = the zoom read short)."""
    out: dict[str, list] = {"epe_expand": [], "epe_contract": [], "gain_expand": [], "gain_contract": []}
    for f, pair in zip(flows, pairs):
        kind = "expand" if pair["zoom"] > 1 else "contract"
        m, g = pair["noc"], pair["flow"].astype(np.float64)
        out[f"epe_{kind}"].append(float(np.linalg.norm(f - g, axis=-1)[m].mean()))
        out[f"gain_{kind}"].append(float((f[m] * g[m]).sum() / (g[m] ** 2).sum()))
    return {k: float(np.mean(v)) for k, v in out.items()}


def shift_metrics(flows: list[np.ndarray], pairs: list[dict]) -> dict:
    """EPE (noc pixels) of the horizontal and of the vertical shifts of `shift_set`, and the gain along the
    motion: median predicted component / true component, over the noc pixels (1 = exact, < 1 = short)."""
    out: dict[str, list] = {"epe_horizontal": [], "epe_vertical": [], "gain_horizontal": [], "gain_vertical": []}
    for f, pair in zip(flows, pairs):
        dx, dy = pair["shift"]
        axis = "horizontal" if dy == 0 else "vertical"
        m = pair["noc"]
        out[f"epe_{axis}"].append(float(np.linalg.norm(f - pair["flow"], axis=-1)[m].mean()))
        c, true = (0, dx) if dy == 0 else (1, dy)
        out[f"gain_{axis}"].append(float(np.median(f[..., c][m]) / true))
    return {k: float(np.mean(v)) for k, v in out.items()}


# ----------------------------------------------------------------------------------------------------------
# Running the checks
# ----------------------------------------------------------------------------------------------------------

def motorcycle() -> dict:
    """scikit-image's Middlebury Motorcycle pair: uint8 left/right (500, 741, 3), disparity (inf = no GT)."""
    from skimage import data as skdata
    left, right, disp = skdata.stereo_motorcycle()
    valid = np.isfinite(disp) & (disp > 0)
    return {"left": left, "right": right, "disp": np.where(valid, disp, 0).astype(np.float32), "valid": valid}


def _mean(rows: list[dict]) -> dict:
    return {k: float(np.nanmean([r[k] for r in rows])) for k in rows[0]}


def run_checks(methods: dict, *, per_photo: int = 3, synthetic_num: int = 16, pictures: str | None = None) -> dict:
    """methods: name -> predictor (or "opencv"/"zero"). Returns {check: {method: metrics}}."""
    results: dict[str, dict] = {"motorcycle": {}, "homography": {}, "heldout_synthetic": {}, "shifts": {},
                                "zooms": {}}
    timing: dict[str, float] = {}
    moto = motorcycle()
    hom = homography_set(per_photo)
    shifts = shift_set()
    zooms = zoom_set()
    syn = synthetic_frames(synthetic_num, HELDOUT_SYNTHETIC_SEED, 256, 512, scene="heldout")
    panels: dict[str, list] = {"motorcycle": [], "homography": [], "heldout_synthetic": []}
    for name, method in methods.items():
        t0 = time.perf_counter()
        # 1. Motorcycle
        if method == "zero":
            d = np.zeros_like(moto["disp"])
        elif method == "opencv":
            d = baselines.sgbm_disparity(moto["left"], moto["right"])
        else:
            d = method.predict([("stereo", moto["left"], moto["right"])])[0]
        results["motorcycle"][name] = _pick(metrics.disparity_metrics(d, moto["disp"], moto["valid"]),
                                            ("epe_all", "d1_all"))
        panels["motorcycle"].append((name, visualize.disparity_to_color(d, vmax=64.0)))
        # 2. Homographies
        rows = []
        for k, (pair, f) in enumerate(zip(hom, _flows(method, hom))):
            rows.append(_pick(metrics.flow_metrics(f, pair["flow"], pair["valid"], pair["noc"]),
                              ("epe_all", "epe_noc", "fl_all")))
            if k == 0:
                panels["homography"].append((name, visualize.flow_to_color(f, max_flow=20.0)))
        results["homography"][name] = _mean(rows)
        # 3. Held-out synthetic
        rows = []
        for k, fr in enumerate(syn):
            im = fr.images
            if method == "zero":
                f, d = np.zeros_like(fr.gt["flow_occ"]), np.zeros(fr.size, np.float32)
            elif method == "opencv":
                f = baselines.dis_flow(im["left_t"], im["left_t1"])
                d = baselines.sgbm_disparity(im["left_t"], im["right_t"])
            else:
                d, f = method.predict([("stereo", im["left_t"], im["right_t"]), ("flow", im["left_t"], im["left_t1"])])
            fm = metrics.flow_metrics(f, fr.gt["flow_occ"], fr.gt["flow_occ_valid"], fr.gt["flow_noc_valid"])
            dm = metrics.disparity_metrics(d, fr.gt["disp_occ_0"])
            rows.append({"flow_epe_all": fm["epe_all"], "flow_epe_noc": fm["epe_noc"], "fl_all": fm["fl_all"],
                         "disp_epe_all": dm["epe_all"], "d1_all": dm["d1_all"]})
            if k == 0:
                panels["heldout_synthetic"].append((name, visualize.flow_to_color(f, max_flow=30.0)))
        results["heldout_synthetic"][name] = _mean(rows)
        # 4. Pure shifts, horizontal and vertical; 5. pure zooms, expanding and contracting
        results["shifts"][name] = shift_metrics(_flows(method, shifts), shifts)
        results["zooms"][name] = zoom_metrics(_flows(method, zooms), zooms)
        timing[name] = time.perf_counter() - t0
        print(f"{name}: {timing[name]:.1f} s", file=sys.stderr, flush=True)
    if pictures:
        os.makedirs(pictures, exist_ok=True)
        gt_images = {"motorcycle": (moto["left"], visualize.disparity_to_color(moto["disp"], vmax=64.0)),
                     "homography": (hom[0]["frame_t"], visualize.flow_to_color(hom[0]["flow"], max_flow=20.0)),
                     "heldout_synthetic": (syn[0].images["left_t"],
                                           visualize.flow_to_color(syn[0].gt["flow_occ"], max_flow=30.0))}
        for check, items in panels.items():
            image, gt = gt_images[check]
            tiles = [image, gt] + [t for _, t in items]
            labels = ["input", "ground truth"] + [n for n, _ in items]
            picture = visualize.panel(tiles, labels, ncols=3)
            picture = cv2.resize(picture, (picture.shape[1] // 2, picture.shape[0] // 2), interpolation=cv2.INTER_AREA)
            visualize.write_image(os.path.join(pictures, f"{check}.jpg"), picture)  # half size: small files
    results["seconds"] = timing
    return results


def _flows(method, pairs: list[dict]) -> list[np.ndarray]:
    """The flow of each of `pairs` (frame_t -> frame_t1) by `method`: a predictor, "zero" or "opencv" (DIS)."""
    if method == "zero":
        return [np.zeros_like(p["flow"]) for p in pairs]
    if method == "opencv":
        return [baselines.dis_flow(p["frame_t"], p["frame_t1"]) for p in pairs]
    return method.predict([("flow", p["frame_t"], p["frame_t1"]) for p in pairs], batch=1)


def _pick(d: dict, keys) -> dict:
    return {k: d[k] for k in keys}


HEADLINE = (("motorcycle", "d1_all"), ("motorcycle", "epe_all"), ("homography", "epe_all"),
            ("heldout_synthetic", "flow_epe_all"), ("heldout_synthetic", "disp_epe_all"))
"""The numbers that choose a model's default working size (lower is better)."""


def pick_working_size(card: dict) -> str:
    """The working size a model's card recommends (and `--working-size` defaults to): the measured size that
    beats every other measured size, one against one, on more of the `HEADLINE` numbers than it loses ("trained",
    "native" or "HxW", as `--sizes` named it); "trained" when no size beats all the others. A tie on a number (a
    check whose images are the trained size, so two sizes run the same) counts for neither."""
    sizes = list(dict.fromkeys(s for c, _ in HEADLINE for s in card.get(c, {}) if s != "opencv"))

    def beats(a: str, b: str) -> bool:
        pairs = [(card[c][a][k], card[c][b][k]) for c, k in HEADLINE if a in card.get(c, {}) and b in card.get(c, {})]
        return sum(x < y for x, y in pairs) > sum(y < x for x, y in pairs)

    winners = [a for a in sizes if all(beats(a, b) for b in sizes if b != a)]
    return winners[0] if winners else "trained"


def markdown(results: dict, header: str) -> str:
    lines = [header, ""]
    cols = {"motorcycle": [("epe_all", "disp EPE px"), ("d1_all", "D1 %")],
            "homography": [("epe_all", "flow EPE-all px"), ("epe_noc", "EPE-noc px"), ("fl_all", "Fl-all %")],
            "heldout_synthetic": [("flow_epe_all", "flow EPE-all"), ("flow_epe_noc", "EPE-noc"), ("fl_all", "Fl %"),
                                  ("disp_epe_all", "disp EPE"), ("d1_all", "D1 %")],
            "shifts": [("epe_horizontal", "EPE horizontal px"), ("epe_vertical", "EPE vertical px"),
                       ("gain_horizontal", "gain horizontal"), ("gain_vertical", "gain vertical")],
            "zooms": [("epe_expand", "EPE expanding px"), ("epe_contract", "EPE contracting px"),
                      ("gain_expand", "gain expanding"), ("gain_contract", "gain contracting")]}
    titles = {"motorcycle": "Middlebury Motorcycle (741x500, disparity)",
              "homography": "Held-out photos under homographies + moving patches (flow)",
              "heldout_synthetic": "Held-out synthetic scenes, 256x512 (flow and disparity)",
              "shifts": "Held-out photos shifted by 4 and 8 px, horizontally and vertically (flow; gain 1 = exact)",
              "zooms": "Held-out photos zoomed by +4 % and -4 % about their centre (flow; gain 1 = exact)"}
    for check, cs in cols.items():
        if check not in results:  # results of an earlier version of the script
            continue
        lines += [f"### {titles[check]}", "", "| method | " + " | ".join(c[1] for c in cs) + " |",
                  "|---" * (len(cs) + 1) + "|"]
        for name, m in results[check].items():
            lines.append(f"| {name} | " + " | ".join(f"{m[c[0]]:.3f}" if c[0].startswith(("epe", "flow_epe",
                                                                                             "disp_epe", "gain"))
                                                      else f"{m[c[0]]:.1f}" for c in cs) + " |")
        lines.append("")
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--models", default="demo", help="comma list of shipped model names or checkpoint paths")
    p.add_argument("--sizes", default="trained,native", help="comma list: trained, native, or HxW")
    p.add_argument("--refine", default="card",
                   help="comma list of test-time refinement passes to score (each a method), or 'card' = what "
                        "each model's card recommends (0 for a checkpoint path)")
    p.add_argument("--symmetry", default="card",
                   help="comma list of test-time symmetry averagings to score (none, flips, dihedral; each a "
                        "method), or 'card' = what each model's card recommends (none for a checkpoint path)")
    p.add_argument("--polish", default="card",
                   help="comma list of test-time polishes to score (none, photometric; each a method), or 'card' = "
                        "what each model's card recommends (none for a checkpoint path)")
    p.add_argument("--per-photo", type=int, default=3, help="homography pairs per held-out photo")
    p.add_argument("--synthetic-num", type=int, default=16, help="held-out synthetic frames")
    p.add_argument("--out", default=None, help="markdown file (a .json with every number is written beside it)")
    p.add_argument("--pictures", default=None, help="folder for the picture panels")
    p.add_argument("--card", default=None,
                   help="write the first model's numbers (per check and size, with OpenCV's) as a model-card JSON "
                        "for `bridge-zoo build NAME --from WORKDIR --card FILE`")
    args = p.parse_args(argv)
    opencv = "OpenCV (SGBM filled / DIS medium)"
    methods: dict = {"zero motion": "zero", opencv: "opencv"}
    card_labels = {}
    for i, model in enumerate(m for m in args.models.split(",") if m):
        passes = [None] if args.refine == "card" else [int(v) for v in args.refine.split(",") if v]
        symmetries = [None] if args.symmetry == "card" else [v for v in args.symmetry.split(",") if v]
        polishes = [None] if args.polish == "card" else [v for v in args.polish.split(",") if v]
        for size in [s for s in args.sizes.split(",") if s]:
            ws = size if size in ("trained", "native") else tuple(int(v) for v in size.lower().split("x"))
            variants = [(r, y, q) for r in passes for y in symmetries for q in polishes]
            for k, (refine, symmetry, polish) in enumerate(variants):
                pred = inference.load_predictor(model, working_size=ws, refine=refine, refine_option="--refine",
                                                symmetry=symmetry, symmetry_option="--symmetry", polish=polish,
                                                polish_option="--polish")
                label = f"{os.path.basename(model.rstrip('/'))} @ {size}"
                if size == "trained":
                    label += f" ({pred.height}x{pred.width})"
                if pred.refine:
                    label += f", refine {pred.refine}"
                if pred.symmetry != "none":
                    label += f", {pred.symmetry}"
                if pred.polish != "none":
                    label += f", {pred.polish} polish"
                methods[label] = pred
                if i == 0 and k == 0:
                    card_labels[size] = label
    results = run_checks(methods, per_photo=args.per_photo, synthetic_num=args.synthetic_num,
                         pictures=args.pictures)
    stamp = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    header = f"## Real-image checks, {stamp}, {timing.machine()}"
    text = markdown(results, header)
    print(text)
    print("seconds per method:", {k: round(v, 1) for k, v in results["seconds"].items()})
    if args.out:
        with open(args.out, "w") as f:
            f.write(text + "\n")
        with open(os.path.splitext(args.out)[0] + ".json", "w") as f:
            json.dump({"date": stamp, "machine": timing.machine(), **results}, f, indent=1)
    if args.card:
        checks = ("motorcycle", "homography", "heldout_synthetic")
        card = {check: {**{size: results[check][label] for size, label in card_labels.items()},
                        "opencv": results[check][opencv]} for check in checks}
        with open(args.card, "w") as f:
            first = methods[next(iter(card_labels.values()))]  # numbers at the first --refine/--symmetry/--polish
            json.dump({"real_images": card, "real_images_measured": f"{stamp}, {timing.machine()}",
                       "default_working_size": pick_working_size(card), "default_refine": first.refine,
                       "default_symmetry": first.symmetry, "default_polish": first.polish}, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
