"""Your own stereo video → consecutive cycles, and the check of every image before training starts.

Accepted layouts of a data folder ROOT (tried in this order; `LAYOUT_HELP` is the same text for `--help`):

  1. One sequence: ROOT/left/ and ROOT/right/ hold the rectified frames of the left and the right camera
     (PNG or JPEG), sorted by file name in natural order (frame2 before frame10). Left and right frames pair
     by name when both folders use the same names (left/0001.png with right/0001.png; a frame present on one
     side only is dropped), otherwise the i-th left frame pairs with the i-th right frame (then both folders
     must hold the same number of images).
  2. KITTI raw: a drive folder (image_02/data/, image_03/data/) or a KITTI raw root
     (<date>/<date>_drive_<NNNN>_sync/..., see `kitti.RAW_LAYOUT`).
  3. Several sequences: every immediate subfolder of ROOT that holds left/ and right/ as in 1 is one sequence
     (ROOT/drive_a/left/, ROOT/drive_a/right/, ROOT/drive_b/left/, ...).

A cycle is (left_t, right_t, left_t+1, right_t+1) for two *consecutive* stereo frames t, t+1 of one sequence.
A cycle never spans a gap: a sequence is split where a frame was dropped (present on one side only) and, when
the file names end in numbers, where the number jumps by more than the sequence's usual step (the most common
difference between neighbours; 0, 1, 2, 5, 6 gives the pieces 0-2 and 5-6). The cycles lost this way are
logged with their cause.

`check_cycles` reads the size of every image from its file header (PNG IHDR / JPEG SOF, without decoding)
before training starts: left and right frames that differ in size in most stereo frames of a sequence are one
ValueError naming both files; a few odd pairs, a sequence whose frame size changes, and unreadable files
(empty, not an image) exclude the cycles concerned, each with its cause (see `bridge_jax.data.pipeline`'s
skip report).
"""
from __future__ import annotations

import collections
import concurrent.futures
import logging
import os
import re
import statistics
import struct
import time

import cv2

from bridge_jax import files
from bridge_jax.data import kitti

log = logging.getLogger(__name__)

EXPECTED_LAYOUT = ("expected ROOT/left/*.png|jpg and ROOT/right/*.png|jpg (rectified stereo frames, sorted by "
                   "name), subfolders each holding left/ and right/, or a KITTI raw drive/root "
                   "(image_02/data, image_03/data)")
"""One line for error messages: the accepted layouts, short."""

LAYOUT_HELP = """\
Data folder layouts (config.data.source=folder, config.data.data_dir=ROOT; config.data.val_dir the same):
  ROOT/left/*.png|jpg  ROOT/right/*.png|jpg
      one rectified stereo video; frames sorted by name (natural order: frame2 before frame10); left and
      right pair by file name when both sides use the same names, else by position (same count needed)
  ROOT/<sequence>/left/  ROOT/<sequence>/right/
      several videos, one per subfolder (each as above)
  ROOT/image_02/data/  ROOT/image_03/data/, or a KITTI raw root (<date>/<date>_drive_NNNN_sync/...)
      KITTI raw layout
Cycles are two consecutive stereo frames of one video; a video is split where a frame is missing (on one
side, or a jump in the frame numbers). Left and right frames must have the same size; every image's size is
read from its header before training starts."""
"""Multi-line description of the accepted layouts, for `train --help` and the docs."""

UNREADABLE = "unreadable image"
LR_SIZE = "left and right differ in size"
SIZE_CHANGE = "frame size changes within the sequence"
"""The three causes `check_cycles` gives (each cause string starts with one of them)."""


def _natural_key(name: str):
    return [int(t) if t.isdigit() else t.lower() for t in re.split(r"(\d+)", name)]


def _images(folder: str) -> list[str]:
    return sorted((n for n in os.listdir(folder) if n.lower().endswith(kitti.IMAGE_EXTS)), key=_natural_key)


# ----------------------------------------------------------------------------------------------------------
# Sequences: pairing left/right frames and splitting at gaps
# ----------------------------------------------------------------------------------------------------------

_TRAILING_NUMBER = re.compile(r"^(.*?)(\d+)$")


