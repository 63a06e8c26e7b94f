r"""Paper ablation "flow only": the network trained on the two optical-flow pairs of each cycle.

    bridge-train --config=bridge_jax/configs/flow_only.py --workdir=work/flow_only
"""

from bridge_jax.configs import default


def get_config(arg=None):
    return default.variant("flow_only", arg, tasks="flow_only")
