"""The paper's network P(I_a, I_b): a Monodepth-style ResNet-50 encoder-decoder, as the upstream code builds it.

Input: two RGB images in [0, 1] concatenated on channels, `(N, H, W, 6)` = [first(3), second(3)], H and W
multiples of 64. Output: the correspondence map from the first image to the second at 4 scales.

Encoder: conv1 7x7/2 (6 -> stem) + ELU = skip1 (H/2); max-pool 3x3/2 = skip2 (H/4); four bottleneck stages
(default 3/4/6/3 blocks, planes 64/128/256/512, output 4*planes) whose **last** block has stride 2, every
block with a 1x1 conv shortcut (even when shapes match) -> skip3 (H/8), skip4 (H/16), skip5 (H/32),
bottleneck (H/64). ELU everywhere, biases, no normalisation.

Decoder: stage upK = nearest x2 upsample -> 3x3 conv -> ELU -> concat [x, skip, udisp] -> 3x3 conv -> ELU.
Heads at 1/8, 1/4, 1/2, 1: frac = 0.3 * tanh(conv3x3(x)) (ch0 fraction of W_s, ch1 fraction of H_s),
px = frac * (W_s, H_s); udisp = nearest x2 upsample of frac, fed to the next stage.

Parameter names mirror the upstream PyTorch module (conv1, layer1..4 / "<i>" / conv1..3 + shortcut,
up6..up1 / conv1, conv2, get_disp4..1 / conv1) so a converted checkpoint is a renaming plus OIHW->HWIO.
The full configuration has 58,461,416 parameters; widths and depths are configuration, so the tiny test
variant runs exactly the same code.
"""
from __future__ import annotations

from collections.abc import Mapping

import jax
import jax.numpy as jnp
from flax import nnx

from bridge_jax.models.coordinates import with_coordinates
from bridge_jax.models.layers import (Conv, check_input_shape, elu, fill_config, max_pool_3x3_s2, upsample_nearest2x,
                                      upsample_nearest2x_conv3x3)

DEFAULT_CONFIG = {
    "name": "resnet_md",
    "in_channels": 6,
    "stem": 64,
    "planes": [64, 128, 256, 512],
    "blocks": [3, 4, 6, 3],
    "expansion": 4,
    "decoder": [512, 256, 128, 64, 32, 16],
    "subpixel_upconv": "auto",
    "head_init": "torch",
    "coords": False,
}
"""Full-size (paper) configuration. `decoder` = output widths of up6..up1. `subpixel_upconv` computes a
decoder's upsample+conv at low resolution (same maths, 4/9 of the FLOPs): True, False (literal upsample then
conv) or "auto" (by map size, see SUBPIXEL_MIN_PIXELS). `head_init`: "torch" (upstream: PyTorch's default
uniform law, like every other layer) or "zeros" (the 2-channel output convs start at zero, so every map
starts at exactly 0 = the zero-motion solution; see HEAD_PREFIXES). `coords`: append normalised x, y channels
to the input (conv1 then sees in_channels + 2; not in the paper)."""

HEAD_PREFIXES = ("get_disp",)
"""Top-level parameter names of the output convs (what `head_init="zeros"` zeroes)."""

TINY_CONFIG = {
    **DEFAULT_CONFIG,
    "name": "resnet_md_tiny",
    "stem": 8,
    "planes": [8, 16, 16, 32],
    "blocks": [1, 2, 1, 1],
    "decoder": [32, 16, 16, 8, 8, 8],
}
"""A ~0.1 M-parameter variant for tests: same code path, same scales, every block type exercised."""

HEAD_INITS = ("torch", "zeros")
MULTIPLE = 64
SUBPIXEL_MIN_PIXELS = 2048
"""`subpixel_upconv="auto"` uses the low-resolution form when the decoder input has at least this many pixels
(at 256x512: up3, up2, up1); on the small deep maps of up6..up4 the plain form is faster on XLA:CPU."""
"""H and W must be multiples of this (six stride-2 stages)."""


