"""Procedural stereo video with exact ground truth (the built-in data set; no download needed).

A rectified stereo rig (left camera = reference, right camera displaced by `baseline` metres along the camera x
axis) moves between time t and t+1 through a scene made of textured *planar layers*:

* a ground plane at the camera height, a far background wall, optional building facades on both sides
    (planes parallel to the driving direction, strong perspective) and
* 3-8 fronto-parallel objects (rectangles or ellipses) at 4-35 m, about half of them moving independently.

The rig moves forward 0-1.4 m per frame with a little sideways motion (±0.1 m) and yaw (±0.03 rad), so there
are occlusions and disocclusions at object borders and points leaving the view at the image borders. Textures
come from a pool of 48 procedurally generated base textures (built lazily once per process) that every layer
re-colours (random 3×3 colour matrix), shifts and scales.

Every pixel of each of the four views is *ray-cast*: the visible surface is the nearest layer that the pixel's
viewing ray hits, and its colour is read from a texture defined in the layer's own (u, v) coordinates in metres.
Because images and ground truth come from the same analytic geometry, the ground truth is exact at pixel centres:

* disparity d = f·B / Z of the visible surface (pixels, positive; right-image match at x − d);
* optical flow (left camera, t → t+1) = projection at t+1 of the same 3-D point (moved with its layer) minus the
    pixel position; x + flow is the match in frame t+1;
* *noc* ("non-occluded") masks are decided by casting the ray through the matching position in the other view:
    the pixel is non-occluded when that ray hits the same layer (a plane meets a ray once, so same layer = same
    point) and the match lies inside the image. The "occ" masks (`valid_*`) hold every pixel with a surface.

Textures have natural-image statistics: 1/f multi-scale noise in luminance and colour, plus sharp-edged shapes
and lines, band-limited (Gaussian, then a mip pyramid chosen per pixel from the footprint) so that sampling the
other view at the GT match reproduces the pixel up to interpolation noise.

Conventions: pixel (x, y) has its centre at integer coordinates (x = column, y = row); world frame of time t is
the left camera at t (X right, Y down, Z forward). Default focal = 721.5377·W/1242 (KITTI scaled), baseline
0.54 m, principal point ((W−1)/2, 0.46·H).

CLI: `bridge-synthetic --out DIR --num N --seed S [--height 256 --width 512]` writes the
KITTI 2015 training layout (see `write_kitti_layout`).
"""
from __future__ import annotations

import dataclasses
import functools
import json
import math
import os
import sys
from typing import Any

import cv2
import numpy as np

from bridge_jax import cli, files
from bridge_jax.data import kitti

cv2.setNumThreads(1)

KITTI_FOCAL_1242 = 721.5377
DEFAULT_BASELINE = 0.54

# Layer shapes.
_PLANE, _RECT, _ELLIPSE = 0, 1, 2


