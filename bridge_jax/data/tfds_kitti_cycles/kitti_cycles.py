"""`kitti_cycles` dataset builder (ArrayRecord; building and reading need no TensorFlow).

manual_dir = a KITTI raw folder (ROOT/<date>/<date>_drive_NNNN_sync/image_02|03/data/*.png + calib files).
Configs select the cycles: "all" (every consecutive frame pair), "kitti" (the KITTI split, 28,968 cycles with the
full raw data), "eigen" (the 8,000 Eigen training cycles). One split, "train".

Features of each example:
  id        text  "<drive>/<frame:010d>" (frame of left_t)
  left_t, right_t, left_t1, right_t1   bytes: the frames' encoded files, copied verbatim (PNG for KITTI raw;
            JPEG if the raw folder was converted to JPEG), decoded with OpenCV by `decode_example`
  focal     float32  pixels (P_rect_02[0,0] of the drive's calib_cam_to_cam.txt; 0 if absent)
  baseline  float32  metres (from P_rect_02 / P_rect_03; 0 if absent)
Cycles with a missing/truncated image are left out at build time (logged and counted).
"""
from __future__ import annotations

import logging
import os

import numpy as np
import tensorflow_datasets as tfds
from etils import epath
from tensorflow_datasets.core import utils as tfds_utils

from bridge_jax.data import kitti

log = logging.getLogger(__name__)
FRAMES = ("left_t", "right_t", "left_t1", "right_t1")


class KittiCycles(tfds.core.GeneratorBasedBuilder):
    """KITTI raw stereo-video cycles (L_t, R_t, L_t+1, R_t+1) with calibration."""

    VERSION = tfds.core.Version("1.0.0")
    RELEASE_NOTES = {"1.0.0": "Initial release."}
    BUILDER_CONFIGS = [
        tfds.core.BuilderConfig(name="all", description="every consecutive frame pair of every drive"),
        tfds.core.BuilderConfig(name="kitti", description="KITTI split (raw drives minus the KITTI 2015 scenes)"),
        tfds.core.BuilderConfig(name="eigen", description="the 8,000 Eigen-split training cycles"),
    ]
    MANUAL_DOWNLOAD_INSTRUCTIONS = (
        "Download the KITTI raw data (synced+rectified drives and the per-date calibration zips) from "
        "https://www.cvlibs.net/datasets/kitti/raw_data.php, unzip into one folder and pass it as manual_dir. "
        "Expected: " + kitti.RAW_LAYOUT)

    # tfds derives this from the package via importlib_resources (an optional dependency that is not
    # installed); give it directly.
    @tfds_utils.classproperty
    @classmethod
    def code_path(cls) -> epath.Path:
        return epath.Path(__file__)

    def _info(self) -> tfds.core.DatasetInfo:
        feats = {"id": tfds.features.Text(),
                 "focal": tfds.features.Scalar(dtype=np.float32),
                 "baseline": tfds.features.Scalar(dtype=np.float32)}
        for f in FRAMES:
            feats[f] = tfds.features.Tensor(shape=(), dtype=np.object_)
        return tfds.core.DatasetInfo(builder=self, features=tfds.features.FeaturesDict(feats),
                                     description=__doc__, homepage="https://www.cvlibs.net/datasets/kitti/raw_data.php")

    def _split_generators(self, dl_manager):
        root = str(dl_manager.manual_dir)
        records = kitti.raw_cycles(root, self.builder_config.name)
        return {"train": self._generate_examples(records)}

    def _generate_examples(self, records):
        calib_cache: dict = {}
        skipped = 0
        for rec in records:
            try:
                blobs = []
                for p in rec["paths"]:
                    data = kitti.read_image_bytes(p)
                    kitti.check_image_bytes(data, p)
                    blobs.append(data)
            except kitti.CorruptImageError as e:
                skipped += 1
                log.warning("kitti_cycles: leaving out cycle %s: %s (%d so far)", rec["id"], e, skipped)
                continue
            cal = rec.get("calib")
            if cal not in calib_cache:
                try:
                    calib_cache[cal] = kitti.focal_baseline(kitti.read_calib_file(cal), (2, 3), cal)
                except (ValueError, TypeError):
                    calib_cache[cal] = (0.0, 0.0)
            focal, baseline = calib_cache[cal]
            ex = {"id": rec["id"], "focal": np.float32(focal), "baseline": np.float32(baseline)}
            ex.update(zip(FRAMES, blobs))
            yield rec["id"], ex


def build(manual_dir: str, data_dir: str, config: str = "all") -> str:
    """Builds `kitti_cycles/<config>` from a KITTI raw folder into `data_dir`; returns the dataset folder."""
    if not os.path.isdir(manual_dir):
        raise ValueError(f"manual_dir {manual_dir!r} does not exist; expected {kitti.RAW_LAYOUT}")
    builder = KittiCycles(config=config, data_dir=data_dir, file_format="array_record")
    builder.download_and_prepare(download_config=tfds.download.DownloadConfig(manual_dir=manual_dir))
    return str(builder.data_dir)


def open_data_source(data_dir: str, config: str = "all", split: str = "train"):
    """Random-access source (len / __getitem__) of the built dataset, via tfds.data_source (no TensorFlow)."""
    try:
        return tfds.data_source(f"kitti_cycles/{config}", data_dir=data_dir, split=split)
    except Exception as e:  # tfds raises several types (DatasetNotFoundError, AssertionError, ...)
        raise ValueError(f"cannot open TFDS dataset kitti_cycles/{config} in {data_dir!r} ({e.__class__.__name__}: "
                         f"{e}); build it with bridge_jax.data.tfds_kitti_cycles.build(manual_dir, data_dir, "
                         f"{config!r})") from None


def decode_example(example: dict) -> dict:
    """A stored example → {"cycle": uint8 (4, H, W, 3), "id": str, "focal": float, "baseline": float}.
    Undecodable bytes raise kitti.CorruptImageError (the pipeline then skips to the next cycle)."""
    cid = example["id"].decode() if isinstance(example["id"], bytes) else str(example["id"])
    frames = [kitti.decode_image(example[f], f"{cid}:{f}") for f in FRAMES]
    if len({f.shape for f in frames}) != 1:
        raise kitti.CorruptImageError(f"{cid}", "the 4 frames differ in size")
    return {"cycle": np.stack(frames), "id": cid, "focal": float(example["focal"]),
            "baseline": float(example["baseline"])}
