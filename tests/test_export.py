"""jax.export round trip: the deserialized StableHLO function gives the same maps as models.apply."""

import jax
import numpy as np
import pytest

from bridge_jax import checkpointing, export, inference, models


@pytest.fixture(scope="module")
def tiny_ckpt(tmp_path_factory):
    graphdef, params = models.init(0, "resnet_md_tiny")
    path = tmp_path_factory.mktemp("export") / "ck"
    checkpointing.save_params(path, params, models.model_config("resnet_md_tiny"))
    return graphdef, params, path


def test_export_round_trip(tiny_ckpt, tmp_path):
    graphdef, params, _ = tiny_ckpt
    predictor = inference.Predictor(graphdef, params, size=inference.WorkingSize(64, 128),
                                    model_cfg=models.model_config("resnet_md_tiny"))
    exp = export.export_network(predictor, batch=2)
    out = export.serialize_to_file(exp, tmp_path / "m.stablehlo")
    loaded = export.load_exported(out)
    x = np.random.default_rng(0).uniform(size=(2, 64, 128, 6)).astype(np.float32)
    px, frac = loaded.call(x)
    ref = jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x)
    np.testing.assert_allclose(px, ref["px"][0], rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(frac, ref["frac"][0], rtol=1e-5, atol=1e-6)
    assert "stablehlo" in loaded.mlir_module() or "func.func" in loaded.mlir_module()


def test_export_with_refinement_is_the_refined_predictor(tiny_ckpt, tmp_path):
    """A predictor with `TestTime(refine=1)` exports its refined maps: the artifact gives what `run_network` gives (the
    refinement itself is checked against hand-built cases in test_refine.py), and frac0 = px0 / (W, H)."""
    graphdef, params, _ = tiny_ckpt
    predictor = inference.Predictor(graphdef, params, size=inference.WorkingSize(64, 128),
                                    test_time=inference.TestTime(refine=1),
                                    model_cfg=models.model_config("resnet_md_tiny"))
    loaded = export.load_exported(export.serialize_to_file(export.export_network(predictor, batch=2),
                                                           tmp_path / "r.stablehlo"))
    x = np.random.default_rng(1).uniform(size=(2, 64, 128, 6)).astype(np.float32)
    px, frac = loaded.call(x)
    np.testing.assert_allclose(px, predictor.run_network(x), rtol=1e-5, atol=1e-4)
    np.testing.assert_allclose(frac, np.asarray(px) / np.array([128, 64], np.float32), rtol=1e-6)
    plain = jax.jit(lambda p, x: models.apply(graphdef, p, x))(params, x)["px"][0]
    assert np.abs(np.asarray(px) - np.asarray(plain)).max() > 1e-3  # the pass is in the artifact


def test_export_cli(tiny_ckpt, tmp_path, capsys):
    _, params, path = tiny_ckpt
    out = tmp_path / "cli.stablehlo"
    rc = export.main(["--checkpoint", str(path), "--out", str(out), "--height", "64", "--width", "128"])
    assert rc == 0 and out.is_file()
    exp = export.load_exported(out)
    assert exp.in_avals[0].shape == (1, 64, 128, 6)
    capsys.readouterr()
    # bad input: one-line error, exit != 0, nothing written
    bad = tmp_path / "bad.stablehlo"
    assert export.main(["--checkpoint", str(path), "--out", str(bad), "--height", "100"]) == 2
    # the width not given is the default 512 (a params-only checkpoint has no trained size)
    assert capsys.readouterr().err.strip().splitlines() == [
        "error: --height/--width 100x512: height and width must be multiples of 64 for model resnet_md_tiny "
        "(try 128x512)"]
    assert export.main(["--checkpoint", str(tmp_path / "nope"), "--out", str(bad)]) == 2
    assert export.main(["--checkpoint", str(path), "--out", str(bad), "--batch", "0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("error:") for e in err)
    assert "nope" in err[0] and "--batch" in err[1]
    assert not bad.exists()


def test_export_defaults_to_the_trained_size(tiny_ckpt, tmp_path, capsys):
    import json
    import shutil
    _, _, path = tiny_ckpt
    ck = tmp_path / "trained"
    shutil.copytree(path, ck)
    (ck / "config.json").write_text(json.dumps({"height": 64, "width": 192}))   # what training writes beside it
    out = tmp_path / "t.stablehlo"
    assert export.main(["--checkpoint", str(ck), "--out", str(out)]) == 0
    assert export.load_exported(out).in_avals[0].shape == (1, 64, 192, 6)
    assert json.loads(capsys.readouterr().out)["input"] == [1, 64, 192, 6]


def test_export_help():
    parser = export.build_parser()
    assert [a.option_strings for a in parser._actions if not a.help] == []
    text = parser.format_help()
    assert "bridge-export --checkpoint demo --out demo.stablehlo" in text
    assert "shipped model name such as demo" in text and "--debug" in text