def numbering_breaks(stems: list[str]) -> dict[int, tuple[str, str]]:
    """Where a sorted list of file stems jumps in its frame numbers: {i: (stems[i-1], stems[i])}.

    Only neighbours whose stems end in a number with the same text before it are compared. A jump is a
    difference larger than the usual step: the most common difference when at least half of the differences
    take that value (frame counters: 0, 1, 2, 5, 6 → step 1, jump 2 → 5), else 1.5 × the median difference
    (timestamps, whose differences jitter).
    """
    parsed = [_TRAILING_NUMBER.match(s) for s in stems]
    diffs = []
    for i in range(1, len(stems)):
        a, b = parsed[i - 1], parsed[i]
        if a and b and a.group(1) == b.group(1):
            diffs.append((i, int(b.group(2)) - int(a.group(2))))
    if len(diffs) < 2:  # one difference is its own usual step
        return {}
    values = [d for _, d in diffs]
    step, count = collections.Counter(values).most_common(1)[0]
    limit = max(step, 1) if 2 * count >= len(values) else 1.5 * statistics.median(values)
    return {i: (stems[i - 1], stems[i]) for i, d in diffs if d > limit}


def _split(pairs: list, breaks) -> list[list]:
    """Cuts `pairs` before every index in `breaks`; pieces of one frame (no cycle) are kept (harmless)."""
    runs, cur = [], []
    for i, p in enumerate(pairs):
        if i in breaks and cur:
            runs.append(cur)
            cur = []
        cur.append(p)
    if cur:
        runs.append(cur)
    return runs


def _names(items, limit: int = 3) -> str:
    items = list(items)
    more = f" and {len(items) - limit} more" if len(items) > limit else ""
    return ", ".join(items[:limit]) + more


def _pair_sequence(seq_dir: str) -> list[list[tuple[str, str]]]:
    """Runs of consecutive (left path, right path) frames of one sequence folder; logs the cycles lost at gaps."""
    ldir, rdir = os.path.join(seq_dir, "left"), os.path.join(seq_dir, "right")
    left, right = _images(ldir), _images(rdir)
    lstem = {os.path.splitext(n)[0]: n for n in left}
    rstem = {os.path.splitext(n)[0]: n for n in right}
    common = lstem.keys() & rstem.keys()
    lost: list[str] = []
    if common and (len(common) >= 0.5 * max(len(left), len(right))):
        # Pair by name. Walk the union of both sides' frames in order: a frame present on one side only is a
        # hole in the video, so the sequence is cut there (its neighbours are not consecutive).
        union = sorted(lstem.keys() | rstem.keys(), key=_natural_key)
        jumps = numbering_breaks(union)
        runs, cur = [], []
        for i, stem in enumerate(union):
            if stem not in common or (i in jumps and cur):
                if cur:
                    runs.append(cur)
                cur = []
            if stem in common:
                cur.append((os.path.join(ldir, lstem[stem]), os.path.join(rdir, rstem[stem])))
        # cycles not formed = transitions of the union that touch a dropped frame, or bridge a numbering jump
        one_sided = len(union) - len(common)
        across_one_sided = sum(1 for i in range(1, len(union))
                               if union[i - 1] not in common or union[i] not in common)
        across_jumps = sum(1 for i in jumps if union[i - 1] in common and union[i] in common)
        if cur:
            runs.append(cur)
        if one_sided:
            only_l = [lstem[s] for s in union if s not in rstem]
            only_r = [rstem[s] for s in union if s not in lstem]
            what = "; ".join(w for w in (f"right/ lacks {_names(only_l)}" if only_l else "",
                                         f"left/ lacks {_names(only_r)}" if only_r else "") if w)
            lost.append(f"{across_one_sided} across {one_sided} frame(s) present on one side only ({what})")
        if across_jumps:
            gaps = [f"{a} -> {b}" for _, (a, b) in sorted(jumps.items()) if a in common and b in common]
            lost.append(f"{across_jumps} across jump(s) in the frame numbers ({_names(gaps)})")
    else:
        if len(left) != len(right):
            raise ValueError(f"{seq_dir!r}: left/ has {len(left)} images and right/ has {len(right)} with different "
                             f"names; cannot pair them ({EXPECTED_LAYOUT})")
        # Pair by position; a jump in either side's numbering cuts the sequence.
        lj = numbering_breaks([os.path.splitext(n)[0] for n in left])
        rj = numbering_breaks([os.path.splitext(n)[0] for n in right])
        breaks = lj.keys() | rj.keys()
        runs = _split([(os.path.join(ldir, a), os.path.join(rdir, b)) for a, b in zip(left, right)], breaks)
        if breaks:
            gaps = [f"{a} -> {b}" for _, (a, b) in sorted({**rj, **lj}.items())]
            lost.append(f"{len(breaks)} across jump(s) in the frame numbers ({_names(gaps)})")
    if lost:
        log.warning("%s: cycles not formed (a cycle never spans a gap): %s", seq_dir, "; ".join(lost))
    return runs


