"""Pictures of flow, disparity, depth and errors (numpy + OpenCV; every image returned is RGB uint8 ``(H, W, 3)``).

* :func:`flow_to_color` — the Middlebury colour code (Baker et al., "A Database and Evaluation Methodology for
  Optical Flow", IJCV 2011): the hue gives the direction, the saturation the magnitude. The wheel is built here
  from its definition: 55 hues in six ramps red→yellow (15), yellow→green (6), green→cyan (4), cyan→blue (11),
  blue→magenta (13), magenta→red (6); the angle ``atan2(-v, -u)`` picks the hue, the normalised radius fades it
  from white (0 motion) to full colour (radius 1) and beyond radius 1 the colour is darkened by 25 %.
  With image axes (x right, y down) that gives: **right → red, down → yellow/orange, left → cyan,
  up → blue/violet** (:data:`DIRECTION_HUES`). :func:`color_wheel_legend` draws the key.
* :func:`disparity_to_color` / :func:`depth_to_color` / :func:`error_to_color` — OpenCV colormaps, with
  :func:`colorbar` drawing the matching legend image (:func:`error_colorbar` for error maps) and
  :func:`attach_colorbar` placing one beside a picture.
* :func:`panel` — side-by-side grid of labelled images (input, prediction, GT, error) used by predict, evaluate
  and the trainer's TensorBoard images; :func:`prediction_panel` is the one-call ``input | flow | disparity``.

Invalid pixels (NaN, ±inf or outside a given ``valid`` mask) are drawn black.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from typing import Optional

import cv2
import numpy as np

from bridge_jax import files

# Middlebury colour-wheel ramp lengths, in wheel order starting at red.
_RAMPS = (("RY", 15), ("YG", 6), ("GC", 4), ("CB", 11), ("BM", 13), ("MR", 6))

DIRECTION_HUES = {"right": "red", "down": "yellow", "left": "cyan", "up": "blue"}
"""Hue of a pure motion in each image direction (x right, y down), as documented by the Middlebury code."""

_COLORMAPS = {
    "magma": cv2.COLORMAP_MAGMA, "inferno": cv2.COLORMAP_INFERNO, "plasma": cv2.COLORMAP_PLASMA,
    "viridis": cv2.COLORMAP_VIRIDIS, "turbo": cv2.COLORMAP_TURBO, "jet": cv2.COLORMAP_JET,
    "hot": cv2.COLORMAP_HOT,
}


def color_wheel() -> np.ndarray:
    """The 55 Middlebury wheel colours, ``(55, 3)`` uint8 RGB, starting at red and turning via yellow, green, cyan,
    blue and magenta back to red. Inside a ramp the rising (or falling) channel is ``floor(255 · i / len)``."""
    rows = []
    for name, n in _RAMPS:
        ramp = np.floor(255.0 * np.arange(n) / n)
        col = np.zeros((n, 3))
        if name == "RY":      # red stays, green rises
            col[:, 0], col[:, 1] = 255, ramp
        elif name == "YG":    # red falls, green stays
            col[:, 0], col[:, 1] = 255 - ramp, 255
        elif name == "GC":    # green stays, blue rises
            col[:, 1], col[:, 2] = 255, ramp
        elif name == "CB":    # green falls, blue stays
            col[:, 1], col[:, 2] = 255 - ramp, 255
        elif name == "BM":    # blue stays, red rises
            col[:, 2], col[:, 0] = 255, ramp
        else:                 # MR: red stays, blue falls
            col[:, 0], col[:, 2] = 255, 255 - ramp
        rows.append(col)
    return np.concatenate(rows).astype(np.uint8)


def _finite_mask(x: np.ndarray, valid: Optional[np.ndarray]) -> np.ndarray:
    ok = np.all(np.isfinite(x), axis=-1) if x.ndim == 3 else np.isfinite(x)
    if valid is not None:
        valid = np.asarray(valid, bool)
        if valid.shape != ok.shape:
            raise ValueError(f"valid mask shape {valid.shape} != map shape {ok.shape}")
        ok &= valid
    return ok


def flow_magnitude_max(flow: np.ndarray, valid: Optional[np.ndarray] = None) -> float:
    """Largest finite flow norm (pixels) over valid pixels; 0 if none."""
    flow = np.asarray(flow, np.float64)
    ok = _finite_mask(flow, valid)
    if not ok.any():
        return 0.0
    return float(np.sqrt((flow[ok] ** 2).sum(-1)).max())


def flow_to_color(flow: np.ndarray, max_flow: Optional[float] = None,
                  valid: Optional[np.ndarray] = None) -> np.ndarray:
    """Middlebury colour coding of a flow field.

    Args:
      flow: ``(H, W, 2)`` flow in pixels (u right, v down).
      max_flow: the radius (pixels) that gets full saturation; default: the largest valid norm of this field.
        Pass a fixed value to make several frames (a video) comparable.
      valid: optional ``(H, W)`` bool; invalid and non-finite pixels are black.
    Returns:
      ``(H, W, 3)`` uint8 RGB.
    """
    flow = np.asarray(flow, np.float64)
    if flow.ndim != 3 or flow.shape[-1] != 2:
        raise ValueError(f"flow must be (H, W, 2), got {flow.shape}")
    ok = _finite_mask(flow, valid)
    if max_flow is None:
        max_flow = flow_magnitude_max(flow, ok)
    max_flow = max(float(max_flow), 1e-9)
    u = np.where(ok, flow[..., 0], 0.0) / max_flow
    v = np.where(ok, flow[..., 1], 0.0) / max_flow
    wheel = color_wheel().astype(np.float64) / 255.0
    ncols = wheel.shape[0]
    rad = np.sqrt(u * u + v * v)
    angle = np.arctan2(-v, -u) / np.pi                   # in [-1, 1]
    fk = (angle + 1.0) / 2.0 * (ncols - 1)               # continuous wheel index in [0, ncols-1]
    k0 = np.floor(fk).astype(np.int64)
    k1 = (k0 + 1) % ncols
    f = (fk - k0)[..., None]
    col = (1.0 - f) * wheel[k0 % ncols] + f * wheel[k1]  # (H, W, 3) in [0, 1]
    inside = (rad <= 1.0)[..., None]
    col = np.where(inside, 1.0 - rad[..., None] * (1.0 - col), col * 0.75)
    img = np.floor(255.0 * np.clip(col, 0.0, 1.0)).astype(np.uint8)
    img[~ok] = 0
    return img


def color_wheel_legend(size: int = 256, max_flow: Optional[float] = None) -> np.ndarray:
    """Key of :func:`flow_to_color`: the wheel for flows of norm ≤ 1 (white outside), with axis labels.

    Args:
      size: side in pixels.
      max_flow: if given, the rim is labelled with this radius in pixels.
    Returns:
      ``(size, size, 3)`` uint8 RGB.
    """
    c = (size - 1) / 2.0
    radius = c * 0.82
    y, x = np.mgrid[0:size, 0:size].astype(np.float64)
    flow = np.stack([(x - c) / radius, (y - c) / radius], -1)
    img = flow_to_color(flow, max_flow=1.0)
    outside = np.hypot(x - c, y - c) > radius
    img[outside] = 255
    img = np.ascontiguousarray(img)
    ci = int(round(c))
    cv2.line(img, (ci, int(c - radius)), (ci, int(c + radius)), (90, 90, 90), 1)
    cv2.line(img, (int(c - radius), ci), (int(c + radius), ci), (90, 90, 90), 1)
    scale = size / 512.0
    label = "+u" if max_flow is None else f"+{max_flow:.3g}px"
    _text(img, label, (int(c + radius) - int(90 * scale), ci - 6), scale, (0, 0, 0))
    _text(img, "+v", (ci + 6, int(c + radius) - 4), scale, (0, 0, 0))
    return img


def _text(img: np.ndarray, text: str, org: tuple[int, int], scale: float, color, thickness: int = 1) -> None:
    cv2.putText(img, text, org, cv2.FONT_HERSHEY_SIMPLEX, max(0.35, 0.9 * scale), color, thickness,
                cv2.LINE_AA)


def _apply_colormap(t: np.ndarray, ok: np.ndarray, colormap: str) -> np.ndarray:
    """``t`` in [0, 1] → RGB uint8 with the named OpenCV colormap; ``~ok`` black."""
    if colormap not in _COLORMAPS:
        raise ValueError(f"unknown colormap {colormap!r}; expected one of {sorted(_COLORMAPS)}")
    idx = np.round(np.clip(np.where(ok, t, 0.0), 0.0, 1.0) * 255.0).astype(np.uint8)
    bgr = cv2.applyColorMap(idx, _COLORMAPS[colormap])
    rgb = bgr[..., ::-1].copy()
    rgb[~ok] = 0
    return rgb


def _robust_max(x: np.ndarray, ok: np.ndarray, q: float = 99.0) -> float:
    return float(np.percentile(x[ok], q)) if ok.any() else 1.0


def disparity_to_color(disp: np.ndarray, vmax: Optional[float] = None, vmin: float = 0.0,
                       valid: Optional[np.ndarray] = None, colormap: str = "magma") -> np.ndarray:
    """Colour-coded disparity (near = large disparity = bright).

    Args:
      disp: ``(H, W)`` disparity in pixels.
      vmax: value mapped to the top of the colormap; default the 99th percentile of valid pixels.
      vmin: value mapped to the bottom.
    Returns:
      ``(H, W, 3)`` uint8 RGB; use :func:`colorbar` with the same ``vmin, vmax, colormap`` for the legend.
    """
    disp = np.asarray(disp, np.float64)
    if disp.ndim != 2:
        raise ValueError(f"disparity must be (H, W), got {disp.shape}")
    ok = _finite_mask(disp, valid)
    vmax = _robust_max(disp, ok) if vmax is None else float(vmax)
    t = (disp - vmin) / max(vmax - vmin, 1e-9)
    return _apply_colormap(t, ok, colormap)


def depth_to_color(depth: np.ndarray, vmin: float = 2.0, vmax: float = 80.0,
                   valid: Optional[np.ndarray] = None, colormap: str = "magma") -> np.ndarray:
    """Colour-coded depth in metres, linear in *inverse* depth (near = bright), ``vmin..vmax`` metres.

    Returns ``(H, W, 3)`` uint8 RGB; legend: ``colorbar(vmin, vmax, colormap, inverse=True, unit="m")``.
    """
    depth = np.asarray(depth, np.float64)
    if depth.ndim != 2:
        raise ValueError(f"depth must be (H, W), got {depth.shape}")
    ok = _finite_mask(depth, valid) & (depth > 0)
    t = _inverse_position(np.where(ok, depth, vmax), vmin, vmax)
    return _apply_colormap(t, ok, colormap)


CONFIDENCE_COLORMAP = "viridis"
"""Colormap of confidence pictures (`confidence_to_color`): dark blue = 0 (not trusted), yellow = 1 (trusted)."""


def confidence_to_color(confidence: np.ndarray, colormap: str = CONFIDENCE_COLORMAP) -> np.ndarray:
    """Colour-coded confidence ``(H, W)`` in [0, 1] -> ``(H, W, 3)`` uint8 RGB; legend:
    ``colorbar(0, 1, CONFIDENCE_COLORMAP, unit="", label="confidence")``."""
    conf = np.asarray(confidence, np.float64)
    if conf.ndim != 2:
        raise ValueError(f"confidence must be (H, W), got {conf.shape}")
    return _apply_colormap(conf, np.isfinite(conf), colormap)


def occlusion_to_image(occlusion: np.ndarray) -> np.ndarray:
    """An occlusion mask ``(H, W)`` bool -> ``(H, W)`` uint8 picture: 255 (white) = occluded (no visible match
    in the other image), 0 (black) = matched; lossless, so the PNG is also the raw mask."""
    occ = np.asarray(occlusion)
    if occ.ndim != 2:
        raise ValueError(f"occlusion must be (H, W), got {occ.shape}")
    return np.where(occ.astype(bool), 255, 0).astype(np.uint8)


def _inverse_position(value: np.ndarray, vmin: float, vmax: float) -> np.ndarray:
    """Position in [0, 1] of ``value`` on an inverse scale: vmax → 0, vmin → 1."""
    value = np.clip(value, vmin, vmax)
    return (1.0 / value - 1.0 / vmax) / (1.0 / vmin - 1.0 / vmax)


ERROR_MAX_PX = 12.0
"""End-point error (pixels) drawn at the top of :func:`error_to_color`'s scale (and everything above it)."""
ERROR_COLORMAP = "jet"
"""The colormap of :func:`error_to_color` (blue = 0, red = large)."""