@dataclasses.dataclass(frozen=True)
class SceneConfig:
    """Knobs of the random scene (all lengths in metres, motions per frame)."""
    min_objects: int = 3
    max_objects: int = 8
    moving_prob: float = 0.5
    max_object_speed: float = 1.2      # |v| per frame of a moving object (x and z components)
    max_ego_forward: float = 1.4       # camera forward motion per frame, U(0, max)
    max_ego_lateral: float = 0.1
    max_ego_yaw: float = 0.03          # radians per frame
    facade_prob: float = 0.6
    min_object_depth: float = 4.0
    max_object_depth: float = 35.0
    noise_std: float = 0.0             # optional per-view sensor noise (on [0,1] values); 0 keeps GT exact
    # Beyond the demo's look (all off by default, so the default samples stay what they were). Their draws come
    # from a second generator seeded by the sample seed, never from the scene's own.
    photo_texture_prob: float = 0.0    # share of layers textured with a real photo crop (`photos.photo_textures`)
    photo_set: str = "train"           # which photos: "train" | "heldout" (kept out of training)
    textureless_prob: float = 0.0      # share of layers that are nearly uniform (sky, painted walls)
    slant_prob: float = 0.0            # share of objects turned up to ±60° about the vertical, ±30° about x
    spin_prob: float = 0.0             # share of moving objects that also rotate between t and t+1
    max_spin: float = 0.15             # radians per frame of a rotating object, about a random axis
    focal_range: tuple = (1.0, 1.0)    # focal length drawn per sample, as multiples of the default focal
    baseline_range: tuple = (1.0, 1.0)  # baseline drawn per sample, as multiples of the baseline argument
    cam_height_range: tuple = (1.5, 1.8)  # camera height above the ground (metres)
    photometric: float = 0.0           # strength of per-view gain/offset/gamma/blur/noise (`camera_response`)
    # Vertical motion. The rig moves rigidly, so the stereo pairs stay rectified; without these, flow is
    # almost only horizontal (forward, lateral and yaw motions), and a model trained on it learns to
    # shrink vertical motion (a 3 px vertical shift of a real photo read as 0.4 px by `demo`).
    max_ego_pitch: float = 0.0         # rig pitch between t and t+1, radians, U(-max, max)
    max_ego_roll: float = 0.0          # rig roll between t and t+1, radians
    max_ego_vertical: float = 0.0      # rig translation along the camera's y axis (metres per frame)
    max_object_vertical_speed: float = 0.0  # vertical velocity of a moving object (metres per frame)

    def __post_init__(self):
        for name in ("photo_texture_prob", "textureless_prob", "slant_prob", "spin_prob"):
            if not 0.0 <= float(getattr(self, name)) <= 1.0:
                raise ValueError(f"scene {name} must be in [0, 1], got {getattr(self, name)!r}")
        if self.photo_texture_prob + self.textureless_prob > 1.0:
            raise ValueError("scene photo_texture_prob + textureless_prob must be <= 1")
        if self.photo_set not in ("train", "heldout"):
            raise ValueError(f"scene photo_set must be 'train' or 'heldout', got {self.photo_set!r}")
        for name in ("focal_range", "baseline_range", "cam_height_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise ValueError(f"scene {name} must be (low, high) with 0 < low <= high, got {getattr(self, name)!r}")
        if self.photometric < 0 or self.max_spin < 0:
            raise ValueError("scene photometric and max_spin must be >= 0")
        for name in ("max_ego_pitch", "max_ego_roll", "max_ego_vertical", "max_object_vertical_speed"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"scene {name} must be >= 0, got {getattr(self, name)!r}")


SCENE_PRESETS = {
    # The demo's scenes: procedural textures, fronto-parallel objects, one rig, identical cameras.
    "demo": SceneConfig(),
    # A training domain that generalises to real images: photo and procedural textures, uniform regions,
    # slanted and rotating objects, varied rigs, larger motions, and cameras that differ photometrically.
    "real": SceneConfig(max_object_speed=2.0, max_ego_forward=2.0, max_ego_lateral=0.2, max_ego_yaw=0.05,
                        photo_texture_prob=0.5, textureless_prob=0.1, slant_prob=0.5, spin_prob=0.3,
                        focal_range=(0.6, 1.6), baseline_range=(0.5, 1.6), cam_height_range=(1.0, 2.5),
                        photometric=1.0),
    # `real` with vertical motion as well: the rig pitches, rolls and moves up and down between t and t+1,
    # and moving objects also move vertically.
    "real_motion": SceneConfig(max_object_speed=2.0, max_ego_forward=2.0, max_ego_lateral=0.2, max_ego_yaw=0.05,
                               photo_texture_prob=0.5, textureless_prob=0.1, slant_prob=0.5, spin_prob=0.3,
                               focal_range=(0.6, 1.6), baseline_range=(0.5, 1.6), cam_height_range=(1.0, 2.5),
                               photometric=1.0, max_ego_pitch=0.04, max_ego_roll=0.03, max_ego_vertical=0.15,
                               max_object_vertical_speed=0.6),
    # Held-out settings for checking generalisation: held-out photos only, stronger photometric differences,
    # a rig none of the presets above draws (longer focal, shorter baseline), more objects.
    "heldout": SceneConfig(min_objects=5, max_objects=10, max_object_speed=1.6, max_ego_forward=1.8,
                           photo_texture_prob=0.8, photo_set="heldout", textureless_prob=0.05, slant_prob=0.7,
                           spin_prob=0.5, focal_range=(1.7, 2.0), baseline_range=(0.3, 0.45),
                           cam_height_range=(1.2, 2.0), photometric=1.2),
}
"""Named scene settings (`data.synthetic_scene` of a training config; `--scene` of the CLI)."""


def scene_config(name: str) -> SceneConfig:
    """`SCENE_PRESETS[name]`; ValueError naming the allowed names."""
    if name not in SCENE_PRESETS:
        raise ValueError(f"synthetic scene must be one of {tuple(SCENE_PRESETS)}, got {name!r}")
    return SCENE_PRESETS[name]


@dataclasses.dataclass
class _Layer:
    normal: np.ndarray          # (3,) world, unit
    origin: np.ndarray          # (3,) world position at time t
    u_axis: np.ndarray          # (3,) world, unit, in-plane
    v_axis: np.ndarray          # (3,)
    half_u: float               # half extents in metres (inf for unbounded)
    half_v: float
    shape: int
    velocity: np.ndarray        # (3,) world displacement t -> t+1
    texel: float                # metres per texel at pyramid level 0
    texture: int                # index into the texture pool
    tint: np.ndarray            # (3, 3) colour matrix applied to the texture's RGB (uint8 scale -> [0, 1])
    offset: np.ndarray          # (2,) texel offset of the layer origin in the texture
    spin: np.ndarray = dataclasses.field(default_factory=lambda: np.eye(3))  # (3,3) rotation t -> t+1 about origin
    is_object: bool = False     # one of the scene's objects (not the ground, the wall or a facade)


def _layer_pose(layer: _Layer, time: int):
    """(origin, normal, u_axis, v_axis) of the layer at `time` (0 or 1): moved by its velocity and turned by
    its spin about its origin, so a material point keeps its in-plane (u, v)."""
    if time == 0:
        return layer.origin, layer.normal, layer.u_axis, layer.v_axis
    r = layer.spin
    return layer.origin + layer.velocity, r @ layer.normal, r @ layer.u_axis, r @ layer.v_axis


@dataclasses.dataclass
class _Camera:
    f: float
    cx: float
    cy: float
    rot: np.ndarray             # (3,3) world -> camera
    centre: np.ndarray          # (3,) world


def default_focal(width: int) -> float:
    """KITTI's focal length scaled to an image of `width` pixels (721.5377 px at 1242)."""
    return KITTI_FOCAL_1242 * width / 1242.0


def sample_seed(base_seed: int, index: int) -> int:
    """The per-sample seed used by the data set with `base_seed` for sample `index` (stable across versions)."""
    return int(np.random.SeedSequence([int(base_seed), int(index)]).generate_state(1, dtype=np.uint32)[0])


# ----------------------------------------------------------------------------------------------------------
# Textures
# ----------------------------------------------------------------------------------------------------------

def _noise_field(rng: np.random.Generator, h: int, w: int, channels: int, beta: float) -> np.ndarray:
    """Sum of upsampled white-noise grids, amplitude ∝ (1/frequency)^beta: 1/f-like multi-scale noise."""
    out = np.zeros((h, w, channels), np.float32)
    g = 2
    total = 0.0
    while g <= max(h, w):
        amp = (1.0 / g) ** beta
        gh, gw = max(2, int(round(g * h / max(h, w)))), max(2, int(round(g * w / max(h, w))))
        grid = rng.standard_normal((gh, gw, channels)).astype(np.float32)
        up = cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC if g < max(h, w) else cv2.INTER_NEAREST)
        out += amp * up.reshape(h, w, channels)
        total += amp * amp
        g *= 2
    return out / np.float32(math.sqrt(total))


def _random_colour(rng: np.random.Generator) -> np.ndarray:
    hsv = np.array([[[rng.uniform(0, 180), rng.uniform(0.1, 0.8) * 255, rng.uniform(0.25, 0.95) * 255]]],
                   np.uint8)
    return cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)[0, 0].astype(np.float32) / 255.0


