"""Colour wheel and colormaps: documented hues, saturation, legends, panels."""

import cv2
import numpy as np
import pytest

from bridge_jax import visualize


def _hue_deg(rgb):
    hsv = cv2.cvtColor(np.asarray(rgb, np.uint8).reshape(1, 1, 3), cv2.COLOR_RGB2HSV_FULL)
    return hsv[0, 0, 0] * 360.0 / 256.0, hsv[0, 0, 1], hsv[0, 0, 2]


def test_wheel_ramps():
    wheel = visualize.color_wheel()
    assert wheel.shape == (55, 3)
    # ramp starts: red, yellow, green, cyan, blue, magenta at indices 0, 15, 21, 25, 36, 49
    expected = {0: (255, 0, 0), 15: (255, 255, 0), 21: (0, 255, 0), 25: (0, 255, 255), 36: (0, 0, 255),
                49: (255, 0, 255)}
    for i, col in expected.items():
        assert tuple(wheel[i]) == col, i
    # inside a ramp the rising channel is floor(255 i / n): RY index 7 → green floor(255·7/15) = 119
    assert tuple(wheel[7]) == (255, 119, 0)


@pytest.mark.parametrize("direction, flow, hue_centre, tol", [
    ("right", (1.0, 0.0), 355.0, 15.0),    # wheel index 0 / 54 = (255, 0, 0) / (255, 0, 43): red
    ("down", (0.0, 1.0), 53.0, 10.0),      # index 13.5, between (255, 221, 0) and (255, 238, 0): yellow
    ("left", (-1.0, 0.0), 191.0, 8.0),     # index 27 = (0, 209, 255): cyan
    ("up", (0.0, -1.0), 260.0, 8.0),       # index 40.5 ≈ (88, 0, 255): blue-violet
])
def test_known_directions_map_to_documented_hues(direction, flow, hue_centre, tol):
    field = np.array(flow, np.float64).reshape(1, 1, 2)
    rgb = visualize.flow_to_color(field, max_flow=1.0)[0, 0]
    hue, sat, val = _hue_deg(rgb)
    dist = abs((hue - hue_centre + 180.0) % 360.0 - 180.0)
    assert dist <= tol, (direction, rgb, hue)
    assert sat > 240 and val == 255                      # full saturation at the unit radius
    assert visualize.DIRECTION_HUES[direction] in {"red", "yellow", "cyan", "blue"}


def test_saturation_and_overflow():
    field = np.array([[[0, 0], [0.5, 0], [1.0, 0], [2.0, 0]]], np.float64)
    rgb = visualize.flow_to_color(field, max_flow=1.0)[0]
    assert tuple(rgb[0]) == (255, 255, 255)              # no motion: white
    _, s_half, _ = _hue_deg(rgb[1])
    _, s_full, v_full = _hue_deg(rgb[2])
    assert s_half < s_full
    assert tuple(rgb[3]) == (191, 0, 0)                   # beyond max: wheel colour 0 (255, 0, 0) × 0.75
    # default normalisation = largest norm of the field
    np.testing.assert_array_equal(visualize.flow_to_color(field)[0, 3], rgb[2])


def test_invalid_pixels_black():
    field = np.array([[[1.0, 0.0], [np.nan, 0.0], [0.0, 1.0]]])
    rgb = visualize.flow_to_color(field, valid=np.array([[True, True, False]]))
    assert rgb[0, 1].tolist() == [0, 0, 0] and rgb[0, 2].tolist() == [0, 0, 0]
    assert rgb[0, 0].sum() > 0


def test_legend_wheel():
    leg = visualize.color_wheel_legend(200, max_flow=10.0)
    assert leg.shape == (200, 200, 3) and leg.dtype == np.uint8
    assert tuple(leg[0, 0]) == (255, 255, 255)            # corner is outside the wheel
    c = 99
    hue, _, _ = _hue_deg(leg[c, c + 60])                  # right of centre: red
    assert hue > 330 or hue < 10


def test_disparity_depth_error_colormaps():
    disp = np.array([[0.0, 10.0, 50.0, np.nan]])
    rgb = visualize.disparity_to_color(disp, vmax=50.0)
    assert rgb.shape == (1, 4, 3) and rgb.dtype == np.uint8
    assert rgb[0, 3].tolist() == [0, 0, 0]
    lum = rgb.astype(float).sum(-1)[0]
    assert lum[0] < lum[1] < lum[2]                       # magma: larger disparity is brighter
    depth = np.array([[2.0, 10.0, 80.0, 0.0]])
    lum = visualize.depth_to_color(depth, 1.0, 80.0).astype(float).sum(-1)[0]
    assert lum[0] > lum[1] > lum[2] and lum[3] == 0       # near is bright; depth 0 is invalid → black
    err = visualize.error_to_color(np.array([[0.0, 20.0]]), max_err=12.0)
    assert err.shape == (1, 2, 3)
    assert err[0, 1, 0] > err[0, 1, 2] and err[0, 0, 2] > err[0, 0, 0]   # jet: 0 blue, large red


