"""Building blocks shared by the networks: PyTorch-convention convolutions on NHWC arrays.

Why not `flax.nnx.Conv`: the ported networks must match PyTorch numerics exactly (so converted upstream
weights behave the same). PyTorch pads *symmetrically* (`padding=k//2` on both sides, also for stride 2),
whereas `'SAME'` pads stride-2 convs asymmetrically; and PyTorch's default init differs from Flax's.

Performance: on XLA:CPU a 1x1 convolution is written as a `jnp.dot` over the channel axis, whose weight gradient
is several times faster than the equivalent `lax.conv`'s; the wider 3x3 (and sub-pixel 2x2) convolutions get
their weight gradient as one matmul per kernel tap for the same reason (`conv_nhwc`, `WEIGHT_GRAD_METHODS`;
`bridge-bench --what conv_backward` times every method on the machine at hand).

Parameter layout: kernels are HWIO `(kh, kw, in, out)` (PyTorch OIHW permuted (2, 3, 1, 0)); biases `(out,)`.
"""
from __future__ import annotations

import contextlib
import contextvars
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from jax import lax

_DN = ("NHWC", "HWIO", "NHWC")


def torch_uniform_init(fan_in: int):
    """PyTorch's default `nn.Conv2d` init: U(-1/sqrt(fan_in), 1/sqrt(fan_in)) for weight and bias.

    (kaiming_uniform with a=sqrt(5) gives exactly this bound for the weight.)
    """
    bound = 1.0 / math.sqrt(fan_in)

    def init(key, shape, dtype=jnp.float32):
        return jax.random.uniform(key, shape, dtype, -bound, bound)

    return init


def kaiming_normal_init(fan_in: int):
    """`nn.init.kaiming_normal_(w, mode='fan_in')` (gain sqrt(2)): N(0, 2/fan_in)."""
    std = math.sqrt(2.0 / fan_in)

    def init(key, shape, dtype=jnp.float32):
        return std * jax.random.normal(key, shape, dtype)

    return init


def zeros_init(key, shape, dtype=jnp.float32):
    del key
    return jnp.zeros(shape, dtype)


_SHAPES_ONLY = contextvars.ContextVar("bridge_jax_shapes_only", default=False)


@contextlib.contextmanager
def shapes_only():
    """Inside, the layers below build their params as `jax.ShapeDtypeStruct`s and draw no random numbers.

    The same module structure (and GraphDef) as a real build, without tracing one initializer: `nnx.eval_shape`
    traces each of them (~0.1-0.4 s for pwc_lite, paid by every prediction that loads a model)."""
    token = _SHAPES_ONLY.set(True)
    try:
        yield
    finally:
        _SHAPES_ONLY.reset(token)


def new_param(init, rngs: nnx.Rngs | None, shape: tuple[int, ...]) -> nnx.Param:
    """`nnx.Param(init(rngs.params(), shape))` (float32; `rngs=None`: no key drawn, for constant inits), or its
    shape alone under `shapes_only()`."""
    if _SHAPES_ONLY.get():
        return nnx.Param(jax.ShapeDtypeStruct(tuple(shape), jnp.float32))
    return nnx.Param(init(rngs.params() if rngs is not None else None, shape))


def elu(x: jax.Array) -> jax.Array:
    """ELU with alpha = 1 (`nn.ELU()`)."""
    return jax.nn.elu(x)


def leaky_relu(x: jax.Array, slope: float = 0.1) -> jax.Array:
    """`nn.LeakyReLU(0.1)`."""
    return jnp.where(x >= 0, x, slope * x)