def make_texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A random natural-looking RGB texture, float32 (height, width, 3) in [0, 1].

    1/f-like noise in luminance (strong) and colour (weak) between two base colours, plus 20-60 sharp-edged
    shapes and lines (edges, corners, occluding contours), then a Gaussian blur of 0.7 texel so that the texture
    is band-limited (sampling it bilinearly at sub-texel offsets is accurate).
    """
    c0, c1 = _random_colour(rng), _random_colour(rng)
    mix = 0.5 + 0.5 * np.tanh(2.0 * _noise_field(rng, height, width, 1, 0.9))
    tex = c0 * (1 - mix) + c1 * mix
    lum = _noise_field(rng, height, width, 1, rng.uniform(0.3, 0.8))
    tex = tex * (1.0 + rng.uniform(0.3, 0.6) * lum)
    tex += 0.05 * _noise_field(rng, height, width, 3, 0.5)
    canvas = np.ascontiguousarray(tex)
    for _ in range(int(rng.integers(20, 60))):
        colour = tuple(float(c) for c in _random_colour(rng))
        kind = rng.integers(0, 4)
        p = (int(rng.integers(0, width)), int(rng.integers(0, height)))
        size = int(rng.integers(3, max(4, min(height, width) // 5)))
        if kind == 0:
            q = (p[0] + int(rng.integers(-size, size + 1)), p[1] + int(rng.integers(-size, size + 1)))
            cv2.rectangle(canvas, p, q, colour, -1, cv2.LINE_AA)
        elif kind == 1:
            cv2.circle(canvas, p, max(2, size // 2), colour, -1, cv2.LINE_AA)
        elif kind == 2:
            q = (p[0] + int(rng.integers(-3 * size, 3 * size + 1)), p[1] + int(rng.integers(-3 * size, 3 * size + 1)))
            cv2.line(canvas, p, q, colour, int(rng.integers(1, 4)), cv2.LINE_AA)
        else:
            n = int(rng.integers(3, 7))
            pts = np.array(p, np.int32) + rng.integers(-size, size + 1, (n, 2)).astype(np.int32)
            cv2.fillPoly(canvas, [pts], colour, cv2.LINE_AA)
    canvas = cv2.GaussianBlur(canvas, (0, 0), 0.7)
    return np.clip(canvas, 0.0, 1.0)


def _pyramid(tex: np.ndarray, levels: int) -> tuple:
    pyr = [tex]
    for _ in range(levels - 1):
        if min(pyr[-1].shape[:2]) < 8:
            break
        pyr.append(cv2.pyrDown(pyr[-1]))
    return tuple(pyr)


# A fixed pool of base textures (each a pure function of its index), built lazily once per process; every
# layer of every sample picks one and gives it its own colour matrix, offset and scale. This keeps per-sample
# cost low while the variety stays large (48 textures x continuous colour/offset/scale draws).
TEXTURE_POOL_SIZE = 48
TEXTURE_SIZE = 256
_MIP_LEVELS = 6


@functools.lru_cache(maxsize=None)
def pool_texture(index: int) -> tuple:
    """Mip pyramid (tuple of uint8 (h, w, 3), finest first) of base texture `index` of the pool."""
    rng = np.random.default_rng([0x5EED7E, int(index)])
    pyr = _pyramid(make_texture(rng, TEXTURE_SIZE, TEXTURE_SIZE), _MIP_LEVELS)
    return tuple(np.clip(np.rint(p * 255.0), 0, 255).astype(np.uint8) for p in pyr)


def make_flat_texture(rng: np.random.Generator, height: int, width: int) -> np.ndarray:
    """A nearly uniform RGB texture (sky, painted wall): one colour, a gentle linear gradient and faint noise
    (1 % of the range), float32 (height, width, 3) in [0, 1]. The photometric loss cannot match such a region;
    only smoothness and the surroundings can."""
    base = _random_colour(rng)
    gy, gx = np.meshgrid(np.linspace(-0.5, 0.5, height, dtype=np.float32),
                         np.linspace(-0.5, 0.5, width, dtype=np.float32), indexing="ij")
    slope = rng.uniform(-0.15, 0.15, 2).astype(np.float32)
    tex = base + (slope[0] * gy + slope[1] * gx)[..., None]
    tex += 0.01 * _noise_field(rng, height, width, 1, 0.5)
    return np.clip(tex, 0.0, 1.0).astype(np.float32)


FLAT_POOL_SIZE = 8


@functools.lru_cache(maxsize=None)
def texture_pyramid(key) -> tuple:
    """Mip pyramid (tuple of uint8 (h, w, 3), finest first) of a layer's texture: `key` is an int (the pool of
    procedural textures, `pool_texture`), ("photo", set, i) (crop i of `photos.photo_textures(set)`) or
    ("flat", i) (nearly uniform texture i)."""
    if isinstance(key, (int, np.integer)):
        return pool_texture(int(key))
    if key[0] == "photo":
        from bridge_jax.data import photos  # scikit-image is loaded only when a scene asks for photos
        return _pyramid(photos.photo_textures(key[1])[key[2]], _MIP_LEVELS)
    rng = np.random.default_rng([0xF1A7, int(key[1])])
    flat = make_flat_texture(rng, TEXTURE_SIZE, TEXTURE_SIZE)
    return tuple(np.clip(np.rint(p * 255.0), 0, 255).astype(np.uint8) for p in _pyramid(flat, _MIP_LEVELS))


# ----------------------------------------------------------------------------------------------------------
# Scene
# ----------------------------------------------------------------------------------------------------------

def _rot_y(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]], np.float64)


def _make_scene(rng: np.random.Generator, height: int, width: int, focal: float, cfg: SceneConfig):
    """Random layers and camera motion. Returns (layers, ego, (cx, cy)); ego = (R_cw, centre) at t+1."""
    f = focal
    cx, cy = (width - 1) / 2.0, 0.46 * height
    lo, hi = cfg.cam_height_range
    cam_h = lo + (hi - lo) * rng.uniform()  # = rng.uniform(lo, hi), the same draw
    layers: list[_Layer] = []
    ex, ey, ez = np.eye(3)
    zero = np.zeros(3)

    def add(normal, origin, u, v, hu, hv, shape, vel, texel):
        tint = np.diag(rng.uniform(0.6, 1.4, 3)) + rng.uniform(-0.25, 0.25, (3, 3))
        tint = tint[:, rng.permutation(3)] * rng.uniform(0.7, 1.3)
        layers.append(_Layer(np.asarray(normal, float), np.asarray(origin, float), np.asarray(u, float),
                             np.asarray(v, float), hu, hv, shape, np.asarray(vel, float), texel,
                             int(rng.integers(TEXTURE_POOL_SIZE)), (tint / 255.0).astype(np.float32),
                             rng.uniform(0, TEXTURE_SIZE, 2).astype(np.float32)))

    # Ground plane Y = cam_h.
    add(ey, [0, cam_h, 0], ex, ez, math.inf, math.inf, _PLANE, zero, rng.uniform(0.015, 0.04))
    # Background wall.
    zb = rng.uniform(40.0, 90.0)
    add(ez, [0, 0, zb], ex, ey, math.inf, math.inf, _PLANE, zero, zb / f * rng.uniform(0.8, 1.5))
    # Facades (planes X = ±s along the driving direction).
    corridor = [-12.0, 12.0]
    for i, side in enumerate((-1.0, 1.0)):
        if rng.uniform() < cfg.facade_prob:
            s = rng.uniform(4.0, 12.0)
            corridor[i] = side * s
            z0 = rng.uniform(-5.0, 20.0)
            z1 = min(zb - 1.0, z0 + rng.uniform(10.0, 60.0))
            hf = rng.uniform(3.0, 12.0)
            add(ex, [side * s, cam_h - hf / 2, (z0 + z1) / 2], ez, ey, (z1 - z0) / 2, hf / 2, _RECT, zero,
                rng.uniform(0.015, 0.05))
    # Objects: fronto-parallel rectangles / ellipses inside the corridor, some moving.
    n_obj = int(rng.integers(cfg.min_objects, cfg.max_objects + 1))
    ego_fwd = rng.uniform(0.0, cfg.max_ego_forward)
    for _ in range(n_obj):
        z = math.exp(rng.uniform(math.log(cfg.min_object_depth), math.log(cfg.max_object_depth)))
        w_obj, h_obj = rng.uniform(0.8, 4.5), rng.uniform(0.8, 3.0)
        x = rng.uniform(corridor[0] + w_obj / 2, corridor[1] - w_obj / 2)
        x = float(np.clip(x, -1.3 * z * cx / f, 1.3 * z * cx / f))   # at most a little outside the view
        if rng.uniform() < 0.7:
            y = cam_h - h_obj / 2          # standing on the ground
        else:
            y = rng.uniform(-2.5, cam_h - h_obj / 2)
        vel = zero
        if rng.uniform() < cfg.moving_prob:
            vx, vz = rng.uniform(-1, 1, 2) * cfg.max_object_speed
            vz = max(vz, 1.5 + ego_fwd - z)  # stays at least 1.5 m in front of the camera at t+1
            vel = np.array([vx, 0.0, vz])
        shape = _RECT if rng.uniform() < 0.6 else _ELLIPSE
        add(ez, [x, y, z], ex, ey, w_obj / 2, h_obj / 2, shape, vel, max(0.01, z / f * rng.uniform(0.7, 1.5)))
        layers[-1].is_object = True
    yaw = rng.uniform(-cfg.max_ego_yaw, cfg.max_ego_yaw)
    lateral = rng.uniform(-cfg.max_ego_lateral, cfg.max_ego_lateral)
    ego = (_rot_y(yaw), np.array([lateral, 0.0, ego_fwd]))
    return layers, ego, (cx, cy)


def _rot_x(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[1, 0, 0], [0, c, -s], [0, s, c]], np.float64)


def _axis_angle(axis: np.ndarray, angle: float) -> np.ndarray:
    """Rotation matrix of `angle` radians about the unit vector `axis` (Rodrigues)."""
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]], np.float64)
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * (k @ k)


def _rot_z(angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    return np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]], np.float64)


def _vertical_ego(ego, extra: np.random.Generator, cfg: SceneConfig):
    """`ego` (R_cw, centre at t+1) with the scene's rig pitch, roll and vertical translation added (draws
    from `extra`; unchanged when all three are 0). The rotation is about the rig's own axes at t+1 and the
    baseline turns with it (`_cameras`), so the right camera stays where the left one's x axis points."""
    if not (cfg.max_ego_pitch or cfg.max_ego_roll or cfg.max_ego_vertical):
        return ego
    r_cw, centre = ego
    pitch = extra.uniform(-cfg.max_ego_pitch, cfg.max_ego_pitch)
    roll = extra.uniform(-cfg.max_ego_roll, cfg.max_ego_roll)
    up = extra.uniform(-cfg.max_ego_vertical, cfg.max_ego_vertical)
    return r_cw @ _rot_x(pitch) @ _rot_z(roll), centre + r_cw @ np.array([0.0, up, 0.0])


