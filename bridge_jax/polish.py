"""Test-time photometric polish: the network's map improved against the images themselves.

The network answers at a quarter of its working size, and its maps come up to full size by bilinear
interpolation, smoothed by the training's smoothness prior. Two errors follow that a look at the images
themselves can correct, with the same photometric criterion the network was trained on and no ground truth:

1. **Bled motion boundaries** (`select_candidates`). Around an object that moves differently from its
   background the network's map blends the two motions over 10-30 pixels. The right motion is usually the
   map's own value a few pixels further into the region. Each pixel therefore tries its map's values 4, 8,
   16 and 24 pixels away in the 8 directions, scores each by the mean absolute difference of the
   locally normalised images over a (2r+1)^2 window (`matching_cost`), and takes the best candidate only if
   it costs at most `ratio` times its own value's cost, less a small margin (so that flat, textureless or
   occluded regions, where every candidate scores alike, keep the network's value). A PatchMatch propagation
   step seeded by the network.
2. **Sub-pixel noise, textureless regions, the image border** (`variational_fit`). A combined
   local-global energy: windowed Lucas-Kanade data terms where the images have texture, an edge-aware robust
   smoothness term everywhere, minimised by warps of red-black SOR (20 on flow maps, 5 on stereo maps). Where
   the images say little (sky, walls, pixels whose match leaves `b`) the map takes its neighbours' motion; a
   motion boundary on an image edge stays sharp. It samples `b` by cubic convolution (`geometry.warp_cubic`):
   bilinear sampling blurs by an amount that depends on the fractional part of the position, and a fit that
   compares blurred and unblurred windows is drawn towards whole-pixel motion.

`polish_maps` runs both twice (`PolishConfig.rounds`): the second round's candidates come from a map that the first
made right on wider areas. Both steps compare locally normalised grey images (zero mean, unit contrast over a
15x15 window, `normalise_locally`): gain, offset and gamma differences between two cameras then cancel to first
order, which raw brightness constancy would read as motion. `b` is normalised *after* it is warped into `a`'s
frame (`warped_normalised`), so that both windows cover the same piece of the scene: normalised in its own
frame, `b`'s windows near its border are reflected where `a`'s are not, which biased every pixel whose match
lies near that border.

The numbers are then the network's answer corrected by a local photometric optimisation, no longer the
network's alone; `TestTime(polish="none")` gives those. Every parameter of the polish is a field of one frozen
`PolishConfig`, which keys its compiled program (`Predictor._polish_program`).
"""
from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np

from bridge_jax import geometry


INTERPOLATIONS = ("cubic", "bilinear")
"""How the variational fit may sample `b` (`PolishConfig.interpolation`)."""
RESOLUTIONS = ("input", "working")
"""Where `Predictor` runs the polish (`PolishConfig.resolution`)."""


