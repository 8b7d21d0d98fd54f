"""Sticker payloads and the renderer: every symbol decodes back, in the right quadrant."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
import zxingcpp
from pylibdmtx import pylibdmtx

from tagloc.core.errors import InputError
from tagloc.core.sticker import (
    ALL_CORNERS,
    INNER_CORNERS,
    OUTER_CORNERS,
    parse_payload,
    payload,
    payloads,
    render_sticker,
    sticker_pixel_to_metres,
    symbol_modules,
)

IDS = (0, 7, 42, 31337, 99999)
SIZES = (120, 200, 400)


def _with_border(img: np.ndarray) -> np.ndarray:
    """The sticker on white paper (a quiet border of 1/8 of its size)."""
    b = img.shape[0] // 8
    return cv2.copyMakeBorder(img, b, b, b, b, cv2.BORDER_CONSTANT, value=255)


def test_payload_format():
    assert payload(42, 3) == "000423"
    assert payloads(42) == ["000420", "000421", "000422", "000423"]
    assert payloads(0)[0] == "000000" and payloads(99999)[3] == "999993"


@pytest.mark.parametrize("bad_id, quadrant", [(-1, 0), (100000, 0), (1.5, 0), (5, 4), (5, -1)])
def test_payload_refuses_bad_input(bad_id, quadrant):
    with pytest.raises(InputError):
        payload(bad_id, quadrant)


def test_parse_payload():
    for sid in IDS:
        for q, text in enumerate(payloads(sid)):
            assert parse_payload(text) == (sid, q)
    for bad in ("", "00042", "0004201", "00042a", "000424", "000429", " 00042", "\u0660" * 6, "12345\u0663"):
        assert parse_payload(bad) is None, bad


def test_render_geometry():
    img = render_sticker(5, 200)  # 0.5 mm cells: frame 16, quadrant 84, module 7, quiet zone 7
    assert img.shape == (200, 200) and img.dtype == np.uint8
    frame = np.ones((200, 200), bool)
    frame[16:184, 16:184] = False
    assert np.all(img[frame] == 0)
    quiet = np.zeros((200, 200), bool)
    for r0 in (16, 100):  # each quadrant's 7-cell quiet border is white
        for c0 in (16, 100):
            quiet[r0 : r0 + 84, c0 : c0 + 84] = True
            quiet[r0 + 7 : r0 + 77, c0 + 7 : c0 + 77] = False
    assert np.all(img[quiet] == 255)
    # Quadrant 1 (top-right) holds exactly symbol_modules of payload q=1, module by module.
    sym = img[16 + 7 : 16 + 77, 100 + 7 : 100 + 77][3::7, 3::7] == 0
    assert np.array_equal(sym, symbol_modules(payload(5, 1)))
    for n in (50, 137, 400):
        assert render_sticker(5, n).shape == (n, n)


def test_corners_and_pixel_mapping():
    assert OUTER_CORNERS[0, :2] == pytest.approx((-0.05, 0.05))  # canonical top-left
    assert INNER_CORNERS[2, :2] == pytest.approx((0.042, -0.042))
    assert ALL_CORNERS.shape == (8, 3)
    A = sticker_pixel_to_metres(200)
    assert A @ np.array([0, 0, 1.0]) == pytest.approx((-0.04975, 0.04975))
    assert A @ np.array([199, 199, 1.0]) == pytest.approx((0.04975, -0.04975))


@pytest.mark.parametrize("size", SIZES)
def test_zxing_decodes_every_symbol_in_its_quadrant(size):
    for sid in IDS:
        img = _with_border(render_sticker(sid, size))
        b = size // 8
        results = zxingcpp.read_barcodes(img, formats=zxingcpp.BarcodeFormat.DataMatrix)
        got = {}
        for r in results:
            p = r.position
            cx = (p.top_left.x + p.top_right.x + p.bottom_right.x + p.bottom_left.x) / 4 - b
            cy = (p.top_left.y + p.top_right.y + p.bottom_right.y + p.bottom_left.y) / 4 - b
            right, bottom = cx > size / 2, cy > size / 2
            got[r.text] = {(False, False): 0, (True, False): 1, (True, True): 2, (False, True): 3}[(right, bottom)]
        assert got == {payload(sid, q): q for q in range(4)}


@pytest.mark.parametrize("size", SIZES)
def test_libdmtx_decodes_every_symbol(size):
    for sid in IDS:
        img = _with_border(render_sticker(sid, size))
        texts = sorted(r.data.decode() for r in pylibdmtx.decode(img, max_count=4, timeout=3000))
        assert texts == payloads(sid)
    # Per quadrant crop: quadrant q holds payload q.
    img = render_sticker(31337, size)
    half = size // 2
    crops = {0: img[:half, :half], 1: img[:half, half:], 2: img[half:, half:], 3: img[half:, :half]}
    for q, crop in crops.items():
        res = pylibdmtx.decode(np.ascontiguousarray(crop), max_count=1, timeout=2000)
        assert [r.data.decode() for r in res] == [payload(31337, q)]
