"""KITTI file formats, layouts, calibration, raw-drive cycles, splits and Velodyne depth ground truth.

Formats (KITTI devkit conventions):
  * Flow PNG: 16-bit, 3 channels; R = u·64 + 2^15, G = v·64 + 2^15, B = valid (0/1); invalid pixels are (0, 0, 0).
    OpenCV reads and writes BGR, so channel 0 of a cv2 array is the *valid* flag and channel 2 is u.
  * Disparity PNG: 16-bit, 1 channel, disparity·256, 0 = invalid (a valid disparity that would round to 0 is
    stored as 1 so that it stays valid).
  * Calibration text: `key: v1 v2 ...` per line (non-numeric lines such as `calib_time` are skipped).

Layouts:
  * KITTI 2015 (`data_scene_flow/training`): image_2/NNNNNN_10.png|_11.png (left t, t+1), image_3/ (right),
    disp_occ_0/, disp_noc_0/, disp_occ_1/, flow_occ/, flow_noc/ (NNNNNN_10.png), calib_cam_to_cam/NNNNNN.txt.
    The synthetic writer (`bridge_jax.data.synthetic`) uses the same layout.
  * KITTI 2012 (`data_stereo_flow/training`): grayscale image_0/image_1 (replicated to RGB; the paper evaluates
    on them), disp_occ/, disp_noc/, flow_occ/, flow_noc/, calib/NNNNNN.txt (P0..P3).
  The readers of these two benchmark layouts are in `bridge_jax.eval.datasets`.
  * KITTI raw: ROOT/<date>/calib_cam_to_cam.txt, calib_velo_to_cam.txt and
    ROOT/<date>/<date>_drive_<NNNN>_sync/{image_02,image_03}/data/<frame:010d>.png|.jpg, velodyne_points/data/*.bin.

Splits (bridge_jax/data/splits/, see README.md there): the KITTI split (28,968 cycles), the Eigen training cycles
(8,000) and the Eigen test frames (697).
"""
from __future__ import annotations

import logging
import os
import re

import cv2
import numpy as np

from bridge_jax import files

cv2.setNumThreads(1)
log = logging.getLogger(__name__)

SPLITS_DIR = os.path.join(os.path.dirname(os.path.abspath(__file__)), "splits")
IMAGE_EXTS = (".png", ".jpg", ".jpeg")
RAW_LAYOUT = ("KITTI raw layout: ROOT/<date>/<date>_drive_<NNNN>_sync/image_02/data/*.png|jpg and "
              "image_03/data/* (calibration in ROOT/<date>/calib_cam_to_cam.txt)")


class CorruptImageError(ValueError):
    """An image (or GT file) is missing, truncated or cannot be decoded. `.path` names the file."""

    def __init__(self, path: str, reason: str):
        super().__init__(f"{path}: {reason}")
        self.path, self.reason = path, reason


# ----------------------------------------------------------------------------------------------------------
# Images
# ----------------------------------------------------------------------------------------------------------

def _encode(ext: str, array: np.ndarray, name: str) -> bytes:
    ok, buf = cv2.imencode(ext, array)
    if not ok:
        raise ValueError(f"could not encode {name} as {ext}")
    return buf.tobytes()