@dataclasses.dataclass(frozen=True)
class PolishConfig:
    """The parameters of the photometric polish (`polish_maps`); hashable, so a compiled polish is kept per
    config. Lengths are pixels of the images the polish runs on (`resolution`), grey levels are in [0, 1]
    (normalised ones where said)."""

    rounds: int = 2
    """Rounds of (`select_candidates`, `variational_fit`) in `polish_maps`."""
    normalise_radius: int = 7
    """Half size of the window `normalise_locally` takes the mean and contrast over (15x15)."""
    contrast_floor: float = 0.05
    """Added to the local contrast before dividing: flat regions are not blown up into noise."""
    candidate_distances: tuple[int, ...] = (4, 8, 16, 24)
    """How far `select_candidates` looks for another value of the map, in each of 8 directions."""
    cost_radius: int = 4
    """Half size of the window `matching_cost` averages over (9x9)."""
    accept_ratio: float = 0.7
    """A candidate replaces a pixel's own value only at no more than this share of its cost..."""
    accept_margin: float = 1e-4
    """...and at least this much below it (normalised grey levels): on a flat image every cost is float
    rounding noise (~1e-7), and no ratio of two rounding noises means anything; weakly textured windows cost
    only a few hundredths, so the margin stays well below that."""
    select_softness: float = 0.0
    """0 = `select_candidates` takes the cheapest acceptable candidate outright. > 0 = it takes the softmin of
    the candidates' values, weights exp(-cost / select_softness) with the pixel's own value entered at its
    acceptance threshold: the same answer wherever one candidate is clearly the cheapest, but continuous in the
    images and the map, so that a tiny change of the input (another runtime's rounding) cannot flip a pixel
    from one candidate to another."""
    smoothness_weight: float = 3.0
    """alpha of `variational_fit` on flow rows: the weight of the smoothness term next to the windowed data
    term."""
    smoothness_weight_stereo: float = 2.0
    """The same on rectified stereo rows. A disparity map has depth edges wherever a nearer surface starts, and a
    stronger smoothness carries the nearer surface further over the background: at 4 instead of 2, Motorcycle's
    D1 rose from 9.4 to 10.2 % while the photo flow improved (`experiments/results/real_images.md`)."""
    edge_scale: float = 0.05
    """Grey-level difference over which a neighbour's smoothness weight falls by e (`edge_weights`)."""
    data_eps: float = 0.1
    """Charbonnier epsilon of the data term (normalised grey levels): residuals much larger weigh 1/|residual|."""
    smooth_eps: float = 0.1
    """Charbonnier epsilon of the smoothness term (pixels): map differences much larger weigh 1/|difference|,
    so a motion boundary the earlier steps made sharp stays sharp."""
    variational_sigma: float = 1.5
    """Standard deviation of the Gaussian window of the data term (the "local" half of the CLG energy) on flow
    rows, pixels. A wider window averages the sensor noise of more pixels into each pixel's data term; unlike a
    stronger smoothness it does not pull a smoothly varying motion (a zoom) towards a constant one."""
    variational_sigma_stereo: float = 1.5
    """The same on rectified stereo rows."""
    variational_warps: int = 20
    """Outer iterations of `variational_fit` on flow rows: b re-warped, the energy re-linearised, the robust
    weights recomputed. Each is one step of iteratively reweighted least squares, and a smooth error over a
    wide area (a zoom, a slow drift of the network's map) takes many of them to leave: 5 left the maps of
    whole-image motion short of the energy's minimum."""
    variational_warps_stereo: int = 5
    """The same for rectified stereo rows, fewer. Each warp may move a pixel by up to 2 px (the linearisation's
    range), so more warps also let pixels that have no true match (background the right view cannot see) travel
    further along their row; on stereo maps more warps did not pay (`experiments/results/real_images.md`)."""
    sor_sweeps: int = 20
    """Red-black successive over-relaxation sweeps per outer iteration."""
    sor_omega: float = 1.9
    """Over-relaxation factor of those sweeps (1 = Gauss-Seidel)."""
    data_prior: float = 1e-3
    """Added to the diagonal of the windowed data term: the 2x2 systems stay well posed without texture or
    smoothness."""
    interpolation: str = "cubic"
    """How `variational_fit` samples `b` at the map's positions: "cubic" = Keys' cubic convolution
    (`geometry.warp_cubic`); "bilinear" = `geometry.warp`, the polish until 2026-12-06, whose blur varies with the
    fractional part of the position and so draws a sub-pixel fit towards whole-pixel motion. The candidate
    selection compares values 4-24 px apart, where that bias does not matter, and keeps the bilinear warp (4
    taps a pixel against 16, for each of its 33 warps a round)."""
    resolution: str = "input"
    """Where a `Predictor` runs the polish: "input" = on the images as given, after the network's map was brought
    to their size (`Predictor.stage_maps`); "working" = on the images resized to the network's working size,
    before the map is brought up (the polish until 2026-12-07). Resizing the images to a working size that is
    not a whole fraction of theirs resamples them differently at every sub-pixel phase, so even an exact
    whole-pixel motion no longer minimises the energy, and an edge the polish made sharp is blurred again when
    the map is brought up. The polish itself is the same function either way; an exported artifact runs it at
    its own input size, the working size (`bridge_jax.export`)."""
    max_pixels: int = 1024 * 768
    """With `resolution="input"`, inputs larger than this many pixels are polished at the working size instead:
    the polish's memory and time grow with the pixels it runs on (the native working size's cap,
    `resizing.NATIVE_MAX_PIXELS`)."""

    def __post_init__(self):
        object.__setattr__(self, "candidate_distances", tuple(int(d) for d in self.candidate_distances))
        if self.rounds < 0 or min((self.normalise_radius, self.cost_radius, self.variational_warps,
                                   self.variational_warps_stereo, self.sor_sweeps), default=0) < 0 \
                or not self.candidate_distances:
            raise ValueError(f"PolishConfig: counts and radii must be >= 0 and candidate_distances non-empty: {self}")
        if not self.select_softness >= 0:
            raise ValueError(f"PolishConfig: select_softness must be >= 0 (0 = the cheapest candidate), got "
                             f"{self.select_softness!r}")
        if self.interpolation not in INTERPOLATIONS:
            raise ValueError(f"PolishConfig: interpolation must be one of {INTERPOLATIONS}, got {self.interpolation!r}")
        if self.resolution not in RESOLUTIONS:
            raise ValueError(f"PolishConfig: resolution must be one of {RESOLUTIONS}, got {self.resolution!r}")
        if self.max_pixels < 1:
            raise ValueError(f"PolishConfig: max_pixels must be >= 1, got {self.max_pixels!r}")
        if not min(self.variational_sigma, self.variational_sigma_stereo) > 0:
            raise ValueError(f"PolishConfig: variational_sigma and variational_sigma_stereo must be > 0, got "
                             f"{self.variational_sigma!r} and {self.variational_sigma_stereo!r}")

    def size_for(self, working: tuple[int, int], full: tuple[int, int]) -> tuple[int, int]:
        """(H, W) the polish runs at for an input of size `full` whose network ran at `working` (`resolution`,
        `max_pixels`)."""
        if self.resolution == "input" and full[0] * full[1] <= self.max_pixels:
            return tuple(full)
        return tuple(working)


