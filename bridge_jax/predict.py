"""Run a trained model on your own images or video and write pictures and raw values.

    # optical flow between two frames (or --task stereo for a rectified left/right pair)
    bridge-predict --checkpoint demo frame0.png frame1.png --out out/
    # with each map's confidence (1 = trusted) and occlusion mask, from the model's own consistency checks
    bridge-predict --checkpoint long frame0.png frame1.png --out out/ --confidence --raw npy
    # a stereo-video cycle: left_t right_t left_t1 right_t1 → disparity at t and t+1, flow, depth
    bridge-predict --checkpoint demo lt.png rt.png lt1.png rt1.png --out out/ --focal 721 --baseline 0.54
    # a folder of frames (mono: flow between consecutive frames; with left/ and right/ sub-folders: stereo video),
    # with raw values as KITTI PNGs, Middlebury .flo (flow) and .pfm (disparity, depth)
    bridge-predict --checkpoint work/demo/train frames/ --out out/ --raw png,flo,pfm
    # a video (mono), a side-by-side stereo video, or two videos (left, right); writes out/video.mp4 too
    bridge-predict --checkpoint CKPT drive.mp4 --out out/ [--stereo-video sbs]
    # KITTI 2015 (or 2012) benchmark submission from a KITTI layout folder (training or testing)
    bridge-predict --checkpoint CKPT --kitti-submission --data-dir data_scene_flow --out sub/

Outputs are named after the inputs: ``<stem>`` is the file stem of the frame's (left) image, e.g.
``frame0.png`` → ``flow/frame0.png`` (made unique with ``_2``, ``_3``, ... when two inputs share a stem); for
video input it is the frame index ``NNNNNN``. Flow ``<stem>`` goes from that frame to the next one (t → t+1);
for a cycle, ``<stem>`` of frame t is the stem of left_t, of frame t+1 the stem of left_t1.

    out/
      flow/<stem>.png             Middlebury colour wheel (key: legend_flow.png)
      disparity/<stem>.png        colormap (colour bar: legend_disparity.png); stereo inputs only
      depth/<stem>.png            with --focal and --baseline (colour bar: legend_depth.png)
      disparity_t1_in_t/<stem>.png   cycle: the t+1 disparity brought into frame t along the flow
      <folder>_kitti/<stem>.png   --raw png: KITTI 16-bit flow / disparity PNGs (flow_kitti/, disparity_kitti/)
      <folder>_npy/<stem>.npy     --raw npy: float32 pixels (depth_npy/: metres)
      flow_flo/<stem>.flo         --raw flo: Middlebury .flo, pixels (`bridge_jax.flowio`)
      <folder>_pfm/<stem>.pfm     --raw pfm: disparity (pixels) / depth (metres) as PFM (disparity_pfm/, depth_pfm/)
      flow_confidence/<stem>.png  --confidence: each map's confidence, 1 = trusted (key: legend_confidence.png);
                                  disparity_confidence/ likewise; float32 arrays in *_confidence_npy/ (--raw npy)
      flow_occlusion/<stem>.png   --confidence: white = no visible match in the other image (occluded or out of
                                  view); disparity_occlusion/ likewise; bool arrays in *_occlusion_npy/ (--raw npy)
      video.mp4                   video input: input | flow [| disparity] per frame
      predict.json                the run; "mapping": for each frame index with outputs its "stem", "inputs"
                                  (the input paths, or video and frame) and "flow_to" (the next frame's inputs)

Maps are at the input resolution, rescaled exactly as in evaluation (`bridge_jax.inference`). Colour scales are
fixed for a whole run (from the first frame unless ``--max-flow`` / ``--max-disp`` are given) so that frames
are comparable.

KITTI submission layout: 2015 → ``disp_0/``, ``disp_1/`` (the t+1 disparity brought into frame t along the
predicted flow) and ``flow/`` with ``<id>_10.png`` (zip the three folders for scene flow; ``disp_0`` alone for
stereo, ``flow`` alone for flow); 2012 → ``stereo/<id>_10.png`` and ``flow/<id>_10.png`` (zip each folder's
files at the archive root, as the KITTI 2012 devkit asks).

The output folder must not exist or be empty (``--overwrite`` replaces it); everything is written to a temporary
sibling folder and renamed at the end, so an interrupted run leaves nothing under the requested name.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import os
import shutil
import sys
from collections.abc import Callable, Iterator, Sequence
from typing import Optional

import cv2
import numpy as np
from tqdm import tqdm

from bridge_jax import (cli, compile_cache, confidence, console, files, flowio, inference, metrics, resizing, testtime,
                        visualize, zoo)
from bridge_jax.data import folders, kitti, videos
from bridge_jax.eval.datasets import Frame, kitti_specs
from bridge_jax.eval.methods import ModelMethod, bring_to_frame_t

IMAGE_EXTS = (".png", ".jpg", ".jpeg", ".bmp", ".ppm", ".pgm", ".tif", ".tiff", ".webp")
VIDEO_EXTS = (".mp4", ".avi", ".mov", ".mkv", ".webm", ".mpg", ".mpeg", ".m4v", ".wmv")
STEREO_SUBDIRS = (("left", "right"), ("image_02", "image_03"), ("image_2", "image_3"), ("image_0", "image_1"))


RAW_FORMATS = ("png", "npy", "flo", "pfm")
"""What --raw can ask for: KITTI 16-bit PNGs, .npy, Middlebury .flo (flow), .pfm (disparity and depth)."""


class PredictError(ValueError):
    """Bad user input for predict (names the file or option)."""


# --------------------------------------------------------------------------------------------------------------
# Inputs: a stream of (index, left, right-or-None) frames


@dataclasses.dataclass
class Source:
    """A frame source. ``stereo``: frames carry a right image.

    ``names``: the output stem of each frame index (image inputs: the stem of the frame's left image, made
    unique); None numbers the outputs ``NNNNNN`` (video). ``inputs``: frame index -> the input it came from, as
    recorded in predict.json (e.g. ``{"left": path, "right": path}``, ``{"image": path}``,
    ``{"video": path, "frame": i}``).
    """

    kind: str                       # "pair" | "cycle" | "folder" | "video"
    stereo: bool
    frames: Iterator[tuple[np.ndarray, Optional[np.ndarray]]]
    num_frames: Optional[int]
    fps: Optional[float] = None
    description: str = ""
    names: Optional[list[str]] = None
    inputs: Optional[Callable[[int], dict]] = None

    @property
    def num_pairs(self) -> Optional[int]:
        """How many pairs the network will see: flow between consecutive frames, plus disparity per frame of a
        stereo input; None when the number of frames is unknown."""
        if self.num_frames is None:
            return None
        return max(0, self.num_frames - 1) + (self.num_frames if self.stereo else 0)

    def name(self, index: int) -> str:
        """The output file stem of frame `index`."""
        return self.names[index] if self.names is not None else f"{index:06d}"


def unique_stems(paths: Sequence[str]) -> list[str]:
    """File stems of `paths` (``a/frame0.png`` -> ``frame0``), made unique in order: a repeated stem gets
    ``_2``, ``_3``, ... (skipping any name another input already has). Compared case-insensitively, so that
    the outputs stay distinct on case-insensitive file systems too."""
    stems = [os.path.splitext(os.path.basename(p))[0] or f"{i:06d}" for i, p in enumerate(paths)]
    taken = {s.casefold() for s in stems}   # every input's own stem is reserved: no suffix may produce one
    seen: set[str] = set()
    out = []
    for stem in stems:
        name, k = stem, 1
        while name.casefold() in seen or (name != stem and name.casefold() in taken):
            k += 1
            name = f"{stem}_{k}"
        seen.add(name.casefold())
        out.append(name)
    return out


def _path_inputs(lefts: Sequence[str], rights: Optional[Sequence[str]]) -> Callable[[int], dict]:
    if rights is None:
        return lambda i: {"image": lefts[i]}
    return lambda i: {"left": lefts[i], "right": rights[i]}


def read_image(path: str, size_for: Optional[Callable[[int, int], tuple]] = None) -> np.ndarray:
    """uint8 RGB ``(H, W, 3)``; grayscale is replicated. Raises PredictError naming the path.

    `size_for`: (h, w) of an input -> the working size it runs at (`Predictor.working_size`). When that is at
    least 4x smaller per side, the file is decoded at 1/2, 1/4 or 1/8 of its size (OpenCV's
    IMREAD_REDUCED_COLOR_*; a JPEG is then never decoded in full), keeping at least twice the working size per
    side, and the image carries the file's size as `full_size` (`inference.input_size`): the maps are
    still brought to it."""
    try:
        if size_for is not None:
            h, w = folders.image_size(path)
            wh, ww = size_for(h, w)
            factor = next((f for f in (8, 4, 2) if h / f >= 2 * wh and w / f >= 2 * ww), 1)
            if factor > 1:
                data = kitti.read_image_bytes(path)
                kitti.check_image_bytes(data, path)
                flag = {2: cv2.IMREAD_REDUCED_COLOR_2, 4: cv2.IMREAD_REDUCED_COLOR_4, 8: cv2.IMREAD_REDUCED_COLOR_8}
                img = cv2.imdecode(np.frombuffer(data, np.uint8), flag[factor])
                del data
                if img is None or img.ndim != 3 or img.shape[0] == 0:
                    raise kitti.CorruptImageError(path, "not a decodable image")
                return ReducedImage.of(np.ascontiguousarray(img[..., ::-1]), (h, w))
        return kitti.read_image(path)
    except ValueError as e:  # missing, truncated or undecodable
        raise PredictError(str(e)) from None


class ReducedImage(np.ndarray):
    """An input image decoded at a reduced size; `full_size` = (h, w) of the file (`read_image`)."""

    full_size: Optional[tuple] = None

    @classmethod
    def of(cls, image: np.ndarray, full_size: tuple) -> "ReducedImage":
        out = image.view(cls)
        out.full_size = tuple(full_size)
        return out

    def __array_finalize__(self, obj):
        self.full_size = getattr(obj, "full_size", None) if obj is not None and obj.shape == self.shape else None


class ImageReader:
    """How the image streams read their files: in full until `predict_source` sets `size_for` to the
    predictor's working size rule, then at a reduced size where that is much smaller (`read_image`)."""

    def __init__(self):
        self.size_for: Optional[Callable[[int, int], tuple]] = None

    def __call__(self, path: str) -> np.ndarray:
        return read_image(path, self.size_for)


