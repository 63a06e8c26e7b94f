""".flo and .pfm: writers against hand-built byte layouts, readers on hand-built files (PFM vertical flip,
big-endian PFM), dispatch by extension, and one clear error for garbage, truncated and absurd files."""

import os
import struct

import numpy as np
import pytest

from bridge_jax import flowio

# A 2x3 (H x W) flow whose every component differs: u = 10*row + col, v = -(10*row + col) - 0.5
FLOW = np.array([[[0.0, -0.5], [1.0, -1.5], [2.0, -2.5]],
                 [[10.0, -10.5], [11.0, -11.5], [12.0, -12.5]]], np.float32)


def _flo_bytes():
    """The .flo layout written out by hand: magic, width 3, height 2, then u, v per pixel, top row first."""
    values = [0.0, -0.5, 1.0, -1.5, 2.0, -2.5, 10.0, -10.5, 11.0, -11.5, 12.0, -12.5]
    return struct.pack("<f", 202021.25) + struct.pack("<ii", 3, 2) + struct.pack("<12f", *values)


def test_flo_magic_is_pieh():
    assert struct.pack("<f", 202021.25) == b"PIEH" == flowio.FLO_MAGIC


def test_write_flo_matches_hand_built_bytes(tmp_path):
    path = tmp_path / "f.flo"
    flowio.write_flo(path, FLOW)
    assert path.read_bytes() == _flo_bytes()
    # float64 and int input are stored as float32 all the same
    flowio.write_flo(path, FLOW.astype(np.float64))
    assert path.read_bytes() == _flo_bytes()
    assert [f for f in os.listdir(tmp_path) if f != "f.flo"] == []      # no temporary file left behind


def test_read_flo_hand_built_file(tmp_path):
    path = tmp_path / "hand.flo"
    path.write_bytes(_flo_bytes())
    flow = flowio.read_flo(path)
    assert flow.dtype == np.float32 and flow.shape == (2, 3, 2)
    assert flow[1, 2].tolist() == [12.0, -12.5]             # row 1, column 2: (u, v) = (12, -12.5)
    assert flow[0, 1].tolist() == [1.0, -1.5]
    np.testing.assert_array_equal(flow, FLOW)


def test_read_flow_dispatch_and_unknown_marker(tmp_path):
    flow = FLOW.copy()
    flow[0, 0] = [2e9, 0.0]                                  # Middlebury "unknown"
    flowio.write_flo(tmp_path / "u.flo", flow)
    got, valid = flowio.read_flow(tmp_path / "u.flo")
    assert valid.tolist() == [[False, True, True], [True, True, True]]
    assert got[0, 0].tolist() == [0.0, 0.0] and got[1, 2].tolist() == [12.0, -12.5]
    np.save(tmp_path / "f.npy", FLOW)
    got, valid = flowio.read_flow(tmp_path / "f.npy")
    np.testing.assert_array_equal(got, FLOW)
    assert valid.all()
    with pytest.raises(flowio.FlowFormatError, match=r"x\.txt.*\.flo"):
        flowio.read_flow(tmp_path / "x.txt")


def _pfm_gray_bytes(endian="<", scale="-1.0"):
    """A 1-channel 3x2 (W x H) PFM by hand: rows stored bottom first, so the bottom row (4, 5, 6) comes first."""
    return (b"Pf\n3 2\n" + scale.encode() + b"\n"
            + struct.pack(endian + "6f", 4.0, 5.0, 6.0, 1.0, 2.0, 3.0))


def test_write_pfm_matches_hand_built_bytes(tmp_path):
    top_first = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]], np.float32)
    path = tmp_path / "d.pfm"
    flowio.write_pfm(path, top_first)
    assert path.read_bytes() == _pfm_gray_bytes()
    flowio.write_pfm(path, top_first[..., None])             # (H, W, 1) is the same 1-channel file
    assert path.read_bytes() == _pfm_gray_bytes()
    rgb = np.arange(2 * 2 * 3, dtype=np.float32).reshape(2, 2, 3)   # top row 0..5, bottom row 6..11
    flowio.write_pfm(path, rgb)
    want = b"PF\n2 2\n-1.0\n" + struct.pack("<12f", 6, 7, 8, 9, 10, 11, 0, 1, 2, 3, 4, 5)
    assert path.read_bytes() == want


