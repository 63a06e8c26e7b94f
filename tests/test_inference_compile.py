"""The network's compile modes ("fast" = XLA's LLVM back end at optimisation level 0) and how the commands pick
one: same maps as "full", separate compiled functions, the "auto" rule, and no padding of a single pair."""
import numpy as np
import pytest

from bridge_jax import inference, predict


def test_compile_mode_rule():
    n = inference.FAST_COMPILE_PAIRS
    assert inference.compile_mode_for("auto", 1) == "fast"
    assert inference.compile_mode_for("auto", n) == "fast"
    assert inference.compile_mode_for("auto", n + 1) == "full"
    assert inference.compile_mode_for("auto", None) == "full"  # unknown length (a stream): optimise
    assert inference.compile_mode_for("fast", 10 ** 6) == "fast"
    assert inference.compile_mode_for("full", 1) == "full"
    with pytest.raises(ValueError, match="compile mode 'quick'"):
        inference.compile_mode_for("quick", 1)


def test_fast_compile_gives_the_same_maps(tiny_checkpoint, rng):
    full = inference.load_predictor(tiny_checkpoint, size=(64, 128))
    fast = inference.load_predictor(tiny_checkpoint, size=(64, 128), compile_mode="fast")
    assert (full.compile_mode, fast.compile_mode) == ("full", "fast")
    pairs = rng.random((1, 64, 128, 6), dtype=np.float32)
    a, b = full.run_network(pairs), fast.run_network(pairs)
    assert np.abs(a).max() > 1e-3  # random weights still give a non-trivial map
    np.testing.assert_allclose(b, a, rtol=1e-4, atol=1e-5 * np.abs(a).max())
    # the option reaches XLA: the fast executable is compiled with its own options
    assert fast._net is not full._net and set(fast._jits) == {"fast"}
    # switching the mode of one predictor keeps both compiled functions
    fast.compile_mode = "full"
    np.testing.assert_allclose(fast.run_network(pairs), a, rtol=1e-6, atol=1e-7)
    assert set(fast._jits) == {"fast", "full"}


def test_number_of_pairs_of_a_source():
    src = predict.Source(kind="pair", stereo=False, frames=iter(()), num_frames=2)
    assert src.num_pairs == 1
    cycle = predict.Source(kind="cycle", stereo=True, frames=iter(()), num_frames=2)
    assert cycle.num_pairs == 3  # flow t -> t+1, disparity at t and at t+1
    video = predict.Source(kind="video", stereo=False, frames=iter(()), num_frames=None)
    assert video.num_pairs is None


class _Recorder:
    """A stand-in predictor that records the batch size each call asks for."""

    def __init__(self):
        self.batches = []

    def predict(self, jobs, batch):
        self.batches.append(batch)
        return [np.zeros(a.shape[:2] + ((2,) if t == "flow" else ()), np.float32) for t, a, _ in jobs]


def test_one_pair_is_not_padded_to_a_batch(tmp_path, rng):
    frames = [(rng.integers(0, 255, (64, 128, 3), dtype=np.uint8), None) for _ in range(2)]
    src = predict.Source(kind="pair", stereo=False, frames=iter(frames), num_frames=2)
    rec = _Recorder()
    predict.predict_source(rec, src, str(tmp_path / "out"), batch=4, progress=False, write_video=False)
    assert rec.batches == [1]
    frames = [(rng.integers(0, 255, (64, 128, 3), dtype=np.uint8), None) for _ in range(7)]
    src = predict.Source(kind="folder", stereo=False, frames=iter(frames), num_frames=7)
    rec = _Recorder()
    predict.predict_source(rec, src, str(tmp_path / "out2"), batch=4, progress=False, write_video=False)
    assert rec.batches == [4, 4]  # 6 pairs: a full batch, then the rest padded to the same compiled shape