def _is_image(path: str) -> bool:
    return os.path.splitext(path)[1].lower() in IMAGE_EXTS


def _is_video(path: str) -> bool:
    return os.path.splitext(path)[1].lower() in VIDEO_EXTS


def _list_images(folder: str) -> list[str]:
    files = sorted(f for f in os.listdir(folder) if _is_image(f) and os.path.isfile(os.path.join(folder, f)))
    return [os.path.join(folder, f) for f in files]


def _checked_size(img: np.ndarray, size: Optional[tuple], path: str) -> tuple:
    h, w = inference.input_size(img)
    if size is not None and (h, w) != size:
        raise PredictError(f"{path} is {h}x{w}, but the first frame is {size[0]}x{size[1]} (height x width)")
    return h, w


class _ImageStream:
    """The (left, right-or-None) frames of image files, read by `reader` (set up by `predict_source`)."""

    def __init__(self, lefts: list[str], rights: Optional[list[str]]):
        self.reader = ImageReader()
        self._frames = self._read(lefts, rights)

    def __iter__(self):
        return self

    def __next__(self):
        return next(self._frames)

    def _read(self, lefts, rights):
        size = None
        for i, lp in enumerate(lefts):
            left = self.reader(lp)
            size = _checked_size(left, size, lp)
            right = None
            if rights is not None:
                right = self.reader(rights[i])
                _checked_size(right, size, rights[i])
            yield left, right


