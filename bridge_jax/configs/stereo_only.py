r"""Paper ablation "stereo only": the network trained on the two stereo pairs of each cycle.

    bridge-train --config=bridge_jax/configs/stereo_only.py --workdir=work/stereo_only
"""

from bridge_jax.configs import default


def get_config(arg=None):
    return default.variant("stereo_only", arg, tasks="stereo_only")
