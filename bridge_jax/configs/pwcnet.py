r"""Supplementary variant: PWC-Net instead of the ResNet-MD network (flow+stereo loss).

Upstream forces a width of 832 for PWC-Net; we keep 512x256 by default (any multiple of 64 works).

    bridge-train --config=bridge_jax/configs/pwcnet.py --workdir=work/pwcnet
"""

from bridge_jax.configs import default


def get_config(arg=None):
    c = default.variant("pwcnet", arg, tasks="flow_stereo", two_warp="none")
    c.model = default.model_section("pwcnet")
    return c