def conv2d(x: jax.Array, kernel: jax.Array, bias: jax.Array | None = None, *, stride: int = 1,
           padding: int | None = None, dilation: int = 1) -> jax.Array:
    """PyTorch `F.conv2d` semantics on NHWC data.

    Args:
      x: `(N, H, W, Cin)`.
      kernel: `(k, k, Cin, Cout)` HWIO.
      bias: `(Cout,)` or None.
      stride: spatial stride (same in both axes).
      padding: symmetric zero padding on every side; default `dilation * (k // 2)` (PyTorch's usual choice).
      dilation: kernel dilation.

    Returns:
      `(N, H_out, W_out, Cout)` with `H_out = floor((H + 2p - dilation*(k-1) - 1) / stride) + 1`.
    """
    k = kernel.shape[0]
    if padding is None:
        padding = dilation * (k // 2)
    kernel = kernel.astype(x.dtype)
    if k == 1 and kernel.shape[1] == 1 and padding == 0:
        # 1x1 conv == per-pixel matmul; XLA:CPU runs its weight gradient much faster as a dot.
        xs = x[:, ::stride, ::stride, :] if stride > 1 else x
        y = jnp.dot(xs, kernel[0, 0])
    elif _use_im2col(x.shape, kernel.shape, stride, dilation):
        y = _conv_im2col(x, kernel, padding)
    else:
        y = conv_nhwc(x, kernel, stride, ((padding, padding), (padding, padding)), dilation)
    if bias is not None:
        y = y + bias.astype(y.dtype)
    return y


IM2COL_MAX_PIXELS = 256
IM2COL_MIN_CHANNELS = 1024


def _use_im2col(x_shape, k_shape, stride, dilation) -> bool:
    """XLA:CPU's conv runs at a fraction of its usual speed on tiny maps with very many channels (e.g. the
    decoder's first 3x3 conv, 2048 channels at 8x16); one big matmul over im2col patches is ~2x faster there."""
    return (stride == 1 and dilation == 1 and x_shape[1] * x_shape[2] <= IM2COL_MAX_PIXELS
            and x_shape[3] >= IM2COL_MIN_CHANNELS)


def _shifted_views(x: jax.Array, kh: int, kw: int, stride: int, padding, dilation: int = 1) -> list[jax.Array]:
    """The `kh * kw` views of `x (N, H, W, C)`, zero-padded by `((top, bottom), (left, right))`, that kernel tap
    (i, j) sees, row-major over taps, each `(N, H_out, W_out, C)`:
    view[i * kw + j][n, h, w] = xpad[n, d*i + stride*h, d*j + stride*w]."""
    _, h, w, _ = x.shape
    (top, bottom), (left, right) = padding
    xp = jnp.pad(x, ((0, 0), (top, bottom), (left, right), (0, 0)))
    ho = (h + top + bottom - dilation * (kh - 1) - 1) // stride + 1
    wo = (w + left + right - dilation * (kw - 1) - 1) // stride + 1
    return [xp[:, dilation * i:dilation * i + stride * (ho - 1) + 1:stride,
               dilation * j:dilation * j + stride * (wo - 1) + 1:stride]
            for i in range(kh) for j in range(kw)]


def _conv_im2col(x: jax.Array, kernel: jax.Array, padding: int) -> jax.Array:
    """Stride-1 conv as `(N*H*W, k*k*Cin) @ (k*k*Cin, Cout)` (same result as `lax.conv`, HWIO kernel)."""
    kh, kw = kernel.shape[:2]
    cols = jnp.concatenate(_shifted_views(x, kh, kw, 1, ((padding, padding), (padding, padding))), axis=-1)
    return jnp.dot(cols, kernel.reshape(kh * kw * kernel.shape[2], kernel.shape[3]))


# ##########################################################################################################
# The weight gradient of a convolution
# ##########################################################################################################

WEIGHT_GRAD_METHODS = ("auto", "xla", "shift_dy", "shift_x", "xla_chunks")
"""How a convolution's weight gradient dW[i, j] = sum_{n, o} x[n, s*o + d*(i, j) - p]^T dy[n, o] is computed:

- "xla": XLA's own backward-filter convolution.
- "shift_dy": one matmul per kernel tap (i, j) between the input x `(N, H, W, Cin)`, unchanged, and the output
  gradient dy placed where that tap reads x (`lax.pad`: zero-filled shift, and for stride s zeros between the
  rows and columns), contracting N, H and W. On XLA:CPU this runs 1.5-3x faster than XLA's backward-filter
  convolution for this network's layers with >= 64 input channels (`bridge-bench --what conv_backward`); it loses on
  the full-resolution layers with 16-32 channels, where the shifted dy copies cost more than the matmuls gain.
- "shift_x": one matmul per tap between the shifted input view and dy (the input is the side that is copied).
- "xla_chunks": XLA's backward-filter convolution on chunks of `WEIGHT_GRAD_CHUNK` rows of the batch, summed
  (XLA:CPU's is slower than linear in the batch on some layers).
- "auto" (the default), on the CPU backend: "shift_dy" for stride-1 convolutions with at least
  `SHIFT_DY_MIN_CHANNELS` input channels; "xla_chunks" for the large-kernel stem on the image pair (kernel
  >= 5, at most `STEM_MAX_CHANNELS` input channels), whose backward-filter convolution takes 1.27 s for 16
  pair-forwards at 512x256 in one piece and 0.43 s in chunks of 2; "xla" for everything else. CPUs without
  AVX-512 (`cpu_vector_isa`) differ at stride 2: there "shift_x" for strided convolutions with at least
  `SHIFT_X_MIN_CHANNELS` input channels and for the stem (measured on a 2-core AVX2-only AMD EPYC VM,
  2026-12-01, batch 16: 128->128 at 64x128 2.66 -> 0.55 s, 256->256 0.66 -> 0.34 s, 512->512 0.34 -> 0.27 s,
  the 7x7 stem 5.65 s (xla), 5.33 s (xla_chunks), 2.67 s (shift_x); at stride 1 the AVX-512 rule held there
  too). On GPU/TPU always "xla" (cuDNN's backward is fast).

The forward pass and the input gradient are XLA's in every method; the gradients agree to float32 rounding.
`Network(conv_weight_grad=...)` (config key `conv_weight_grad`) picks the method for a network's forward."""

SHIFT_DY_MIN_CHANNELS = 64
SHIFT_X_MIN_CHANNELS = 64
"""Without AVX-512, "auto" computes strided convolutions' weight gradients by "shift_x" from this many input
channels (the smallest measured there was 128; pwc_lite's narrower strided pyramid convs keep XLA's)."""
STEM_MAX_CHANNELS = 8
WEIGHT_GRAD_CHUNK = 2

_WEIGHT_GRAD = contextvars.ContextVar("bridge_jax_conv_weight_grad", default="auto")


@contextlib.contextmanager
def weight_grad_method(method: str):
    """Within this context (at trace time), convolutions compute their weight gradient by `method`, one of
    `WEIGHT_GRAD_METHODS`."""
    if method not in WEIGHT_GRAD_METHODS:
        raise ValueError(f"conv_weight_grad must be one of {list(WEIGHT_GRAD_METHODS)}, got {method!r}")
    token = _WEIGHT_GRAD.set(method)
    try:
        yield
    finally:
        _WEIGHT_GRAD.reset(token)


def resolve_weight_grad(x_shape, k_shape, stride: int, method: str | None = None) -> str:
    """The method ("xla", "shift_dy", "shift_x" or "xla_chunks") a convolution of these shapes uses under
    `method` (default: the current `weight_grad_method` context's)."""
    method = _WEIGHT_GRAD.get() if method is None else method
    if method != "auto":
        return method
    if jax.default_backend() != "cpu":
        return "xla"
    if stride == 1 and x_shape[3] >= SHIFT_DY_MIN_CHANNELS:
        return "shift_dy"
    stem = min(k_shape[:2]) >= 5 and x_shape[3] <= STEM_MAX_CHANNELS
    if cpu_vector_isa() in ("AVX2", "older") and stride > 1 and (stem or x_shape[3] >= SHIFT_X_MIN_CHANNELS):
        return "shift_x"
    if stem and x_shape[0] > WEIGHT_GRAD_CHUNK:
        return "xla_chunks"
    return "xla"


@functools.lru_cache(maxsize=None)
def cpu_vector_isa() -> str | None:
    """The widest x86 vector ISA this CPU reports: "AVX-512", "AVX2" or "older"; None where /proc/cpuinfo is
    missing (not Linux) or has no x86 flags (e.g. ARM). XLA:CPU's convolution kernels differ between the kinds,
    so the fastest weight-gradient method does too (`resolve_weight_grad`). None keeps the AVX-512 rule."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("flags"):
                    flags = set(line.split(":", 1)[1].split())
                    return "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else "older"
    except OSError:
        pass
    return None


def _lax_conv(x, kernel, stride: int, padding, dilation: int):
    return lax.conv_general_dilated(x, kernel, (stride, stride), [tuple(p) for p in padding],
                                    rhs_dilation=(dilation, dilation), dimension_numbers=_DN)


def conv_nhwc(x: jax.Array, kernel: jax.Array, stride: int = 1, padding=((0, 0), (0, 0)),
              dilation: int = 1) -> jax.Array:
    """`lax.conv_general_dilated` on NHWC / HWIO with padding `((top, bottom), (left, right))`, whose weight
    gradient is computed by the method `resolve_weight_grad` picks (see `WEIGHT_GRAD_METHODS`)."""
    padding = tuple((int(a), int(b)) for a, b in padding)
    method = resolve_weight_grad(x.shape, kernel.shape, stride)
    if method == "xla":
        return _lax_conv(x, kernel, stride, padding, dilation)
    return _conv_custom_wgrad(x, kernel, stride, padding, dilation, method)


@functools.partial(jax.custom_vjp, nondiff_argnums=(2, 3, 4, 5))
def _conv_custom_wgrad(x, kernel, stride, padding, dilation, method):
    return _lax_conv(x, kernel, stride, padding, dilation)


def _conv_custom_wgrad_fwd(x, kernel, stride, padding, dilation, method):
    return _lax_conv(x, kernel, stride, padding, dilation), (x, kernel)


def _conv_custom_wgrad_bwd(stride, padding, dilation, method, res, dy):
    x, kernel = res
    _, vjp_x = jax.vjp(lambda a: _lax_conv(a, kernel, stride, padding, dilation), x)
    (dx,) = vjp_x(dy)
    wgrad = {"shift_dy": weight_grad_shift_dy, "shift_x": weight_grad_shift_x,
             "xla_chunks": weight_grad_xla_chunks}[method]
    dk = wgrad(x, dy, kernel.shape, stride, padding, dilation).astype(kernel.dtype)
    return dx, dk


_conv_custom_wgrad.defvjp(_conv_custom_wgrad_fwd, _conv_custom_wgrad_bwd)

_CONTRACT_NHW = (((0, 1, 2), (0, 1, 2)), ((), ()))


def weight_grad_shift_dy(x, dy, k_shape, stride: int, padding, dilation: int = 1) -> jax.Array:
    """dW `(kh, kw, Cin, Cout)` of a convolution from its input `x (N, H, W, Cin)` and output gradient
    `dy (N, Ho, Wo, Cout)`, one matmul per tap with dy moved onto the input grid.

    Tap (i, j) reads x at q = s*o + d*(i, j) - (top, left) for output pixel o, so dy padded by lo = d*i - top
    (negative = cropped), s - 1 zeros between rows and hi = H - 1 - (s*(Ho - 1) + lo) is dy_ij with
    dy_ij[q] = dy[o]; then dW[i, j] = sum_{n, q} x[n, q]^T dy_ij[n, q]."""
    kh, kw = k_shape[:2]
    (top, _), (left, _) = padding
    h, w = x.shape[1:3]
    ho, wo = dy.shape[1:3]
    zero = jnp.zeros((), dy.dtype)
    acc = jnp.promote_types(x.dtype, jnp.float32)  # bf16 inputs still sum in float32
    taps = []
    for i in range(kh):
        for j in range(kw):
            lo_h, lo_w = dilation * i - top, dilation * j - left
            cfg = ((0, 0, 0), (lo_h, h - 1 - (stride * (ho - 1) + lo_h), stride - 1),
                   (lo_w, w - 1 - (stride * (wo - 1) + lo_w), stride - 1), (0, 0, 0))
            taps.append(lax.dot_general(x, lax.pad(dy, zero, cfg), _CONTRACT_NHW, preferred_element_type=acc))
    return jnp.stack(taps).reshape(k_shape)


def weight_grad_xla_chunks(x, dy, k_shape, stride: int, padding, dilation: int = 1) -> jax.Array:
    """dW as XLA's backward-filter convolution on `WEIGHT_GRAD_CHUNK` rows of the batch at a time, summed."""
    dk = None
    for c in range(0, x.shape[0], WEIGHT_GRAD_CHUNK):
        xc, dyc = x[c:c + WEIGHT_GRAD_CHUNK], dy[c:c + WEIGHT_GRAD_CHUNK]
        transpose = jax.linear_transpose(lambda k, xc=xc: _lax_conv(xc, k, stride, padding, dilation),
                                         jax.ShapeDtypeStruct(k_shape, x.dtype))
        (part,) = transpose(dyc)
        part = part.astype(jnp.promote_types(x.dtype, jnp.float32))
        dk = part if dk is None else dk + part
    return dk


def weight_grad_shift_x(x, dy, k_shape, stride: int, padding, dilation: int = 1) -> jax.Array:
    """dW as in `weight_grad_shift_dy`, but with the zero-padded input sliced to each tap's view
    xpad[n, s*o + d*(i, j)] (the input is the side that is copied)."""
    acc = jnp.promote_types(x.dtype, jnp.float32)
    taps = [lax.dot_general(view, dy, _CONTRACT_NHW, preferred_element_type=acc)
            for view in _shifted_views(x, k_shape[0], k_shape[1], stride, padding, dilation)]
    return jnp.stack(taps).reshape(k_shape)


def conv_transpose2d(x: jax.Array, kernel: jax.Array, bias: jax.Array | None = None, *, stride: int = 2,
                     padding: int = 1) -> jax.Array:
    """PyTorch `F.conv_transpose2d` semantics on NHWC data (no output_padding, no dilation).

    Args:
      x: `(N, H, W, Cin)`.
      kernel: `(k, k, Cin, Cout)`: the PyTorch ConvTranspose2d weight `(Cin, Cout, k, k)` permuted (2, 3, 0, 1),
        i.e. *not* spatially flipped.
      bias: `(Cout,)` or None.

    Returns:
      `(N, (H-1)*stride - 2*padding + k, ..., Cout)`; for k=4, stride=2, padding=1 exactly `(N, 2H, 2W, Cout)`.
    """
    k = kernel.shape[0]
    pad = k - 1 - padding
    w = kernel[::-1, ::-1].astype(x.dtype)  # transposed conv == dilated-input conv with the flipped kernel
    y = lax.conv_general_dilated(x, w, window_strides=(1, 1), padding=[(pad, pad), (pad, pad)],
                                 lhs_dilation=(stride, stride), dimension_numbers=_DN)
    if bias is not None:
        y = y + bias.astype(y.dtype)
    return y


def max_pool_3x3_s2(x: jax.Array) -> jax.Array:
    """`nn.MaxPool2d(kernel_size=3, stride=2, padding=1)`: pads with -inf. `(N,H,W,C) -> (N,ceil(H/2),ceil(W/2),C)`."""
    # A Python scalar init lets JAX pick reduce_window_max, which is differentiable (an array init is not).
    return lax.reduce_window(x, -jnp.inf, lax.max, (1, 3, 3, 1), (1, 2, 2, 1), ((0, 0), (1, 1), (1, 1), (0, 0)))


def upsample_nearest2x(x: jax.Array) -> jax.Array:
    """`nn.Upsample(scale_factor=2)` (nearest): `(N, H, W, C) -> (N, 2H, 2W, C)`."""
    n, h, w, c = x.shape
    x = jnp.broadcast_to(x[:, :, None, :, None, :], (n, h, 2, w, 2, c))
    return x.reshape(n, 2 * h, 2 * w, c)


def upsample_nearest2x_conv3x3(x: jax.Array, kernel: jax.Array, bias: jax.Array | None = None) -> jax.Array:
    """`conv3x3(pad=1)(upsample_nearest2x(x))` computed at the *low* resolution (same result, 4/9 of the FLOPs).

    Output pixel (2i+a, 2j+b) of the upsampled-then-convolved map only sees low-res rows {i-1, i} (a=0) or
    {i, i+1} (a=1), with kernel rows merged: a=0 -> [w0, w1+w2], a=1 -> [w0+w1, w2] (same for columns). Each of
    the 4 phases is a 2x2 conv on the low-res map; the phases are interleaved back (depth-to-space).

    Args:
      x: `(N, H, W, Cin)`; kernel `(3, 3, Cin, Cout)` HWIO; bias `(Cout,)`.
    Returns:
      `(N, 2H, 2W, Cout)`.
    """
    n, h, w, _ = x.shape
    kernel = kernel.astype(x.dtype)
    cout = kernel.shape[-1]
    # merge matrices M[a] (2 taps x 3 rows): tap t of phase a sums kernel rows M[a][t].
    merge = jnp.array([[[1, 0, 0], [0, 1, 1]], [[1, 1, 0], [0, 0, 1]]], kernel.dtype)  # (phase, tap, row)
    # k2[a, b, ty, tx, ci, co] = sum_r sum_s merge[a, ty, r] merge[b, tx, s] kernel[r, s, ci, co]
    k2 = jnp.einsum("aur,bvs,rsio->abuvio", merge, merge, kernel)
    outs = []
    for a in range(2):
        row = []
        for b in range(2):
            # phase a uses rows (i-1, i) for a=0 -> pad top 1; (i, i+1) for a=1 -> pad bottom 1.
            pad_h = (1, 0) if a == 0 else (0, 1)
            pad_w = (1, 0) if b == 0 else (0, 1)
            y = conv_nhwc(x, k2[a, b], 1, (pad_h, pad_w))
            row.append(y)
        outs.append(jnp.stack(row, axis=3))  # (N, H, W, 2[b], Cout)
    y = jnp.stack(outs, axis=2)  # (N, H, 2[a], W, 2[b], Cout)
    y = y.reshape(n, 2 * h, 2 * w, cout)
    if bias is not None:
        y = y + bias.astype(y.dtype)
    return y


class Conv(nnx.Module):
    """A 2-D convolution with PyTorch semantics (symmetric padding, bias, PyTorch default init).

    Params: `kernel (k, k, in, out)` HWIO, `bias (out,)`.
    """

    def __init__(self, in_features: int, out_features: int, kernel_size: int, *, stride: int = 1,
                 dilation: int = 1, padding: int | None = None, init: str = "torch", rngs: nnx.Rngs):
        self.stride = stride
        self.dilation = dilation
        self.padding = padding
        self.init_kind = init
        fan_in = in_features * kernel_size * kernel_size
        if init == "torch":
            w_init, b_init = torch_uniform_init(fan_in), torch_uniform_init(fan_in)
        elif init == "kaiming_normal":
            w_init, b_init = kaiming_normal_init(fan_in), zeros_init
        else:
            raise ValueError(f"unknown init {init!r}; expected 'torch' or 'kaiming_normal'")
        self.kernel = new_param(w_init, rngs, (kernel_size, kernel_size, in_features, out_features))
        self.bias = new_param(b_init, rngs, (out_features,))

    def __call__(self, x: jax.Array) -> jax.Array:
        return conv2d(x, self.kernel[...], self.bias[...], stride=self.stride, padding=self.padding,
                      dilation=self.dilation)


class ConvTranspose(nnx.Module):
    """PyTorch `nn.ConvTranspose2d(in, out, k, stride, padding)` on NHWC; kernel `(k, k, in, out)` unflipped.

    Init as upstream PWC-Net: kaiming_normal fan_in where PyTorch's fan_in of a transposed-conv weight
    `(in, out, k, k)` is `out * k * k`; bias zero.
    """

    def __init__(self, in_features: int, out_features: int, kernel_size: int = 4, *, stride: int = 2,
                 padding: int = 1, rngs: nnx.Rngs):
        self.stride = stride
        self.padding = padding
        self.init_kind = "kaiming_normal_transpose"
        fan_in = out_features * kernel_size * kernel_size
        self.kernel = new_param(kaiming_normal_init(fan_in), rngs,
                                (kernel_size, kernel_size, in_features, out_features))
        self.bias = new_param(zeros_init, None, (out_features,))

    def __call__(self, x: jax.Array) -> jax.Array:
        return conv_transpose2d(x, self.kernel[...], self.bias[...], stride=self.stride, padding=self.padding)


class ConvLeaky(nnx.Module):
    """A kaiming-normal conv (3x3 unless told; optionally strided / dilated) + LeakyReLU(0.1): upstream PWC-Net's
    `myconv`, also pwc_lite's layer. Params under `conv`."""

    def __init__(self, cin: int, cout: int, *, stride: int = 1, dilation: int = 1, kernel: int = 3,
                 rngs: nnx.Rngs):
        self.conv = Conv(cin, cout, kernel, stride=stride, dilation=dilation, init="kaiming_normal", rngs=rngs)

    def __call__(self, x):
        return leaky_relu(self.conv(x))


def init_params_like(model: nnx.Module, abstract_params: dict, rng: jax.Array) -> dict:
    """Draw every Conv / ConvTranspose parameter of `model` (may be abstract) from its `init_kind` law.

    Same distributions as the modules' own initialisers, but drawn from two flat random vectors (one
    uniform, one normal) so that initialising the 58 M-parameter net compiles at most two kernels instead of one
    per parameter shape (eager per-shape compilation took minutes on 2 cores). Deterministic in `rng`.

    Returns:
      a params dict with the structure of `abstract_params`, float32 numpy arrays.
    """
    specs = []  # (path to kernel's parent, kernel shape, bias shape, kind)
    for path, node in nnx.iter_graph(model):
        if isinstance(node, (Conv, ConvTranspose)):
            specs.append((tuple(str(p) for p in path), tuple(node.kernel.shape), tuple(node.bias.shape),
                          node.init_kind))
    n_uni = sum(math.prod(k) + math.prod(b) for _, k, b, kind in specs if kind == "torch")
    n_nor = sum(math.prod(k) for _, k, _, kind in specs if kind != "torch")
    k_u, k_n = jax.random.split(rng)
    uni = np.asarray(jax.random.uniform(k_u, (n_uni,), jnp.float32, -1.0, 1.0)) if n_uni else None
    nor = np.asarray(jax.random.normal(k_n, (n_nor,), jnp.float32)) if n_nor else None
    out = jax.tree.map(lambda _: None, abstract_params)
    off_u = off_n = 0
    for path, kshape, bshape, kind in specs:
        nk, nb = math.prod(kshape), math.prod(bshape)
        if kind == "torch":
            bound = 1.0 / math.sqrt(math.prod(kshape[:3]))
            kernel = uni[off_u:off_u + nk] * bound
            bias = uni[off_u + nk:off_u + nk + nb] * bound
            off_u += nk + nb
        else:
            fan_in = math.prod(kshape[:3]) if kind == "kaiming_normal" else kshape[0] * kshape[1] * kshape[3]
            kernel = nor[off_n:off_n + nk] * math.sqrt(2.0 / fan_in)
            bias = np.zeros(nb, np.float32)
            off_n += nk
        node = out
        for p in path:
            node = node[p]
        node["kernel"] = kernel.reshape(kshape).astype(np.float32)
        node["bias"] = bias.reshape(bshape).astype(np.float32)
    missing = [kp for kp, v in jax.tree_util.tree_flatten_with_path(out, is_leaf=lambda x: x is None)[0]
               if v is None]
    if missing:
        raise ValueError(f"parameters without an initialiser: {missing[:5]}")
    return out


def fill_config(config, defaults: dict, *, lists=(), ints=(), bools=(), head_inits=()) -> dict:
    """A model config with defaults filled and values coerced (lists of ints, ints, bools): JSON-serialisable.

    Raises ValueError naming unknown keys (all of `defaults` and "dtype" are known) or a head_init outside
    `head_inits`.
    """
    name = defaults["name"]
    unknown = set(config) - set(defaults) - {"dtype"}
    if unknown:
        raise ValueError(f"unknown {name} config keys {sorted(unknown)}; known: {sorted(defaults)}")
    out = dict(defaults)
    out.update(config)
    for k in lists:
        out[k] = [int(v) for v in out[k]]
    for k in ints:
        out[k] = int(out[k])
    for k in bools:
        out[k] = bool(out[k])
    if head_inits and out["head_init"] not in head_inits:
        raise ValueError(f"model head_init must be one of {list(head_inits)}, got {out['head_init']!r}")
    return out


def pixel_and_fraction_maps(px) -> dict:
    """`{"px": px, "frac": px / (W_s, H_s)}` of per-scale float32 pixel maps `(N, H_s, W_s, 2)`."""
    px = tuple(p.astype(jnp.float32) for p in px)
    frac = tuple(p / jnp.array([p.shape[2], p.shape[1]], jnp.float32) for p in px)
    return {"px": px, "frac": frac}


def check_input_shape(pair, multiple: int) -> None:
    """Raise ValueError unless `pair` is `(N, H, W, 6)` with H, W multiples of `multiple`."""
    if pair.ndim != 4 or pair.shape[-1] != 6:
        raise ValueError(f"model input must be (N, H, W, 6) (two RGB images concatenated), got {pair.shape}")
    h, w = pair.shape[1:3]
    if h % multiple or w % multiple or h == 0 or w == 0:
        raise ValueError(f"model input height and width must be positive multiples of {multiple}, got {h}x{w}")
