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
    if not files.opencv_can_open(path):  # OpenCV would crash (no error) on the name
        raise VideoError(f"video {files.shown_name(path)}: OpenCV cannot open a file whose name is not valid UTF-8 "
                         "(rename it)")
    cap = cv2.VideoCapture(path)
    if not cap.isOpened():
        cap.release()
        raise VideoError(f"cannot open video {path} (not a video, or a codec OpenCV lacks)")
    return cap


def note(text: str) -> None:
    """Prints `note: <text>` to stderr: something the user should know, though the run goes on."""
    print(f"note: {text}", file=sys.stderr, flush=True)


def _stated_count(cap) -> Optional[int]:
    n = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
    return n if n > 0 else None


def video_frames(path: str, *, note_short: bool = True) -> Iterator[np.ndarray]:
    """The frames of a video file as uint8 RGB `(H, W, 3)`, in order; VideoError when none can be read.

    Read to its end, a video that decodes to fewer frames than its container states (a truncated or damaged
    file) prints one `note` naming both counts, unless `note_short` is False (`stereo_frames` words it for the
    pair instead)."""
    cap = _open(path)
    try:
        stated = _stated_count(cap)
        n = 0
        while True:
            ok, frame = cap.read()
            if not ok:
                break
            n += 1
            yield np.ascontiguousarray(frame[..., ::-1])
        if n == 0:
            raise VideoError(f"cannot read any frame from video {path}")
        if note_short and stated is not None and n < stated:
            note(f"video {path} has {n} decodable frames, its header states {stated} (a truncated or damaged "
                 f"file?): using those {n}")
    finally:
        cap.release()


def video_info(path: str) -> tuple[Optional[int], Optional[float]]:
    """(frame count, frames per second) as the container states them (None when it does not)."""
    cap = _open(path)
    try:
        fps = cap.get(cv2.CAP_PROP_FPS)
        return _stated_count(cap), (fps if fps and fps > 0 else None)
    finally:
        cap.release()


def split_side_by_side(frame: np.ndarray, path: str = "video") -> tuple[np.ndarray, np.ndarray]:
    """A side-by-side frame `(H, 2W, 3)` → (left `(H, W, 3)`, right `(H, W, 3)`): left half, right half."""
    w = frame.shape[1]
    if w % 2:
        raise VideoError(f"side-by-side video {path} has odd width {w}: expected left | right halves of equal width")
    return np.ascontiguousarray(frame[:, : w // 2]), np.ascontiguousarray(frame[:, w // 2:])


def stereo_frames(paths: Sequence[str], side_by_side: bool = False) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """(left, right) uint8 RGB frames of a stereo video: two files (left, right) or one side-by-side file.
    VideoError naming the file when sizes disagree. Two files of different lengths give as many pairs as the
    shorter one has frames, with one `note` naming both files and their counts."""
    paths = list(paths)
    if len(paths) == 2 and not side_by_side:
        yield from _paired_frames(paths[0], paths[1])
        return
    if len(paths) != 1 or not side_by_side:
        raise VideoError(f"expected two videos (left, right) or one side-by-side video, got {len(paths)} "
                         f"file(s){'' if side_by_side or len(paths) != 1 else ' without --side-by-side'}")
    for frame in video_frames(paths[0]):
        yield split_side_by_side(frame, paths[0])


def _paired_frames(left_path: str, right_path: str) -> Iterator[tuple[np.ndarray, np.ndarray]]:
    """`stereo_frames` of a left and a right video file: pairs until either ends, then one `note` when the
    two differ in length (or a file decodes to fewer frames than its header states)."""
    paths = (left_path, right_path)
    stated = [video_info(p)[0] for p in paths]
    streams = [video_frames(p, note_short=False) for p in paths]
    try:
        i = 0
        while True:
            # both are read every time: when one ends, whether the other had a frame more tells who was short
            a, b = (next(s, None) for s in streams)
            if a is None or b is None:
                break
            if a.shape != b.shape:
                raise VideoError(f"frame {i}: {left_path} is {a.shape[0]}x{a.shape[1]} but {right_path} is "
                                 f"{b.shape[0]}x{b.shape[1]} (left and right videos must have the same size)")
            yield a, b
            i += 1
    finally:
        for s in streams:
            s.close()

    def counted(k: int) -> str:  # file k ended after i frames
        header = f" (its header states {stated[k]}: a truncated or damaged file?)" if (stated[k] or 0) > i else ""
        return f"{paths[k]} has {i} frames{header}"

    if (a is None) != (b is None):  # one ended first: the other is cut to its length
        k = 0 if a is None else 1
        other = stated[1 - k] if (stated[1 - k] or 0) > i else "more"
        note(f"{counted(k)}, {paths[1 - k]} {other}: using the first {i} of each")
    else:
        for k in (0, 1):
            if (stated[k] or 0) > i:
                note(f"{counted(k)}: using those {i}")


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
                files.imwrite(os.path.join(tmp, side, f"{written:06d}.png"), img[..., ::-1])
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