def _vary_scene(layers: list, extra: np.random.Generator, cfg: SceneConfig) -> None:
    """Applies the scene's photo/uniform textures, slants, spins and vertical object motion to `layers` in
    place (draws from `extra`)."""
    n_photos = None
    for layer in layers:
        u = extra.uniform()
        if u < cfg.photo_texture_prob:
            if n_photos is None:
                from bridge_jax.data import photos
                n_photos = len(photos.photo_textures(cfg.photo_set))
            layer.texture = ("photo", cfg.photo_set, int(extra.integers(n_photos)))
            # photos keep their own colours: only a mild per-channel gain
            layer.tint = (np.diag(extra.uniform(0.8, 1.2, 3)) / 255.0).astype(np.float32)
        elif u < cfg.photo_texture_prob + cfg.textureless_prob:
            layer.texture = ("flat", int(extra.integers(FLAT_POOL_SIZE)))
            layer.tint = (np.eye(3) * extra.uniform(0.8, 1.2) / 255.0).astype(np.float32)
        if not layer.is_object:
            continue
        if extra.uniform() < cfg.slant_prob:
            turn = _rot_y(extra.uniform(-1.05, 1.05)) @ _rot_x(extra.uniform(-0.52, 0.52))
            layer.normal, layer.u_axis, layer.v_axis = turn @ layer.normal, turn @ layer.u_axis, turn @ layer.v_axis
        if np.any(layer.velocity) and extra.uniform() < cfg.spin_prob:
            axis = extra.standard_normal(3)
            layer.spin = _axis_angle(axis / np.linalg.norm(axis), extra.uniform(-cfg.max_spin, cfg.max_spin))
    # In a pass of its own, so the textures, slants and spins drawn above are those of the same scene without it.
    for layer in layers:
        if layer.is_object and np.any(layer.velocity) and cfg.max_object_vertical_speed > 0:
            v = extra.uniform(-cfg.max_object_vertical_speed, cfg.max_object_vertical_speed)
            layer.velocity = layer.velocity + np.array([0.0, v, 0.0])


def camera_response(img: np.ndarray, rng: np.random.Generator, strength: float) -> np.ndarray:
    """One camera's photometric rendering of a float RGB image `(H, W, 3)` in [0, 1] (any range in, clipped
    out): per-channel gain (±12 %·s) and offset (±4 %·s), a gamma (±15 %·s), with probability 1/2 a slight
    Gaussian blur (sigma up to 0.7·s px), and sensor noise (std up to 1.5 %·s). `s` = `strength`; 0 returns
    the image unchanged. Applied to each of the four views with its own draw, so left/right and t/t+1 differ
    as the cameras of a real rig do; the ground truth never sees it."""
    if strength <= 0:
        return img
    gain = 1.0 + strength * rng.uniform(-0.12, 0.12, 3)
    offset = strength * rng.uniform(-0.04, 0.04, 3)
    gamma = 1.0 + strength * rng.uniform(-0.15, 0.15)
    blur = rng.uniform() < 0.5
    sigma = strength * rng.uniform(0.2, 0.7)
    noise = strength * rng.uniform(0.0, 0.015)
    out = np.clip(img * gain.astype(np.float32) + offset.astype(np.float32), 0.0, 1.0) ** np.float32(gamma)
    if blur:
        out = cv2.GaussianBlur(out, (0, 0), sigma)
    out = out + rng.normal(0.0, noise, out.shape).astype(np.float32)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def _cameras(f, cx, cy, baseline, ego):
    """The four cameras, in cycle order (left_t, right_t, left_t1, right_t1)."""
    r_cw1, c1 = ego
    cams = []
    for r_cw, c in ((np.eye(3), np.zeros(3)), (r_cw1, c1)):
        rot = r_cw.T
        cams.append(_Camera(f, cx, cy, rot, c))
        cams.append(_Camera(f, cx, cy, rot, c + r_cw @ np.array([baseline, 0.0, 0.0])))
    return cams