def test_read_pfm_flips_rows_and_honours_endianness(tmp_path):
    little = tmp_path / "le.pfm"
    little.write_bytes(_pfm_gray_bytes())
    a = flowio.read_pfm(little)
    assert a.dtype == np.float32 and a.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]]   # top row first
    big = tmp_path / "be.pfm"
    big.write_bytes(_pfm_gray_bytes(">", "2.5"))               # positive scale: big-endian, scale 2.5
    b, scale = flowio.read_pfm(big, with_scale=True)
    assert b.tolist() == [[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]] and scale == 2.5
    # big-endian bytes read as little-endian would be garbage: the endianness really is taken from the sign
    assert struct.pack(">f", 4.0) != struct.pack("<f", 4.0)
    rgb = tmp_path / "rgb.pfm"
    rgb.write_bytes(b"PF\n1 2\n-1\n" + struct.pack("<6f", 7, 8, 9, 1, 2, 3))
    c = flowio.read_pfm(rgb)
    assert c.shape == (2, 1, 3) and c[0, 0].tolist() == [1, 2, 3] and c[1, 0].tolist() == [7, 8, 9]
    # dispatch: a disparity .pfm; inf = unknown (Middlebury 2014)
    inf = tmp_path / "inf.pfm"
    inf.write_bytes(b"Pf\n2 1\n-1.0\n" + struct.pack("<2f", float("inf"), 3.5))
    disp, valid = flowio.read_disparity(inf)
    assert disp.tolist() == [[0.0, 3.5]] and valid.tolist() == [[False, True]]
    # a 3-channel flow .pfm (Scene Flow datasets): the first two channels
    flow, valid = flowio.read_flow(rgb)
    assert flow.shape == (2, 1, 2) and flow[0, 0].tolist() == [1, 2] and valid.all()


def test_round_trips(tmp_path):
    rng = np.random.default_rng(0)
    flow = rng.normal(size=(5, 7, 2)).astype(np.float32)
    np.testing.assert_array_equal(flowio.read_flo(flowio.write_flo(tmp_path / "r.flo", flow)), flow)
    disp = rng.uniform(0, 90, size=(4, 6)).astype(np.float32)
    np.testing.assert_array_equal(flowio.read_pfm(flowio.write_pfm(tmp_path / "r.pfm", disp)), disp)


@pytest.mark.parametrize("data, message", [
    (b"", "shorter than the 12-byte header"),
    (b"NOPE" + struct.pack("<ii", 3, 2) + bytes(48), "magic bytes b'PIEH'"),
    (b"PIEH" + struct.pack("<ii", 3, 2) + bytes(47), r"truncated: expected 48 bytes .* got 47"),
    (b"PIEH" + struct.pack("<ii", 3, 2) + bytes(52), "trailing bytes"),
    (b"PIEH" + struct.pack("<ii", 0, 2), "width 0 is not in 1..99999"),
    (b"PIEH" + struct.pack("<ii", 3, 1 << 30), "height 1073741824"),
    (b"PIEH" + struct.pack("<ii", -5, 2), "width -5"),
])
def test_bad_flo(tmp_path, data, message):
    path = tmp_path / "bad.flo"
    path.write_bytes(data)
    with pytest.raises(flowio.FlowFormatError, match=message) as info:
        flowio.read_flo(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("data, message", [
    (b"\x89PNG\r\n\x1a\n" + bytes(40), "type line 'PF'"),
    (b"P6\n3 2\n255\n" + bytes(18), "type line 'PF'"),
    (b"Pf\nthree two\n-1.0\n" + bytes(24), "size line must be '<width> <height>'"),
    (b"Pf\n3 2\nabc\n" + bytes(24), "scale line must be a non-zero number"),
    (b"Pf\n3 2\n0\n" + bytes(24), "scale line must be a non-zero number"),
    (b"Pf\n3 2\n-1.0\n" + bytes(23), r"truncated: expected 24 bytes for 3x2x1"),
    (b"PF\n3 2\n-1.0\n" + bytes(24), r"truncated: expected 72 bytes for 3x2x3"),
    (b"Pf\n3 2\n-1.0\n" + bytes(28), "trailing bytes"),
    (b"Pf\n100000 2\n-1.0\n", "width 100000 is not in 1..99999"),
    (b"Pf" + bytes(300), "no end of line"),
])
def test_bad_pfm(tmp_path, data, message):
    path = tmp_path / "bad.pfm"
    path.write_bytes(data)
    with pytest.raises(flowio.FlowFormatError, match=message) as info:
        flowio.read_pfm(path)
    assert str(path) in str(info.value) and "\n" not in str(info.value)


def test_bad_arrays_to_write(tmp_path):
    with pytest.raises(flowio.FlowFormatError, match=r"f\.flo: .*\(H, W, 2\).*\(2, 3\)"):
        flowio.write_flo(tmp_path / "f.flo", np.zeros((2, 3)))
    with pytest.raises(flowio.FlowFormatError, match=r"d\.pfm: .*\(H, W\) or \(H, W, 3\).*\(2, 3, 2\)"):
        flowio.write_pfm(tmp_path / "d.pfm", np.zeros((2, 3, 2)))
    assert os.listdir(tmp_path) == []                          # nothing half-written
    with pytest.raises(OSError):
        flowio.read_flo(tmp_path / "missing.flo")
