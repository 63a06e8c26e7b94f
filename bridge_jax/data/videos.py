r"""Stereo video files → frames: the training folder layout from a side-by-side video or a left + right pair.

    bridge-frames left.mp4 right.mp4 --out my_video                     # two files, one per camera
    bridge-frames drive_sbs.mp4 --side-by-side --out my_video           # left | right in each frame
    bridge-frames drive_sbs.mp4 --side-by-side --out my_video --every 2 --max-frames 5000
    bridge-train --config=demo --workdir=work/mine \
        --config.data.source=folder --config.data.data_dir=my_video --config.init_from=demo

Output (written to a temporary folder beside OUT and renamed when complete):

    OUT/left/000000.png, 000001.png, ...    left camera, RGB PNG, in the video's frame order
    OUT/right/000000.png, ...               right camera, the same names
    OUT/video.json                          the sources, frame count, --every, size

The videos must already be rectified (rows of the left and right frame show the same scene line), as for any
stereo matcher. `predict` reads the same videos directly (`stereo_frames`), without extracting them.
"""
from __future__ import annotations

import json
import os
import sys
from collections.abc import Iterator, Sequence
from typing import Optional

import cv2
import numpy as np

from bridge_jax import cli, files


class VideoError(ValueError):
    """A video that cannot be read, or a stereo pair of videos that does not fit together (names the file)."""


def _open(path: str):
    """A cv2.VideoCapture of `path` that opened; VideoError naming the file otherwise."""
    if not os.path.isfile(path):
        raise VideoError(f"video {path} does not exist")
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        cap.release()
        raise VideoError(f"cannot open video {path} (not a video, or a codec OpenCV lacks)")
    return cap


def video_frames(path: str) -> Iterator[np.ndarray]:
    """The frames of a video file as uint8 RGB `(H, W, 3)`, in order; VideoError when none can be read."""
    cap = _open(path)
    try:
        n = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            n += 1
            yield np.ascontiguousarray(frame[..., ::-1])
        if n == 0:
            raise VideoError(f"cannot read any frame from video {path}")
    finally:
        cap.release()


def video_info(path: str) -> tuple[Optional[int], Optional[float]]:
    """(frame count, frames per second) as the container states them (None when it does not)."""
    cap = _open(path)
    try:
        n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        fps = cap.get(cv2.CAP_PROP_FPS)
        return (n if n > 0 else None), (fps if fps and fps > 0 else None)
    finally:
        cap.release()


def split_side_by_side(frame: np.ndarray, path: str = "video") -> tuple[np.ndarray, np.ndarray]:
    """A side-by-side frame `(H, 2W, 3)` → (left `(H, W, 3)`, right `(H, W, 3)`): left half, right half."""
    w = frame.shape[1]
    if w % 2:
        raise VideoError(f"side-by-side video {path} has odd width {w}: expected left | right halves of equal width")
    return np.ascontiguousarray(frame[:, : w // 2]), np.ascontiguousarray(frame[:, w // 2:])


def stereo_frames(paths: Sequence[str], side_by_side: bool = False) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(left, right) uint8 RGB frames of a stereo video: two files (left, right; the shorter one ends it) or one
    side-by-side file. VideoError naming the file when sizes disagree."""
    paths = list(paths)
    if len(paths) == 2 and not side_by_side:
        for i, (a, b) in enumerate(zip(video_frames(paths[0]), video_frames(paths[1]))):
            if a.shape != b.shape:
                raise VideoError(f"frame {i}: {paths[0]} is {a.shape[0]}x{a.shape[1]} but {paths[1]} is "
                                 f"{b.shape[0]}x{b.shape[1]} (left and right videos must have the same size)")
            yield a, b
        return
    if len(paths) != 1 or not side_by_side:
        raise VideoError(f"expected two videos (left, right) or one side-by-side video, got {len(paths)} "
                         f"file(s){'' if side_by_side or len(paths) != 1 else ' without --side-by-side'}")
    for frame in video_frames(paths[0]):
        yield split_side_by_side(frame, paths[0])


def extract_stereo_video(paths: Sequence[str], out_dir: str, *, side_by_side: bool = False, every: int = 1,
                         max_frames: Optional[int] = None, overwrite: bool = False) -> dict:
    """Writes OUT/left/NNNNNN.png and OUT/right/NNNNNN.png (every `every`-th frame, at most `max_frames`) and
    OUT/video.json; returns that description. The folder appears only when complete."""
    if every < 1:
        raise VideoError(f"--every must be >= 1, got {every}")
    if max_frames is not None and max_frames < 2:
        raise VideoError(f"--max-frames must be >= 2 (a cycle needs two frames), got {max_frames}")
    for p in paths:
        video_info(p)  # each file exists and opens, before anything is written
    files.check_output_dir(out_dir, overwrite)
    written, size = 0, None
    with files.staged_dir(out_dir, overwrite=overwrite) as tmp:
        for side in ("left", "right"):
            os.makedirs(os.path.join(tmp, side))
        for i, (left, right) in enumerate(stereo_frames(paths, side_by_side)):
            if i % every:
                continue
            if max_frames is not None and written >= max_frames:
                break
            size = left.shape[:2]
            for side, img in (("left", left), ("right", right)):
                if not cv2.imwrite(os.path.join(tmp, side, f"{written:06d}.png"), img[..., ::-1]):
                    raise OSError(f"cannot write frames into {out_dir}")
            written += 1
        if written < 2:
            raise VideoError(f"{' + '.join(paths)}: {written} frame(s) extracted; a cycle needs at least two")
        desc = {"sources": [os.path.abspath(p) for p in paths], "side_by_side": bool(side_by_side),
                "every": int(every), "frames": written, "height": int(size[0]), "width": int(size[1])}
        files.write_json(os.path.join(tmp, "video.json"), desc)
    return desc


def build_parser():
    p = cli.make_parser("bridge_jax.data.videos", __doc__)
    p.add_argument("videos", nargs="+", metavar="VIDEO", help="left.mp4 right.mp4, or one side-by-side video")
    p.add_argument("--out", required=True, help="output folder (the training layout OUT/left, OUT/right)")
    p.add_argument("--side-by-side", action="store_true", help="one video holding left | right in each frame")
    p.add_argument("--every", type=int, default=1, help="keep every N-th frame (a larger motion between frames)")
    p.add_argument("--max-frames", type=int, default=None, help="stop after this many stereo frames")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out folder")
    cli.add_debug_flag(p)
    return p


@cli.entry_point
def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        desc = extract_stereo_video(args.videos, args.out, side_by_side=args.side_by_side, every=args.every,
                                    max_frames=args.max_frames, overwrite=args.overwrite)
    except (ValueError, OSError) as e:
        return cli.report_error(e, debug=args.debug)
    print(json.dumps(desc, indent=1))
    print(f"wrote {desc['frames']} stereo frames to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