def _sequence_cycles(seq_dir: str, name: str) -> list[dict]:
    out = []
    for run in _pair_sequence(seq_dir):
        for k in range(len(run) - 1):
            (l0, r0), (l1, r1) = run[k], run[k + 1]
            out.append({"id": f"{name}/{os.path.splitext(os.path.basename(l0))[0]}", "paths": (l0, r0, l1, r1),
                        "calib": None})
    return out


def not_a_folder(path: str) -> str:
    """Why `path` cannot be read as a data folder, for an error message: "is a file, not a folder" when it
    exists as something else, else "does not exist"."""
    return "is a file, not a folder" if os.path.exists(path) else "does not exist"


def _is_sequence(d: str) -> bool:
    return os.path.isdir(os.path.join(d, "left")) and os.path.isdir(os.path.join(d, "right"))


def folder_cycles(root: str) -> list[dict]:
    """Cycle records {"id": "<sequence>/<left_t stem>", "paths": (left_t, right_t, left_t1, right_t1),
    "calib": None | calibration path} of a stereo-video folder in one of the layouts of the module docstring.

    Only lists files (no image is opened; `check_cycles` does that). Raises ValueError naming `root` and the
    expected layout when no cycle can be formed.
    """
    root = os.path.abspath(os.path.expanduser(root))
    if not os.path.isdir(root):
        raise ValueError(f"stereo video folder {root!r} {not_a_folder(root)}; {EXPECTED_LAYOUT}")
    records: list[dict] = []
    if _is_sequence(root):
        records = _sequence_cycles(root, os.path.basename(root))
    elif kitti.find_raw_drives(root) or os.path.isdir(os.path.join(root, "image_02", "data")):
        if os.path.isdir(os.path.join(root, "image_02", "data")) and not kitti.find_raw_drives(root):
            fr = kitti.raw_drive_frames(root)
            name = os.path.basename(os.path.normpath(root))
            # frames k and k + 1 both present: a missing frame number never pairs its neighbours
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


# ----------------------------------------------------------------------------------------------------------
# Image sizes from file headers
# ----------------------------------------------------------------------------------------------------------

_PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
# Start-of-frame markers (baseline, progressive, lossless, arithmetic...); C4 (DHT), C8 (JPG), CC (DAC) are not.
_JPEG_SOF = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}


def _jpeg_size(fh) -> tuple[int, int] | None:
    """(height, width) from the first SOF segment of a JPEG opened after its SOI marker; None if not found."""
    while True:
        b = fh.read(1)
        if not b:
            return None
        if b != b"\xff":
            continue  # stray bytes between segments: tolerated, as decoders do
        marker = fh.read(1)
        while marker == b"\xff":  # fill bytes
            marker = fh.read(1)
        if not marker:
            return None
        m = marker[0]
        if m == 0x01 or 0xD0 <= m <= 0xD8:  # markers without a length field
            continue
        if m in (0xD9, 0xDA):  # end of image / start of scan before any frame header
            return None
        raw = fh.read(2)
        if len(raw) < 2:
            return None
        (length,) = struct.unpack(">H", raw)
        if m in _JPEG_SOF:
            body = fh.read(5)
            if len(body) < 5:
                return None
            _, h, w = struct.unpack(">BHH", body)
            return (h, w) if h and w else None  # height 0 = defined later (DNL): let the decoder answer
        if length < 2:
            return None
        fh.seek(length - 2, os.SEEK_CUR)