def error_to_color(err: np.ndarray, valid: Optional[np.ndarray] = None, max_err: float = ERROR_MAX_PX,
                   colormap: str = ERROR_COLORMAP) -> np.ndarray:
    """Colour-coded end-point error (pixels), on a log scale ``log(1 + e) / log(1 + max_err)`` (blue = 0,
    red ≥ ``max_err``); invalid pixels black. Legend: :func:`error_colorbar` (= ``colorbar(0, max_err,
    colormap, log=True, unit="px")``)."""
    err = np.asarray(err, np.float64)
    ok = _finite_mask(err, valid)
    t = np.log1p(np.maximum(err, 0.0)) / np.log1p(max_err)
    return _apply_colormap(t, ok, colormap)


def _nice_ticks(vmin: float, vmax: float, n: int = 5) -> list[float]:
    span = vmax - vmin
    if span <= 0:
        return [vmin]
    raw = span / max(n - 1, 1)
    mag = 10 ** math.floor(math.log10(raw))
    step = min((m * mag for m in (1, 2, 2.5, 5, 10) if m * mag >= raw), default=10 * mag)
    start = math.ceil(vmin / step) * step
    return [round(v, 10) for v in np.arange(start, vmax + 1e-9 * span, step)]


def colorbar(vmin: float, vmax: float, colormap: str = "magma", *, height: int = 256, width: int = 80,
             unit: str = "px", label: str = "", inverse: bool = False, log: bool = False) -> np.ndarray:
    """A vertical colour-bar legend (top = high end of the colormap) with tick labels.

    Args:
      vmin, vmax: value range (same as given to the colouring function).
      inverse: the scale is linear in 1/value (:func:`depth_to_color`): vmin at the top.
      log: the scale is ``log(1+v)`` (:func:`error_to_color`).
    Returns:
      ``(height, width, 3)`` uint8 RGB, white background.
    """
    pad = 10
    bar_h = height - 2 * pad - (14 if label else 0)
    top = pad + (14 if label else 0)
    t = np.linspace(1.0, 0.0, bar_h)[:, None].repeat(18, axis=1)
    img = np.full((height, width, 3), 255, np.uint8)
    img[top:top + bar_h, 4:22] = _apply_colormap(t, np.ones_like(t, bool), colormap)
    if label:
        _text(img, label, (2, 12), 0.35, (0, 0, 0))

    def position(v: float) -> float:
        if inverse:
            return float(_inverse_position(np.asarray(v), vmin, vmax))
        if log:
            return math.log1p(max(v, 0.0)) / math.log1p(vmax)
        return (v - vmin) / max(vmax - vmin, 1e-9)

    if inverse:
        candidates = [0.5, 1, 2, 3, 5, 7, 10, 15, 20, 30, 50, 80, 100, 150, 200, 300, 500]
        ticks = [v for v in candidates if vmin <= v <= vmax] or [vmin, vmax]
    elif log:
        ticks = [v for v in (0, 1, 2, 3, 5, 10, 20, 50, 100) if v <= vmax] + [vmax]
    else:
        ticks = _nice_ticks(vmin, vmax)
    last_y = None
    for v in sorted(set(ticks), key=position, reverse=True):   # top to bottom; drop ticks closer than 11 px
        y = int(round(top + (1.0 - position(v)) * (bar_h - 1)))
        if last_y is not None and y - last_y < 11:
            continue
        last_y = y
        cv2.line(img, (22, y), (27, y), (0, 0, 0), 1)
        _text(img, f"{v:g}{unit}", (29, y + 4), 0.35, (0, 0, 0))
    return img


