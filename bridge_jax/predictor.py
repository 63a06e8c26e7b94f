"""The one predictor of bridge_jax: a network bound to its params, a working size and its test-time stages.

    pred = load_predictor("demo")                                    # or a checkpoint path
    pred = load_predictor("long", test_time={"refine": 0})           # the card's settings, one of them replaced
    pred = load_predictor(ckpt, size=WorkingSize(128, 256), test_time=TestTime(symmetry="flips"))

Training's validation, `evaluate`, `predict`, `export` and the library all go through `Predictor`, so they
resize, batch and rescale the same way (`bridge_jax.resizing`) and run the same stages (`bridge_jax.stages`).
The network runs once per pair (`run_network`), compiled once per working size, batch size, tasks and test-time
record; resizing runs in numpy, so new input sizes never recompile it. Parameters stay float32;
`dtype="bfloat16"` only changes the compute dtype.
"""
from __future__ import annotations

import copy
import json
import os
from collections.abc import Mapping, Sequence
from typing import Any, Callable, Optional

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import NamedSharding, PartitionSpec as P

from bridge_jax import checkpointing, compile_cache, executable_cache, memory, models, stages, zoo
from bridge_jax import confidence as checks
from bridge_jax.cycle import check_task
from bridge_jax.network import Network, check_separate_params, compute_dtype
from bridge_jax.polish import DEFAULT_CONFIG, PolishConfig, config_for_rows
from bridge_jax.resizing import (DEFAULT_HEIGHT, DEFAULT_WIDTH, DEFAULT_WORKING_SIZE, NATIVE, NATIVE_MAX_PIXELS,
                                 REDUCED_READ_NOTICE, TRAINED, WorkingSize, flow_to_input_resolution,
                                 input_size, map_to_input_resolution, map_to_size, minimum_input_size,
                                 native_working_size, resize_images, to_rgb_float)
from bridge_jax.testtime import TestTime

COMPILE_MODES = ("auto", "fast", "full")
"""How the network is compiled. "full": XLA's default optimisation. "fast": the LLVM back end at optimisation
level 0 (`xla_backend_optimization_level=0`): quicker to compile, slower per call, so a few pairs answer sooner
"fast", long runs sooner "full". "auto": `compile_mode_for`. The polish is compiled at full optimisation
whatever the mode (`stages.POLISH_APART`)."""
FAST_COMPILE_PAIRS = 64
"""`compile_mode_for("auto", n)`: runs of at most this many pairs per working size compile "fast" (up to about
this many pairs, the compile time "fast" saves pays for its slower calls)."""


def compile_mode_for(mode: str, num_pairs: Optional[int]) -> str:
    """"fast" or "full" for a run of `num_pairs` pairs (None = unknown) under `mode` (one of `COMPILE_MODES`;
    "auto" = "fast" up to `FAST_COMPILE_PAIRS` pairs, else "full")."""
    if mode not in COMPILE_MODES:
        raise ValueError(f"compile mode {mode!r}: expected one of {', '.join(COMPILE_MODES)}")
    if mode != "auto":
        return mode
    return "fast" if num_pairs is not None and num_pairs <= FAST_COMPILE_PAIRS else "full"