# ----------------------------------------------------------------------------------------------------------
# Ray casting
# ----------------------------------------------------------------------------------------------------------
# For normalised image coords (a, b) = ((x - cx)/f, (y - cy)/f) the camera ray is r_c = (a, b, 1) and the
# world ray R^T r_c. A plane through O with normal n is hit at depth (camera z) t = n·(O - C) / (n·R^T r_c), and
# the in-plane coords of the hit are u = u_axis·(C - O) + t (R u_axis)·r_c, likewise v.

def _layer_terms(layer: _Layer, cam: _Camera, time: int):
    origin, normal, u_axis, v_axis = _layer_pose(layer, time)
    rel = cam.centre - origin
    return (float(normal @ (origin - cam.centre)), (cam.rot @ normal).astype(np.float32),
            (cam.rot @ u_axis).astype(np.float32), (cam.rot @ v_axis).astype(np.float32),
            np.float32(u_axis @ rel), np.float32(v_axis @ rel))


def _dot(r, a, b):
    return r[0] * a + r[1] * b + r[2]


def _hit(layer: _Layer, terms, a, b):
    """Depth of the layer's hit (inf where missed) for normalised coords a, b (broadcastable float32)."""
    num, rn, ru, rv, u0, v0 = terms
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        t = np.float32(num) / _dot(rn, a, b)
        ok = t > np.float32(0.05)
        if layer.shape == _RECT:
            ok &= np.abs(u0 + t * _dot(ru, a, b)) <= layer.half_u
            ok &= np.abs(v0 + t * _dot(rv, a, b)) <= layer.half_v
        elif layer.shape == _ELLIPSE:
            uu = (u0 + t * _dot(ru, a, b)) * np.float32(1.0 / layer.half_u)
            vv = (v0 + t * _dot(rv, a, b)) * np.float32(1.0 / layer.half_v)
            ok &= uu * uu + vv * vv <= 1.0
    return np.where(ok, t, np.float32(np.inf))


def _bbox(layer: _Layer, cam: _Camera, time: int, height: int, width: int):
    """Pixel box (y0, y1, x0, x1) covering a bounded layer, or None (unbounded / crosses the camera plane)."""
    if layer.shape == _PLANE:
        return None
    origin, _, u_axis, v_axis = _layer_pose(layer, time)
    corners = []
    for su in (-1, 1):
        for sv in (-1, 1):
            p = cam.rot @ (origin + su * layer.half_u * u_axis + sv * layer.half_v * v_axis - cam.centre)
            if p[2] <= 0.05:
                return None
            corners.append((cam.f * p[0] / p[2] + cam.cx, cam.f * p[1] / p[2] + cam.cy))
    c = np.array(corners)
    x0, x1 = int(math.floor(c[:, 0].min())) - 1, int(math.ceil(c[:, 0].max())) + 2
    y0, y1 = int(math.floor(c[:, 1].min())) - 1, int(math.ceil(c[:, 1].max())) + 2
    return max(0, y0), min(height, y1), max(0, x0), min(width, x1)


def _cast_grid(layers, cam: _Camera, time: int, height: int, width: int):
    """Visible layer id (-1: none) and depth Z (inf: none) at every pixel centre: two (H, W) arrays."""
    a = ((np.arange(width, dtype=np.float32) - np.float32(cam.cx)) / np.float32(cam.f))[None, :]
    b = ((np.arange(height, dtype=np.float32) - np.float32(cam.cy)) / np.float32(cam.f))[:, None]
    zbuf = np.full((height, width), np.inf, np.float32)
    lid = np.full((height, width), -1, np.int32)
    for k, layer in enumerate(layers):
        box = _bbox(layer, cam, time, height, width)
        if box is None:
            sl, aa, bb = (slice(None), slice(None)), a, b
        else:
            y0, y1, x0, x1 = box
            if y0 >= y1 or x0 >= x1:
                continue
            sl, aa, bb = (slice(y0, y1), slice(x0, x1)), a[:, x0:x1], b[y0:y1]
        t = _hit(layer, _layer_terms(layer, cam, time), aa, bb)
        zsub, lsub = zbuf[sl], lid[sl]
        closer = t < zsub
        np.copyto(zsub, t, where=closer)
        lsub[closer] = k
    return lid, zbuf


def _cast_points(layers, cam: _Camera, time: int, x: np.ndarray, y: np.ndarray, height: int,
                 width: int) -> np.ndarray:
    """Visible layer id at sub-pixel positions x, y (same shape, inside [0, W-1] x [0, H-1])."""
    shape = x.shape
    x = x.astype(np.float32).ravel()
    y = y.astype(np.float32).ravel()
    a = (x - np.float32(cam.cx)) / np.float32(cam.f)
    b = (y - np.float32(cam.cy)) / np.float32(cam.f)
    zbuf = np.full(a.shape, np.inf, np.float32)
    lid = np.full(a.shape, -1, np.int32)
    for k, layer in enumerate(layers):
        terms = _layer_terms(layer, cam, time)
        box = _bbox(layer, cam, time, height, width)
        if box is None:
            t = _hit(layer, terms, a, b)
            closer = t < zbuf
            np.copyto(zbuf, t, where=closer)
            lid[closer] = k
        else:
            y0, y1, x0, x1 = box
            sel = np.flatnonzero((x >= x0 - 1) & (x <= x1) & (y >= y0 - 1) & (y <= y1))
            if sel.size == 0:
                continue
            t = _hit(layer, terms, a[sel], b[sel])
            closer = t < zbuf[sel]
            zbuf[sel[closer]] = t[closer]
            lid[sel[closer]] = k
    return lid.reshape(shape)


