"""Test-time symmetry averaging (`inference.symmetric_maps`, `TestTime(symmetry=)`, `--symmetry`): the map
transforms on hand-built cases (an exact translation matcher, a constant stand-in network), and the predictor
and the exported artifact against numpy averages over their own plain calls on flipped copies."""

import json

import jax.numpy as jnp
import numpy as np
import pytest

from bridge_jax import export, inference, models, zoo
from bridge_jax.inference import TestTime, WorkingSize
from tests.test_refine import shift_matcher

H, W = 64, 128


def _shifted_pair(rng, dx: int, dy: int):
    """A periodic random texture and the same rolled so that a(x, y) is found at b(x + dx, y + dy)."""
    a = rng.uniform(size=(1, H, W, 3)).astype(np.float32)
    b = np.roll(a, shift=(dy, dx), axis=(1, 2))
    return jnp.asarray(np.concatenate([a, b], -1))


@pytest.mark.parametrize("symmetry", inference.SYMMETRY_MODES)
def test_an_exact_matcher_stays_exact_under_every_copy(rng, symmetry):
    """The matcher finds the true integer shift of any copy it is given, so the average of the copies mapped
    back is the true (3, -2) again, for flow and stereo rows; a copy mapped back with a wrong sign (u of a
    left-right flip, v of an upside-down flip) or unswapped channels (a transposition) would pull the mean
    off it (u to 1.5 with one wrong sign among four copies)."""
    pairs = _shifted_pair(rng, 3, -2)
    for flow_rows in (None, jnp.ones(1), jnp.zeros(1)):
        out = np.asarray(inference.symmetric_maps(shift_matcher(), pairs, symmetry, flow_rows))
        np.testing.assert_allclose(out, np.broadcast_to([3.0, -2.0], (1, H, W, 2)), atol=1e-6)


def test_copies_are_mapped_back_and_stereo_rows_keep_stereo_copies():
    """A stand-in network that answers a constant (1, 2) whatever it sees: mapped back, the left-right
    copies say u = -1, the upside-down ones v = -2, a transposed copy (2, 1) before its flips. A flow row
    averages all of them: (0, 0). A stereo row counts only the copy as given and the upside-down one: (1, 0),
    with "flips" and with "dihedral"."""
    estimate = lambda x: jnp.broadcast_to(jnp.asarray([1.0, 2.0]), x.shape[:3] + (2,))
    pairs = jnp.zeros((2, H, W, 6))
    flow_rows = jnp.asarray([1.0, 0.0])  # row 0 flow, row 1 stereo
    for symmetry in ("flips", "dihedral"):
        out = np.asarray(inference.symmetric_maps(estimate, pairs, symmetry, flow_rows))
        np.testing.assert_allclose(out[0], np.zeros((H, W, 2)), atol=1e-6)
        np.testing.assert_allclose(out[1], np.broadcast_to([1.0, 0.0], (H, W, 2)), atol=1e-6)


def test_unknown_symmetry_is_one_clear_error():
    graphdef, params = models.init(0, "pwc_lite")
    with pytest.raises(ValueError, match=r"symmetry 'mirror': expected one of none, flips, dihedral"):
        inference.Predictor(graphdef, params, size=WorkingSize(H, W), model_cfg=models.model_config("pwc_lite"),
                            test_time=TestTime(symmetry="mirror"))


def _numpy_symmetric(plain: inference.Predictor, pairs: np.ndarray, stereo: bool, transposed: bool) -> np.ndarray:
    """The mean of the plain predictor's maps on numpy-flipped (and transposed) copies, mapped back by hand."""
    out = []
    views = [False, True] if transposed else [False]
    for t in views:
        for lr in (False, True):
            for ud in (False, True):
                if stereo and (lr or t):
                    continue
                x = pairs.transpose(0, 2, 1, 3) if t else pairs
                x = x[:, :, ::-1] if lr else x
                x = x[:, ::-1] if ud else x
                m = plain.run_network(np.ascontiguousarray(x), "stereo" if stereo else "flow")
                m = m[:, ::-1] if ud else m
                m = m[:, :, ::-1] if lr else m
                m = m * np.array([-1.0 if lr else 1.0, -1.0 if ud else 1.0], np.float32)
                out.append(m.transpose(0, 2, 1, 3)[..., ::-1] if t else m)
    return np.mean(out, 0)


PWC = {**models.model_config("pwc_lite"), "head_init": "kaiming_normal"}  # non-zero maps from a random network


@pytest.fixture(scope="module")
def pwc():
    return models.init(0, PWC)


