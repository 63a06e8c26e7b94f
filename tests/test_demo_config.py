"""configs/demo.py: the demo's two phases and the stages of the shipped `long` model."""

from __future__ import annotations

import pytest

from bridge_jax.configs import demo


def test_second_phase_is_the_first_at_twice_the_size_from_its_weights():
    first, second = demo.get_config(), demo.get_config("finish")
    assert (first.height, first.width) == (64, 128) and (second.height, second.width) == (128, 256)
    assert first.init_from == "" and second.init_from == "work/demo/train_64x128"
    # the same loss, model and data; a constant lr (one epoch = the whole phase), the first phase's last one
    assert second.loss.to_dict() == first.loss.to_dict() and second.model.to_dict() == first.model.to_dict()
    assert second.data.to_dict() == first.data.to_dict() and second.global_batch == first.global_batch == 1
    assert second.loop.steps_per_epoch == second.loop.num_train_steps == demo.FINISH_STEPS
    # the second phase continues the first's schedule: the lr of the halving at the step where the first ends
    halvings = sum(1 for e in first.lr_milestones if e * first.loop.steps_per_epoch <= first.loop.num_train_steps)
    assert halvings == 2 and second.lr == pytest.approx(first.lr / 2 ** halvings)
    assert demo.get_config("finish,short").loop.num_train_steps == 10
    with pytest.raises(ValueError, match="'finish' is the demo's second phase"):
        demo.get_config("long,finish")


def test_long_stages_apply_in_order_and_refuse_a_missing_one():
    """Each argument of `long` sets its stage on top of the ones before it; one given without the stages it builds
    on is refused (it used to be ignored)."""
    s4 = demo.get_config("long,real,selfsup,motion,census")
    s5 = demo.get_config("long,real,selfsup,motion,census,hires")
    assert (s4.init_from, s5.init_from) == ("work/long3", "work/long4")
    assert (s4.height, s5.height) == (128, 256) and (s4.lr, s5.lr) == (1.25e-4, 1.25e-4)
    assert s5.loss.photometric == "census" and s5.data.synthetic_scene == "real_motion"
    assert s5.loss.self_supervision == 0.3 and s5.data.augment_shift == 0.08
    assert demo.get_config("real").data.synthetic_scene == "real" and demo.get_config("real").init_from == ""
    for arg, missing in (("long,real,hires", "'selfsup', 'motion', 'census'"), ("selfsup", "'long', 'real'"),
                         ("long,real,selfsup,census", "'motion'")):
        with pytest.raises(ValueError, match=f"needs \\[{missing}\\] too"):
            demo.get_config(arg)
