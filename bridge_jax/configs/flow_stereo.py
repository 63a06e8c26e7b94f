r"""Paper "flow+stereo": one shared network on all four pairs, no 2-warp (= default.py, named explicitly).

This is the model the full-1/2/3 variants start from (`--config.init_from`).

    bridge-train --config=bridge_jax/configs/flow_stereo.py --workdir=work/flow_stereo
"""

from bridge_jax.configs import default


def get_config(arg=None):
    return default.variant("flow_stereo", arg, tasks="flow_stereo", two_warp="none")
