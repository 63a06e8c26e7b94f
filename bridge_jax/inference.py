"""Run a trained network on your own images: the library's entry point.

    from bridge_jax.inference import load_predictor
    pred = load_predictor("demo")                                   # the shipped model, or a checkpoint path
    flow = pred.predict_pair(frame_t, frame_t1)                     # (h, w, 2) pixels, uint8 or float images
    disp = pred.predict_pair(left, right, task="stereo")            # (h, w) disparity in pixels
    out = pred.predict_cycle(left_t, right_t, left_t1, right_t1)   # disp_t, disp_t1 (h, w), flow (h, w, 2)
    flow, conf, occ = pred.predict_pair(frame_t, frame_t1, confidence=True, occlusion=True)   # + (h, w) maps

What this module gathers lives in one file per job:

* `bridge_jax.resizing`: image conversion, resizing to the working size and back (the paper's evaluation
  protocol), the size rules and the one working-size value `WorkingSize`;
* `bridge_jax.testtime`: the one test-time record `TestTime(refine, symmetry, polish)`;
* `bridge_jax.stages`: the test-time stages and their one composition (`predicted_maps`), which both
  `Predictor` and `bridge_jax.export` run;
* `bridge_jax.predictor`: `Predictor` and `load_predictor`;
* `bridge_jax.confidence`: confidence and occlusion maps from the forward-backward and left-right checks.

A shipped model's card may recommend a working size and a `TestTime` (`zoo.card_working_size`,
`zoo.card_test_time`); `load_predictor` uses them unless told otherwise.
"""
from __future__ import annotations

from bridge_jax.cycle import TASKS, check_task
from bridge_jax.polish import PolishConfig
from bridge_jax.predictor import (COMPILE_MODES, FAST_COMPILE_PAIRS, Predictor, compile_mode_for, load_predictor,
                                  resize_notice, resolve_working_size, trained_working_size)
from bridge_jax.resizing import (DEFAULT_HEIGHT, DEFAULT_WIDTH, DEFAULT_WORKING_SIZE, MAX_UPSAMPLING, NATIVE,
                                 NATIVE_MAX_PIXELS, REDUCED_READ_NOTICE, TRAINED, WorkingSize,
                                 disparity_to_input_resolution, flow_to_input_resolution, input_size,
                                 map_to_input_resolution, minimum_input_size, native_working_size, resize_images,
                                 resize_weights_align_corners, resize_weights_antialias, to_rgb_float)
from bridge_jax.stages import flow_rows, network_maps, predicted_maps, refine_maps, symmetric_maps
from bridge_jax.testtime import MAX_REFINE, POLISH_MODES, SYMMETRY_MODES, TestTime

__all__ = ["Predictor", "load_predictor", "TestTime", "WorkingSize", "PolishConfig", "resolve_working_size",
           "trained_working_size", "native_working_size", "NATIVE", "TRAINED", "resize_notice", "to_rgb_float",
           "resize_images", "COMPILE_MODES", "FAST_COMPILE_PAIRS", "compile_mode_for", "flow_to_input_resolution",
           "disparity_to_input_resolution", "map_to_input_resolution", "TASKS", "check_task", "input_size",
           "minimum_input_size", "MAX_UPSAMPLING", "SYMMETRY_MODES", "POLISH_MODES", "MAX_REFINE",
           "symmetric_maps", "refine_maps", "network_maps", "predicted_maps", "flow_rows", "DEFAULT_HEIGHT",
           "DEFAULT_WIDTH", "DEFAULT_WORKING_SIZE", "NATIVE_MAX_PIXELS", "REDUCED_READ_NOTICE",
           "resize_weights_align_corners", "resize_weights_antialias"]