_image_stream = _ImageStream


def _video_stream(paths: Sequence[str], sbs: bool):
    """(left, right-or-None) frames: a mono video, a side-by-side one, or a left + right pair of videos."""
    if len(paths) == 2 or sbs:
        yield from videos.stereo_frames(paths, side_by_side=sbs)
        return
    for frame in videos.video_frames(paths[0]):
        yield frame, None


def open_inputs(inputs: Sequence[str], *, mode: str = "auto", task: str = "flow",
                stereo_video: str = "none") -> Source:
    """Work out what the inputs are and return a frame stream (errors name the offending path)."""
    if not inputs:
        raise PredictError("no INPUTS given (images, a folder or a video)")
    for p in inputs:
        if not os.path.exists(p):
            raise PredictError(f"input {p} does not exist")
    if mode == "auto":
        if len(inputs) == 1 and os.path.isdir(inputs[0]):
            mode = "folder"
        elif all(_is_video(p) for p in inputs) and len(inputs) in (1, 2):
            mode = "video"
        elif len(inputs) == 2 and all(_is_image(p) for p in inputs):
            mode = "pair"
        elif len(inputs) == 4 and all(_is_image(p) for p in inputs):
            mode = "cycle"
        else:
            raise PredictError(f"cannot tell what {list(inputs)} are: give 2 images (pair), 4 images (cycle: "
                               "left_t right_t left_t1 right_t1), one folder, or 1-2 videos (or set --mode)")
    if mode == "pair":
        if len(inputs) != 2:
            raise PredictError(f"--mode pair needs 2 images, got {len(inputs)}")
        if task == "stereo":
            return Source("pair", True, _image_stream([inputs[0]], [inputs[1]]), 1,
                          description="stereo pair (left, right)", names=unique_stems([inputs[0]]),
                          inputs=_path_inputs([inputs[0]], [inputs[1]]))
        return Source("pair", False, _image_stream(list(inputs), None), 2, description="image pair (t, t+1)",
                      names=unique_stems(inputs), inputs=_path_inputs(list(inputs), None))
    if mode == "cycle":
        if len(inputs) != 4:
            raise PredictError(f"--mode cycle needs 4 images (left_t right_t left_t1 right_t1), got {len(inputs)}")
        lefts, rights = [inputs[0], inputs[2]], [inputs[1], inputs[3]]
        return Source("cycle", True, _image_stream(lefts, rights), 2, description="stereo cycle",
                      names=unique_stems(lefts), inputs=_path_inputs(lefts, rights))
    if mode == "folder":
        folder = inputs[0]
        if len(inputs) != 1 or not os.path.isdir(folder):
            raise PredictError(f"--mode folder needs one folder, got {list(inputs)}")
        for ln, rn in STEREO_SUBDIRS:
            ld, rd = os.path.join(folder, ln), os.path.join(folder, rn)
            if os.path.isdir(ld) and os.path.isdir(rd):
                if os.path.isdir(os.path.join(ld, "data")):   # KITTI raw drive: image_02/data
                    ld, rd = os.path.join(ld, "data"), os.path.join(rd, "data")
                lefts, rights = _list_images(ld), _list_images(rd)
                if len(lefts) != len(rights):
                    raise PredictError(f"mismatched counts: {ld} has {len(lefts)} images, {rd} has {len(rights)}")
                if not lefts:
                    raise PredictError(f"no images in {ld}")
                return Source("folder", True, _image_stream(lefts, rights), len(lefts),
                              description=f"stereo frames {ld} / {rd}", names=unique_stems(lefts),
                              inputs=_path_inputs(lefts, rights))
        frames = _list_images(folder)
        if len(frames) < 2:
            raise PredictError(f"folder {folder} has {len(frames)} images; need at least 2 consecutive frames "
                               "(or left/ and right/ sub-folders)")
        return Source("folder", False, _image_stream(frames, None), len(frames), description=f"frames {folder}",
                      names=unique_stems(frames), inputs=_path_inputs(frames, None))
    if mode == "video":
        if len(inputs) not in (1, 2):
            raise PredictError(f"--mode video needs 1 video (or 2: left, right), got {len(inputs)}")
        counts = [videos.video_info(p) for p in inputs]
        n, fps = counts[0]
        if len(inputs) == 2 and counts[1][0] is not None and n is not None:
            n = min(n, counts[1][0])
        stereo = len(inputs) == 2 or stereo_video == "sbs"
        paths = list(inputs)
        if len(paths) == 2:
            def video_inputs(i):
                return {"left": paths[0], "right": paths[1], "frame": i}
        else:
            def video_inputs(i):
                return {"video": paths[0], "frame": i, **({"side_by_side": True} if stereo_video == "sbs" else {})}
        # names=None: video frames keep their frame-index numbering NNNNNN
        return Source("video", stereo, _video_stream(inputs, stereo_video == "sbs"), n, fps,
                      description=f"video {' + '.join(inputs)}" + (" (side by side)" if stereo_video == "sbs" else ""),
                      inputs=video_inputs)
    raise PredictError(f"unknown --mode {mode!r}")


# --------------------------------------------------------------------------------------------------------------
# Running the model