def image_size(path: str) -> tuple[int, int]:
    """(height, width) in pixels of a PNG/JPEG file, read from its header without decoding the image.

    Files whose header is neither PNG nor JPEG (or a JPEG without a usable frame header) are asked of Pillow
    when it is installed, else decoded with OpenCV, as the training reader would. Raises
    kitti.CorruptImageError(path, "unreadable image (...)") for a missing or empty file or one that is not an
    image. A truncated image body is not detected here (the pipeline skips it when decoding fails).
    """
    try:
        with open(path, "rb") as fh:
            head = fh.read(24)
            if not head:
                raise kitti.CorruptImageError(path, f"{UNREADABLE} (empty file)")
            if len(head) < 24 and _PNG_SIGNATURE.startswith(head[:8]):
                raise kitti.CorruptImageError(path, f"{UNREADABLE} (truncated PNG: only {len(head)} bytes)")
            if head[:8] == _PNG_SIGNATURE:
                if len(head) < 24 or head[12:16] != b"IHDR":
                    raise kitti.CorruptImageError(path, f"{UNREADABLE} (PNG without an IHDR header)")
                w, h = struct.unpack(">II", head[16:24])
                if not (h and w):
                    raise kitti.CorruptImageError(path, f"{UNREADABLE} (PNG header says {h}x{w})")
                return int(h), int(w)
            if head[:2] == b"\xff\xd8":
                fh.seek(2)
                size = _jpeg_size(fh)
                if size is not None:
                    return size
    except OSError as e:
        raise kitti.CorruptImageError(path, f"{UNREADABLE} (cannot read: {e.strerror or e})") from None
    try:  # another format behind a .png/.jpg name: Pillow reads most headers without decoding
        from PIL import Image
        with Image.open(path) as im:
            w, h = im.size
        if h and w:
            return int(h), int(w)
    except Exception:  # noqa: BLE001  (no Pillow, or Pillow cannot read it: the decoder decides)
        pass
    try:
        img = files.imread(path, cv2.IMREAD_COLOR)
    except OSError as e:
        raise kitti.CorruptImageError(path, f"{UNREADABLE} (cannot read: {e.strerror or e})") from None
    if img is None or img.ndim < 2 or img.shape[0] == 0:
        raise kitti.CorruptImageError(path, f"{UNREADABLE} (not a PNG or JPEG image)")
    return int(img.shape[0]), int(img.shape[1])


def image_sizes(paths, threads: int = 16) -> dict:
    """{path: (height, width) | kitti.CorruptImageError} for every path (headers read by `threads` threads:
    the work is waiting on the disk)."""
    paths = list(dict.fromkeys(paths))

    def one(p):
        try:
            return image_size(p)
        except kitti.CorruptImageError as e:
            return e

    if len(paths) < 64:
        return {p: one(p) for p in paths}
    with concurrent.futures.ThreadPoolExecutor(max_workers=threads) as pool:
        return dict(zip(paths, pool.map(one, paths, chunksize=64)))


def _hw(size) -> str:
    return f"{size[0]}x{size[1]}"


def _sequence_of(record: dict) -> str:
    return record["id"].rsplit("/", 1)[0] if "/" in record["id"] else ""


