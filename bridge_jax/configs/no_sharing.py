r"""Paper ablation "without sharing weights": separate stereo and flow networks.

Stereo pairs go through one ResNet-MD, flow pairs through another; the loss is the flow+stereo loss.

    bridge-train --config=bridge_jax/configs/no_sharing.py --workdir=work/no_sharing
"""

from bridge_jax.configs import default


def get_config(arg=None):
    c = default.variant("no_sharing", arg, tasks="flow_stereo", two_warp="none")
    c.separate_networks = True
    return c