def _sample_points(tex: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear samples (N, 3) float32 of `tex` at texel coords x, y (N,), mirrored outside the texture."""
    n = x.shape[0]
    cols = 1024
    rows = -(-n // cols)
    mx = np.zeros(rows * cols, np.float32)
    my = np.zeros(rows * cols, np.float32)
    mx[:n], my[:n] = x, y
    out = cv2.remap(tex, mx.reshape(rows, cols), my.reshape(rows, cols), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_REFLECT_101)
    return out.reshape(rows * cols, -1)[:n].astype(np.float32)


def _shade(layers, cam: _Camera, time: int, lid: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """RGB float32 (H, W, 3): every pixel coloured from its layer's texture at the hit point's (u, v), with a
    trilinear mip lookup whose level is log2 of the pixel's footprint on the plane in texels.

    Vectorised over the whole frame: per-layer coefficients are gathered by layer id, then the pixels are sorted
    by (layer, mip level) so that each texture lookup is one cv2.remap over a contiguous slice.
    """
    height, width = lid.shape
    n_layers = len(layers)
    # Per-layer coefficients (row n_layers = "no surface", all zeros).
    coef = np.zeros((n_layers + 1, 14), np.float32)
    for k, layer in enumerate(layers):
        _, rn, ru, rv, u0, v0 = _layer_terms(layer, cam, time)
        inv_t = 1.0 / layer.texel
        coef[k] = (*rn, *ru, *rv, u0, v0, inv_t, layer.offset[0], layer.offset[1])
    lid_f = lid.ravel()
    key_layer = np.where(lid_f >= 0, lid_f, n_layers)
    c = coef[key_layer]
    a = np.tile((np.arange(width, dtype=np.float32) - np.float32(cam.cx)) / np.float32(cam.f), height)
    b = np.repeat((np.arange(height, dtype=np.float32) - np.float32(cam.cy)) / np.float32(cam.f), width)
    z = np.where(lid_f >= 0, depth.ravel(), np.float32(0.0))
    inv_t = c[:, 11]
    tu = (c[:, 9] + z * (c[:, 3] * a + c[:, 4] * b + c[:, 5])) * inv_t + c[:, 12]
    tv = (c[:, 10] + z * (c[:, 6] * a + c[:, 7] * b + c[:, 8])) * inv_t + c[:, 13]
    nrm = np.sqrt(a * a + b * b + np.float32(1.0))
    cos = np.abs(c[:, 0] * a + c[:, 1] * b + c[:, 2]) / nrm
    foot = z * nrm * inv_t * np.float32(1.0 / cam.f) / np.maximum(cos, np.float32(0.05))
    level = np.clip(np.log2(np.maximum(foot, np.float32(1e-6))), np.float32(0.0), np.float32(_MIP_LEVELS - 1))
    lo = np.minimum(level.astype(np.int16), np.int16(_MIP_LEVELS - 2))
    frac = level - lo
    # Sort key: layer, mip level, and whether a second level is needed (frac > 0; magnified texels are not).
    key = key_layer.astype(np.int16) * np.int16(16) + lo * np.int16(2) + (frac > 0)
    order = np.argsort(key, kind="stable")
    key_s = key[order]
    tu, tv, frac = tu[order], tv[order], frac[order][:, None]
    out = np.zeros((height * width, 3), np.float32)
    starts = np.flatnonzero(np.concatenate([[True], key_s[1:] != key_s[:-1]]))
    ends = np.append(starts[1:], key_s.size)
    for s_, e_ in zip(starts, ends):
        k, rest = divmod(int(key_s[s_]), 16)
        lv, blend = divmod(rest, 2)
        if k >= n_layers:
            continue
        layer = layers[k]
        pyr = texture_pyramid(layer.texture)
        sc0, sc1 = np.float32(0.5 ** lv), np.float32(0.5 ** (lv + 1))
        col = _sample_points(pyr[lv], (tu[s_:e_] + 0.5) * sc0 - 0.5, (tv[s_:e_] + 0.5) * sc0 - 0.5)
        if blend:
            hi_smp = _sample_points(pyr[lv + 1], (tu[s_:e_] + 0.5) * sc1 - 0.5, (tv[s_:e_] + 0.5) * sc1 - 0.5)
            col += frac[s_:e_] * (hi_smp - col)
        out[s_:e_] = cv2.transform(col[:, None, :], layer.tint)[:, 0, :]
    img = np.empty_like(out)
    img[order] = out
    return img.reshape(height, width, 3)


# ----------------------------------------------------------------------------------------------------------
# Public API
# ----------------------------------------------------------------------------------------------------------

def render_sample(seed: int, height: int = 256, width: int = 512, *, focal: float | None = None,
                  baseline: float = DEFAULT_BASELINE, scene: SceneConfig | None = None, with_gt: bool = True,
                  **scene_kw: Any) -> dict:
    """Renders one stereo-video cycle with exact ground truth, deterministically from `seed`.

    Args:
        seed: any int ≥ 0; the whole sample (scene, textures, motion) is a function of it and of the sizes.
        height, width: image size in pixels.
        focal: focal length in pixels (default: KITTI's 721.5377 scaled to `width`).
        baseline: stereo baseline in metres.
        scene / scene_kw: a `SceneConfig`, the name of one of `SCENE_PRESETS`, or the fields as keywords.
        with_gt: False skips the ground truth (about half the cost; the images are identical) and returns only
            "cycle", "focal", "baseline", "seed".

    Returns a dict:
        "cycle": uint8 (4, H, W, 3) RGB, frames (left_t, right_t, left_t1, right_t1);
        "disp_t": float32 (H, W) disparity of left_t in pixels (≥ 0; left x ↔ right x − d);
        "valid_disp_t", "noc_disp_t": bool (H, W) — surface present / also visible in right_t;
        "disp_t1", "valid_disp_t1", "noc_disp_t1": the same for left_t1 on the t+1 pixel grid;
        "disp_t1_ref_t", "valid_disp_t1_ref_t", "noc_disp_t1_ref_t": disparity at t+1 of the point seen at
            each pixel of left_t (KITTI 2015 `disp_occ_1` / `disp_noc_1` semantics; noc = also visible in left_t1
            and right_t1 and inside both);
        "flow": float32 (H, W, 2) pixels (dx, dy): left_t pixel (x, y) is at (x + dx, y + dy) in left_t1;
        "valid_flow", "noc_flow": bool (H, W) — point in front of the camera at t+1 / also visible and in view;
        "depth_t": float32 (H, W) metres (inf where no surface);
        "focal": float (pixels), "baseline": float (metres), "seed": int.
    """
    if height < 8 or width < 8:
        raise ValueError(f"render_sample: height and width must be >= 8, got {height}x{width}")
    if isinstance(scene, str):
        scene = scene_config(scene)
    cfg = scene if scene is not None else SceneConfig(**scene_kw)
    # The draws of the scene variations use their own generator, so the default scenes stay as they were.
    extra = np.random.default_rng([int(seed), 0xE7A])
    f = (float(focal) if focal is not None else default_focal(width)) * extra.uniform(*cfg.focal_range)
    baseline = float(baseline) * extra.uniform(*cfg.baseline_range)
    rng = np.random.default_rng(int(seed))
    layers, ego, (cx, cy) = _make_scene(rng, height, width, f, cfg)
    _vary_scene(layers, extra, cfg)
    ego = _vertical_ego(ego, extra, cfg)
    cams = _cameras(f, cx, cy, baseline, ego)
    times = (0, 0, 1, 1)
    casts = [_cast_grid(layers, cam, tm, height, width) for cam, tm in zip(cams, times)]
    frames = []
    for cam, tm, (lid, z) in zip(cams, times, casts):
        img = camera_response(_shade(layers, cam, tm, lid, z), extra, cfg.photometric)
        if cfg.noise_std > 0:
            img = img + rng.normal(0, cfg.noise_std, img.shape).astype(np.float32)
        frames.append(np.clip(np.rint(img * 255.0), 0, 255).astype(np.uint8))
    cycle = np.stack(frames)
    if not with_gt:
        return {"cycle": cycle, "focal": f, "baseline": float(baseline), "seed": int(seed)}

    fb = np.float32(f * baseline)
    xs = np.broadcast_to(np.arange(width, dtype=np.float32)[None, :], (height, width))
    ys = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], (height, width))

    def stereo_gt(lid, z, cam_right, time):
        valid = lid >= 0
        disp = np.where(valid, fb / z, 0.0).astype(np.float32)
        xr = xs - disp
        lid_r = _cast_points(layers, cam_right, time, np.maximum(xr, 0), ys, height, width)
        noc = valid & (xr >= 0) & (lid_r == lid)
        return disp, valid, noc

    lid0, z0 = casts[0][0], casts[0][1]
    disp_t, valid_t, noc_t = stereo_gt(lid0, z0, cams[1], 0)
    lid1, z1 = casts[2][0], casts[2][1]
    disp_t1, valid_t1, noc_t1 = stereo_gt(lid1, z1, cams[3], 1)

    # Flow: 3-D point of each left_t pixel, moved with its layer, projected into left_t1.
    valid0 = lid0 >= 0
    zf = np.where(valid0, z0, 0.0).astype(np.float32)
    pts = np.stack([(xs - np.float32(cx)) / np.float32(f) * zf, (ys - np.float32(cy)) / np.float32(f) * zf, zf], -1)
    # Each layer moves rigidly t -> t+1: p1 = spin (p0 - origin) + origin + velocity.
    spin = np.array([lay.spin for lay in layers] + [np.eye(3)], np.float32)
    shift = np.array([lay.velocity + (lay.origin - lay.spin @ lay.origin) for lay in layers] + [np.zeros(3)],
                     np.float32)
    k = np.where(valid0, lid0, len(layers))
    pts = np.einsum("hwij,hwj->hwi", spin[k], pts) + shift[k]
    cam1 = cams[2]
    pc = (pts - cam1.centre.astype(np.float32)) @ cam1.rot.T.astype(np.float32)
    in_front = pc[..., 2] > 0.05
    zc = np.where(in_front, pc[..., 2], 1.0)
    x1 = np.float32(f) * pc[..., 0] / zc + np.float32(cx)
    y1 = np.float32(f) * pc[..., 1] / zc + np.float32(cy)
    valid_flow = valid0 & in_front
    flow = np.where(valid_flow[..., None], np.stack([x1 - xs, y1 - ys], -1), 0.0).astype(np.float32)
    in_view = (x1 >= 0) & (x1 <= width - 1) & (y1 >= 0) & (y1 <= height - 1)
    lid_at = _cast_points(layers, cam1, 1, np.where(in_view, x1, 0), np.where(in_view, y1, 0), height, width)
    noc_flow = valid_flow & in_view & (lid_at == lid0)
    disp_t1_ref_t = np.where(valid_flow, fb / zc, 0.0).astype(np.float32)
    # ... and also visible in right_t1 at (x1 - d, y1) (KITTI's disp_noc_1).
    xr1 = x1 - disp_t1_ref_t
    ok_r1 = noc_flow & (xr1 >= 0)
    lid_r1 = _cast_points(layers, cams[3], 1, np.where(ok_r1, xr1, 0), np.where(ok_r1, y1, 0), height, width)
    noc_disp_t1_ref_t = ok_r1 & (lid_r1 == lid0)

    return {
            "cycle": cycle,
            "disp_t": disp_t, "valid_disp_t": valid_t, "noc_disp_t": noc_t,
            "disp_t1": disp_t1, "valid_disp_t1": valid_t1, "noc_disp_t1": noc_t1,
            "disp_t1_ref_t": disp_t1_ref_t, "valid_disp_t1_ref_t": valid_flow.copy(),
            "noc_disp_t1_ref_t": noc_disp_t1_ref_t,
            "flow": flow, "valid_flow": valid_flow, "noc_flow": noc_flow,
            "depth_t": np.where(valid0, z0, np.inf).astype(np.float32),
            "focal": f, "baseline": float(baseline), "seed": int(seed),
    }


class SyntheticCycles:
    """grain RandomAccessDataSource of synthetic cycles, rendered on the fly (no files).

    Record i = `render_sample(sample_seed(seed, i), height, width, ...)` reduced to
    `{"cycle": uint8 (4, H, W, 3), "id": "synthetic-<seed>-<i>"}` (plus all GT arrays when `with_gt=True`).
    """

    def __init__(self, num: int = 100_000, seed: int = 0, height: int = 256, width: int = 512, *,
                 with_gt: bool = False, **render_kw: Any):
        if num <= 0:
            raise ValueError(f"SyntheticCycles: num must be > 0, got {num}")
        self.num, self.seed, self.height, self.width = int(num), int(seed), int(height), int(width)
        self.with_gt, self.render_kw = with_gt, render_kw

    def __len__(self) -> int:
        return self.num

    def __getitem__(self, index: int) -> dict:
        index = int(index) % self.num
        sample = render_sample(sample_seed(self.seed, index), self.height, self.width, with_gt=self.with_gt,
                               **self.render_kw)
        rid = f"synthetic-{self.seed}-{index:06d}"
        if self.with_gt:
            sample["id"] = rid
            return sample
        return {"cycle": sample["cycle"], "id": rid}

    def __repr__(self) -> str:
        return f"SyntheticCycles(num={self.num}, seed={self.seed}, size={self.height}x{self.width})"


def _calib_text(f: float, cx: float, cy: float, baseline: float, height: int, width: int) -> str:
    def row(name, vals):
        return name + ": " + " ".join(f"{v:.12e}" for v in vals) + "\n"
    p2 = [f, 0, cx, 0, 0, f, cy, 0, 0, 0, 1, 0]
    p3 = [f, 0, cx, -f * baseline, 0, f, cy, 0, 0, 0, 1, 0]
    return (row("S_rect_02", [width, height]) + row("R_rect_02", np.eye(3).ravel()) + row("P_rect_02", p2)
            + row("S_rect_03", [width, height]) + row("R_rect_03", np.eye(3).ravel()) + row("P_rect_03", p3))


def write_kitti_layout(out_dir: str, num: int, seed: int = 0, height: int = 256, width: int = 512, *,
                       overwrite: bool = False, **render_kw: Any) -> str:
    """Writes `num` synthetic samples in the KITTI 2015 training layout under `out_dir`.

    Files (NNNNNN = sample index, 6 digits):
        image_2/NNNNNN_10.png, image_2/NNNNNN_11.png   left_t, left_t1
        image_3/NNNNNN_10.png, image_3/NNNNNN_11.png   right_t, right_t1
        disp_occ_0/NNNNNN_10.png, disp_noc_0/NNNNNN_10.png   disparity of left_t (KITTI 16-bit, ·256, 0 invalid)
        disp_occ_1/NNNNNN_10.png, disp_noc_1/NNNNNN_10.png   disparity at t+1 of left_t's pixels (KITTI semantics)
        flow_occ/NNNNNN_10.png, flow_noc/NNNNNN_10.png  flow left_t → left_t1 (KITTI 16-bit flow PNG)
        calib_cam_to_cam/NNNNNN.txt                     KITTI-style: S_rect_02/03, R_rect_02/03, P_rect_02/03
                                                        (focal = P_rect_02[0,0], baseline = -P_rect_03[0,3]/focal)
        synthetic.json                                  generator settings and per-sample seeds
    The folder appears complete or not at all (written to a temporary sibling, then renamed).
    """
    if num <= 0:
        raise ValueError(f"write_kitti_layout: --num must be > 0, got {num}")
    with files.staged_dir(out_dir, overwrite=overwrite) as tmp:
        sub = ["image_2", "image_3", "disp_occ_0", "disp_noc_0", "disp_occ_1", "disp_noc_1", "flow_occ",
               "flow_noc", "calib_cam_to_cam"]
        for s in sub:
            os.makedirs(os.path.join(tmp, s))
        seeds = []
        focal = None
        for i in range(num):
            s = sample_seed(seed, i)
            seeds.append(s)
            smp = render_sample(s, height, width, **render_kw)
            focal = smp["focal"]
            name = f"{i:06d}"
            cyc = smp["cycle"]
            for frame, folder, suffix in ((0, "image_2", "10"), (1, "image_3", "10"), (2, "image_2", "11"),
                                          (3, "image_3", "11")):
                kitti.write_image(os.path.join(tmp, folder, f"{name}_{suffix}.png"), cyc[frame])
            kitti.write_disp_png(os.path.join(tmp, "disp_occ_0", f"{name}_10.png"), smp["disp_t"], smp["valid_disp_t"])
            kitti.write_disp_png(os.path.join(tmp, "disp_noc_0", f"{name}_10.png"), smp["disp_t"], smp["noc_disp_t"])
            kitti.write_disp_png(os.path.join(tmp, "disp_occ_1", f"{name}_10.png"), smp["disp_t1_ref_t"],
                                 smp["valid_disp_t1_ref_t"])
            kitti.write_disp_png(os.path.join(tmp, "disp_noc_1", f"{name}_10.png"), smp["disp_t1_ref_t"],
                                 smp["noc_disp_t1_ref_t"])
            kitti.write_flow_png(os.path.join(tmp, "flow_occ", f"{name}_10.png"), smp["flow"], smp["valid_flow"])
            kitti.write_flow_png(os.path.join(tmp, "flow_noc", f"{name}_10.png"), smp["flow"], smp["noc_flow"])
            with open(os.path.join(tmp, "calib_cam_to_cam", f"{name}.txt"), "w") as fh:
                fh.write(_calib_text(smp["focal"], (width - 1) / 2.0, 0.46 * height, smp["baseline"], height, width))
        meta = {"generator": "bridge_jax.data.synthetic", "num": num, "seed": seed, "height": height,
                "width": width, "focal": focal, "baseline": render_kw.get("baseline", DEFAULT_BASELINE),
                "sample_seeds": seeds, "render_kw": {k: v for k, v in render_kw.items() if k != "scene"},
                "scene": render_kw["scene"] if isinstance(render_kw.get("scene"), str) else None,
                "layout": "KITTI 2015 training (image_2/3 *_10/_11.png, disp_occ_0, disp_noc_0, disp_occ_1, "
                          "disp_noc_1, flow_occ, flow_noc, calib_cam_to_cam/NNNNNN.txt)"}
        with open(os.path.join(tmp, "synthetic.json"), "w") as fh:
            json.dump(meta, fh, indent=1)
    return os.path.abspath(out_dir)


def build_parser():
    parser = cli.make_parser("bridge_jax.data.synthetic", CLI_DOC)
    parser.add_argument("--out", required=True, help="output folder (must be new or empty unless --overwrite)")
    parser.add_argument("--num", type=int, default=20, help="number of samples")
    parser.add_argument("--seed", type=int, default=0, help="base seed: sample i is rendered from seed + i")
    parser.add_argument("--height", type=int, default=256, help="image height in pixels")
    parser.add_argument("--width", type=int, default=512, help="image width in pixels")
    parser.add_argument("--focal", type=float, default=None, help="focal length in pixels (default 721.5377*width/1242)")
    parser.add_argument("--baseline", type=float, default=DEFAULT_BASELINE, help="stereo baseline in metres")
    parser.add_argument("--scene", default="demo", choices=tuple(SCENE_PRESETS),
                        help="scene settings: demo (procedural textures), real (photo textures, photometric "
                             "differences between the cameras, slanted and rotating objects, varied rigs) or "
                             "heldout (held-out photos and settings, for checking generalisation)")
    parser.add_argument("--overwrite", action="store_true", help="replace a non-empty --out folder")
    cli.add_debug_flag(parser)
    return parser


CLI_DOC = """Write procedural stereo-video samples with exact ground truth in the KITTI 2015 training layout.

    bridge-synthetic --out work/synthetic_val --num 16 --seed 1000003 --height 64 --width 128
    bridge-evaluate --checkpoint demo --dataset synthetic --data-dir work/synthetic_val --out work/ev

Output: image_2/ and image_3/ (NNNNNN_10.png, NNNNNN_11.png: left/right at t and t+1), disp_occ_0/, disp_noc_0/,
disp_occ_1/, disp_noc_1/ (KITTI 16-bit disparity PNGs), flow_occ/, flow_noc/ (KITTI 16-bit flow PNGs),
calib_cam_to_cam/NNNNNN.txt and synthetic.json (generator settings and per-sample seeds). The same seed gives
the same samples.
"""


@cli.entry_point
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.height < 8 or args.width < 8:
            raise ValueError(f"--height/--width must be >= 8, got {args.height}x{args.width}")
        out = write_kitti_layout(args.out, args.num, args.seed, args.height, args.width, overwrite=args.overwrite,
                                 focal=args.focal, baseline=args.baseline, scene=args.scene)
    except (ValueError, OSError) as e:
        return cli.report_error(e, debug=args.debug)
    print(f"wrote {args.num} samples to {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