class Bottleneck(nnx.Module):
    """1x1 -> ELU -> 3x3 (stride here) -> ELU -> 1x1 to expansion*planes; + 1x1 conv shortcut; ELU."""

    def __init__(self, in_ch: int, planes: int, stride: int, expansion: int, *, rngs: nnx.Rngs):
        self.conv1 = Conv(in_ch, planes, 1, rngs=rngs)
        self.conv2 = Conv(planes, planes, 3, stride=stride, rngs=rngs)
        self.conv3 = Conv(planes, planes * expansion, 1, rngs=rngs)
        self.shortcut = Conv(in_ch, planes * expansion, 1, stride=stride, rngs=rngs)

    def __call__(self, x: jax.Array) -> jax.Array:
        y = elu(self.conv1(x))
        y = elu(self.conv2(y))
        y = self.conv3(y)
        return elu(y + self.shortcut(x))


class DecoderBlock(nnx.Module):
    """upsample x2 -> conv3x3 -> ELU -> concat([x, *extras]) -> conv3x3 -> ELU."""

    def __init__(self, in_ch: int, out_ch: int, concat_ch: int, subpixel: bool | str, *, rngs: nnx.Rngs):
        self.subpixel = subpixel
        self.conv1 = Conv(in_ch, out_ch, 3, rngs=rngs)
        self.conv2 = Conv(out_ch + concat_ch, out_ch, 3, rngs=rngs)

    def __call__(self, x: jax.Array, *extras: jax.Array) -> jax.Array:
        sub = self.subpixel
        if sub == "auto":  # low-res phase convs win on large, few-channel maps; lose on tiny deep ones
            sub = x.shape[1] * x.shape[2] >= SUBPIXEL_MIN_PIXELS
        if sub:
            x = upsample_nearest2x_conv3x3(x, self.conv1.kernel[...], self.conv1.bias[...])
        else:
            x = self.conv1(upsample_nearest2x(x))
        x = elu(x)
        x = jnp.concatenate([x, *extras], axis=-1)
        return elu(self.conv2(x))


class DispHead(nnx.Module):
    """3x3 conv to 2 channels -> frac = 0.3 tanh; px = frac * (W_s, H_s). Computed in float32."""

    def __init__(self, in_ch: int, *, rngs: nnx.Rngs):
        self.conv1 = Conv(in_ch, 2, 3, rngs=rngs)

    def __call__(self, x: jax.Array) -> tuple[jax.Array, jax.Array]:
        frac = 0.3 * jnp.tanh(self.conv1(x).astype(jnp.float32))
        h, w = x.shape[1:3]
        px = frac * jnp.array([w, h], jnp.float32)
        return frac, px


