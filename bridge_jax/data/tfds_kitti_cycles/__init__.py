"""TFDS builder `kitti_cycles`: KITTI raw stereo-video cycles as ArrayRecord, readable without TensorFlow.

    from bridge_jax.data import tfds_kitti_cycles
    tfds_kitti_cycles.build(manual_dir="/data/kitti_raw", data_dir="/data/tfds", config="kitti")
    src = tfds_kitti_cycles.open_data_source("/data/tfds", "kitti")      # tfds.data_source, random access
    record = tfds_kitti_cycles.decode_example(src[0])                   # {"cycle": uint8 (4,H,W,3), "id", ...}

or in training: data.source = "tfds", data.data_dir = "/data/tfds", data.split = "kitti".
"""
from bridge_jax.data.tfds_kitti_cycles.kitti_cycles import (  # noqa: F401
    KittiCycles, build, decode_example, open_data_source)