class Predictor:
    """A network bound to its params, a working size and its test-time stages, numpy in and numpy out.

    Args:
      graphdef, params: from `bridge_jax.models.init` or a checkpoint. With `separate=True`, params is
        `{"stereo": ..., "flow": ...}` (two networks; stereo pairs use the first, flow pairs the second).
      size: the `WorkingSize` (default 256 x 512, the paper's); height and width are multiples of the model's
        input multiple.
      test_time: the `TestTime` stages (default: none); settable later through the `test_time` attribute (each
        record compiles once).
      polish_config: the polish's parameters (`polish.PolishConfig`; each config compiles once).
      dtype: compute dtype, None/"float32" or "bfloat16" (params stay float32).
      model_cfg: the model config (for the input-size multiple and for export metadata).
      mesh: optional 1-D device mesh; pairs are then sharded over it (padded to a multiple of its size) and the
        maps come back replicated (training's validation runs on the training mesh). Default: one device.
      compile_mode: "full" (default) or "fast" (`COMPILE_MODES`), or "auto" = "full"; settable later through the
        `compile_mode` attribute (`compile_mode_for` picks one for a run whose number of pairs is known).
      executable_cache: a folder (the commands pass the compilation cache's) where each compiled program is kept
        whole (`bridge_jax.executable_cache`), so that a later process with the same code, model and shapes loads
        it without tracing or lowering; None (default) = off. Needs `model_cfg`; one device only.
    Attributes:
      trace_count: how many times the network function was traced (== compiled) so far.
      check: the `TestTime` stages the backward maps of a confidence check run with (`predict(...,
        confidence=True)`); None (default) = `confidence.default_check(test_time)`.
    """

    size = WorkingSize()
    test_time = TestTime()
    check: Optional[TestTime] = None
    polish_config = DEFAULT_CONFIG
    model_name = "resnet_md"

    def __init__(self, graphdef, params, *, size: Optional[WorkingSize] = None, test_time: Optional[TestTime] = None,
                 polish_config: PolishConfig = DEFAULT_CONFIG, dtype: Any = None, model_cfg: Optional[dict] = None,
                 separate: bool = False, mesh=None, compile_mode: str = "full",
                 executable_cache: Optional[str] = None):
        self.test_time = test_time or TestTime()
        self.polish_config = polish_config
        self.executable_cache = executable_cache
        self._kept: dict[tuple, Callable] = {}  # key -> kept compiled program (`_kept_program`)
        self.model_cfg = dict(model_cfg) if model_cfg else None
        self.model_name = (model_cfg or {}).get("name", "resnet_md")
        self.size = size or WorkingSize()
        models.check_working_size(self.model_name, self.size.height, self.size.width)
        check_separate_params(params, separate)
        self.net = Network(graphdef, separate=separate, dtype=compute_dtype(dtype))
        self.graphdef, self.separate, self.dtype = graphdef, separate, self.net.dtype
        self.mesh = mesh
        self.trace_count = 0
        self.compile_mode = compile_mode_for(compile_mode, None)
        self._jits: dict[str, Callable] = {}  # compile mode -> jitted network (each keeps its own executables)
        if mesh is None:
            self.params = jax.device_put(params)
        else:
            self._pairs_sharding = NamedSharding(mesh, P(mesh.axis_names[0]))
            self.params = params

    # the working size and the test-time stages, read one by one
    height = property(lambda self: self.size.height)
    width = property(lambda self: self.size.width)
    native = property(lambda self: self.size.native)
    max_pixels = property(lambda self: self.size.max_pixels)
    refine = property(lambda self: self.test_time.refine)
    symmetry = property(lambda self: self.test_time.symmetry)
    polish = property(lambda self: self.test_time.polish)

    @property
    def _net(self):
        """The jitted network program (`stages.network_maps`) for the current `compile_mode`."""
        fn = self._jits.get(self.compile_mode)
        if fn is None:
            options = {"xla_backend_optimization_level": 0} if self.compile_mode == "fast" else None
            shardings = {} if self.mesh is None else {"out_shardings": NamedSharding(self.mesh, P())}
            fn = self._jits[self.compile_mode] = jax.jit(self._network_maps, static_argnums=_NETWORK_STATIC,
                                                         compiler_options=options, **shardings)
        return fn

    def _network_maps(self, params, pairs, tasks, flow_rows, test_time):
        self.trace_count += 1  # Python side effect: runs once per trace
        return stages.network_maps(self.net, params, pairs, tasks, flow_rows, test_time)

    def with_params(self, params) -> "Predictor":
        """The same predictor (and compiled function) with other params, e.g. a training state's."""
        other = copy.copy(self)
        other.params = params  # the shallow copy shares `_jits`: the compiled functions do not depend on the values
        return other

    def forward(self, pairs: jax.Array, tasks: Sequence[str], polish: bool = True) -> jax.Array:
        """The compiled stages on device arrays: `(N, H, W, 6)` -> `(N, H, W, 2)` working-size pixel maps (N a
        multiple of the mesh size); `tasks` the task of each row ("flow" / "stereo"). `polish=False` leaves out
        the polish (`stage_maps` then runs it at the input size)."""
        flows = stages.flow_rows(tasks)
        static = self.net.static_tasks([check_task(t) for t in tasks])
        args = (self.params, pairs, static, flows, self.test_time.network_part)
        polish_program = self._polish_program if stages.POLISH_APART else None
        test_time = self.test_time if polish else self.test_time.network_part
        return stages.predicted_maps(pairs, flows, test_time, lambda x: self._network_program(args)(*args),
                                     polish_program)

    def _kept_program(self, key: tuple, jitted: Callable, args: tuple, config: dict, static_argnums: tuple) -> Callable:
        """`jitted`, or with `executable_cache` the program compiled for `args`, loaded from that folder or
        compiled and kept there (`executable_cache.cached_compile`), once per `key` in this process."""
        if self.executable_cache is None or self.mesh is not None:
            return jitted
        key = key + (self.executable_cache,)
        fn = self._kept.get(key)
        if fn is None:
            fn = self._kept[key] = executable_cache.cached_compile(jitted, args, config=config,
                                                                   folder=self.executable_cache,
                                                                   static_argnums=static_argnums)
        return fn

    def _network_program(self, args: tuple) -> Callable:
        """The network program (stages 1-2) for `args` (`_NETWORK_STATIC` static), kept as `_kept_program` says."""
        if self.model_cfg is None:
            return self._net
        pairs, static, test_time = args[1], args[2], args[4]
        # What the network function closes over besides its arguments: the model, the compute dtype, one or two
        # networks and the compile options.
        config = {"program": "predictor", "model": self.model_cfg, "dtype": str(self.dtype),
                  "separate": self.separate, "compile_mode": self.compile_mode}
        key = ("network", self.compile_mode, tuple(pairs.shape), str(pairs.dtype), static, test_time)
        return self._kept_program(key, self._net, args, config, _NETWORK_STATIC)

    def _polish_program(self, pairs: jax.Array, maps: jax.Array, flow_rows: np.ndarray) -> jax.Array:
        """The polish program (stage 3) run on `maps`: compiled at full optimisation whatever `compile_mode`
        (`stages.POLISH_APART`), kept per shape, test-time record and `PolishConfig` (`_kept_program`)."""
        test_time = self.test_time.photometric_part  # the fill runs on the host (`fill_maps`)
        config = config_for_rows(self.polish_config, flow_rows)
        args = (pairs, maps, flow_rows, test_time, config)
        key = ("polish", tuple(pairs.shape), str(pairs.dtype), test_time, config)
        return self._kept_program(key, _POLISH_JIT, args, {"program": "polish"}, _POLISH_STATIC)(*args)

    def lower(self, batch: int, task: str = "flow"):
        """`jax.stages.Lowered` of the network program for `batch` pairs of `task` (compile time, cost and memory
        analysis), with its refinement passes and symmetry averaging and without the polish (its own program)."""
        spec = jax.ShapeDtypeStruct((batch, self.height, self.width, 6), jnp.float32)
        static = self.net.static_tasks([check_task(task)] * batch)
        return self._net.lower(self.params, spec, static, stages.flow_rows([task] * batch),
                               self.test_time.network_part)

    def run_network(self, pairs: np.ndarray, tasks: str | Sequence[str] = "flow", polish: bool = True) -> np.ndarray:
        """`(N, H, W, 6)` float32 working-size pairs -> `(N, H, W, 2)` pixel maps at the working size, through
        every test-time stage (the polish on these pairs, whatever `PolishConfig.resolution`; `polish=False`:
        without it).

        `tasks`: one task ("flow" / "stereo") for all rows, or one per row.
        """
        pairs = np.asarray(pairs, np.float32)
        n = pairs.shape[0]
        rows = (tasks,) * n if isinstance(tasks, str) else tuple(tasks)
        if self.mesh is None:
            x = jax.device_put(pairs)  # not jnp.asarray: that compiles a small program per new shape
        else:
            pad = (-n) % self.mesh.size
            if pad:
                pairs = np.concatenate([pairs, np.repeat(pairs[-1:], pad, 0)])
                rows = rows + (rows[-1],) * pad
            x = jax.make_array_from_callback(pairs.shape, self._pairs_sharding, lambda idx: pairs[idx])
        return np.asarray(self.forward(x, rows, polish))[:n]

    def working_size(self, height: int, width: int) -> tuple[int, int]:
        """(H, W) the network runs at for an input of `height x width` (`WorkingSize.for_input`)."""
        return self.size.for_input(self.model_name, height, width)

    def prepare(self, images_a: Sequence, images_b: Sequence) -> tuple[np.ndarray, tuple[int, int]]:
        """Validate, convert and resize N pairs -> (`(N, H, W, 6)` float32 at `working_size(h, w)`, (h, w) of
        the inputs)."""
        if len(images_a) != len(images_b) or len(images_a) == 0:
            raise ValueError(f"need the same, non-zero number of first and second images, got {len(images_a)} "
                             f"and {len(images_b)}")
        full = input_size(images_a[0])
        a = [to_rgb_float(x, f"image_a[{i}]") for i, x in enumerate(images_a)]
        b = [to_rgb_float(x, f"image_b[{i}]") for i, x in enumerate(images_b)]
        size = a[0].shape[:2]
        for i, img in enumerate(a + b):
            if img.shape[:2] != size:
                which = f"image_a[{i}]" if i < len(a) else f"image_b[{i - len(a)}]"
                raise ValueError(f"all images must have the same size: image_a[0] is {size[0]}x{size[1]}, "
                                 f"{which} is {img.shape[0]}x{img.shape[1]} (height x width)")
        low = minimum_input_size(self.model_name)
        if full[0] < low[0] or full[1] < low[1]:
            raise ValueError(f"a {full[0]}x{full[1]} input is smaller than model {self.model_name} accepts (at least "
                             f"{low[0]}x{low[1]} pixels, height x width)")
        pairs = np.concatenate([np.stack(a), np.stack(b)], axis=-1)
        return resize_images(pairs, *self.working_size(*full)), full

    def polish_size(self, image: Any) -> tuple[int, int]:
        """(H, W) the polish runs at for the pairs whose first image is `image`: the size of the image as given
        (for an image read at a reduced size, `predict.ImageReader`, the size it was read at, not the file's) or
        the working size (`PolishConfig.resolution`, `PolishConfig.size_for`); the working size when there is no
        photometric polish."""
        working = self.working_size(*input_size(image))
        if not self.test_time.photometric:
            return working
        return self.polish_config.size_for(working, tuple(np.shape(image)[:2]))

    def working_maps(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        """Working-size pixel maps `(H, W, 2)` of `jobs` = [(task, image a, image b), ...], a -> b, through the
        stages that run at the working size: all of them, but the polish of the jobs that `stage_maps` polishes
        at their input size (`polish_size`).

        The network is called on exactly `batch` pairs at a time (default: all jobs at once; the last call
        padded by repetition), so one compiled function serves a whole run; each pair is resized on its own,
        so images of different sizes can share a call (with `native`, pairs share a call when their working
        sizes agree). Separate networks get one call per task.
        """
        out: list[Optional[np.ndarray]] = [None] * len(jobs)
        tasks = [check_task(task) for task, _, _ in jobs]
        # one shared network: no need to split (and pad) by task; the rows still say their task (the stages' rule)
        groups = tasks if self.separate else ["flow"] * len(jobs)
        sizes = [self.working_size(*input_size(a)) for _, a, _ in jobs]
        here = [self.polish_size(a) == s for (_, a, _), s in zip(jobs, sizes)]
        keys = list(zip(groups, sizes, here))
        for kind in dict.fromkeys(keys):
            idx = [i for i, key in enumerate(keys) if key == kind]
            size = batch or len(idx)
            for start in range(0, len(idx), size):
                chunk = idx[start:start + size]
                pairs = np.concatenate([self.prepare([jobs[i][1]], [jobs[i][2]])[0] for i in chunk])
                rows = [tasks[i] for i in chunk]
                if len(chunk) < size:
                    pairs = np.concatenate([pairs, np.repeat(pairs[-1:], size - len(chunk), 0)])
                    rows += rows[-1:] * (size - len(chunk))
                for i, m in zip(chunk, self.run_network(pairs, rows, polish=kind[2])):
                    out[i] = m
        return out  # type: ignore[return-value]

    def stage_maps(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        """The pixel maps `(H, W, 2)` of `jobs` after every test-time stage, each at the size its polish ran at
        (`polish_size`): `working_maps`, then for the jobs polished at the size of their images, the map brought to
        that size (`map_to_input_resolution`'s rule: a stereo map's disparity as the prediction gets it) and
        polished there against the images as given, `batch` pairs of one size at a time (padded by repetition)."""
        maps = self.working_maps(jobs, batch)
        polish_sizes = [self.polish_size(a) for _, a, _ in jobs]
        todo = [i for i, (m, size) in enumerate(zip(maps, polish_sizes)) if m.shape[:2] != size]
        sizes = [polish_sizes[i] for i in todo]
        for size in dict.fromkeys(sizes):
            idx = [i for i, s in zip(todo, sizes) if s == size]
            step = batch or len(idx)
            for start in range(0, len(idx), step):
                chunk = idx[start:start + step]
                chunk = chunk + chunk[-1:] * (step - len(chunk))
                pairs = np.stack([np.concatenate([to_rgb_float(jobs[i][1]), to_rgb_float(jobs[i][2])], -1)
                                  for i in chunk])
                rows = stages.flow_rows([jobs[i][0] for i in chunk])
                up = np.stack([map_to_size(check_task(jobs[i][0]), maps[i], *size) for i in chunk])
                polished = np.asarray(self._polish_program(jax.device_put(pairs), jax.device_put(up), rows))
                for i, m in zip(chunk, polished):
                    maps[i] = m
        return maps

    def predict(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None, *,
                confidence: bool = False) -> list:
        """Predictions of `jobs` = [(task, image a, image b), ...] at each pair's input size: flow `(h, w, 2)`
        for "flow" jobs, disparity `(h, w)` for "stereo" jobs (`resizing.map_to_input_resolution`); `batch` as
        in `working_maps`.

        With `confidence`, each job's entry is `(prediction, confidence (h, w) float32 in [0, 1], occlusion
        (h, w) bool)` from the consistency check of `bridge_jax.confidence` (forward-backward for flow,
        left-right for disparity): the jobs' backward maps are predicted too, with the stages of `check`
        (`confidence.default_check` of `test_time` when None), in the same batches when those are the same.

        When the polish has its fill step (`testtime.POLISH_STEPS`), each job's reverse pair is predicted too,
        with this predictor's own stages, and the map is filled where the left-right (disparity) or
        forward-backward (flow) check fails (`fill_maps`); its confidence and occlusion are those of the check of
        the map before the fill (the filled pixels are the ones the check distrusted)."""
        jobs = [(check_task(task), a, b) for task, a, b in jobs]
        n, fill = len(jobs), self.fill_jobs(jobs)
        # reverse pairs run with this predictor's own stages, in the forward pairs' batches: every job's when the
        # check runs those stages too (shared by the check and the fill), else those the fill needs
        shared = confidence and self._check_record() == self.test_time
        reversed_jobs = jobs if shared else [jobs[i] for i in fill]
        maps = self.stage_maps(jobs + [checks.reverse_job(*job) for job in reversed_jobs], batch)
        forward, reverse = maps[:n], maps[n:]
        fill_reverse = [reverse[i] for i in fill] if shared else reverse
        if not confidence:
            out = [map_to_input_resolution(task, m, *input_size(a)) for (task, a, _), m in zip(jobs, forward)]
            return self.fill_maps(jobs, out, fill_reverse)
        rows = self.checked_predictions(jobs, forward, reverse if shared else self.backward_maps(jobs, batch))
        filled = self.fill_maps(jobs, [r[0] for r in rows], fill_reverse)
        return [(value, conf, occ) for value, (_, conf, occ) in zip(filled, rows)]

    def fill_jobs(self, jobs: Sequence[tuple[str, Any, Any]]) -> list[int]:
        """Indices of the `jobs` the polish's fill step changes: every job when `test_time.fill` (stereo and flow
        alike), else none."""
        return list(range(len(jobs))) if self.test_time.fill else []

    def fill_maps(self, jobs: Sequence[tuple[str, Any, Any]], predictions: list,
                  reverse_maps: Sequence[np.ndarray], indices: Optional[Sequence[int]] = None) -> list:
        """The polish's fill step (`testtime.POLISH_STEPS`): `predictions` (at the input resolution, one per
        job) with each stereo job's disparity passed through `confidence.left_right_fill` against the right
        view's disparity, and each flow job's flow through `confidence.forward_backward_fill` against the
        backward flow. `reverse_maps`: the `stage_maps` of the `fill_jobs` jobs' `confidence.reverse_job`
        pairs, in that order, predicted with this predictor's own stages (a check is sharp only between maps that
        went through the same stages); `indices`: the jobs they belong to when only some of the `fill_jobs` are
        filled. Other jobs come back as they are."""
        out = list(predictions)
        for i, reverse in zip(self.fill_jobs(jobs) if indices is None else indices, reverse_maps, strict=True):
            task, image_a, _ = jobs[i]
            task, (height, width) = check_task(task), input_size(image_a)
            reverse = map_to_input_resolution(task, reverse, height, width)
            if task == "stereo":
                out[i] = checks.left_right_fill(out[i], checks.right_view_disparity(reverse))[0]
            else:
                # the colour guide at the map's size (an image read at a reduced size is brought up to it)
                guide = resize_images(to_rgb_float(image_a), height, width)
                out[i] = checks.forward_backward_fill(out[i], reverse, guide)[0]
        return out

    def backward_maps(self, jobs: Sequence[tuple[str, Any, Any]], batch: Optional[int] = None) -> list[np.ndarray]:
        """`stage_maps` of the jobs' reverse pairs (`confidence.reverse_job`), run with the stages of
        `check` (`confidence.default_check(test_time)` when None); `batch` as in `working_maps`."""
        reverse = [checks.reverse_job(check_task(task), a, b) for task, a, b in jobs]
        own = self.test_time
        self.test_time = self._check_record()
        try:
            return self.stage_maps(reverse, batch)
        finally:
            self.test_time = own

    def checked_predictions(self, jobs: Sequence[tuple[str, Any, Any]], forward: Sequence[np.ndarray],
                            backward: Sequence[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
        """(prediction, confidence, occlusion) at each job's input size from its `forward` map (`stage_maps`)
        and the map of its reverse pair (`backward_maps`, run with `check`), by
        `confidence.checked_map` at the occlusion threshold of the check's mode (`confidence.check_mode`)."""
        threshold = checks.OCCLUSION_THRESHOLD[checks.check_mode(self._check_record(), self.test_time)]
        return [checks.checked_map(check_task(task), fw, bw, *input_size(a), threshold)
                for (task, a, _), fw, bw in zip(jobs, forward, backward)]

    def _check_record(self) -> TestTime:
        """The `TestTime` the backward maps of a check run with: `check`, else `confidence.default_check`."""
        return self.check or checks.default_check(self.test_time)

    def predict_pairs(self, images_a: Sequence, images_b: Sequence, task: str = "flow", *, confidence: bool = False,
                      occlusion: bool = False):
        """N pairs (sequences or `(N, h, w, C)` arrays of same-size images) -> predictions at the input
        resolution, by the task's rule (`map_to_input_resolution`): flow `(N, h, w, 2)` float32 pixels for
        "flow" pairs, disparity `(N, h, w)` float32 pixels for "stereo" pairs (as `predict` gives them).

        With `confidence` and/or `occlusion`: a tuple (predictions, [confidence `(N, h, w)` float32 in [0, 1],
        1 = trusted], [occlusion `(N, h, w)` bool, True = no visible match in the other image]), in that order
        (`predict(..., confidence=True)`)."""
        if confidence or occlusion:
            if len(images_a) != len(images_b):
                raise ValueError(f"need the same number of first and second images, got {len(images_a)} "
                                 f"and {len(images_b)}")
            rows = self.predict([(task, a, b) for a, b in zip(images_a, images_b)], len(images_a) or None,
                                confidence=True)
            if not rows:
                raise ValueError("need at least one pair")
            out = (np.stack([r[0] for r in rows]),)
            if confidence:
                out += (np.stack([r[1] for r in rows]),)
            if occlusion:
                out += (np.stack([r[2] for r in rows]),)
            return out
        pairs, (h, w) = self.prepare(images_a, images_b)  # validates, and names bad inputs
        if self.test_time.fill or self.polish_size(images_a[0]) != pairs.shape[1:3]:
            # the fill predicts the reverse pairs too, the polish at the input size needs the images as given
            return np.stack(self.predict([(task, a, b) for a, b in zip(images_a, images_b)], len(images_a)))
        maps = self.run_network(pairs, check_task(task))
        if task == "flow":
            return flow_to_input_resolution(maps, h, w)
        return np.stack([map_to_input_resolution(task, m, h, w) for m in maps])

    def predict_pair(self, image_a: Any, image_b: Any, task: str = "flow", *, confidence: bool = False,
                     occlusion: bool = False):
        """The prediction of one pair at the input resolution: flow `(h, w, 2)` from `image_a` to `image_b`
        ("flow"), or the disparity `(h, w)` of a left image `image_a` against its right image `image_b`
        ("stereo"); float32 pixels of the input resolution.

        With `confidence` and/or `occlusion`: `(map, [confidence], [occlusion])`, each `(h, w)` at the input
        resolution: confidence float32 in [0, 1] (1 = trusted), occlusion bool (True = no visible match in
        `image_b`), from the forward-backward (flow) or left-right (stereo) check (`bridge_jax.confidence`)."""
        out = self.predict_pairs([image_a], [image_b], task, confidence=confidence, occlusion=occlusion)
        return tuple(x[0] for x in out) if isinstance(out, tuple) else out[0]

    def predict_cycle(self, left_t: Any, right_t: Any, left_t1: Any, right_t1: Any, *, confidence: bool = False,
                      occlusion: bool = False) -> dict[str, np.ndarray]:
        """Disparity at t and t+1 and left-camera optical flow t -> t+1 for two stereo frames.

        Returns:
          {"disp_t": (h, w), "disp_t1": (h, w)} = disparity of left_t / left_t1 (pixels, >= 0 for a sensible
          model), {"flow": (h, w, 2)} = flow left_t -> left_t1 in pixels; as `evaluate` and `predict` compute
          them. With `confidence`: also "conf_disp_t", "conf_disp_t1", "conf_flow" (float32 in [0, 1], 1 =
          trusted); with `occlusion`: "occ_disp_t", "occ_disp_t1", "occ_flow" (bool, True = no visible match
          in the other image), each `(h, w)` in the frame of the map it belongs to (`predict_pair`).
        """
        jobs = [("stereo", left_t, right_t), ("stereo", left_t1, right_t1), ("flow", left_t, left_t1)]
        keys = ("disp_t", "disp_t1", "flow")
        if not (confidence or occlusion):
            return dict(zip(keys, self.predict(jobs)))
        out = {}
        for key, (value, conf, occ) in zip(keys, self.predict(jobs, confidence=True)):
            out[key] = value
            if confidence:
                out[f"conf_{key}"] = conf
            if occlusion:
                out[f"occ_{key}"] = occ
        return out

    def settings(self) -> dict:
        """{"working_size": "native" | "HxW", "refine", "symmetry", "polish"}: what info files record."""
        return {"working_size": str(self.size), **self.test_time.to_dict()}


_NETWORK_STATIC = (2, 4)
"""Static positions of the network program's (params, pairs, tasks, flow_rows, test_time)."""
_POLISH_STATIC = (3, 4)
"""Static positions of the polish program's (pairs, maps, flow_rows, test_time, config)."""
_POLISH_JIT = jax.jit(stages.polish_stage, static_argnums=_POLISH_STATIC)
"""The polish as a program of its own (`Predictor._polish_program`)."""


def trained_working_size(path: str | os.PathLike) -> tuple[int, int] | None:
    """(height, width) a training workdir (or one of its step dirs) was trained at, from its config.json, or a
    shipped model (by name) was trained at; None for params-only checkpoints or when unknown."""
    try:
        if zoo.is_name(path):
            return zoo.trained_size(path) or trained_working_size(zoo.resolve_path(path))
        model_json, _, _ = checkpointing.resolve_checkpoint(path)
        with open(model_json.parent / checkpointing.CONFIG_JSON) as f:
            cfg = json.load(f)
        return int(cfg["height"]), int(cfg["width"])
    except (ValueError, OSError, KeyError, TypeError):
        return None


def resize_notice(predictor: Predictor, height: int, width: int, factor: float = 2.0) -> Optional[str]:
    """One line for the user when an input of `height x width` is resized by more than `factor` on a side to
    run, naming the native size where that is another one: shrunk (fine structure and small motions are lost
    there), or upscaled (each pair then costs a network call at the larger working size and gains no detail).
    None otherwise."""
    wh, ww = predictor.working_size(height, width)
    native = native_working_size(predictor.model_name, height, width, predictor.max_pixels)
    hint = "" if (wh, ww) == native else f"; --working-size native runs it at {native[0]}x{native[1]}"
    shrink = max(height / wh, width / ww)
    if shrink > factor:
        if shrink > REDUCED_READ_NOTICE:
            hint += ("; it is decoded at a reduced size to save memory, and the maps are written at the input's "
                     f"{height}x{width}")
        return f"note: the {height}x{width} input runs at {wh}x{ww} ({shrink:.1f}x smaller per side){hint}"
    grow = max(wh / height, ww / width)
    if grow > factor:
        return (f"note: the {height}x{width} input runs at {wh}x{ww} ({grow:.1f}x larger per side: upscaled, each "
                f"pair costs a {wh}x{ww} network call){hint}")
    return None


def resolve_working_size(path: str | os.PathLike, choice: Any = None, option: str = "working size",
                         max_pixels: int = NATIVE_MAX_PIXELS) -> WorkingSize:
    """The `WorkingSize` of the command-line choice `choice` (`cli.parse_working_size`) for the model at `path`:
    (H, W); "native"; "trained" (the size a training workdir or shipped model was trained at: a net trained at
    64x128 sees 4x larger motions at 256x512, else 256 x 512); a `WorkingSize` as it is; None = what the card
    recommends (`zoo.card_working_size`), else `DEFAULT_WORKING_SIZE`. ValueError naming `option` otherwise."""
    if isinstance(choice, WorkingSize):
        return choice
    if choice is None:
        choice = zoo.card_working_size(path) or DEFAULT_WORKING_SIZE
    if choice in (NATIVE, TRAINED):
        trained = trained_working_size(path) or (DEFAULT_HEIGHT, DEFAULT_WIDTH)
        return WorkingSize(*trained, native=choice == NATIVE, max_pixels=max_pixels)
    if isinstance(choice, tuple) and len(choice) == 2:
        try:
            return WorkingSize(*choice, max_pixels=max_pixels)
        except ValueError as e:
            raise ValueError(f"{option} {choice[0]!r}x{choice[1]!r}: {e}") from None
    raise ValueError(f"{option} {choice!r}: expected HxW, 'native' or 'trained'")


def load_predictor(path: str | os.PathLike, *, size: Any = None, test_time: TestTime | Mapping | None = None,
                   dtype: Any = None, compile_mode: str = "full", executable_cache: Optional[str] = "auto",
                   polish_config: Optional[PolishConfig] = None, size_option: str = "working size",
                   options: Optional[Mapping[str, str]] = None) -> Predictor:
    """A Predictor from a shipped model's name (`"demo"`, see `bridge_jax.zoo`) or any checkpoint
    `bridge_jax.checkpointing.read_params` accepts (params-only dir, training workdir, step dir).

    "The card" below: that of the shipped model `path` names or was fine-tuned from (`zoo.defaults_source`,
    which follows a checkpoint's recorded `init_from`).

    Args:
      size: a `WorkingSize`, or its command-line form (`resolve_working_size`): (H, W), "native", "trained", or
        None = what the card recommends, else `DEFAULT_WORKING_SIZE`.
      test_time: a `TestTime` as it is, or a mapping of the settings given ({"refine": 0}; None values = not
        given) applied to the card's record (`zoo.card_test_time`; the defaults without a card); None = the
        card's.
      polish_config: the polish's parameters; None = `polish.DEFAULT_CONFIG` with the fields the card sets
        (`zoo.card_polish_settings`: where the polish runs, its data window on flow maps, ...).
      dtype: None = the model config's "dtype" if it has one, else float32. `compile_mode`: see `Predictor`.
      executable_cache: the folder where compiled programs are kept whole (see `Predictor`); "auto" (the
        default) = the folder of JAX's persistent compilation cache, turning on the one the commands use first
        when none is on (`compile_cache.enable("auto")`), so that a second Python process gets its first answer
        as fast as `bridge-predict` does; None = off.
      size_option, options: how the caller's user gave the size ("--working-size") and each test-time setting
        ({"refine": "--refine", ...}, `testtime.OPTIONS`), for the error messages.
    Raises:
      ValueError naming the checkpoint (missing, unreadable), `size_option` with the model's input multiple and
      a size that fits, or for a size that cannot fit in memory (`memory.check_fits`, before the weights are
      read), or the option of a bad test-time setting.
    """
    if executable_cache == "auto":
        executable_cache = compile_cache.active_dir() or compile_cache.enable("auto", option="executable_cache")
    if not isinstance(test_time, TestTime):
        test_time = zoo.card_test_time(path).with_given(test_time or {}, options)
    if polish_config is None:
        polish_config = zoo.card_polish_config(path)
    size = resolve_working_size(path, size, size_option)
    # before the weights are read: a size that cannot fit is refused without allocating anything
    memory.check_fits(size_option, size.height, size.width, memory.prediction_bytes(size.height, size.width),
                      "a prediction (one pair per call)", jax.devices()[0])
    cfg, params = zoo.load_params(path)
    models.check_working_size(cfg["name"], size.height, size.width, what=size_option)
    separate = bool(cfg.pop("separate_networks", False))
    graphdef, _ = models.abstract_init(cfg)
    if dtype is None:
        dtype = cfg.get("dtype")
    return Predictor(graphdef, params, size=size, test_time=test_time, polish_config=polish_config, dtype=dtype,
                     model_cfg=cfg, separate=separate, compile_mode=compile_mode, executable_cache=executable_cache)


__all__ = ["Predictor", "load_predictor", "resolve_working_size", "trained_working_size", "resize_notice",
           "COMPILE_MODES", "FAST_COMPILE_PAIRS", "compile_mode_for"]
