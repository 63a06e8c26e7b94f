r"""Paper "full-2": flow+stereo plus the full-2 2-warp consistency terms (losses.py names the chains).

Paper recipe: initialise from a trained flow+stereo model.

    bridge-train --config=bridge_jax/configs/full2.py --workdir=work/full2 \
            --config.init_from=work/flow_stereo
"""

from bridge_jax.configs import default


def get_config(arg=None):
    return default.variant("full2", arg, tasks="flow_stereo", two_warp="full2")