DEFAULT_CONFIG = PolishConfig()

def component_mask(flow_rows: jax.Array) -> jax.Array:
    """`(N, 1, 1, 2)` 1 for the map components a row keeps: (1, 1) for flow rows, (1, 0) for rectified stereo rows
    (`flow_rows (N,)`: 1.0 flow, 0.0 stereo), to multiply `(N, H, W, 2)` maps by."""
    return jnp.stack([jnp.ones_like(flow_rows), flow_rows], -1)[:, None, None, :]


# ------------------------------------------------------------------------------------------ filters
def _separable(x: jax.Array, taps: np.ndarray) -> jax.Array:
    """`(N, H, W)` filtered by the 1-D kernel `taps` along H and then W, edges reflected (no new dark border)."""
    r = len(taps) // 2
    k = jnp.asarray(taps, x.dtype)
    y = jnp.pad(x, ((0, 0), (r, r), (r, r)), mode="reflect")
    h, w = x.shape[1:]
    y = sum(k[i] * y[:, i:i + h, :] for i in range(len(taps)))
    return sum(k[i] * y[:, :, i:i + w] for i in range(len(taps)))


def box_filter(x: jax.Array, radius: int) -> jax.Array:
    """Mean over the (2r+1)^2 window of each pixel of `(N, H, W)`, edges reflected."""
    return _separable(x, np.full(2 * radius + 1, 1.0 / (2 * radius + 1), np.float32))


def gaussian_filter(x: jax.Array, sigma: float) -> jax.Array:
    """`(N, H, W)` smoothed by a normalised Gaussian of `sigma` pixels (truncated at 2 sigma), edges reflected."""
    r = int(np.ceil(2 * sigma))
    t = np.exp(-0.5 * (np.arange(-r, r + 1) / sigma) ** 2)
    return _separable(x, (t / t.sum()).astype(np.float32))


def normalise_locally(grey: jax.Array, radius: int = DEFAULT_CONFIG.normalise_radius,
                      floor: float = DEFAULT_CONFIG.contrast_floor) -> jax.Array:
    """`(N, H, W)` grey image minus its local mean, over its local contrast (std) plus `floor`."""
    centred = grey - box_filter(grey, radius)
    return centred / (jnp.sqrt(box_filter(centred * centred, radius)) + floor)


def _pad_edge(x: jax.Array, axis: int, before: int, after: int) -> jax.Array:
    """`x` with its first slice along `axis` repeated `before` times in front and its last `after` times behind:
    `jnp.pad(mode="edge")` on one axis, the same values, but without the zero-size pieces jnp.pad makes for the
    axes it does not pad (the ONNX export, `bridge_jax.onnx_export`, gets their shapes wrong)."""
    n = x.shape[axis]
    first = jax.lax.slice_in_dim(x, 0, 1, axis=axis)
    last = jax.lax.slice_in_dim(x, n - 1, n, axis=axis)
    return jnp.concatenate([first] * before + [x] + [last] * after, axis=axis)


