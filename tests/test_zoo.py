"""Models by name (`bridge_jax.zoo`): the shipped demo weights, the registry, and `--checkpoint demo` anywhere."""
import hashlib
import json
import os
import shutil
import subprocess
import sys

import cv2
import jax
import numpy as np
import pytest

from bridge_jax import checkpointing, configs, inference, recipe, setup, train, zoo
from bridge_jax.data import synthetic
from tests.train_helpers import REPO


def _changed(recorded: dict, current: dict, prefix: str = "") -> list[str]:
    out = []
    for k, v in recorded.items():
        if isinstance(v, dict) and isinstance(current.get(k), dict):
            out += _changed(v, current[k], f"{prefix}{k}.")
        elif k not in current or current[k] != v:
            out.append(f"{prefix}{k}: {v!r} -> {current.get(k, '<removed>')!r}")
    return out


SHIPPED = {  # name -> (the recipe config, its stage whose config the shipped model's run recorded, how to rebuild)
    "demo": ("demo", "finish", "retrain with `make demo` (the recipe trains in work/demo/train), then `bridge-zoo build "
                               "demo --from work/demo/train --card work/demo_card.json`"),
    "long": ("long:legacy", "hires",
             "the shipped `long` came from the legacy chain's stages run by hand; its stages' settings live in "
             "configs/long.py (`long:legacy`): a change there calls for retraining it"),
}


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_shipped_model_matches_its_config(name):
    """When a shipped model's config changes, its weights must be regenerated (this test says how)."""
    spec, stage, how = SHIPPED[name]
    meta = zoo.info(name)
    run = setup.parse(recipe.stage_config(configs.load(spec), stage), devices=jax.devices()[:1])
    assert meta["model"] == json.loads(json.dumps(run.model.model_json())), how
    # every setting the shipped run recorded still has that value (fields added since keep the old behaviour
    # by default, so they do not call for retraining); init_from names where the stage started on the machine
    # that trained it (a recipe sets it to the previous stage's folder)
    recorded = dict(meta["config"])  # a run of an earlier release recorded the loop fields at the top level
    moved = {k: recorded.pop(k) for k in configs.MOVED_KEYS if k in recorded}
    recorded["loop"] = dict(recorded.get("loop", {}), **moved)
    recorded.pop("init_from")
    assert _changed(recorded, json.loads(json.dumps(run.config_json))) == [], how
    assert (meta["height"], meta["width"]) == (run.height, run.width)
    data = (zoo.ZOO_DIR / f"{name}.npz").read_bytes()
    assert hashlib.sha256(data).hexdigest() == meta["sha256"]
    assert len(data) < 3_000_000  # "a few MB at most"


def test_long_card_says_how_it_was_trained_and_what_it_measured(capsys):
    """`bridge-zoo show long`: the recipe, the steps, the training time and machine, and its real-image numbers
    next to OpenCV's, from its card."""
    from bridge_jax.zoo.__main__ import main
    meta = zoo.info("long")
    # stage 5: stage 4's recipe at 256x512, on top of stage 4
    assert (meta["height"], meta["width"]) == (256, 512) and meta["config"]["init_from"] == "work/long4"
    assert meta["config"]["loss"]["photometric"] == "census"  # the census photometric term, since stage 4
    assert meta["config"]["data"]["synthetic_scene"] == "real_motion"  # vertical motion, since stage 3
    assert meta["config"]["data"]["augment_shift"] > 0
    assert meta["config"]["loss"]["self_supervision"] > 0  # the self-supervision term, since stage 2
    # the demo model fine-tuned on the `real` scenes, then self-supervised, then taught vertical motion, then census
    stage1, stage2, stage3, stage4 = meta["earlier_stages"]
    assert stage1["config"] == "demo:long,real" and stage1["init_from"] == "demo" and stage1["steps"] > 0
    assert stage2["config"] == "demo:long,real,selfsup" and stage2["init_from"] == "work/long" and stage2["steps"] > 0
    assert stage3["config"] == "demo:long,real,selfsup,motion" and stage3["init_from"] == "work/long2"
    assert stage3["steps"] > 0
    assert stage4["config"] == "demo:long,real,selfsup,motion,census" and stage4["init_from"] == "work/long3"
    assert stage4["steps"] > 0
    assert meta["training"]["seconds"] > 0 and "core" in meta["training"]["machine"]
    assert set(meta["real_images"]) == {"motorcycle", "homography", "heldout_synthetic"}
    for by_size in meta["real_images"].values():
        assert {"trained", "native", "opencv"} <= set(by_size)
    assert main(["show", "long"]) == 0
    out = capsys.readouterr().out
    assert f"long: pwc_lite trained at 256x512, {meta['steps']} steps" in out
    assert "scenes real_motion" in out and meta["training"]["machine"] in out
    assert f"stage 1: --config=demo:long,real, {stage1['steps']} steps from demo" in out
    d1 = meta["real_images"]["motorcycle"]["native"]["d1_all"]
    line = next(ln for ln in out.splitlines() if "motorcycle @ native:" in ln)
    assert f"d1_all {d1:.3f}" in line
    assert f"default working size: {meta['default_working_size']}" in out
    assert f"default refinement: {meta['default_refine']} pass(es)" in out and meta["default_refine"] >= 1


