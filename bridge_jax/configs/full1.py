r"""Paper "full-1": flow+stereo plus the full-1 2-warp consistency terms (losses.py names the chains).

Paper recipe: initialise from a trained flow+stereo model.

    bridge-train --config=bridge_jax/configs/full1.py --workdir=work/full1 \
            --config.init_from=work/flow_stereo
"""

from bridge_jax.configs import default


def get_config(arg=None):
    return default.variant("full1", arg, tasks="flow_stereo", two_warp="full1")