def gradients(x: jax.Array) -> tuple[jax.Array, jax.Array]:
    """Central differences of `(N, H, W)` along W and H (one-sided half steps at the edges: edge replicated)."""
    px, py = _pad_edge(x, 2, 1, 1), _pad_edge(x, 1, 1, 1)
    return 0.5 * (px[:, :, 2:] - px[:, :, :-2]), 0.5 * (py[:, 2:] - py[:, :-2])


def _warp_grey(image: jax.Array, maps: jax.Array, interpolation: str = "bilinear") -> jax.Array:
    """`(N, H, W)` image sampled at x + map, border clamped (`geometry.warp_cubic` or the bilinear `geometry.warp`)."""
    warp = geometry.warp_cubic if interpolation == "cubic" else geometry.warp
    return warp(image[..., None], maps)[..., 0]


def warped_normalised(grey_b: jax.Array, maps: jax.Array, config: PolishConfig = DEFAULT_CONFIG,
                      interpolation: str = "bilinear") -> jax.Array:
    """`(N, H, W)` grey image `b` warped into `a`'s frame by `maps` (`interpolation`: "bilinear" or "cubic"),
    then normalised there (`normalise_locally`)."""
    return normalise_locally(_warp_grey(grey_b, maps, interpolation), config.normalise_radius,
                             config.contrast_floor)


# ------------------------------------------------------------------------------ candidate selection
def matching_cost(norm_a: jax.Array, grey_b: jax.Array, maps: jax.Array,
                  config: PolishConfig = DEFAULT_CONFIG) -> jax.Array:
    """Windowed mean |norm(a) - norm(warp(b, map))| over `config.cost_radius` (`(N, H, W)`: `a` normalised, `b`
    grey; `maps (N, H, W, 2)`)."""
    return box_filter(jnp.abs(warped_normalised(grey_b, maps, config) - norm_a), config.cost_radius)


def _shifted(maps: jax.Array, dx: jax.Array, dy: jax.Array) -> jax.Array:
    """`maps` read (dx, dy) pixels away: out[y, x] = maps[clip(y + dy), clip(x + dx)]."""
    h, w = maps.shape[1:3]
    rows = jnp.clip(jnp.arange(h) + dy, 0, h - 1)
    cols = jnp.clip(jnp.arange(w) + dx, 0, w - 1)
    return maps[:, rows][:, :, cols]


def candidate_offsets(distances=DEFAULT_CONFIG.candidate_distances) -> np.ndarray:
    """`(8 * len(distances), 2)` int (dx, dy): each distance in the 8 directions of the compass."""
    dirs = [(1, 0), (-1, 0), (0, 1), (0, -1), (1, 1), (1, -1), (-1, 1), (-1, -1)]
    return np.array([(ux * d, uy * d) for d in distances for ux, uy in dirs], np.int32)


def select_candidates(norm_a: jax.Array, grey_b: jax.Array, maps: jax.Array, mask: jax.Array,
                      config: PolishConfig = DEFAULT_CONFIG) -> jax.Array:
    """Each pixel's map value replaced by the best of its neighbours' (`candidate_offsets` of
    `config.candidate_distances`) where that one matches clearly better (cost < `config.accept_ratio` x its own -
    `config.accept_margin`; then the cheapest wins; with `config.select_softness` > 0 a softmin of them instead,
    `_softmin_candidates`).

    Args:
      norm_a: `(N, H, W)` grey image `a`, locally normalised (`normalise_locally`).
      grey_b: `(N, H, W)` grey image `b` (normalised after each warp, `warped_normalised`).
      maps: `(N, H, W, 2)` pixel maps a -> b.
      mask: `(N, 1, 1, 2)` 1 for the components a row keeps (stereo rows: (1, 0)).
    Returns:
      `(N, H, W, 2)` maps.
    """
    own = matching_cost(norm_a, grey_b, maps, config)
    threshold = own * config.accept_ratio - config.accept_margin  # the cost a candidate must beat
    offsets = jnp.asarray(candidate_offsets(config.candidate_distances))
    if config.select_softness > 0:
        return _softmin_candidates(norm_a, grey_b, maps, mask, threshold, offsets, config)

    def try_one(carry, offset):
        best_cost, best = carry
        cand, cost = _candidate(norm_a, grey_b, maps, mask, offset, config)
        better = cost < best_cost
        return (jnp.where(better, cost, best_cost), jnp.where(better[..., None], cand, best)), None

    (_, best), _ = jax.lax.scan(try_one, (threshold, maps), offsets)
    return best