def test_shipped_descriptions_name_their_cards_defaults():
    """`bridge-zoo list` says how each shipped model runs by default: its card's working size, refinement
    passes, symmetry averaging and polish (a description left behind when a card changed was caught here)."""
    words = {1: "one"}
    for name in ("demo", "long"):
        meta, text = zoo.info(name), zoo.entry(name).description
        size = {"native": "--working-size native",
                "trained": f"its trained {meta['height']}x{meta['width']}"}.get(meta["default_working_size"],
                                                                                meta["default_working_size"])
        assert f"by default at {size} with {words[meta['default_refine']]} --refine pass" in text, name
        symmetry = meta.get("default_symmetry", "none")
        assert (f"--symmetry {symmetry}" in text) == (symmetry != "none"), name
        polish = meta.get("default_polish", "none")
        assert (f"--polish {polish}" in text) == (polish != "none"), name


def test_default_refine_comes_from_a_shipped_card_only(tmp_path):
    """The shipped cards recommend test-time refinement passes, which load_predictor then uses unless told
    otherwise; a checkpoint path (no card) runs unrefined."""
    for name in ("long", "demo"):
        meta = zoo.info(name)
        assert zoo.card_test_time(name).refine == meta["default_refine"] >= 1
        assert inference.load_predictor(name).refine == meta["default_refine"]
    assert inference.load_predictor("long", test_time={"refine": 0}).refine == 0
    assert zoo.card_test_time(str(tmp_path)).refine == zoo.card_test_time("no-such-name").refine == 0


def test_default_working_size_comes_from_a_shipped_card(monkeypatch):
    """A card's "native" / "trained" pass through; its "HxW" is a fixed size, which load_predictor then runs at
    unless told otherwise; a model without a card entry has none."""
    for name in ("long", "demo"):
        want = zoo.info(name)["default_working_size"]
        got = zoo.card_working_size(name)
        p = inference.load_predictor(name)
        if want in ("native", "trained"):
            assert got == want and p.native == (want == "native")
        else:
            h, w = (int(v) for v in want.split("x"))
            assert got == (h, w) and (p.height, p.width) == (h, w) and not p.native
    info = dict(zoo.info("demo"))
    for card, size in (("192x384", (192, 384)), ("256X512", (256, 512)), ("native", "native"), (None, None)):
        monkeypatch.setattr(zoo, "_shipped_info", lambda spec, card=card: {**info, "default_working_size": card})
        assert zoo.card_working_size("demo") == size
    monkeypatch.setattr(zoo, "_shipped_info", lambda spec: {**info, "default_working_size": "192x384"})
    p = inference.load_predictor("demo")
    assert (p.height, p.width) == (192, 384)
    p = inference.load_predictor("demo", size="trained")
    assert (p.height, p.width) == (info["height"], info["width"])


def test_shipped_demo_beats_zero_motion_on_the_validation_cycles():
    """The shipped model, through the one predictor, on the trainer's held-out synthetic frames: flow and
    disparity well below zero motion, and the numbers recorded when it was built are reproduced."""
    predictor = inference.load_predictor("demo", size="trained",
                                         test_time={"refine": 0, "polish": "none"})  # as trained
    assert (predictor.height, predictor.width) == (128, 256)  # the second phase's size
    run = setup.parse(recipe.stage_config(configs.load("demo"), "finish"), devices=jax.devices()[:1])
    res, _ = train.validate(predictor, predictor.params, train.validation_frames(run), 4, picture=False)
    assert res["flow_epe_all"] < 0.6 * res["zero_flow_epe_all"], res
    assert res["disp_epe_all"] < 0.3 * res["zero_disp_epe_all"], res
    recorded = zoo.info("demo")["validation"]
    assert res["flow_epe_all"] == pytest.approx(recorded["flow_epe_all"], rel=1e-3)
    assert res["disp_epe_all"] == pytest.approx(recorded["disp_epe_all"], rel=1e-3)