class MonodepthResNet(nnx.Module):
    """See the module docstring. `__call__(pair (N, H, W, 6)) -> {"px": (s0..s3), "frac": (s0..s3)}`."""

    def __init__(self, config: Mapping, *, rngs: nnx.Rngs):
        stem, planes, blocks = int(config["stem"]), list(config["planes"]), list(config["blocks"])
        expansion, dec = int(config["expansion"]), list(config["decoder"])
        sub = config.get("subpixel_upconv", "auto")
        if sub not in ("auto", True, False):
            raise ValueError(f"subpixel_upconv must be 'auto', true or false, got {sub!r}")
        if len(planes) != 4 or len(blocks) != 4 or len(dec) != 6 or min(blocks) < 1:
            raise ValueError(f"resnet_md config needs 4 planes, 4 block counts >= 1 and 6 decoder widths, "
                             f"got planes={planes}, blocks={blocks}, decoder={dec}")
        self.coords = bool(config.get("coords", False))
        self.conv1 = Conv(int(config["in_channels"]) + (2 if self.coords else 0), stem, 7, stride=2, rngs=rngs)
        in_ch = stem
        for s in range(4):
            stage = {}
            for i in range(blocks[s]):
                stride = 2 if i == blocks[s] - 1 else 1
                stage[str(i)] = Bottleneck(in_ch, planes[s], stride, expansion, rngs=rngs)
                in_ch = planes[s] * expansion
            setattr(self, f"layer{s + 1}", nnx.Dict(stage))
        skip = [stem, stem, planes[0] * expansion, planes[1] * expansion, planes[2] * expansion]  # skip1..5
        bottleneck = planes[3] * expansion
        self.up6 = DecoderBlock(bottleneck, dec[0], skip[4], sub, rngs=rngs)
        self.up5 = DecoderBlock(dec[0], dec[1], skip[3], sub, rngs=rngs)
        self.up4 = DecoderBlock(dec[1], dec[2], skip[2], sub, rngs=rngs)
        self.get_disp4 = DispHead(dec[2], rngs=rngs)
        self.up3 = DecoderBlock(dec[2], dec[3], skip[1] + 2, sub, rngs=rngs)
        self.get_disp3 = DispHead(dec[3], rngs=rngs)
        self.up2 = DecoderBlock(dec[3], dec[4], skip[0] + 2, sub, rngs=rngs)
        self.get_disp2 = DispHead(dec[4], rngs=rngs)
        self.up1 = DecoderBlock(dec[4], dec[5], 2, sub, rngs=rngs)
        self.get_disp1 = DispHead(dec[5], rngs=rngs)

    def encode(self, x: jax.Array) -> tuple[jax.Array, ...]:
        """`(N,H,W,6) -> (skip1 H/2, skip2 H/4, skip3 H/8, skip4 H/16, skip5 H/32, bottleneck H/64)`."""
        skip1 = elu(self.conv1(x))
        x = skip2 = max_pool_3x3_s2(skip1)
        outs = [skip1, skip2]
        for s in range(1, 5):
            stage = getattr(self, f"layer{s}")
            for i in range(len(stage)):
                x = stage[str(i)](x)
            outs.append(x)
        return tuple(outs)

    def forward_with_activations(self, pair: jax.Array) -> tuple[dict, dict[str, jax.Array]]:
        """Like `__call__`, plus the intermediate activations named as upstream's fixture (`conv1`, `pool1`,
        `layer1..4`, `up6..up1`), for locating a numerical mismatch."""
        check_input_shape(pair, MULTIPLE)
        skip1, skip2, skip3, skip4, skip5, x = self.encode(with_coordinates(pair) if self.coords else pair)
        acts = {"conv1": skip1, "pool1": skip2, "layer1": skip3, "layer2": skip4, "layer3": skip5, "layer4": x}
        x = acts["up6"] = self.up6(x, skip5)
        x = acts["up5"] = self.up5(x, skip4)
        x = acts["up4"] = self.up4(x, skip3)
        frac4, px4 = self.get_disp4(x)
        x = acts["up3"] = self.up3(x, skip2, upsample_nearest2x(frac4.astype(x.dtype)))
        frac3, px3 = self.get_disp3(x)
        x = acts["up2"] = self.up2(x, skip1, upsample_nearest2x(frac3.astype(x.dtype)))
        frac2, px2 = self.get_disp2(x)
        x = acts["up1"] = self.up1(x, upsample_nearest2x(frac2.astype(x.dtype)))
        frac1, px1 = self.get_disp1(x)
        return {"px": (px1, px2, px3, px4), "frac": (frac1, frac2, frac3, frac4)}, acts

    def __call__(self, pair: jax.Array) -> dict[str, tuple[jax.Array, ...]]:
        return self.forward_with_activations(pair)[0]


def build(config: Mapping, rngs: nnx.Rngs) -> MonodepthResNet:
    return MonodepthResNet(config, rngs=rngs)


def normalize_config(config: Mapping) -> dict:
    """Fill defaults and return a JSON-serialisable dict (lists, ints, bools)."""
    base = TINY_CONFIG if config.get("name") == "resnet_md_tiny" else DEFAULT_CONFIG
    return fill_config(config, base, lists=("planes", "blocks", "decoder"), bools=("coords",), head_inits=HEAD_INITS)
