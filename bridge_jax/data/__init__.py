"""Data: cycle sources, KITTI formats and the grain input pipeline.

A *cycle* is uint8 (4, H, W, 3) on disk / in sources and float32 [0, 1] after the pipeline, frames ordered
(left_t, right_t, left_t1, right_t1) as `bridge_jax.cycle.FRAMES`.

  synthetic          procedural stereo video with exact GT: render_sample, SyntheticCycles, write_kitti_layout,
                     CLI `bridge-synthetic --out DIR --num N --seed S`
  kitti              flow / disparity PNGs, calibration, KITTI 2012/2015 layouts, raw drives, splits, Velodyne GT
  folders            own stereo video (left/ + right/ folders, or KITTI raw) → cycles
  pipeline           DataConfig, make_train_dataset (grain), augmentation, resize, shard_batch
  tfds_kitti_cycles  TFDS builder (ArrayRecord) of KITTI raw cycles, readable without TensorFlow
  splits/            KITTI split / Eigen split id lists (see splits/README.md)
"""