def check_cycles(records: list[dict], where: str = "the data folder", threads: int = 16
                 ) -> tuple[list[dict], list[dict]]:
    """Checks every image of `records` from its header, before anything is decoded or written.

    Args:
      records: cycle records (`folder_cycles`, `kitti.raw_cycles`): {"id": "<sequence>/<frame>", "paths": 4}.
      where: the data folder, for messages.
    Returns:
      (kept records, excluded) where excluded = [{"id", "path", "cause"}, ...] names, per excluded cycle, the
      file at fault and why: "unreadable image (...)", "left and right differ in size: <left> is HxW, <right> is
      HxW" (a few odd stereo frames), or "frame size changes within the sequence: <a> is HxW, <b> is HxW" (the
      cycle spans the change). The odd frame is the one whose size differs from its sequence's usual size.
    Raises:
      ValueError "left and right differ in size: <left path> is HxW, <right path> is HxW ..." when more than
      half of the readable stereo frames of a sequence differ (a systematic mistake: e.g. one camera's frames
      were resized), and ValueError when every cycle is excluded.
    """
    t0 = time.perf_counter()
    sizes = image_sizes((p for r in records for p in r["paths"]), threads)
    log.info("%s: read the headers of %d images in %.1f s", where, len(sizes), time.perf_counter() - t0)
    by_seq = collections.defaultdict(list)
    for r in records:
        by_seq[_sequence_of(r)].append(r)
    usual = {}
    for seq, recs in by_seq.items():
        stereo_frames = {(r["paths"][k], r["paths"][k + 1]) for r in recs for k in (0, 2)}
        readable = [(a, b) for a, b in stereo_frames if isinstance(sizes[a], tuple) and isinstance(sizes[b], tuple)]
        odd = sorted((a, b) for a, b in readable if sizes[a] != sizes[b])
        if odd and 2 * len(odd) > len(readable):
            a, b = odd[0]
            raise ValueError(f"{LR_SIZE}: {a} is {_hw(sizes[a])}, {b} is {_hw(sizes[b])} (height x width; "
                             f"{len(odd)} of {len(readable)} stereo frames of sequence {seq or where!r} in {where} "
                             f"differ): rectified left and right frames must have the same size")
        counts = collections.Counter(sizes[p] for r in recs for p in r["paths"] if isinstance(sizes[p], tuple))
        usual[seq] = counts.most_common(1)[0][0] if counts else None

    kept, excluded = [], []
    for r in records:
        cause = _cycle_fault(r["paths"], sizes, usual[_sequence_of(r)])
        if cause is None:
            kept.append(r)
        else:
            excluded.append({"id": r["id"], "path": cause[0], "cause": cause[1]})
    if excluded:
        kinds = collections.Counter(e["cause"].split(" (")[0].split(":")[0] for e in excluded)
        log.warning("%s: %d of %d cycles excluded before training (%s); first: %s: %s", where, len(excluded),
                    len(records), ", ".join(f"{n} {k}" for k, n in kinds.most_common()), excluded[0]["path"],
                    excluded[0]["cause"])
    if not kept:
        e = excluded[0]
        raise ValueError(f"no usable cycles in {where}: all {len(records)} cycles have unreadable or mismatched "
                         f"images (first: {e['path']}: {e['cause']})")
    return kept, excluded


def _cycle_fault(paths, sizes: dict, usual) -> tuple[str, str] | None:
    """(file at fault, cause) of a cycle, None when its four frames are readable and of one size."""
    for p in paths:
        if not isinstance(sizes[p], tuple):
            return p, sizes[p].reason
    s = [sizes[p] for p in paths]
    if len(set(s)) == 1:
        return None

    def odd_one(i, j):  # of two frames of different sizes, the one off the sequence's usual size
        return j if s[i] == usual or s[j] != usual else i

    for i in (0, 2):  # a stereo frame whose left and right differ
        if s[i] != s[i + 1]:
            bad = odd_one(i, i + 1)
            return paths[bad], f"{LR_SIZE}: {paths[i]} is {_hw(s[i])}, {paths[i + 1]} is {_hw(s[i + 1])}"
    bad = odd_one(0, 2)  # both stereo frames consistent, but t and t+1 differ
    return paths[bad], f"{SIZE_CHANGE}: {paths[0]} is {_hw(s[0])}, {paths[2]} is {_hw(s[2])}"


def frames_differ_message(paths, sizes) -> tuple[str, str]:
    """(odd path, message) for the frames of one cycle whose (height, width) `sizes` differ: names the frame
    whose size differs from the others' most common size (for a 2 + 2 split: right_t if it differs from
    left_t, else left_t1), and one frame of the common size."""
    hw = [tuple(int(v) for v in s[:2]) for s in sizes]
    common = collections.Counter(hw).most_common(1)[0][0]
    if list(hw).count(common) == 2:  # 2 + 2: name left_t1 against left_t (or right against left)
        common = hw[0]
    bad = next(i for i, v in enumerate(hw) if v != common)
    ref = next(i for i, v in enumerate(hw) if v == common)
    return paths[bad], (f"the frames of the cycle differ in size: {paths[bad]} is {_hw(hw[bad])} but "
                        f"{paths[ref]} is {_hw(hw[ref])}")