def test_colorbar_and_panel():
    bar = visualize.colorbar(0, 80, "magma", height=200, unit="m", label="depth", inverse=False)
    assert bar.shape == (200, 80, 3)
    # top of the bar is the bright end of magma, bottom the dark end
    assert bar[30, 10].astype(int).sum() > bar[185, 10].astype(int).sum()
    a = np.zeros((20, 40, 3), np.uint8)
    b = np.ones((10, 20, 3), np.float32)                  # float image, other size → resized
    p = visualize.panel([a, b, a], labels=["input", "pred", ""], ncols=2, gap=2)
    assert p.shape == (42, 82, 3)
    assert (p[30:, 42:] == 255).all()                     # empty 4th tile stays white
    assert (p[20:22] == 255).all()                         # horizontal gap
    assert p[19, 81].tolist() == [255, 255, 255]           # tile b (float ones → 255), below its label
    assert p[2, 2].tolist() == [0, 0, 0] and p[19, 39].tolist() == [0, 0, 0]
    # the captions are drawn on copies: a uint8 input (e.g. a validation frame reused at every validation) is
    # left as it was
    frame = np.full((20, 40, 3), 77, np.uint8)
    p = visualize.panel([frame, frame], labels=["left t", "again"])
    assert (frame == 77).all() and p[2, 2].tolist() == [0, 0, 0]


def test_write_image_roundtrip(tmp_path):
    img = visualize.flow_to_color(np.random.default_rng(0).normal(size=(8, 9, 2)))
    path = tmp_path / "f.png"
    visualize.write_image(path, img)
    back = cv2.imread(str(path))[..., ::-1]
    np.testing.assert_array_equal(back, img)
    (tmp_path / "a_file").write_text("")
    with pytest.raises(OSError, match="a_file"):
        visualize.write_image(tmp_path / "a_file" / "x.png", img)
    with pytest.raises(ValueError, match=r"cannot write image .*f\.xyz: OpenCV cannot encode .* as \.xyz"):
        visualize.write_image(tmp_path / "f.xyz", img)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["a_file", "f.png"]


def test_prediction_panel():
    img = np.zeros((16, 32, 3), np.float32)
    flow = np.ones((8, 16, 2), np.float32)                # a smaller map is shown at the image size
    p = visualize.prediction_panel(img, flow=flow, disparity=np.ones((16, 32)), max_flow=1.0)
    assert p.shape == (16, 3 * 32 + 2 * 4, 3)
    right_down = visualize.flow_to_color(np.ones((1, 1, 2)), max_flow=1.0)[0, 0]
    assert p[15, 36 + 31].tolist() == right_down.tolist()   # bottom-right of the flow tile (below the label)


def _jet_rgb(index):
    """OpenCV's jet colour at colormap index 0..255, RGB (computed here, independently of visualize)."""
    return cv2.applyColorMap(np.array([[index]], np.uint8), cv2.COLORMAP_JET)[0, 0, ::-1].tolist()


def test_error_colorbar_matches_error_to_color_scale():
    bar = visualize.error_colorbar(96)
    np.testing.assert_array_equal(bar, visualize.colorbar(0.0, 12.0, "jet", height=96, unit="px", label="error",
                                                          log=True))
    # the bar occupies rows 24..85 (10 px pad + 14 px label; 96 - 20 - 14 = 62 rows), columns 4..21
    assert bar[24, 10].tolist() == _jet_rgb(255) == visualize.error_to_color(np.array([[12.0]]))[0, 0].tolist()
    assert bar[85, 10].tolist() == _jet_rgb(0) == visualize.error_to_color(np.array([[0.0]]))[0, 0].tolist()
    # ticks (black, columns 22..27) at the ends: 12 px at the top row, 0 px at the bottom row
    assert bar[24, 24].tolist() == [0, 0, 0] and bar[85, 24].tolist() == [0, 0, 0]


def test_attach_colorbar():
    img = np.full((30, 10, 3), 7, np.uint8)
    bar = np.full((50, 5, 3), 100, np.uint8)
    out = visualize.attach_colorbar(img, bar, gap=2)
    assert out.shape == (50, 17, 3)
    assert (out[:30, :10] == 7).all() and (out[30:, :10] == 255).all()    # image top-aligned, white below
    assert (out[:, 10:12] == 255).all() and (out[:, 12:] == 100).all()    # gap, then the bar
