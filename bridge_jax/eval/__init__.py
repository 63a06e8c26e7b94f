"""Evaluation building blocks, used by `bridge-evaluate`, `predict` and training's validation.

  datasets   frames and ground truth: KITTI 2015 / 2012, Eigen (Velodyne), synthetic (folder or in memory)
  methods    frames -> predictions: the model (through `bridge_jax.inference.Predictor`), disp_1, occlusion
  baselines  zero motion, OpenCV StereoSGBM (disparity) and DIS (flow)
  scoring    per-frame metric sums by task, accumulated per method
  report     Markdown tables, picture panels, the results folder
"""