def error_colorbar(height: int = 256, max_err: float = ERROR_MAX_PX, colormap: str = ERROR_COLORMAP,
                   label: str = "error") -> np.ndarray:
    """The legend of :func:`error_to_color` with the same ``max_err`` and ``colormap``: a ``(height, 80, 3)``
    uint8 RGB colour bar, 0 px at the bottom, ``max_err`` px at the top, log-spaced ticks in px."""
    return colorbar(0.0, max_err, colormap, height=height, unit="px", label=label, log=True)


def attach_colorbar(image: np.ndarray, bar: np.ndarray, gap: int = 4) -> np.ndarray:
    """``image (H, W, 3)`` with ``bar (h, w, 3)`` to its right after a white ``gap``, both top-aligned:
    ``(max(H, h), W + gap + w, 3)`` uint8 RGB, white where neither covers (so the bar can be read next to a
    whole panel without resizing, which would blur its tick labels)."""
    image, bar = to_uint8(image), to_uint8(bar)
    h = max(image.shape[0], bar.shape[0])
    out = np.full((h, image.shape[1] + gap + bar.shape[1], 3), 255, np.uint8)
    out[:image.shape[0], :image.shape[1]] = image
    out[:bar.shape[0], image.shape[1] + gap:] = bar
    return out


def to_uint8(image: np.ndarray) -> np.ndarray:
    """An image as uint8 RGB ``(H, W, 3)``: float in [0, 1] is scaled by 255; grayscale ``(H, W)`` replicated."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = np.round(np.clip(image.astype(np.float64), 0.0, 1.0) * 255.0).astype(np.uint8)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    return image


def panel(images: Sequence[np.ndarray], labels: Optional[Sequence[str]] = None, ncols: Optional[int] = None,
          height: Optional[int] = None, gap: int = 4) -> np.ndarray:
    """Side-by-side grid of labelled images (e.g. input, prediction, GT, error map).

    Args:
      images: RGB ``(H_i, W_i, 3)`` uint8 or float in [0, 1]; each is resized to the first image's size (or to
        ``height`` rows with the first image's aspect), maps with nearest neighbour.
      labels: optional captions drawn at the top-left of each tile.
      ncols: tiles per row (default: all in one row).
    Returns:
      ``(rows·H + gaps, cols·W + gaps, 3)`` uint8 RGB, white gaps.
    """
    if not images:
        raise ValueError("panel needs at least one image")
    tiles = [to_uint8(im) for im in images]
    h0, w0 = tiles[0].shape[:2]
    if height is not None:
        w0, h0 = max(1, round(w0 * height / h0)), height
    ncols = len(tiles) if ncols is None else max(1, ncols)
    nrows = -(-len(tiles) // ncols)
    out = np.full((nrows * h0 + (nrows - 1) * gap, ncols * w0 + (ncols - 1) * gap, 3), 255, np.uint8)
    for i, tile in enumerate(tiles):
        if tile.shape[:2] != (h0, w0):
            tile = cv2.resize(tile, (w0, h0), interpolation=cv2.INTER_NEAREST)
        if labels is not None and i < len(labels) and labels[i]:
            tile = tile.copy()  # the caption is drawn on a copy: the caller's image (a frame) stays as it was
            scale = max(0.4, h0 / 400.0)
            (tw, th), _ = cv2.getTextSize(labels[i], cv2.FONT_HERSHEY_SIMPLEX, scale, 1)
            cv2.rectangle(tile, (0, 0), (tw + 6, th + 8), (0, 0, 0), -1)
            cv2.putText(tile, labels[i], (3, th + 4), cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1,
                        cv2.LINE_AA)
        r, c = divmod(i, ncols)
        out[r * (h0 + gap): r * (h0 + gap) + h0, c * (w0 + gap): c * (w0 + gap) + w0] = tile
    return out


def prediction_panel(image: np.ndarray, flow: Optional[np.ndarray] = None, disparity: Optional[np.ndarray] = None,
                     *, max_flow: Optional[float] = None, max_disp: Optional[float] = None) -> np.ndarray:
    """One row ``input | flow | disparity`` (the ones given) for logs and TensorBoard.

    Args:
      image: ``(H, W, 3)`` uint8 or float in [0, 1].
      flow: ``(h, w, 2)`` pixels (any size; shown at the image size); disparity: ``(h, w)`` pixels.
    Returns:
      ``(H, W·k + gaps, 3)`` uint8 RGB.
    """
    tiles, labels = [image], ["input"]
    if flow is not None:
        tiles.append(flow_to_color(flow, max_flow=max_flow))
        labels.append("flow")
    if disparity is not None:
        tiles.append(disparity_to_color(disparity, vmax=max_disp))
        labels.append("disparity")
    return panel(tiles, labels)


def write_image(path: str | os.PathLike, rgb: np.ndarray) -> None:
    """Write an RGB uint8 image (PNG/JPEG by extension) atomically, under any file name (`files.imwrite`);
    ValueError naming the path if OpenCV cannot encode it, OSError if it cannot be written."""
    files.imwrite(path, to_uint8(rgb)[..., ::-1])
