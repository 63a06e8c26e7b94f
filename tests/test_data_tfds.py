"""TFDS builder kitti_cycles: build from a tiny fake KITTI raw folder, read back without TensorFlow."""
import os
import sys

import numpy as np
import pytest

from bridge_jax.data import kitti, pipeline
from tests.test_data_fakes import make_fake_raw, truncate_file


def test_tfds_round_trip_without_tensorflow(tmp_path):
    from bridge_jax.data import tfds_kitti_cycles as tkc

    raw = make_fake_raw(str(tmp_path / "raw"), {"2011_09_26_drive_0001": 3, "2011_09_28_drive_0002": 2},
                        height=10, width=14)
    bad = os.path.join(raw, "2011_09_28", "2011_09_28_drive_0002_sync", "image_02", "data", "0000000001.png")
    truncate_file(bad)                                      # the only cycle of drive_0002 is left out
    tkc.build(manual_dir=raw, data_dir=str(tmp_path / "tfds"), config="all")
    src = tkc.open_data_source(str(tmp_path / "tfds"), "all")
    assert len(src) == 2
    records = {r["id"]: r for r in kitti.raw_cycles(raw, "all")}
    got = sorted(tkc.decode_example(src[i])["id"] for i in range(len(src)))
    assert got == ["2011_09_26_drive_0001/0000000000", "2011_09_26_drive_0001/0000000001"]
    for i in range(len(src)):
        ex = tkc.decode_example(src[i])
        ref = np.stack([kitti.read_image(p) for p in records[ex["id"]]["paths"]])
        np.testing.assert_array_equal(ex["cycle"], ref)
        assert ex["focal"] == pytest.approx(721.5377) and ex["baseline"] == pytest.approx(0.5327, abs=1e-3)
    # As a grain source of the training pipeline.
    ds = pipeline.make_train_dataset(pipeline.DataConfig(source="tfds", data_dir=str(tmp_path / "tfds"), split="all",
                                      augment=False), global_batch=2, seed=0, height=10, width=14,
                                     process_index=0, process_count=1)
    b = next(iter(ds))["cycle"]
    assert b.shape == (2, 4, 10, 14, 3)
    assert "tensorflow" not in sys.modules


def test_tfds_missing_dataset_clear_error(tmp_path):
    from bridge_jax.data import tfds_kitti_cycles as tkc
    with pytest.raises(ValueError, match="build it with"):
        tkc.open_data_source(str(tmp_path / "none"), "all")
    with pytest.raises(ValueError, match="manual_dir"):
        tkc.build(manual_dir=str(tmp_path / "nothing"), data_dir=str(tmp_path / "t"))