def check_image_bytes(data: bytes, path: str = "<bytes>") -> None:
    """Raises CorruptImageError when PNG/JPEG bytes are empty or visibly truncated (no IEND / EOI marker).

    A truncated JPEG decodes "successfully" (grey bottom) in libjpeg, so the end marker is checked explicitly.
    """
    if len(data) == 0:
        raise CorruptImageError(path, "empty file")
    if len(data) < 8 and b"\x89PNG\r\n\x1a\n".startswith(bytes(data)):
        raise CorruptImageError(path, f"truncated PNG (only {len(data)} bytes)")
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if b"IEND" not in data[-16:]:
            raise CorruptImageError(path, "truncated PNG (no IEND chunk at the end)")
    elif data[:2] == b"\xff\xd8":
        # EOI must appear in the file's tail (some cameras append trailing data after it; an EXIF thumbnail's
        # EOI sits near the start, so only the second half / last 64 kB is searched).
        if b"\xff\xd9" not in data[max(len(data) // 2, len(data) - 65536):]:
            raise CorruptImageError(path, "truncated JPEG (no end-of-image marker)")


def decode_image(data: bytes, path: str = "<bytes>") -> np.ndarray:
    """Encoded PNG/JPEG bytes → uint8 RGB (H, W, 3); grayscale is replicated to 3 channels."""
    check_image_bytes(data, path)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    if img is None or img.ndim != 3 or img.shape[0] == 0:
        raise CorruptImageError(path, "not a decodable image")
    return np.ascontiguousarray(img[..., ::-1])


def read_image_bytes(path: str) -> bytes:
    try:
        with open(path, "rb") as fh:
            return fh.read()
    except OSError as e:
        raise CorruptImageError(path, f"cannot read ({e.strerror or e})") from None


def read_image(path: str) -> np.ndarray:
    """Reads a PNG/JPEG file → uint8 RGB (H, W, 3). Missing/truncated/corrupt → CorruptImageError."""
    return decode_image(read_image_bytes(path), path)


def encode_png(rgb: np.ndarray) -> bytes:
    """uint8 RGB (H, W, 3) → PNG bytes."""
    return _encode(".png", np.ascontiguousarray(np.asarray(rgb)[..., ::-1]), "image")


def write_image(path: str, rgb: np.ndarray) -> None:
    """Writes uint8 RGB (H, W, 3) to `path` (format from the extension), atomically."""
    rgb = np.asarray(rgb)
    if rgb.dtype != np.uint8 or rgb.ndim != 3 or rgb.shape[2] != 3:
        raise ValueError(f"write_image({path!r}): expected uint8 (H, W, 3), got {rgb.dtype} {rgb.shape}")
    files.write_bytes(path, _encode(os.path.splitext(path)[1] or ".png", rgb[..., ::-1].copy(), path))


# ----------------------------------------------------------------------------------------------------------
# Flow and disparity PNGs
# ----------------------------------------------------------------------------------------------------------

def flow_png_array(flow: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """flow float (H, W, 2) pixels (u, v), valid bool (H, W) (default: finite) → the uint16 BGR array of a KITTI
    flow PNG (`encode_flow_png`); pixelwise, so a large map can be converted a block of rows at a time.

    Values are clipped to the representable range ±512 px; invalid pixels are stored as (0, 0, 0).
    """
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[2] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    if valid is None:
        valid = np.isfinite(flow).all(-1)
    valid = np.asarray(valid, bool)
    enc = np.clip(np.rint(np.nan_to_num(flow) * 64.0 + 32768.0), 0, 65535).astype(np.uint16)
    bgr = np.zeros(flow.shape[:2] + (3,), np.uint16)
    bgr[..., 0] = valid
    bgr[..., 1] = np.where(valid, enc[..., 1], 0)
    bgr[..., 2] = np.where(valid, enc[..., 0], 0)
    return bgr


def encode_flow_png(flow: np.ndarray, valid: np.ndarray | None = None) -> bytes:
    """flow float (H, W, 2) pixels (u, v), valid bool (H, W) (default: finite) → KITTI flow PNG bytes.

    Values are clipped to the representable range ±512 px; invalid pixels are stored as (0, 0, 0).
    """
    return bytes(encode_png16(flow_png_array(flow, valid), "flow"))


def encode_png16(array: np.ndarray, name: str) -> memoryview:
    """A uint16 (H, W[, 3]) array (`flow_png_array`, `disp_png_array`) → the PNG's bytes, as a view of OpenCV's
    buffer (no copy: a large map's PNG is not held twice)."""
    ok, buf = cv2.imencode(".png", array)
    if not ok:
        raise ValueError(f"could not encode {name} as .png")
    return memoryview(buf).cast("B")


def decode_flow_png(data: bytes, path: str = "<bytes>") -> tuple[np.ndarray, np.ndarray]:
    """KITTI flow PNG bytes → (flow float32 (H, W, 2) pixels, valid bool (H, W)); invalid flow is 0."""
    check_image_bytes(data, path)
    bgr = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if bgr is None or bgr.ndim != 3 or bgr.shape[2] != 3 or bgr.dtype != np.uint16:
        raise CorruptImageError(path, "not a 16-bit 3-channel KITTI flow PNG")
    valid = bgr[..., 0] > 0
    flow = (np.stack([bgr[..., 2], bgr[..., 1]], -1).astype(np.float32) - 32768.0) / 64.0
    flow[~valid] = 0.0
    return flow, valid


def read_flow_png(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Reads a KITTI flow PNG → (flow float32 (H, W, 2) pixels (u, v), valid bool (H, W))."""
    return decode_flow_png(read_image_bytes(path), path)


def write_flow_png(path: str, flow: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Writes a KITTI flow PNG atomically (see `encode_flow_png`)."""
    files.write_bytes(path, encode_flow_png(flow, valid))


def disp_png_array(disp: np.ndarray, valid: np.ndarray | None = None) -> np.ndarray:
    """disp float (H, W) pixels ≥ 0, valid bool (default: finite and > 0) → the uint16 array of a KITTI disparity
    PNG (`encode_disp_png`); pixelwise."""
    disp = np.asarray(disp, np.float64)
    if disp.ndim != 2:
        raise ValueError(f"disparity must be (H, W), got {disp.shape}")
    if valid is None:
        valid = np.isfinite(disp) & (disp > 0)
    valid = np.asarray(valid, bool)
    enc = np.clip(np.rint(np.nan_to_num(disp) * 256.0), 1, 65535).astype(np.uint16)
    return np.where(valid, enc, 0).astype(np.uint16)


def encode_disp_png(disp: np.ndarray, valid: np.ndarray | None = None) -> bytes:
    """disp float (H, W) pixels ≥ 0, valid bool (default: finite and > 0) → KITTI disparity PNG bytes."""
    return bytes(encode_png16(disp_png_array(disp, valid), "disparity"))


def decode_disp_png(data: bytes, path: str = "<bytes>") -> tuple[np.ndarray, np.ndarray]:
    """KITTI disparity PNG bytes → (disp float32 (H, W) pixels, valid bool (H, W))."""
    check_image_bytes(data, path)
    img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    if img is None or img.ndim != 2 or img.dtype != np.uint16:
        raise CorruptImageError(path, "not a 16-bit 1-channel KITTI disparity PNG")
    return img.astype(np.float32) / 256.0, img > 0


def read_disp_png(path: str) -> tuple[np.ndarray, np.ndarray]:
    """Reads a KITTI disparity PNG → (disp float32 (H, W) pixels, valid bool (H, W)); invalid = 0."""
    return decode_disp_png(read_image_bytes(path), path)


def write_disp_png(path: str, disp: np.ndarray, valid: np.ndarray | None = None) -> None:
    """Writes a KITTI disparity PNG atomically (see `encode_disp_png`)."""
    files.write_bytes(path, encode_disp_png(disp, valid))


# ----------------------------------------------------------------------------------------------------------
# Calibration
# ----------------------------------------------------------------------------------------------------------

def read_calib_file(path: str) -> dict:
    """KITTI calibration text → {key: float64 array}; lines whose values are not all numbers are skipped."""
    out = {}
    try:
        with open(path) as fh:
            lines = fh.readlines()
    except OSError as e:
        raise ValueError(f"cannot read calibration file {path!r}: {e.strerror or e}") from None
    for line in lines:
        if ":" not in line:
            continue
        key, val = line.split(":", 1)
        try:
            out[key.strip()] = np.array([float(v) for v in val.split()], np.float64)
        except ValueError:
            continue
    return out


def focal_baseline(calib: dict, cams: tuple[int, int] = (2, 3), path: str = "calibration") -> tuple[float, float]:
    """(focal px, baseline m) of the rectified pair `cams` from P_rect_0X (raw / 2015) or PX (2012) matrices.

    focal = P_left[0, 0]; baseline = x-offset(right) − x-offset(left), x-offset = −P[0, 3] / P[0, 0].
    """
    mats = []
    for c in cams:
        for key in (f"P_rect_{c:02d}", f"P{c}"):
            if key in calib and calib[key].size == 12:
                mats.append(calib[key].reshape(3, 4))
                break
        else:
            raise ValueError(f"{path}: no P_rect_{c:02d} / P{c} projection matrix (keys: {sorted(calib)})")
    pl, pr = mats
    return float(pl[0, 0]), float(-pr[0, 3] / pr[0, 0] + pl[0, 3] / pl[0, 0])


def raw_calib_path(date_dir: str) -> str:
    return os.path.join(date_dir, "calib_cam_to_cam.txt")


# ----------------------------------------------------------------------------------------------------------
# KITTI raw drives
# ----------------------------------------------------------------------------------------------------------

_DRIVE_RE = re.compile(r"^(\d{4}_\d\d_\d\d)_drive_(\d{4})_sync$")
_ID_RE = re.compile(r"(\d{4}_\d\d_\d\d_drive_\d{4})(?:_sync)?(?:/image_0[23]/data/|\s+)(\d+)")


def find_raw_drives(root: str) -> list[str]:
    """Drive folders (…/<date>_drive_NNNN_sync) under a KITTI raw root, a date folder, or the drive itself."""
    root = os.path.abspath(root)
    if _DRIVE_RE.match(os.path.basename(root)):
        return [root]
    found = []
    for d1 in sorted(os.listdir(root)) if os.path.isdir(root) else []:
        p1 = os.path.join(root, d1)
        if _DRIVE_RE.match(d1) and os.path.isdir(p1):
            found.append(p1)
        elif os.path.isdir(p1):
            for d2 in sorted(os.listdir(p1)):
                p2 = os.path.join(p1, d2)
                if _DRIVE_RE.match(d2) and os.path.isdir(p2):
                    found.append(p2)
    return found


def drive_name(drive_dir: str) -> str:
    """'2011_09_26_drive_0001' for …/2011_09_26_drive_0001_sync."""
    return os.path.basename(os.path.normpath(drive_dir))[: -len("_sync")]


def _list_images(folder: str) -> dict:
    """{stem: filename} of the images in a folder (empty if missing)."""
    try:
        names = os.listdir(folder)
    except OSError:
        return {}
    return {os.path.splitext(n)[0]: n for n in names if n.lower().endswith(IMAGE_EXTS)}


def raw_drive_frames(drive_dir: str) -> dict:
    """{frame index: (left path, right path)} for frames present in both image_02/data and image_03/data."""
    d2, d3 = (os.path.join(drive_dir, f"image_0{c}", "data") for c in (2, 3))
    left, right = _list_images(d2), _list_images(d3)
    out = {}
    for stem in left.keys() & right.keys():
        if stem.isdigit():
            out[int(stem)] = (os.path.join(d2, left[stem]), os.path.join(d3, right[stem]))
    return out


def _cycle_record(drive_dir: str, frames: dict, k: int) -> dict:
    (l0, r0), (l1, r1) = frames[k], frames[k + 1]
    return {"id": f"{drive_name(drive_dir)}/{k:010d}", "paths": (l0, r0, l1, r1),
            "calib": raw_calib_path(os.path.dirname(drive_dir))}


def read_split_ids(name_or_path: str) -> list[tuple[str, int]]:
    """(drive, frame) pairs of a split file: a name in bridge_jax/data/splits/ ("eigen_train_cycles_8000") or a
    path. Accepted line formats: 'DRIVE FRAME', or any line containing
    '<date>_drive_NNNN_sync/image_02/data/<frame>.<ext>' (upstream / Monodepth list files: the first such path
    on the line is the cycle's left_t)."""
    path = name_or_path
    if not os.path.exists(path):
        path = os.path.join(SPLITS_DIR, name_or_path + ("" if name_or_path.endswith(".txt") else ".txt"))
    if not os.path.exists(path):
        raise ValueError(f"split {name_or_path!r}: no such file (nor in {SPLITS_DIR})")
    ids = []
    with open(path) as fh:
        for ln, line in enumerate(fh, 1):
            if not line.strip() or line.lstrip().startswith("#"):
                continue
            m = _ID_RE.search(line)
            if not m:
                raise ValueError(f"{path}:{ln}: cannot parse a drive and frame from {line.strip()!r}")
            ids.append((m.group(1), int(m.group(2))))
    return ids


def kitti_split_ids() -> list[tuple[str, int]]:
    """The KITTI-split training cycles (drive, first frame): 28,968 when all 32 drives are complete.

    Rule: every frame k of the 32 drives in kitti_split_drives_32.txt (drive, number of frames) whose successor
    k+1 exists, minus the 1,159 frames held out for validation (kitti_split_holdout_1159.txt). Both files derive
    from Monodepth's kitti_train/val lists (splits/README.md); the 29 excluded raw drives contain the KITTI
    2015 training scenes.
    """
    holdout = set(read_split_ids("kitti_split_holdout_1159"))
    ids = []
    with open(os.path.join(SPLITS_DIR, "kitti_split_drives_32.txt")) as fh:
        for line in fh:
            drive, n = line.split()
            ids.extend((drive, k) for k in range(int(n) - 1) if (drive, k) not in holdout)
    return ids


def raw_cycles(root: str, split: str = "all") -> list[dict]:
    """Consecutive-frame cycles of a KITTI raw folder.

    split: "all" (every (k, k+1) of every drive found), "kitti" (`kitti_split_ids`), "eigen" (the 8,000 Eigen
    training cycles of the paper), or a split/list file (see `read_split_ids`).
    Returns records {"id": "<drive>/<frame:010d>", "paths": (left_t, right_t, left_t1, right_t1),
    "calib": path of calib_cam_to_cam.txt}. Listed cycles whose images are absent are dropped with one warning.
    Raises ValueError (naming the folder and the expected layout) when no cycle is found.
    """
    drives = find_raw_drives(root)
    if not drives:
        raise ValueError(f"no KITTI raw drives found in {root!r}; expected {RAW_LAYOUT}")
    by_name = {drive_name(d): d for d in drives}
    frames_cache: dict = {}

    def frames_of(name):
        if name not in frames_cache:
            frames_cache[name] = raw_drive_frames(by_name[name])
        return frames_cache[name]

    records = []
    if split == "all":
        for name in sorted(by_name):
            fr = frames_of(name)
            records.extend(_cycle_record(by_name[name], fr, k) for k in sorted(fr) if k + 1 in fr)
        wanted = len(records)
    else:
        if split == "kitti":
            ids = kitti_split_ids()
        elif split == "eigen":
            ids = read_split_ids("eigen_train_cycles_8000")
        else:
            ids = read_split_ids(split)
        wanted = len(ids)
        for name, k in ids:
            if name in by_name:
                fr = frames_of(name)
                if k in fr and k + 1 in fr:
                    records.append(_cycle_record(by_name[name], fr, k))
        if len(records) < wanted:
            log.warning("split %r: %d of %d listed cycles are missing in %s (drive or images absent); using %d",
                        split, wanted - len(records), wanted, root, len(records))
    if not records:
        raise ValueError(f"no usable cycles (split {split!r}) in {root!r}; expected {RAW_LAYOUT}")
    return records


# ----------------------------------------------------------------------------------------------------------
# Eigen split evaluation: Velodyne ground truth
# ----------------------------------------------------------------------------------------------------------

def eigen_test_ids() -> list[tuple[str, int]]:
    """The 697 Eigen test frames (drive, frame), in the standard (Monodepth eigen_test_files) order."""
    return read_split_ids("eigen_test_697")


def eigen_test_samples(root: str) -> list[dict]:
    """Eigen test samples of a KITTI raw root: {"id", "left", "right", "velo", "calib_dir"} in list order.
    Missing frames raise ValueError listing how many and the first one."""
    drives = {drive_name(d): d for d in find_raw_drives(root)}
    out, missing = [], []
    for name, k in eigen_test_ids():
        d = drives.get(name)
        fr = raw_drive_frames(d) if d else {}
        velo = os.path.join(d, "velodyne_points", "data", f"{k:010d}.bin") if d else ""
        if k not in fr or not os.path.exists(velo):
            missing.append(f"{name}/{k:010d}")
            continue
        out.append({"id": f"{name}/{k:010d}", "left": fr[k][0], "right": fr[k][1], "velo": velo,
                    "calib_dir": os.path.dirname(d)})
    if missing:
        raise ValueError(f"{len(missing)} of 697 Eigen test frames missing under {root!r} (first: {missing[0]}); "
                         f"expected {RAW_LAYOUT} plus velodyne_points/data/*.bin")
    return out


def load_velodyne_points(path: str) -> np.ndarray:
    """KITTI Velodyne scan (.bin, float32 x, y, z, reflectance) → (N, 4) float32."""
    data = np.fromfile(path, dtype=np.float32)
    if data.size % 4:
        raise CorruptImageError(path, "Velodyne file size is not a multiple of 4 floats")
    return data.reshape(-1, 4)


def velodyne_depth_map(calib_dir: str, velo_path: str, shape: tuple[int, int], cam: int = 2,
                       vel_depth: bool = True) -> np.ndarray:
    """Sparse GT depth (H, W) float32 in metres (0 = no point) from a Velodyne scan (Eigen-split convention).

    Projects with P_rect_0{cam} · R_rect_00 · [R|T]_velo→cam, drops points behind the LiDAR (x_velo < 0), rounds
    pixel coordinates and subtracts 1 (MATLAB devkit convention), keeps points inside the image and the minimum
    depth where several land on one pixel. The stored depth is the LiDAR x coordinate when `vel_depth` (the
    legacy Eigen/Monodepth convention), else the camera z.
    """
    c2c = read_calib_file(os.path.join(calib_dir, "calib_cam_to_cam.txt"))
    v2c = read_calib_file(os.path.join(calib_dir, "calib_velo_to_cam.txt"))
    velo2cam = np.eye(4)
    velo2cam[:3, :3] = v2c["R"].reshape(3, 3)
    velo2cam[:3, 3] = v2c["T"]
    rect = np.eye(4)
    rect[:3, :3] = c2c["R_rect_00"].reshape(3, 3)
    proj = c2c[f"P_rect_{cam:02d}"].reshape(3, 4) @ rect @ velo2cam
    velo = load_velodyne_points(velo_path).astype(np.float64)
    velo = velo[velo[:, 0] >= 0]
    pts = np.concatenate([velo[:, :3], np.ones((len(velo), 1))], 1) @ proj.T
    z = pts[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        x = np.round(pts[:, 0] / z) - 1
        y = np.round(pts[:, 1] / z) - 1
    depth_val = velo[:, 0] if vel_depth else z
    h, w = shape
    ok = (x >= 0) & (y >= 0) & (x < w) & (y < h) & np.isfinite(x) & np.isfinite(y)
    depth = np.full(h * w, np.inf)
    np.minimum.at(depth, (y[ok] * w + x[ok]).astype(np.int64), depth_val[ok])
    depth[~np.isfinite(depth) | (depth < 0)] = 0.0
    return depth.reshape(h, w).astype(np.float32)


def raw_focal_baseline(calib_dir: str) -> tuple[float, float]:
    """(focal px, baseline m) of cameras 2/3 from <date>/calib_cam_to_cam.txt."""
    path = raw_calib_path(calib_dir)
    return focal_baseline(read_calib_file(path), (2, 3), path)