def _candidate(norm_a, grey_b, maps, mask, offset, config: PolishConfig) -> tuple[jax.Array, jax.Array]:
    """(the map read `offset` (dx, dy) away, kept to the row's components; its `matching_cost`)."""
    cand = _shifted(maps, offset[0], offset[1]) * mask
    return cand, matching_cost(norm_a, grey_b, cand, config)


def _softmin_candidates(norm_a, grey_b, maps, mask, threshold, offsets, config: PolishConfig) -> jax.Array:
    """`select_candidates` with `config.select_softness` = t > 0: sum_i w_i v_i / sum_i w_i over the pixel's own
    value (cost: `threshold`) and its candidates, w_i = exp(-(cost_i - min cost) / t). Accumulated as a running
    softmin over the scan (the minimum so far rescales the sums), so memory stays that of one candidate."""
    t = config.select_softness

    def try_one(carry, offset):
        low, total, weighted = carry
        cand, cost = _candidate(norm_a, grey_b, maps, mask, offset, config)
        new_low = jnp.minimum(low, cost)
        rescale, w = jnp.exp((new_low - low) / t), jnp.exp((new_low - cost) / t)
        return (new_low, total * rescale + w, weighted * rescale[..., None] + w[..., None] * cand), None

    start = (threshold, jnp.ones_like(threshold), maps)
    (_, total, weighted), _ = jax.lax.scan(try_one, start, offsets)
    return weighted / total[..., None]


# ----------------------------------------------------------------------------- variational fit
_NEIGHBOURS = ((0, 1), (1, 0), (0, -1), (-1, 0))
"""(dy, dx) of the 4 neighbours the smoothness term couples."""


def _neighbour(x: jax.Array, dy: int, dx: int) -> jax.Array:
    """`(N, H, W, ...)` read at (y + dy, x + dx), edge replicated (slices, not a gather: XLA:CPU gathers are slow)."""
    h, w = x.shape[1:3]
    y = _pad_edge(_pad_edge(x, 1, max(-dy, 0), max(dy, 0)), 2, max(-dx, 0), max(dx, 0))
    return y[:, max(dy, 0):max(dy, 0) + h, max(dx, 0):max(dx, 0) + w]


def edge_weights(grey_a: jax.Array, scale: float = DEFAULT_CONFIG.edge_scale) -> list[jax.Array]:
    """Smoothness weight of each pixel to each of its 4 `_NEIGHBOURS`, `(N, H, W)` each:
    exp(-|a_neighbour - a| / scale) on `a` lightly smoothed (sigma 0.7 px), 0 where the neighbour is outside
    the image. A map may change where the image changes, and is pulled together where it does not."""
    g = gaussian_filter(grey_a, 0.7)
    h, w = grey_a.shape[1:]
    rows, cols = jnp.arange(h)[:, None], jnp.arange(w)[None, :]
    out = []
    for dy, dx in _NEIGHBOURS:
        inside = (rows + dy >= 0) & (rows + dy < h) & (cols + dx >= 0) & (cols + dx < w)
        out.append(jnp.exp(-jnp.abs(_neighbour(g, dy, dx) - g) / scale) * inside)
    return out


