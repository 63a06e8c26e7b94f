"""What a workdir says after a restart: metrics.jsonl without the records of a killed attempt that never finished a
checkpoint (a single run and a recipe stage), and status.json's "last_checkpoint" naming only a checkpoint whose
save has finished."""
from __future__ import annotations

import json
import os

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import checkpointing, workdir as workdir_mod
from bridge_jax.workdir import METRICS_JSONL, MetricsLogger, truncate_metrics


def _write(path, records) -> None:
    path.write_text("".join(json.dumps(r) + "\n" for r in records))


def _read(path) -> list[tuple]:
    return [(r["step"], r["kind"], r.get("stage")) for r in map(json.loads, path.read_text().splitlines())]


# --------------------------------------------------------------------------------------------------------
# metrics.jsonl after a restart from scratch
# --------------------------------------------------------------------------------------------------------

def test_a_restart_from_scratch_drops_every_record_of_the_killed_attempt(tmp_path):
    """Killed while writing its first checkpoint: the attempt logged its step-0 validation and steps 1-2; the
    restart logs them again, so none of them may stay (step 1 twice otherwise)."""
    path = tmp_path / METRICS_JSONL
    _write(path, [{"step": 0, "kind": "val"}, {"step": 1, "kind": "train"}, {"step": 2, "kind": "train"}])
    logger = MetricsLogger(str(tmp_path), True, resume_step=0)
    logger.scalars(0, {"flow_epe_all": 1.0}, kind="val")
    logger.scalars(1, {"loss": 2.0})
    logger.close()
    assert _read(path) == [(0, "val", None), (1, "train", None)]


def test_a_resume_from_a_checkpoint_keeps_the_records_up_to_it(tmp_path):
    path = tmp_path / METRICS_JSONL
    _write(path, [{"step": 0, "kind": "val"}, {"step": 1, "kind": "train"}, {"step": 2, "kind": "train"},
                  {"step": 2, "kind": "val"}, {"step": 3, "kind": "train"}])
    MetricsLogger(str(tmp_path), True, resume_step=2).close()
    assert _read(path) == [(0, "val", None), (1, "train", None), (2, "train", None), (2, "val", None)]


def test_a_stage_restarting_from_scratch_keeps_the_previous_stages_last_step(tmp_path):
    """Stage "finish" starts at recipe step 4, the last step of stage "coarse": coarse's records of step 4 stay,
    those a killed attempt of finish wrote (its start record at step 4 included) go."""
    path = tmp_path / METRICS_JSONL
    coarse = [{"step": s, "kind": k, "stage": "coarse", "stage_step": s} for s, k in ((3, "train"), (4, "train"),
                                                                                     (4, "val"))]
    finish = [{"step": 4, "kind": "stage_start", "stage": "finish", "stage_step": 0},
              {"step": 5, "kind": "train", "stage": "finish", "stage_step": 1}]
    _write(path, coarse + finish)
    logger = MetricsLogger(str(tmp_path), True, resume_step=0, stage={"name": "finish", "offset": 4})
    logger.stage_start(1, 2)
    logger.close()
    assert _read(path) == [(3, "train", "coarse"), (4, "train", "coarse"), (4, "val", "coarse"),
                           (4, "stage_start", "finish")]


def test_truncate_metrics_restart_drops_the_restart_step_too_of_that_stage_only(tmp_path):
    path = tmp_path / METRICS_JSONL
    records = [{"step": 1, "kind": "train", "stage": "a"}, {"step": 2, "kind": "val", "stage": "a"},
               {"step": 2, "kind": "stage_start", "stage": "b"}, {"step": 3, "kind": "train", "stage": "b"}]
    _write(path, records)
    assert truncate_metrics(str(path), 2) == 1  # a resume at step 2: the records of step 2 stay
    _write(path, records)
    assert truncate_metrics(str(path), 2, restart=True, stage="b") == 2
    assert _read(path) == [(1, "train", "a"), (2, "val", "a")]
    _write(path, records)
    assert truncate_metrics(str(path), 2, restart=True) == 3  # a single run: every record of that step
    assert _read(path) == [(1, "train", "a")]


# --------------------------------------------------------------------------------------------------------
# status.json's last_checkpoint: finished saves only
# --------------------------------------------------------------------------------------------------------

def _state(v: float) -> dict:
    return {"params": {"w": jnp.full((8,), v, jnp.float32)}, "step": jnp.int32(int(v))}


def test_status_written_during_an_async_save_names_the_previous_finished_checkpoint(tmp_path, monkeypatch):
    wd = tmp_path / "wd"
    ck = checkpointing.TrainCheckpointer(wd, save_every=1, keep=3, async_save=True)
    assert ck.save(1, _state(1.0), {"next_index": 1})
    ck.wait()
    assert ck.save(2, _state(2.0), {"next_index": 2})
    ck.manager.wait_until_finished()  # step 2 on disk; orbax is then told to say it is still writing it:
    monkeypatch.setattr(ck.manager, "is_saving_in_progress", lambda: True)  # deterministic, unlike a real race
    assert 2 in ck.all_steps()  # orbax lists a step from the moment its save starts
    status = workdir_mod.RunStatus(str(wd), True, heartbeat_s=60.0, step=2)
    status.update(step=2, last_checkpoint=ck.latest_step())  # what the training loop writes at a log interval
    assert json.loads((wd / workdir_mod.STATUS_JSON).read_text())["last_checkpoint"] == 1
    monkeypatch.setattr(ck.manager, "is_saving_in_progress", lambda: False)
    assert ck.latest_step() == 2  # finished: named from now on
    status.end("finished", last_checkpoint=ck.latest_step())
    ck.close()
    assert json.loads((wd / workdir_mod.STATUS_JSON).read_text())["last_checkpoint"] == 2


def test_a_step_that_orbax_lists_without_a_folder_is_not_a_checkpoint(tmp_path, monkeypatch):
    """After a failed write (a full disk) the partial step is removed; whatever orbax still lists, the last
    checkpoint is the one whose folder exists."""
    wd = tmp_path / "wd"
    ck = checkpointing.TrainCheckpointer(wd, save_every=1, keep=3, async_save=False)
    assert ck.save(1, _state(1.0), {"next_index": 1})
    monkeypatch.setattr(ck.manager, "all_steps", lambda: [1, 2])
    assert not (wd / "checkpoints" / "2").exists() and ck.latest_step() == 1
    ck.close()
    restored, _ = checkpointing.TrainCheckpointer(wd).restore(1, jax.tree.map(
        lambda x: jax.ShapeDtypeStruct(x.shape, x.dtype), _state(0.0)))
    np.testing.assert_array_equal(restored["params"]["w"], np.full((8,), 1.0, np.float32))
    assert os.listdir(wd / "checkpoints") == ["1"]
