"""Own stereo video → consecutive cycles.

Accepted layouts of `root` (checked in this order):
  1. `root/left/` and `root/right/` holding rectified frames (PNG or JPEG), sorted by file name (natural order:
     frame2 before frame10); the i-th left
     frame pairs with the i-th right frame (if both folders use the same names, frames pair by name and names
     present on one side only are dropped with a warning);
  2. a KITTI raw drive folder (`image_02/data`, `image_03/data`) or a KITTI raw root (see kitti.RAW_LAYOUT);
  3. several sequences: every immediate subfolder of `root` that matches layout 1.
Cycle k = (left_k, right_k, left_k+1, right_k+1) for consecutive frames k, k+1 of one sequence.
"""
from __future__ import annotations

import logging
import os
import re

from bridge_jax.data import kitti

log = logging.getLogger(__name__)

EXPECTED_LAYOUT = ("expected ROOT/left/*.png|jpg and ROOT/right/*.png|jpg (rectified stereo frames, sorted by "
                   "name), subfolders each holding left/ and right/, or a KITTI raw drive/root "
                   "(image_02/data, image_03/data)")


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _images(folder: str) -> list[str]:
    return sorted((n for n in os.listdir(folder) if n.lower().endswith(kitti.IMAGE_EXTS)), key=_natural_key)


def _pair_sequence(seq_dir: str) -> list[tuple[str, str]]:
    ldir, rdir = os.path.join(seq_dir, "left"), os.path.join(seq_dir, "right")
    left, right = _images(ldir), _images(rdir)
    lstem = {os.path.splitext(n)[0]: n for n in left}
    rstem = {os.path.splitext(n)[0]: n for n in right}
    common = lstem.keys() & rstem.keys()
    if common and (len(common) >= 0.5 * max(len(left), len(right))):
        dropped = (len(lstem) - len(common)) + (len(rstem) - len(common))
        if dropped:
            log.warning("%s: %d frames exist on one side only and are dropped", seq_dir, dropped)
        names = sorted(common, key=_natural_key)
        return [(os.path.join(ldir, lstem[s]), os.path.join(rdir, rstem[s])) for s in names]
    if len(left) != len(right):
        raise ValueError(f"{seq_dir!r}: left/ has {len(left)} images and right/ has {len(right)} with different "
                         f"names; cannot pair them ({EXPECTED_LAYOUT})")
    return [(os.path.join(ldir, a), os.path.join(rdir, b)) for a, b in zip(left, right)]


def _sequence_cycles(seq_dir: str, name: str) -> list[dict]:
    pairs = _pair_sequence(seq_dir)
    out = []
    for k in range(len(pairs) - 1):
        (l0, r0), (l1, r1) = pairs[k], pairs[k + 1]
        out.append({"id": f"{name}/{os.path.splitext(os.path.basename(l0))[0]}", "paths": (l0, r0, l1, r1),
                    "calib": None})
    return out


def _is_sequence(d: str) -> bool:
    return os.path.isdir(os.path.join(d, "left")) and os.path.isdir(os.path.join(d, "right"))


def folder_cycles(root: str) -> list[dict]:
    """Cycle records {"id", "paths": (left_t, right_t, left_t1, right_t1), "calib"} of a stereo-video folder.

    Raises ValueError naming `root` and the expected layout when no cycle can be formed.
    """
    root = os.path.abspath(os.path.expanduser(root))
    if not os.path.isdir(root):
        raise ValueError(f"stereo video folder {root!r} does not exist; {EXPECTED_LAYOUT}")
    records: list[dict] = []
    if _is_sequence(root):
        records = _sequence_cycles(root, os.path.basename(root))
    elif kitti.find_raw_drives(root) or os.path.isdir(os.path.join(root, "image_02", "data")):
        if os.path.isdir(os.path.join(root, "image_02", "data")) and not kitti.find_raw_drives(root):
            fr = kitti.raw_drive_frames(root)
            name = os.path.basename(os.path.normpath(root))
            records = [{"id": f"{name}/{k:010d}", "paths": fr[k] + fr[k + 1], "calib": None}
                       for k in sorted(fr) if k + 1 in fr]
        else:
            try:
                records = kitti.raw_cycles(root, "all")
            except ValueError:
                records = []
    else:
        for sub in sorted(os.listdir(root), key=_natural_key):
            d = os.path.join(root, sub)
            if _is_sequence(d):
                records.extend(_sequence_cycles(d, sub))
    if not records:
        raise ValueError(f"no usable stereo cycles (two consecutive stereo frames) in {root!r}; {EXPECTED_LAYOUT}")
    return records