def variational_fit(norm_a: jax.Array, grey_a: jax.Array, grey_b: jax.Array, maps: jax.Array,
                    flow_rows: jax.Array, config: PolishConfig = DEFAULT_CONFIG) -> jax.Array:
    """`maps` fitted to the images by a combined local-global energy (Bruhn, Weickert and Schnorr's CLG).

    Minimises over the map D, linearised about the current D0 (D = D0 + d),

        sum_x  d^T J d + 2 d^T j  +  alpha sum_{x~y} c_xy psi_s(|D0_x - D0_y|) |D_x - D_y|^2,

    where J = G * (rho g g^T) and j = G * (rho g I_t) are the Gaussian-windowed (`variational_sigma`;
    `variational_sigma_stereo` on stereo rows) data terms of Lucas-Kanade on the locally normalised images,
    rho = 1 / sqrt(I_t^2 + eps^2) re-weights them robustly (occlusions), c_xy are the `edge_weights` of `a`, and
    psi_s = eps_s / sqrt(|.|^2 + eps_s^2) the robust smoothness weight. A pixel whose match falls outside `b` has
    no data term: border clamping would make one up, so its value comes from its neighbours. Each of
    `config.variational_warps` outer iterations (`config.variational_warps_stereo` on stereo rows; a row past its
    count keeps its map) re-warps `b`, recomputes the weights and runs `config.sor_sweeps` red-black SOR sweeps
    (`config.sor_omega`) on the 2x2 (stereo rows: 1x1) per-pixel systems; alpha = `config.smoothness_weight`
    (`config.smoothness_weight_stereo` on stereo rows), eps = `config.data_eps`, eps_s = `config.smooth_eps`.

    Where the earlier steps leave noise the smoothness term averages it with the neighbours' values, weighted by
    how well each is determined; textureless regions (sky, walls) and the image border take their neighbours'
    motion instead of keeping the network's guess. Robust weights in both terms keep occlusions from pulling
    their neighbours and motion boundaries from blurring.

    Args:
      norm_a: `(N, H, W)` grey image `a`, locally normalised.
      grey_a: `(N, H, W)` grey image `a` in [0, 1] (for the edge weights).
      grey_b: `(N, H, W)` grey image `b` (normalised after each warp, `warped_normalised`).
      maps: `(N, H, W, 2)` pixel maps a -> b.
      flow_rows: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows (vertical component stays 0).
    Returns:
      `(N, H, W, 2)` maps.
    """
    omega, smooth_eps, data_eps = config.sor_omega, config.smooth_eps, config.data_eps
    alpha = jnp.where(flow_rows > 0.5, config.smoothness_weight, config.smoothness_weight_stereo)[:, None, None]
    h, w = norm_a.shape[1:]
    flow_row = (flow_rows > 0.5)[:, None, None]
    mask = component_mask(flow_rows)
    ax, ay = gradients(norm_a)
    edges = edge_weights(grey_a, config.edge_scale)
    red = ((jnp.arange(h)[:, None] + jnp.arange(w)[None, :]) % 2 == 0)[None, ..., None]
    xs = jnp.arange(w, dtype=jnp.float32)[None, None, :]
    ys = jnp.arange(h, dtype=jnp.float32)[None, :, None]
    if config.variational_sigma == config.variational_sigma_stereo:
        win = lambda x: gaussian_filter(x, config.variational_sigma)
    else:  # each row its own window (a batch of one kind is compiled with one, `config_for_rows`)
        win = lambda x: jnp.where(flow_row, gaussian_filter(x, config.variational_sigma),
                                  gaussian_filter(x, config.variational_sigma_stereo))

    # each row's own number of outer iterations: the loop runs the larger, and a row past its count keeps its map
    warps = jnp.where(flow_rows > 0.5, config.variational_warps, config.variational_warps_stereo)[:, None, None, None]

    def warp_iteration(i, d0):
        warped = warped_normalised(grey_b, d0, config, config.interpolation)
        it = warped - norm_a
        bx, by = gradients(warped)
        gx, gy = 0.5 * (ax + bx), 0.5 * (ay + by)
        px, py = xs + d0[..., 0], ys + d0[..., 1]
        inside = (px >= 0) & (px <= w - 1) & (py >= 0) & (py <= h - 1)
        rho = jnp.where(inside, 1.0 / jnp.sqrt(it * it + data_eps ** 2), 0.0)
        prior = config.data_prior
        jxx, jxy, jyy = win(rho * gx * gx) + prior, win(rho * gx * gy), win(rho * gy * gy) + prior
        jx, jy = win(rho * gx * it), win(rho * gy * it)
        coupling = [alpha * c * smooth_eps / jnp.sqrt(jnp.sum((_neighbour(d0, dy, dx) - d0) ** 2, -1) + smooth_eps ** 2)
                    for c, (dy, dx) in zip(edges, _NEIGHBOURS)]
        total = sum(coupling)
        sxx, syy = jxx + total, jyy + total
        det = sxx * syy - jxy * jxy

        # right-hand side -j + sum c (D0_y - D0_x), the part that does not change within the sweeps
        rhs = sum(c[..., None] * (_neighbour(d0, dy, dx) - d0) for c, (dy, dx) in zip(coupling, _NEIGHBOURS))
        rhs = rhs - jnp.stack([jx, jy], -1)

        def solve(d):
            """Each pixel's d with its neighbours' held: (J + total I) d = -j + sum c (D0_y + d_y - D0_x)."""
            r = rhs + sum(c[..., None] * _neighbour(d, dy, dx) for c, (dy, dx) in zip(coupling, _NEIGHBOURS))
            rx, ry = r[..., 0], r[..., 1]
            du = jnp.where(flow_row, (syy * rx - jxy * ry) / det, rx / sxx)
            dv = jnp.where(flow_row, (sxx * ry - jxy * rx) / det, 0.0)
            return jnp.stack([du, dv], -1)

        def sweep(_, d):
            for colour in (red, ~red):
                d = jnp.where(colour, (1.0 - omega) * d + omega * solve(d), d)
            return d

        d = jax.lax.fori_loop(0, config.sor_sweeps, sweep, jnp.zeros_like(d0))
        step = jnp.clip(d, -2.0, 2.0) * mask  # the linearisation holds about a pixel or two
        return d0 + jnp.where(i < warps, step, 0.0)

    iterations = max(config.variational_warps, config.variational_warps_stereo)
    return jax.lax.fori_loop(0, iterations, warp_iteration, maps * mask)