class Runner:
    """Collects (task, index, image a, image b) jobs (task "flow" or "stereo") and runs them through the predictor in
    fixed-size batches (`inference.Predictor.predict`): flow and disparity at each input's resolution, with
    `confidence` also their confidence and occlusion maps."""

    def __init__(self, predictor, batch_pairs: int, confidence: bool = False):
        self.predictor = predictor
        self.batch_pairs = max(1, int(batch_pairs))
        self.confidence = confidence
        self.jobs: list[tuple[str, int, np.ndarray, np.ndarray]] = []

    def add(self, task: str, index: int, a: np.ndarray, b: np.ndarray) -> list[tuple]:
        self.jobs.append((task, index, a, b))
        return self.run() if len(self.jobs) >= self.batch_pairs else []

    def run(self) -> list[tuple]:
        """(task, index, value, checked) of the jobs so far: `checked` = (confidence, occlusion) with
        `confidence`, else None."""
        if not self.jobs:
            return []
        jobs, self.jobs = self.jobs, []
        # without confidence any object with predict(jobs, batch) serves (the keyword is passed only when asked)
        preds = self.predictor.predict([(t, a, b) for t, _, a, b in jobs], self.batch_pairs,
                                       **({"confidence": True} if self.confidence else {}))
        if self.confidence:
            return [(task, index, p[0], p[1:]) for (task, index, _, _), p in zip(jobs, preds)]
        return [(task, index, value, None) for (task, index, _, _), value in zip(jobs, preds)]


# --------------------------------------------------------------------------------------------------------------
# Writing


DISK_FULL_BYTES = 1 << 20
"""A failed write that gives no reason, on a file system with less free space than this, says "the disk is full"."""

PERCENTILE_SAMPLE = 1 << 22
"""Colour scales (99th percentiles) of maps with more pixels are taken from an evenly strided sample of them."""