def test_flatten_unflatten_are_inverse_and_refuse_slashes():
    tree = {"a": {"b": np.arange(3, dtype=np.float32), "c": {"d": np.ones((2, 2), np.float32)}}, "e": np.zeros(1)}
    flat = zoo._flatten(tree)
    assert sorted(flat) == ["a/b", "a/c/d", "e"]
    back = zoo._unflatten(flat)
    np.testing.assert_array_equal(back["a"]["c"]["d"], tree["a"]["c"]["d"])
    np.testing.assert_array_equal(back["a"]["b"], [0, 1, 2])
    with pytest.raises(ValueError, match="contains '/'"):
        zoo._flatten({"x/y": np.ones(1)})


def test_damaged_shipped_file_is_refused(tmp_path, monkeypatch):
    shutil.copy(zoo.ZOO_DIR / "demo.json", tmp_path / "demo.json")
    data = bytearray((zoo.ZOO_DIR / "demo.npz").read_bytes())
    data[len(data) // 2] ^= 0xFF
    (tmp_path / "demo.npz").write_bytes(bytes(data))
    monkeypatch.setattr(zoo, "ZOO_DIR", tmp_path)
    with pytest.raises(ValueError, match="SHA-256.*reinstall"):
        zoo.load_params("demo")


def test_unknown_and_missing_names_are_one_clear_error(tmp_path, monkeypatch):
    with pytest.raises(ValueError, match=r"'dmeo' is neither an existing path nor a model name \(did you mean demo"):
        inference.load_predictor("dmeo")
    monkeypatch.setenv(zoo.HOME_ENV, str(tmp_path))
    with pytest.raises(ValueError, match=r"upstream_ver_b.*not on this machine.*bridge-convert --from "
                                         r"monodepth_ver_b.pth --out " + str(tmp_path)):
        zoo.load_params("upstream_ver_b")
    # a path-like spec is never looked up in the registry
    assert not zoo.is_name("./demo") and not zoo.is_name("runs/demo") and zoo.is_name("demo")


def test_registered_and_local_names_load_their_folder(tmp_path, monkeypatch):
    cfg, params = zoo.load_params("demo")
    checkpointing.save_params(tmp_path / "upstream_ver_a", params, cfg)
    monkeypatch.setenv(zoo.HOME_ENV, str(tmp_path))
    cfg2, params2 = zoo.load_params("upstream_ver_a")
    assert cfg2 == cfg
    np.testing.assert_array_equal(np.asarray(params2["estimator_flow"]["kernel"]),
                                  np.asarray(params["estimator_flow"]["kernel"]))
    zoo.register("mine_for_test", tmp_path / "upstream_ver_a")
    try:
        assert zoo.load_params("mine_for_test")[0] == cfg
    finally:
        zoo._ENTRIES.pop("mine_for_test")


@pytest.mark.parametrize("name", sorted(SHIPPED))
def test_predict_with_the_shipped_model_from_another_directory(tmp_path, name):
    """`predict --checkpoint NAME a.png b.png --out o` from a folder outside the repo: the flow it writes (as
    .npy) is closer to the exact synthetic flow than zero motion."""
    sample = synthetic.render_sample(synthetic.sample_seed(7, 0), 64, 128)
    a, b = (tmp_path / "frame_a.png"), (tmp_path / "frame_b.png")
    cv2.imwrite(str(a), sample["cycle"][0][..., ::-1])
    cv2.imwrite(str(b), sample["cycle"][2][..., ::-1])
    env = dict(os.environ, JAX_PLATFORMS="cpu", PYTHONPATH=REPO + os.pathsep + os.environ.get("PYTHONPATH", ""))
    r = subprocess.run([sys.executable, "-m", "bridge_jax.predict", "--checkpoint", name, str(a), str(b),
                        "--out", "o", "--raw", "npy"], cwd=tmp_path, env=env, capture_output=True, text=True,
                       timeout=300)
    assert r.returncode == 0, r.stderr[-2000:]
    npys = [os.path.join(dp, f) for dp, _, fs in os.walk(tmp_path / "o") for f in fs if f.endswith(".npy")]
    assert len(npys) == 1, npys
    flow = np.load(npys[0])
    gt, valid = sample["flow"], sample["valid_flow"]
    epe = np.linalg.norm(flow - gt, axis=-1)[valid].mean()
    zero = np.linalg.norm(gt, axis=-1)[valid].mean()
    assert epe < 0.8 * zero, (epe, zero)


def test_the_listing_says_how_to_get_weights_that_are_not_converted_yet(tmp_path, monkeypatch, capsys):
    from bridge_jax.zoo.__main__ import main
    monkeypatch.setenv(zoo.HOME_ENV, str(tmp_path))
    assert main([]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("upstream_ver_a"))
    assert "not converted yet" in line and "bridge-convert --from monodepth_ver_a.pth" in line
    assert str(tmp_path / "upstream_ver_a") in line


def test_earlier_stage_is_read_from_its_workdir_and_bad_values_are_refused(tmp_path, capsys):
    """`bridge-zoo build --earlier-stage CONFIG=WORKDIR`: the stage's steps (its last checkpoint), init_from, lr
    and wall time (first to last logged train step) come from its workdir; a malformed value or a folder that is
    not a finished run is one error line and exit code 2, before anything is written."""
    from bridge_jax.zoo.__main__ import main
    run = tmp_path / "stage1"
    (run / "checkpoints" / "250" / "state").mkdir(parents=True)
    (run / "checkpoints" / "4000" / "state").mkdir(parents=True)
    (run / "config.json").write_text(json.dumps({"init_from": "demo", "lr": 5e-4}))
    (run / "metrics.jsonl").write_text("\n".join(json.dumps(r) for r in [
        {"step": 25, "kind": "train", "time": 1000.0}, {"step": 500, "kind": "val", "time": 1500.0},
        {"step": 4000, "kind": "train", "time": 1000.0 + 7200.0}]) + "\n")
    stage = zoo.stage_summary("demo:long,real", run, machine="m")
    assert stage == {"config": "demo:long,real", "steps": 4000, "init_from": "demo", "lr": 5e-4, "seconds": 7200.0,
                     "machine": "m"}
    before = (zoo.ZOO_DIR / "long.json").read_bytes()
    assert main(["build", "long", "--from", str(run), "--earlier-stage", "no-equals-sign"]) == 2
    assert "expected CONFIG=WORKDIR" in capsys.readouterr().err
    assert main(["build", "long", "--from", str(run), "--earlier-stage", f"x={tmp_path / 'missing'}"]) == 2
    assert (zoo.ZOO_DIR / "long.json").read_bytes() == before


def test_after_shipped_takes_the_stages_from_the_shipped_card(tmp_path, capsys):
    """`--after-shipped CONFIG=NAME`: a run that continued shipped model NAME lists NAME's own earlier stages,
    then NAME itself (steps, init_from, lr, training time and machine from its card); a malformed value or a name
    that is not a shipped model is one error line and exit code 2, before anything is written."""
    from bridge_jax.zoo.__main__ import main
    meta = zoo.info("long")
    stages = zoo.shipped_stages("demo:long,real,selfsup", "long")
    assert stages[:-1] == meta.get("earlier_stages", [])
    assert stages[-1] == {"config": "demo:long,real,selfsup", "steps": meta["steps"],
                          "init_from": meta["config"]["init_from"], "lr": meta["config"]["lr"],
                          "seconds": meta["training"]["seconds"], "machine": meta["training"]["machine"]}
    before = (zoo.ZOO_DIR / "long.json").read_bytes()
    run = tmp_path / "run"
    run.mkdir()
    assert main(["build", "long", "--from", str(run), "--after-shipped", "no-equals"]) == 2
    assert "expected CONFIG=NAME" in capsys.readouterr().err
    assert main(["build", "long", "--from", str(run), "--after-shipped", "demo:long=nosuchmodel"]) == 2
    assert "not a shipped model" in capsys.readouterr().err
    assert (zoo.ZOO_DIR / "long.json").read_bytes() == before
