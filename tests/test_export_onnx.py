"""bridge-export --format onnx: onnxruntime's answer against the StableHLO artifact's on real photo pairs, the
no-JAX runner (experiments/onnx_predict.py), and the refusals (missing extra, a stage the converter cannot
express, bfloat16)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bridge_jax import export, inference, onnx_export

ROOT = Path(__file__).resolve().parents[1]
TOLERANCE = 0.05
"""Largest |ONNX - StableHLO| (working pixels) the issue allows."""
PLAIN = ["--refine", "0", "--symmetry", "none", "--polish", "none"]


def _needs_onnx():
    pytest.importorskip("onnxruntime")
    pytest.importorskip("jax2onnx")
    try:
        onnx_export.require_converter()
    except onnx_export.MissingExtra as e:
        pytest.skip(str(e))


@pytest.fixture(scope="module")
def photo_pairs():
    """Two real pairs: a held-out photo under a homography with moving patches (flow), and Middlebury's
    Motorcycle (a rectified stereo pair, run as a pair like any other)."""
    from bridge_jax.data import photos
    from bridge_jax.eval import real_checks
    pair = real_checks.homography_pair(photos.load_photo("astronaut"), photos.load_photo("coffee"),
                                       np.random.default_rng(0))
    moto = real_checks.motorcycle()
    return [(pair["frame_t"], pair["frame_t1"]), (moto["left"], moto["right"])]


def _inputs(pairs, height, width):
    out = []
    for a, b in pairs:
        x = np.concatenate([inference.to_rgb_float(a), inference.to_rgb_float(b)], -1)
        out.append(inference.resize_images(x, height, width)[None])
    return out


def _session(path):
    import onnxruntime as ort
    options = ort.SessionOptions()
    options.log_severity_level = 3
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def _both_formats(tmp_path, name, args):
    """Export `name` with `args` in both formats through the command; (onnxruntime session, StableHLO)."""
    paths = {}
    for fmt in ("stablehlo", "onnx"):
        paths[fmt] = tmp_path / f"{name}.{fmt}"
        assert export.main(["--checkpoint", name, "--format", fmt, "--out", str(paths[fmt])] + args) == 0
    return _session(paths["onnx"]), export.load_exported(paths["stablehlo"]), paths


def _differences(sess, exp, inputs):
    """Per pair: (|px| differences, |frac| differences) of onnxruntime against the StableHLO artifact."""
    out = []
    for x in inputs:
        px, frac = sess.run(None, {"pairs": x})
        ref_px, ref_frac = (np.asarray(v) for v in exp.call(x))
        assert px.shape == ref_px.shape == x.shape[:3] + (2,)
        out.append((np.abs(px - ref_px), np.abs(frac - ref_frac)))
    return out


@pytest.fixture(scope="module")
def plain_demo(tmp_path_factory, photo_pairs):
    """`demo` at 64x128 with no test-time stages, in both formats."""
    _needs_onnx()
    tmp = tmp_path_factory.mktemp("onnx_plain")
    sess, exp, paths = _both_formats(tmp, "demo", ["--height", "64", "--width", "128"] + PLAIN)
    return sess, exp, paths, _inputs(photo_pairs, 64, 128)


def test_onnx_matches_stablehlo_without_test_time_stages(plain_demo, capsys):
    sess, exp, paths, inputs = plain_demo
    assert [i.name for i in sess.get_inputs()] == ["pairs"] and sess.get_inputs()[0].shape == [1, 64, 128, 6]
    assert [o.name for o in sess.get_outputs()] == ["px0", "frac0"]   # the map in pixels first, then fractions
    meta = sess.get_modelmeta().custom_metadata_map
    assert meta["bridge_jax.refine"] == "0" and meta["bridge_jax.polish"] == "none"
    for d_px, d_frac in _differences(sess, exp, inputs):
        assert d_px.max() <= TOLERANCE and d_frac.max() <= TOLERANCE / 128
        assert d_px.max() < 1e-3  # in fact float rounding only


def test_onnx_runner_needs_no_jax(plain_demo, photo_pairs, tmp_path):
    """experiments/onnx_predict.py, run with jax, flax and bridge_jax made unimportable: writes the flow picture at
    the input's size, and the flow it writes is what the StableHLO artifact's map gives at that size."""
    import cv2
    _, exp, paths, inputs = plain_demo
    a, b = photo_pairs[0]
    cv2.imwrite(str(tmp_path / "a.png"), a[..., ::-1])
    cv2.imwrite(str(tmp_path / "b.png"), b[..., ::-1])
    blocker = ("import runpy, sys\n"
               "for name in ('jax', 'jaxlib', 'flax', 'bridge_jax', 'skimage'):\n"
               "    sys.modules[name] = None  # importing any of them raises ImportError\n"
               "sys.argv = sys.argv[1:]\n"
               "runpy.run_path(sys.argv[0], run_name='__main__')\n")
    runner = str(ROOT / "experiments" / "onnx_predict.py")
    cmd = [sys.executable, "-c", blocker, runner, str(paths["onnx"]), str(tmp_path / "a.png"),
           str(tmp_path / "b.png"), "--out", str(tmp_path / "flow.png"), "--npy", str(tmp_path / "flow.npy")]
    done = subprocess.run(cmd, capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    assert report["working_size"] == [64, 128] and report["input_size"] == list(a.shape[:2])
    picture = cv2.imread(str(tmp_path / "flow.png"))
    assert picture.shape == a.shape and picture.std() > 0
    flow = np.load(tmp_path / "flow.npy")
    ref = inference.flow_to_input_resolution(np.asarray(exp.call(inputs[0])[0])[0], *a.shape[:2])
    assert np.abs(flow - ref).max() < TOLERANCE
    # bad input: one line, exit 2, nothing written
    done = subprocess.run(cmd[:6] + [str(tmp_path / "missing.png"), "--out", str(tmp_path / "no.png")],
                          capture_output=True, text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 2 and done.stderr.strip().startswith("error: image_b")
    assert len(done.stderr.strip().splitlines()) == 1 and not (tmp_path / "no.png").exists()


def test_onnx_export_refusals(tmp_path, capsys, monkeypatch):
    """Missing extra, bfloat16, and a stage the converter cannot express: one line, exit 2, nothing written."""
    out = tmp_path / "m.onnx"
    base = ["--checkpoint", "demo", "--format", "onnx", "--out", str(out), "--height", "64", "--width", "128"]
    with monkeypatch.context() as m:
        m.setitem(sys.modules, "jax2onnx", None)  # as if the extra were not installed
        assert export.main(base) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --format onnx needs") and "pip install 'bridge-jax[onnx]'" in err[0]
    assert not out.exists()
    _needs_onnx()
    assert export.main(base + ["--dtype", "bfloat16"] + PLAIN) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --dtype bfloat16")

    import jax2onnx

    def no_flips(*args, **kwargs):  # a converter without an ONNX form of lax.rev (the flips' primitive)
        raise NotImplementedError("[jaxpr] No plugins registered for primitive 'rev'")

    monkeypatch.setattr(jax2onnx, "to_onnx", no_flips)
    assert export.main(base + ["--refine", "0", "--symmetry", "flips", "--polish", "none"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("error: --format onnx: --symmetry flips uses primitive 'rev'")
    assert not out.exists() and not list(tmp_path.iterdir())


def _check_card_defaults(tmp_path, name, size, photo_pairs):
    """`name` at its card's refine, symmetry and polish (at working size `size`, None = the card's): ONNX against
    StableHLO. Returns the per-pair (max, share of pixels within TOLERANCE) of |px0| differences."""
    args = [] if size is None else ["--height", str(size[0]), "--width", str(size[1])]
    sess, exp, _ = _both_formats(tmp_path, name, args)
    meta = sess.get_modelmeta().custom_metadata_map
    card = inference.load_predictor(name, executable_cache=None)
    # an artifact holds the polish's photometric step only: the fill runs on the host (`export.without_fill`)
    assert (meta["bridge_jax.refine"], meta["bridge_jax.symmetry"], meta["bridge_jax.polish"]) == (
        str(card.refine), card.symmetry, card.test_time.photometric_part.polish)
    height, width = sess.get_inputs()[0].shape[1:3]
    found = []
    for d_px, d_frac in _differences(sess, exp, _inputs(photo_pairs, height, width)):
        found.append((float(d_px.max()), float((d_px <= TOLERANCE).mean())))
        assert np.median(d_px) < 1e-3 and np.percentile(d_px, 99.9) <= TOLERANCE
    return found


@pytest.mark.slow
def test_onnx_matches_stablehlo_at_demo_card_defaults(tmp_path, photo_pairs):
    """demo's card: one refinement pass and the photometric polish. The polish's candidate selection takes, at
    each pixel, the cheapest of 32 neighbouring map values when it is clearly cheaper: on near ties a float
    rounding difference of the network (~1e-4 px between onnxruntime and XLA) can pick another candidate, so a
    few pixels may differ by more than 0.05 px (the same happens to JAX's own polish when its input moves by
    1e-5 px); every other pixel agrees to float rounding."""
    _needs_onnx()
    for worst, share in _check_card_defaults(tmp_path, "demo", (64, 128), photo_pairs):
        assert share >= 0.999 and worst < 1.0


@pytest.mark.slow
def test_onnx_polish_alone_matches_jax(photo_pairs):
    """The polish stage by itself, given the same maps: onnxruntime's answer within 0.05 px of JAX's."""
    _needs_onnx()
    import jax
    import jax.numpy as jnp
    from bridge_jax import polish
    height, width = 64, 128
    pred = inference.load_predictor("demo", size=(height, width), executable_cache=None,
                                    test_time={"refine": 1, "symmetry": "none", "polish": "none"})
    fn = lambda pairs, maps: polish.polish_maps(pairs, maps, jnp.ones((1,), jnp.float32))
    specs = [jax.ShapeDtypeStruct((1, height, width, 6), jnp.float32),
             jax.ShapeDtypeStruct((1, height, width, 2), jnp.float32)]
    sess = _session_from_model(onnx_export.convert(fn, specs, input_names=["pairs", "maps"]))
    for x in _inputs(photo_pairs, height, width):
        maps = pred.run_network(x)
        got = sess.run(None, {"pairs": x, "maps": maps})[0]
        assert np.abs(got - np.asarray(jax.jit(fn)(x, maps))).max() <= TOLERANCE


def _session_from_model(model):
    import onnxruntime as ort
    options = ort.SessionOptions()
    options.log_severity_level = 3
    return ort.InferenceSession(model.SerializeToString(), options, providers=["CPUExecutionProvider"])


@pytest.mark.slow
def test_onnx_matches_stablehlo_at_long_card_defaults(tmp_path, photo_pairs):
    """long at its card's defaults: the trained 256x512, one refinement pass, flips symmetry, the polish."""
    _needs_onnx()
    for worst, share in _check_card_defaults(tmp_path, "long", None, photo_pairs):
        assert share >= 0.999 and worst < 1.0