def _sample(values: np.ndarray) -> np.ndarray:
    """`values` (first axis: pixels), or an evenly strided sample of about `PERCENTILE_SAMPLE` of them."""
    step = -(-len(values) // PERCENTILE_SAMPLE)
    return values[::step] if step > 1 else values


def _by_rows(fn: Callable, *maps: np.ndarray) -> np.ndarray:
    """`fn(*maps)` for a pixelwise `fn` (colour coding, PNG encoding) computed `resizing.ROW_BLOCK_PIXELS` pixels
    at a time, so a large map never has full-size float64 temporaries."""
    h, w = maps[0].shape[:2]
    rows = max(1, resizing.ROW_BLOCK_PIXELS // max(1, w))
    if h <= rows:
        return fn(*maps)
    first = fn(*(m[:rows] for m in maps))
    out = np.empty((h,) + first.shape[1:], first.dtype)
    out[:rows] = first
    for r0 in range(rows, h, rows):
        out[r0:r0 + rows] = fn(*(m[r0:r0 + rows] for m in maps))
    return out


def save_file(path: str, write: Callable[[str, object], object], data) -> None:
    """`write(path, data)`; an OSError that names no file (a full disk fails in a write call; numpy and OpenCV
    raise one with no error number, or only say that they failed) is raised again naming `path`, so that the
    one-line error says which output could not be written (under the output folder the user named:
    `files.staged_dir`)."""
    try:
        write(path, data)
    except OSError as e:
        if e.filename is not None:
            raise
        reason = e.strerror or "cannot write it"
        if not e.strerror and str(e) and path not in str(e):  # numpy's "N requested and M written"
            reason += f" ({e})"
        with contextlib.suppress(OSError):
            if not e.strerror and shutil.disk_usage(os.path.dirname(path)).free < DISK_FULL_BYTES:
                reason += "; the disk is full"
        raise OSError(e.errno, reason, path) from e


class Writer:
    """Writes the per-frame outputs into ``root`` (a temporary folder), with colour scales fixed on first use."""

    def __init__(self, root: str, *, raw: Sequence[str], max_flow: Optional[float], max_disp: Optional[float],
                 focal: Optional[float], baseline: Optional[float], video_fps: Optional[float],
                 name: Callable[[int], str] = lambda index: f"{index:06d}"):
        self.root = root
        self.name = name                      # frame index -> output file stem
        self.written: dict[int, set[str]] = {}   # frame index -> the sub-folders that got a file for it
        self.raw = set(raw)
        self.max_flow = max_flow
        self.max_disp = max_disp
        self.focal, self.baseline = focal, baseline
        self.video_fps = video_fps
        self.video: Optional[cv2.VideoWriter] = None
        self.video_size = None
        self.counts: dict[str, int] = {}

    def _path(self, sub: str, index: int, ext: str) -> str:
        d = os.path.join(self.root, sub)
        os.makedirs(d, exist_ok=True)
        self.written.setdefault(index, set()).add(sub)
        return os.path.join(d, f"{self.name(index)}{ext}")

    def _save(self, sub: str, index: int, ext: str, write: Callable[[str, object], object], data) -> None:
        """`write(path, data)` for the file of frame `index` in `sub` (`_path`), with its OSError naming it."""
        save_file(self._path(sub, index, ext), write, data)

    def flow(self, index: int, flow: np.ndarray, sub: str = "flow") -> np.ndarray:
        if self.max_flow is None:
            sample = _sample(flow.reshape(-1, 2)).astype(np.float64)
            self.max_flow = max(1.0, float(np.percentile(np.sqrt((sample ** 2).sum(-1)), 99)))
        if "png" in self.raw:  # before the colour picture: the two large arrays are never held together
            valid = np.broadcast_to(True, flow.shape[:2])
            self._save(f"{sub}_kitti", index, ".png", files.write_bytes,
                       kitti.encode_png16(_by_rows(kitti.flow_png_array, flow, valid), "flow"))
        color = _by_rows(lambda f: visualize.flow_to_color(f, max_flow=self.max_flow), flow)
        self._save(sub, index, ".png", visualize.write_image, color)
        if "npy" in self.raw:
            self._save(f"{sub}_npy", index, ".npy", np.save, np.asarray(flow, np.float32))
        if "flo" in self.raw:
            self._save(f"{sub}_flo", index, ".flo", flowio.write_flo, flow)
        self.counts[sub] = self.counts.get(sub, 0) + 1
        return color

    def disparity(self, index: int, disp: np.ndarray, sub: str = "disparity") -> np.ndarray:
        if self.max_disp is None:
            self.max_disp = max(1.0, 1.1 * float(np.percentile(_sample(disp.reshape(-1)), 99)))
        color = _by_rows(lambda d: visualize.disparity_to_color(d, vmax=self.max_disp), disp)
        self._save(sub, index, ".png", visualize.write_image, color)
        if "png" in self.raw:
            valid = np.broadcast_to(True, disp.shape)
            self._save(f"{sub}_kitti", index, ".png", files.write_bytes, kitti.encode_png16(
                _by_rows(lambda d, v: kitti.disp_png_array(np.clip(d, 1 / 256, 255.0), v), disp, valid), "disparity"))
        if "npy" in self.raw:
            self._save(f"{sub}_npy", index, ".npy", np.save, np.asarray(disp, np.float32))
        if "pfm" in self.raw:
            self._save(f"{sub}_pfm", index, ".pfm", flowio.write_pfm, disp)
        self.counts[sub] = self.counts.get(sub, 0) + 1
        if self.focal and self.baseline and sub == "disparity":
            def depth(d):
                return metrics.disparity_to_depth(d, self.focal, self.baseline)

            self._save("depth", index, ".png", visualize.write_image,
                       _by_rows(lambda d: visualize.depth_to_color(depth(d)), disp))
            if "npy" in self.raw or "pfm" in self.raw:
                full = depth(disp)
                if "npy" in self.raw:
                    self._save("depth_npy", index, ".npy", np.save, full.astype(np.float32, copy=False))
                if "pfm" in self.raw:
                    self._save("depth_pfm", index, ".pfm", flowio.write_pfm, full)
            self.counts["depth"] = self.counts.get("depth", 0) + 1
        return color

    def checked(self, index: int, confidence: np.ndarray, occlusion: np.ndarray, sub: str) -> None:
        """The confidence picture (`<sub>_confidence/`, legend_confidence.png) and occlusion mask
        (`<sub>_occlusion/`, white = occluded) of frame `index`'s map `sub` ("flow" / "disparity"), and with
        --raw npy their arrays (float32 in [0, 1] / bool, in `*_npy/`)."""
        self._save(f"{sub}_confidence", index, ".png", visualize.write_image,
                   _by_rows(visualize.confidence_to_color, confidence))
        self._save(f"{sub}_occlusion", index, ".png", files.imwrite, visualize.occlusion_to_image(occlusion))
        if "npy" in self.raw:
            self._save(f"{sub}_confidence_npy", index, ".npy", np.save, np.asarray(confidence, np.float32))
            self._save(f"{sub}_occlusion_npy", index, ".npy", np.save, np.asarray(occlusion, bool))
        for kind in ("confidence", "occlusion"):
            self.counts[f"{sub}_{kind}"] = self.counts.get(f"{sub}_{kind}", 0) + 1

    def video_frame(self, tiles: list[np.ndarray], labels: list[str]) -> None:
        img = visualize.panel(tiles, labels)
        if self.video is None:
            h, w = img.shape[:2]
            self.video_size = (w, h)
            path = os.path.join(self.root, "video.mp4")
            self.video = cv2.VideoWriter(path, cv2.VideoWriter_fourcc(*"mp4v"), self.video_fps or 10.0, (w, h))
            if not self.video.isOpened():
                raise OSError(None, "cannot open a video writer (OpenCV) for it", path)
        self.video.write(np.ascontiguousarray(img[..., ::-1]))

    def legends(self) -> None:
        if self.max_flow is not None:
            save_file(os.path.join(self.root, "legend_flow.png"), visualize.write_image,
                      visualize.color_wheel_legend(256, max_flow=self.max_flow))
        if self.max_disp is not None:
            save_file(os.path.join(self.root, "legend_disparity.png"), visualize.write_image,
                      visualize.colorbar(0.0, self.max_disp, "magma", unit="px", label="disparity"))
        if any(k.endswith("_confidence") for k in self.counts):
            save_file(os.path.join(self.root, "legend_confidence.png"), visualize.write_image,
                      visualize.colorbar(0.0, 1.0, visualize.CONFIDENCE_COLORMAP, unit="", label="confidence"))
        if self.counts.get("depth"):
            save_file(os.path.join(self.root, "legend_depth.png"), visualize.write_image,
                      visualize.colorbar(2.0, 80.0, "magma", unit="m", label="depth", inverse=True))

    def close(self) -> None:
        if self.video is not None:
            self.video.release()
            self.video = None


def _progress(total: Optional[int], enabled: bool, desc: str):
    return tqdm(total=total, desc=desc, unit="frame", file=sys.stderr, disable=not enabled)


def predict_source(predictor, source: Source, out_dir: str, *, overwrite: bool = False, batch: int = 4,
                   raw: Sequence[str] = ("png",), max_flow: Optional[float] = None, max_disp: Optional[float] = None,
                   focal: Optional[float] = None, baseline: Optional[float] = None, write_video: Optional[bool] = None,
                   progress: bool = True, info: Optional[dict] = None, confidence: bool = False) -> dict:
    """Run the predictor over a frame stream and write everything into ``out_dir`` (atomically).

    Flow is predicted between consecutive left frames (t → t+1), disparity for every stereo frame; for a cycle
    also the t+1 disparity brought into frame t (``disparity_t1_in_t/``). Returns the run description that is
    also written to ``predict.json``. With ``confidence``, each flow and disparity also gets its confidence
    picture and occlusion mask (`Writer.checked`, `inference.Predictor.predict(..., confidence=True)`).
    """
    write_video = source.kind == "video" if write_video is None else write_video
    if write_video and not files.opencv_can_open(os.path.abspath(out_dir)):  # the staging folder is a sibling
        raise PredictError(f"output folder {files.shown_name(out_dir)}: OpenCV cannot write video.mp4 into a folder "
                           "whose path is not valid UTF-8 (rename it, or --no-video)")
    if source.num_pairs:  # one pair is not padded to a batch of 4: each padded row costs a full network call
        batch = min(batch, source.num_pairs)
    runner = Runner(predictor, batch, confidence)
    pending: dict[int, dict] = {}          # frame index -> {"image":..., "flow":..., "stereo":...} for the video (colour pictures)
    results: dict[tuple[str, int], np.ndarray] = {}
    n_frames = 0
    with files.staged_dir(out_dir, overwrite=overwrite) as tmp, \
            _progress(source.num_frames, progress, "predict") as bar:
        writer = Writer(tmp, raw=raw, max_flow=max_flow, max_disp=max_disp, focal=focal, baseline=baseline,
                        video_fps=source.fps, name=source.name)

        def handle(outputs):
            for task, index, value, checked in outputs:
                color = writer.flow(index, value) if task == "flow" else writer.disparity(index, value)
                if checked is not None:
                    writer.checked(index, *checked, sub="flow" if task == "flow" else "disparity")
                if source.kind == "cycle":
                    results[(task, index)] = value
                if write_video:
                    pending.setdefault(index, {})[task] = color
            if write_video:
                _flush_video(writer, pending, source.stereo, final=False)

        reader = getattr(source.frames, "reader", None)
        if reader is not None and hasattr(predictor, "working_size"):
            reader.size_for = predictor.working_size  # large inputs are decoded at a reduced size
        try:
            prev = None
            for index, (left, right) in enumerate(source.frames):
                if hasattr(predictor, "model_name"):
                    _check_minimum(predictor.model_name, left, source, index)
                if index == 0 and hasattr(predictor, "working_size"):
                    note = inference.resize_notice(predictor, *inference.input_size(left))
                    if note:
                        print(note, file=sys.stderr)
                if write_video:
                    pending.setdefault(index, {})["image"] = left
                if prev is not None:
                    handle(runner.add("flow", index - 1, prev, left))
                if right is not None:
                    handle(runner.add("stereo", index, left, right))
                prev = left
                n_frames += 1
                bar.update(1)
            handle(runner.run())
            if n_frames == 0:
                raise PredictError("the input has no frame")
            if not source.stereo and n_frames < 2:
                raise PredictError("a single frame has no optical flow: give at least 2 frames")
            if source.kind == "cycle":
                disp_1 = bring_to_frame_t(results[("stereo", 1)], results[("flow", 0)])
                writer.disparity(0, disp_1, sub="disparity_t1_in_t")
            if write_video:
                _flush_video(writer, pending, source.stereo, final=True)
        finally:
            writer.close()
        writer.legends()
        desc = {"input": source.description, "kind": source.kind, "stereo": source.stereo, "frames": n_frames,
                "outputs": writer.counts, "max_flow_px": writer.max_flow, "max_disparity_px": writer.max_disp,
                "focal_px": focal, "baseline_m": baseline, "raw": sorted(set(raw)),
                "mapping": _mapping(source, writer.written)}
        if info:
            desc.update(info)
        files.write_text(os.path.join(tmp, "predict.json"), json.dumps(desc, indent=1))
    return desc


def _check_minimum(model_name: str, image: np.ndarray, source: Source, index: int) -> None:
    """PredictError naming the input when frame `index` is below the model's minimum
    (`inference.minimum_input_size`)."""
    h, w = inference.input_size(image)
    low = inference.minimum_input_size(model_name)
    if h < low[0] or w < low[1]:
        inputs = source.inputs(index) if source.inputs is not None else {}
        where = inputs.get("left") or inputs.get("image") or inputs.get("video") or f"frame {index}"
        raise PredictError(f"{where}: a {h}x{w} input is smaller than model {model_name} accepts (at least "
                           f"{low[0]}x{low[1]} pixels, height x width)")


def _mapping(source: Source, written: dict[int, set[str]]) -> list[dict]:
    """predict.json's ``mapping``: for each frame index that has output files, its output stem, its inputs and,
    when flow was written for it, the frame the flow goes to (the next one)."""
    out = []
    for index in sorted(written):
        entry = {"index": index, "stem": source.name(index)}
        if source.inputs is not None:
            entry["inputs"] = source.inputs(index)
            if "flow" in written[index]:
                entry["flow_to"] = source.inputs(index + 1)
        out.append(entry)
    return out


def _flush_video(writer: Writer, pending: dict[int, dict], stereo: bool, final: bool) -> None:
    """Write video frames in order as soon as their tiles are complete (at the end: whatever is there; the last
    frame has no flow and gets a black tile)."""
    while pending:
        index = min(pending)
        entry = pending[index]
        complete = "image" in entry and "flow" in entry and ("stereo" in entry or not stereo)
        if not complete and not final:
            return
        blank = np.zeros_like(entry["image"])
        tiles, labels = [entry["image"], entry.get("flow", blank)], ["input", "flow"]
        if stereo:
            tiles.append(entry.get("stereo", blank))
            labels.append("disparity")
        writer.video_frame(tiles, labels)
        del pending[index]


# --------------------------------------------------------------------------------------------------------------
# KITTI submission


def kitti_submission(predictor, data_dir: str, out_dir: str, *, split: Optional[str] = None, year: Optional[int] = None,
                     overwrite: bool = False, batch: int = 1, progress: bool = True) -> dict:
    """Write a KITTI 2015 scene-flow (``disp_0``, ``disp_1``, ``flow``) or KITTI 2012 (``stereo``, ``flow``)
    submission for every frame id of a KITTI layout folder (``split`` default: ``testing`` if present)."""
    if not os.path.isdir(data_dir):
        raise PredictError(f"--data-dir {data_dir} is not a directory")
    if split is None:
        split = "testing" if os.path.isdir(os.path.join(data_dir, "testing")) else "training"
    if year is None:
        root = os.path.join(data_dir, split) if os.path.isdir(os.path.join(data_dir, split)) else data_dir
        year = 2015 if os.path.isdir(os.path.join(root, "image_2")) else 2012
    specs = kitti_specs(data_dir, split, year=year, require_gt=False)
    method = ModelMethod(predictor, batch)
    folders = ("disp_0", "disp_1", "flow") if year == 2015 else ("stereo", "flow")
    with files.staged_dir(out_dir, overwrite=overwrite) as tmp, \
            _progress(len(specs), progress, f"KITTI {year} submission") as bar:
        for d in folders:
            os.makedirs(os.path.join(tmp, d))
        for start in range(0, len(specs), max(1, batch)):
            frames = []
            for spec in specs[start:start + max(1, batch)]:
                images = {k: read_image(p) for k, p in spec.images.items()}
                if year == 2012:
                    images.pop("right_t1")
                # a GT-less frame; mark disp_1 as wanted for 2015 so that the t+1 disparity is predicted
                gt = {"disp_occ_1": np.zeros(1)} if year == 2015 else {}
                frames.append(Frame(spec.frame_id, images, gt))
            for frame, pred in zip(frames, method(frames)):
                ones = np.ones(frame.size, bool)
                name = f"{frame.frame_id}_10.png"
                disp_files = ((("disp_0", "disp_t"), ("disp_1", "disp_1")) if year == 2015
                              else (("stereo", "disp_t"),))
                for folder, key in disp_files:   # dense: every pixel valid, inside the 16-bit PNG range
                    kitti.write_disp_png(os.path.join(tmp, folder, name), np.clip(pred[key], 1 / 256, 255.0), ones)
                kitti.write_flow_png(os.path.join(tmp, "flow", name), np.clip(pred["flow"], -511.0, 511.0), ones)
            bar.update(len(frames))
        desc = {"kitti_year": year, "data_dir": os.path.abspath(data_dir), "split": split, "frames": len(specs),
                "folders": list(folders)}
        files.write_text(os.path.join(tmp, "submission.json"), json.dumps(desc, indent=1))
    return desc


# --------------------------------------------------------------------------------------------------------------
# Command line


def build_parser() -> argparse.ArgumentParser:
    p = cli.make_parser("bridge_jax.predict", __doc__)
    p.add_argument("inputs", nargs="*", metavar="INPUTS",
                   help="2 images (a pair), 4 images (a cycle: left_t right_t left_t1 right_t1), one folder, or 1-2 "
                        "videos (left, right)")
    p.add_argument("--checkpoint", required=True,
                   help="the model: a params dir, a training workdir, a step dir, or a shipped model name such as demo")
    p.add_argument("--out", required=True, help="output folder (must not exist or be empty)")
    p.add_argument("--overwrite", action="store_true", help="replace a non-empty --out folder")
    p.add_argument("--mode", default="auto", choices=("auto", "pair", "cycle", "folder", "video"),
                   help="what INPUTS are; auto: 2 images = pair, 4 images = cycle, a folder = folder, "
                        "1-2 videos = video")
    cli.add_task_option(p, help="two images: consecutive frames (flow) or a rectified left/right pair (stereo)")
    p.add_argument("--stereo-video", default="none", choices=("none", "sbs"),
                   help="one video: mono (none) or left|right side by side in each frame (sbs)")
    p.add_argument("--working-size", type=cli.parse_working_size, default=None, metavar="HxW|native|trained",
                   help=cli.WORKING_SIZE_HELP + "; default: what the card of the shipped model it is or was "
                        f"fine-tuned from recommends (long: native), else {inference.DEFAULT_WORKING_SIZE}")
    cli.add_test_time_options(p)
    p.add_argument("--batch", type=int, default=4,
                   help="pairs per inference call (one compiled shape; fewer when the input has fewer pairs)")
    p.add_argument("--compile", default="auto", choices=inference.COMPILE_MODES,
                   help="how the network is compiled: 'fast' (about 2-3x quicker to compile, 10-25%% slower per "
                        "pair), 'full' (XLA's default optimisation) or 'auto' (fast for inputs of at most "
                        f"{inference.FAST_COMPILE_PAIRS} pairs, else full); the --polish program is always "
                        "compiled full; compiled programs are cached between runs either way")
    p.add_argument("--raw", default="png",
                   help="raw values besides the pictures, a comma list: png (KITTI 16-bit, *_kitti/), npy "
                        "(*_npy/), flo (flow, flow_flo/), pfm (disparity and depth, *_pfm/), or none; "
                        "e.g. png,flo,pfm")
    p.add_argument("--confidence", action="store_true",
                   help="also write each map's confidence (flow_confidence/, disparity_confidence/: 1 = trusted; "
                        "legend_confidence.png) and occlusion mask (flow_occlusion/, disparity_occlusion/: white = "
                        "no visible match in the other image), from the forward-backward / left-right check; one "
                        "more prediction per pair; with --raw npy also their arrays (*_npy/)")
    p.add_argument("--confidence-check", default=None, choices=confidence.CHECK_MODES,
                   help="with --confidence: what the backward maps of the check run with: network (one plain network "
                        "call per pair, the default) or same (the prediction's own --refine/--symmetry/--polish "
                        "stages: twice the cost, sharper occlusion masks)")
    p.add_argument("--max-flow", type=float, default=None,
                   help="flow colour-wheel radius in px (default: 99th percentile of the first flow)")
    p.add_argument("--max-disp", type=float, default=None,
                   help="disparity colormap top in px (default: 1.1 x 99th percentile of the first disparity)")
    p.add_argument("--focal", type=float, default=None,
                   help="focal length in px at the input resolution; with --baseline, writes depth/")
    p.add_argument("--baseline", type=float, default=None, help="stereo baseline in metres (with --focal)")
    p.add_argument("--no-video", dest="video", action="store_false", default=None,
                   help="do not write video.mp4 for video input")
    p.add_argument("--kitti-submission", action="store_true",
                   help="write a KITTI benchmark submission for every frame of --data-dir (takes no INPUTS)")
    p.add_argument("--data-dir", default=None, help="KITTI 2015/2012 layout folder (with --kitti-submission)")
    p.add_argument("--split", default=None,
                   help="KITTI sub-folder: testing or training (default: testing if present)")
    p.add_argument("--kitti-year", type=int, choices=(2012, 2015), default=None,
                   help="KITTI benchmark of the submission (default: 2015 if --data-dir has image_2/, else 2012)")
    # store_true into no_progress (not store_false into progress): the help would otherwise show "(default: True)"
    p.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    compile_cache.add_option(p)
    cli.add_debug_flag(p)
    return p


def parse_raw(text: str) -> list[str]:
    """``--raw`` "png,flo" -> ["png", "flo"]; "none" or "" -> []; PredictError for unknown formats."""
    raw = [r.strip().lower() for r in text.split(",") if r.strip() and r.strip().lower() != "none"]
    bad = [r for r in raw if r not in RAW_FORMATS]
    if bad:
        raise PredictError(f"--raw {text}: unknown format(s) {', '.join(bad)}; expected a comma list of "
                           f"{', '.join(RAW_FORMATS)}, or none")
    return list(dict.fromkeys(raw))


SETTINGS_OPTIONS = ("--working-size", "--refine", "--symmetry", "--polish")
"""The options of the test-time settings that a model's card (`zoo.defaults_source`) chooses by default."""


def settings_line(checkpoint: str, predictor, given: Sequence[str] = ()) -> str:
    """The one line saying which test-time settings `predictor` (loaded from `checkpoint`) runs with and why:
    the card of the shipped model the checkpoint is or was fine-tuned from (`zoo.card_lineage`), or the plain
    defaults; settings of `given` (those of `SETTINGS_OPTIONS` the user gave) are marked as given."""
    settings = predictor.settings()  # working_size, then the test-time fields, in SETTINGS_OPTIONS' order
    values = zip(SETTINGS_OPTIONS, (f"{name.replace('_', ' ')} {value}" for name, value in settings.items()))
    parts = [f"{text} ({option})" if option in given else text for option, text in values]
    chain = zoo.card_lineage(checkpoint)
    if len(chain) == 1:
        why = f"the card of {chain[0]!r}"
    elif chain:
        via = f" (through {', '.join(chain[1:-1])})" if len(chain) > 2 else ""
        why = f"the card of {chain[-1]!r}, which {checkpoint} was fine-tuned from{via}"
    else:
        why = "defaults"
    return f"test-time settings: {', '.join(parts)} ({why}; {'/'.join(SETTINGS_OPTIONS)} override)"


def predictor_from_args(args: argparse.Namespace, num_pairs: Optional[int]):
    """The predictor of the command line `args` (`inference.load_predictor`), after printing its
    `settings_line`; `num_pairs`: how many pairs it will run (`inference.compile_mode_for`), None if unknown."""
    test_time = cli.given_test_time(args)
    predictor = inference.load_predictor(args.checkpoint, size=args.working_size, size_option="--working-size",
                                         test_time=test_time, options=testtime.OPTIONS,
                                         executable_cache=compile_cache.active_dir(),
                                         compile_mode=inference.compile_mode_for(args.compile, num_pairs))
    given = [option for option, value in zip(SETTINGS_OPTIONS, (args.working_size, *test_time.values()))
             if value is not None]
    print(settings_line(args.checkpoint, predictor, given), flush=True)
    return predictor


@cli.entry_point
def main(argv: Optional[Sequence[str]] = None) -> int:
    args = build_parser().parse_args(argv)
    console.install(enabled=not cli.debug_enabled(args))  # XLA's slow-compile banner stays out of the console
    try:
        compile_cache.enable(args.compilation_cache)
        if args.batch < 1:
            raise PredictError(f"--batch must be >= 1, got {args.batch}")
        raw = parse_raw(args.raw)
        if (args.focal is None) != (args.baseline is None):
            raise PredictError("--focal and --baseline go together")
        files.check_output_dir(args.out, args.overwrite)
        if args.kitti_submission:
            if not args.data_dir:
                raise PredictError("--kitti-submission needs --data-dir")
            if args.inputs:
                raise PredictError("--kitti-submission takes no INPUTS (it reads --data-dir)")
            if args.confidence:
                raise PredictError("--confidence does not apply to --kitti-submission (the benchmark takes the maps "
                                   "only)")
            predictor = predictor_from_args(args, num_pairs=None)
            desc = kitti_submission(predictor, args.data_dir, args.out, split=args.split, year=args.kitti_year,
                                    overwrite=args.overwrite, batch=args.batch, progress=not args.no_progress)
        else:
            if args.confidence_check and not args.confidence:
                raise PredictError("--confidence-check goes with --confidence")
            source = open_inputs(args.inputs, mode=args.mode, task=args.task,
                                 stereo_video=args.stereo_video)
            predictor = predictor_from_args(args, num_pairs=source.num_pairs)
            checked = {}
            if args.confidence:
                checked = {"confidence_check": args.confidence_check or confidence.DEFAULT_CHECK}
                predictor.check = confidence.check_record(checked["confidence_check"], predictor.test_time,
                                                          "--confidence-check")
            desc = predict_source(predictor, source, args.out, overwrite=args.overwrite, batch=args.batch, raw=raw,
                                  max_flow=args.max_flow, max_disp=args.max_disp, focal=args.focal,
                                  baseline=args.baseline, write_video=args.video, progress=not args.no_progress,
                                  info={"checkpoint": args.checkpoint, **predictor.test_time.to_dict(), **checked},
                                  confidence=args.confidence)
    except (ValueError, OSError) as e:  # PredictError, EvaluationError, CorruptImageError: one line naming the path
        return cli.report_error(e, debug=args.debug)
    print(json.dumps({k: v for k, v in desc.items() if k != "mapping"}, indent=1))
    print(f"wrote {files.shown_name(args.out)}")  # a name that is not UTF-8 would not print as it is
    return 0


if __name__ == "__main__":
    sys.exit(main())