def test_predictor_symmetry_is_the_mean_of_its_plain_calls_on_flipped_copies(pwc, rng):
    """`TestTime(symmetry=...)` on a batch with a flow and a stereo row = the numpy mean of the plain
    predictor on the copies (stereo: as given and upside-down only); one compile per symmetry value."""
    cfg = PWC
    plain = inference.Predictor(*pwc, size=WorkingSize(H, W), model_cfg=cfg)
    pairs = rng.uniform(size=(2, H, W, 6)).astype(np.float32)
    for symmetry in ("flips", "dihedral"):
        sym = inference.Predictor(*pwc, size=WorkingSize(H, W), test_time=TestTime(symmetry=symmetry), model_cfg=cfg)
        got = sym.run_network(pairs, ["flow", "stereo"])
        np.testing.assert_allclose(got[0], _numpy_symmetric(plain, pairs[:1], False, symmetry == "dihedral")[0],
                                   atol=2e-5)
        np.testing.assert_allclose(got[1], _numpy_symmetric(plain, pairs[1:], True, symmetry == "dihedral")[0],
                                   atol=2e-5)
        assert np.abs(got[0] - plain.run_network(pairs[:1])[0]).max() > 1e-4  # the copies changed the map
        sym.run_network(pairs, ["stereo", "flow"])
        assert sym.trace_count == 1


def test_export_with_symmetry_is_the_symmetric_predictor(pwc, tmp_path):
    cfg = PWC
    predictor = inference.Predictor(*pwc, size=WorkingSize(H, W), test_time=TestTime(refine=1, symmetry="flips"),
                                    model_cfg=cfg)
    loaded = export.load_exported(export.serialize_to_file(export.export_network(predictor, batch=1),
                                                           tmp_path / "s.stablehlo"))
    x = np.random.default_rng(2).uniform(size=(1, H, W, 6)).astype(np.float32)
    px, frac = loaded.call(x)
    np.testing.assert_allclose(px, predictor.run_network(x), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(frac, np.asarray(px) / np.array([W, H], np.float32), rtol=1e-6)


def test_default_symmetry_comes_from_a_shipped_card_only(tmp_path):
    """A shipped card may recommend a symmetry, which load_predictor then uses unless told otherwise; a
    checkpoint path (no card) runs without."""
    for name in ("long", "demo"):
        want = zoo.info(name).get("default_symmetry", "none")
        assert zoo.card_test_time(name).symmetry == want
        assert inference.load_predictor(name).symmetry == want
    assert inference.load_predictor("long", test_time={"symmetry": "none"}).symmetry == "none"
    assert zoo.card_test_time("long").symmetry == "flips"  # what its real-image checks chose (real_images.md)
    assert any(line.startswith("  default symmetry averaging: flips") for line in zoo.card_lines("long"))
    assert not any("symmetry" in line for line in zoo.card_lines("demo"))
    assert zoo.card_test_time(str(tmp_path)) == zoo.card_test_time("no-such-name") == inference.TestTime()


def predict_pair_command(checkpoint: str, tmp_path):
    """Two 128x256 frames of a smooth random texture, 8 px apart, written to `tmp_path` as f0.png / f1.png, and
    the `bridge-predict` arguments that write their flow as .npy into `tmp_path/out` at 128x256. Returns
    (paths, out, args)."""
    import cv2

    rng = np.random.default_rng(3)
    base = cv2.resize(rng.integers(0, 255, (32, 72, 3), dtype=np.uint8), (288, 128), interpolation=cv2.INTER_CUBIC)
    paths = []
    for i, img in enumerate((base[:, :256], base[:, 8:264])):
        paths.append(str(tmp_path / f"f{i}.png"))
        cv2.imwrite(paths[-1], np.ascontiguousarray(img[..., ::-1]))
    out = tmp_path / "out"
    args = ["--checkpoint", checkpoint, *paths, "--out", str(out), "--working-size", "128x256", "--raw", "npy",
            "--no-progress"]
    return paths, out, args


def check_predict_option(checkpoint: str, tmp_path, capsys, option: str, value: str, bad: str, **load_kwargs):
    """`bridge-predict --OPTION VALUE` on `predict_pair_command`'s pair writes the flow that
    `load_predictor(checkpoint, size=(128, 256), test_time={OPTION: VALUE}, **load_kwargs)` predicts and records
    VALUE in predict.json; `--OPTION BAD` is one argparse error (exit 2) that writes nothing."""
    import cv2

    from bridge_jax import predict
    paths, out, args = predict_pair_command(checkpoint, tmp_path)
    assert predict.main(args + [f"--{option}", value]) == 0
    assert json.loads((out / "predict.json").read_text())[option] == value
    predictor = inference.load_predictor(checkpoint, size=(128, 256), test_time={option: value}, **load_kwargs)
    want = predictor.predict_pair(cv2.imread(paths[0])[..., ::-1], cv2.imread(paths[1])[..., ::-1])
    np.testing.assert_allclose(np.load(out / "flow_npy" / "f0.npy"), want, rtol=1e-4, atol=1e-4)
    with pytest.raises(SystemExit) as e:
        predict.main([str(tmp_path / "bad") if a == str(out) else a for a in args] + [f"--{option}", bad])
    assert e.value.code == 2 and not (tmp_path / "bad").exists()
    assert f"--{option}: invalid choice: '{bad}'" in capsys.readouterr().err


def test_predict_symmetry_option(tiny_checkpoint, tmp_path, capsys):
    """`bridge-predict --symmetry flips` writes the symmetric predictor's flow and says so in predict.json; an
    unknown mode is one argparse error (exit 2) and writes nothing."""
    check_predict_option(tiny_checkpoint, tmp_path, capsys, "symmetry", "flips", "mirror")