def config_for_rows(config: PolishConfig, flow_rows) -> PolishConfig:
    """`config` for a batch whose rows' kinds are known when it is compiled (`flow_rows`: host values, 1 = flow,
    0 = stereo): a batch of stereo rows only runs `variational_warps_stereo` outer iterations in all, not
    `variational_warps` of which every row would discard the rest, and a batch of one kind of rows windows its
    data terms once, with its kind's window, not with both. The same maps either way."""
    rows = np.asarray(flow_rows) > 0.5
    if rows.all():
        return dataclasses.replace(config, variational_sigma_stereo=config.variational_sigma)
    if rows.any():
        return config
    return dataclasses.replace(config, variational_warps=config.variational_warps_stereo,
                               variational_sigma=config.variational_sigma_stereo)


def grey_images(pairs: jax.Array, config: PolishConfig = DEFAULT_CONFIG) -> tuple[jax.Array, jax.Array, jax.Array]:
    """(grey `a`, grey `b`, grey `a` locally normalised), each `(N, H, W)`, of `(N, H, W, 6)` pairs: what both
    steps of the polish compare."""
    grey_a, grey_b = pairs[..., :3].mean(-1), pairs[..., 3:].mean(-1)
    return grey_a, grey_b, normalise_locally(grey_a, config.normalise_radius, config.contrast_floor)


def polish_maps(pairs: jax.Array, maps: jax.Array, flow_rows: jax.Array,
                config: PolishConfig = DEFAULT_CONFIG) -> jax.Array:
    """The "photometric" polish: `config.rounds` rounds of `select_candidates`, then `variational_fit`
    (the second round's candidates come from a map the first round made right on wider areas).

    Args:
      pairs: `(N, H, W, 6)` = [image a, image b], RGB in [0, 1], at the size the polish runs at
        (`PolishConfig.resolution`).
      maps: `(N, H, W, 2)` pixel maps a -> b at that size (the network's, refined and averaged as asked, brought
        to that size).
      flow_rows: `(N,)` 1.0 for flow rows, 0.0 for rectified stereo rows (their vertical component stays 0).
      config: the parameters (hashable: a static argument where jitted).
    Returns:
      `(N, H, W, 2)` polished maps.
    """
    pairs, maps = pairs.astype(jnp.float32), maps.astype(jnp.float32)
    flow_rows = flow_rows.astype(jnp.float32)
    grey_a, grey_b, norm_a = grey_images(pairs, config)
    mask = component_mask(flow_rows)
    maps = maps * mask
    for _ in range(config.rounds):
        maps = select_candidates(norm_a, grey_b, maps, mask, config)
        maps = variational_fit(norm_a, grey_a, grey_b, maps, flow_rows, config)
    return maps
