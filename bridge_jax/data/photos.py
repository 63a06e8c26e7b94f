"""Real photographs for the synthetic generator's textures and for the real-image checks.

scikit-image ships a few photographs with its wheel (no download). They are split once, by name, into the
photos the generator may texture its training scenes with (`TRAIN_PHOTOS`) and the photos kept out of training
(`HELDOUT_PHOTOS`): the real-image flow check and the held-out synthetic set use only those, so a number measured
on them shows generalisation, not memory.

    tex = photo_textures("train")      # tuple of uint8 (S, S, 3) crops, S = TEXTURE_SIZE
    img = load_photo("astronaut")      # uint8 (512, 512, 3)
"""
from __future__ import annotations

import functools

import cv2
import numpy as np

TRAIN_PHOTOS = ("rocket", "hubble_deep_field", "immunohistochemistry", "retina", "brick", "grass", "gravel",
                "moon", "clock", "coins", "page", "text", "colorwheel")
"""Photos whose crops may texture training scenes (colour and grey; natural, man-made and micrograph content)."""
HELDOUT_PHOTOS = ("astronaut", "coffee", "chelsea", "camera")
"""Photos never used in training: the real-image flow check and the held-out synthetic set draw from these."""
PHOTO_SETS = {"train": TRAIN_PHOTOS, "heldout": HELDOUT_PHOTOS}
TEXTURE_SIZE = 384
"""Side of the square crops `photo_textures` cuts (texels)."""


def load_photo(name: str) -> np.ndarray:
    """scikit-image's photo `name` as uint8 RGB `(h, w, 3)` (grey replicated, alpha dropped).

    Raises ValueError naming the photo when scikit-image is missing or does not ship it."""
    try:
        from skimage import data as skdata
    except ImportError:
        raise ValueError(f"photo {name!r}: real-photo textures need scikit-image (pip install scikit-image)") from None
    loader = getattr(skdata, name, None)
    if loader is None:
        raise ValueError(f"photo {name!r}: not one of scikit-image's photos")
    try:
        img = np.asarray(loader())
    except Exception as e:  # a photo that scikit-image would have to download: not shipped with the wheel
        raise ValueError(f"photo {name!r}: scikit-image could not load it ({type(e).__name__})") from None
    if img.dtype == bool:
        img = img.astype(np.uint8) * 255
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    return np.ascontiguousarray(img[..., :3].astype(np.uint8))


@functools.lru_cache(maxsize=None)
def photo_textures(which: str) -> tuple:
    """Square uint8 `(TEXTURE_SIZE, TEXTURE_SIZE, 3)` crops of the photos of set `which` ("train" | "heldout").

    Each photo is scaled so that its shorter side is at least `TEXTURE_SIZE`, then cut into the crops of a
    regular grid (1-4 per photo): different crops of one photo differ in content, and every texel is a photo
    pixel or an average of a few (no upsampling beyond 1.5x).
    """
    if which not in PHOTO_SETS:
        raise ValueError(f"photo set must be one of {tuple(PHOTO_SETS)}, got {which!r}")
    crops = []
    for name in PHOTO_SETS[which]:
        img = load_photo(name)
        h, w = img.shape[:2]
        scale = max(1.0, TEXTURE_SIZE / min(h, w))
        if scale > 1.0:
            img = cv2.resize(img, (round(w * scale), round(h * scale)), interpolation=cv2.INTER_CUBIC)
        h, w = img.shape[:2]
        ny, nx = (1 + (n >= 1.25 * TEXTURE_SIZE) for n in (h, w))  # two (overlapping) crops where room
        for y in np.linspace(0, h - TEXTURE_SIZE, ny).astype(int):
            for x in np.linspace(0, w - TEXTURE_SIZE, nx).astype(int):
                crops.append(np.ascontiguousarray(img[y:y + TEXTURE_SIZE, x:x + TEXTURE_SIZE]))
    return tuple(crops)
