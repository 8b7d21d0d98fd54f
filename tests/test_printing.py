"""Printable sheets: true scale, decodable stickers, page sizes, ID-list parsing."""

from __future__ import annotations

import re

import cv2
import numpy as np
import pytest
import zxingcpp
from PIL import Image

from tagloc.cli import main
from tagloc.core.errors import InputError
from tagloc.core.sticker import payloads, render_sticker
from tagloc.io.printing import PAPER_MM, SheetConfig, page_paths, parse_ids, sheet_layout, write_sheets

A4_PT = (210 / 25.4 * 72, 297 / 25.4 * 72)


def test_parse_ids_tokens_and_ranges():
    assert parse_ids(["12", "13", "20-23"]) == [12, 13, 20, 21, 22, 23]
    assert parse_ids(["5,7", "0", "99999"]) == [5, 7, 0, 99999]
    assert parse_ids(["3", "1-3"]) == [3, 1, 2]  # order kept, duplicates dropped


@pytest.mark.parametrize(
    "tokens, fragment",
    [
        (["12x"], "'12x'"),
        (["-3"], "'-3'"),
        (["1.5"], "'1.5'"),
        (["29-20"], "reversed"),
        (["100000"], "outside"),
        (["99990-100001"], "outside"),
        ([], "no sticker"),
        (["0-99999"], "at most"),
    ],
)
def test_parse_ids_refuses_bad_tokens(tokens, fragment):
    with pytest.raises(InputError, match=re.escape(fragment)):
        parse_ids(tokens)


def test_layout_fits_page_with_room_for_cut_marks():
    for paper, (w, h) in PAPER_MM.items():
        lay = sheet_layout(SheetConfig(paper=paper))
        assert lay.per_page >= 2
        x, y = lay.origins[:, 0], lay.origins[:, 1]
        assert x.min() >= 10 - 1e-9 and x.max() + 100 <= w - 10 + 1e-9
        assert y.min() >= 10 and y.max() + 100 <= h - 10
    assert sheet_layout(SheetConfig(paper="a3")).per_page == 6
    with pytest.raises(InputError, match="gap"):
        sheet_layout(SheetConfig(gap_mm=4))
    with pytest.raises(InputError, match="paper"):
        sheet_layout(SheetConfig(paper="b5"))


def _black_squares(grey: np.ndarray) -> list[tuple[float, float, float, float]]:
    """Bounding boxes (x, y, w, h) px of the large dark squares (the stickers' outer frames)."""
    dark = (grey < 128).astype(np.uint8)
    contours, _ = cv2.findContours(dark, cv2.RETR_EXTERNAL, cv2.CHAIN_APPROX_SIMPLE)
    boxes = [cv2.boundingRect(c) for c in contours]
    return sorted((b for b in boxes if b[2] > grey.shape[1] / 4), key=lambda b: b[1])


def test_png_sheet_true_scale_and_decodes(tmp_path):
    dpi = 300
    ids = [0, 42, 99999]
    files = write_sheets(ids, tmp_path / "s.png", SheetConfig(dpi=dpi))
    assert [f.name for f in files] == ["s-1.png", "s-2.png"]  # A4 holds 2 stickers
    assert Image.open(files[0]).info["dpi"] == pytest.approx((dpi, dpi), abs=0.01)
    px_per_mm = dpi / 25.4
    found: list[int] = []
    for f, page_ids in zip(files, ([0, 42], [99999])):
        grey = cv2.imread(str(f), cv2.IMREAD_GRAYSCALE)
        assert grey.shape[1] / px_per_mm == pytest.approx(210, abs=0.2)
        assert grey.shape[0] / px_per_mm == pytest.approx(297, abs=0.2)
        boxes = _black_squares(grey)
        assert len(boxes) == len(page_ids)
        for (x, y, w, h), sid in zip(boxes, page_ids):
            assert w / px_per_mm == pytest.approx(100, abs=0.5)
            assert h / px_per_mm == pytest.approx(100, abs=0.5)
            # The printed raster is render_sticker's, upright (not mirrored or rotated).
            crop = cv2.resize(grey[y : y + h, x : x + w], (200, 200), interpolation=cv2.INTER_AREA)
            diff = np.abs(crop.astype(float) - render_sticker(sid, 200))
            assert diff.mean() < 8
        texts = sorted(r.text for r in zxingcpp.read_barcodes(grey, formats=zxingcpp.BarcodeFormat.DataMatrix))
        assert texts == sorted(p for sid in page_ids for p in payloads(sid))
        found += page_ids
    assert found == ids


def test_pdf_is_a4_multipage_with_unresampled_stickers(tmp_path):
    out = write_sheets(list(range(10, 15)), tmp_path / "sheet.pdf")
    assert out == [tmp_path / "sheet.pdf"]
    data = out[0].read_bytes()
    assert data.startswith(b"%PDF")
    boxes = re.findall(rb"/MediaBox \[ *0 0 ([\d.]+) ([\d.]+) *\]", data)
    assert len(boxes) == 3  # 5 stickers, 2 per A4 page
    for w, h in boxes:
        assert (float(w), float(h)) == pytest.approx(A4_PT, abs=0.01)
    # Each sticker is embedded as the exact 200x200 raster (0.5 mm cells), not resampled.
    assert len(re.findall(rb"/Width 200\b", data)) == 5


def test_svg_sticker_is_100_mm(tmp_path):
    (f,) = write_sheets([7], tmp_path / "one.svg")
    text = f.read_text()
    w, h = (float(v) for v in re.search(r'<svg[^>]*width="([\d.]+)pt" height="([\d.]+)pt"', text).groups())
    assert (w, h) == pytest.approx(A4_PT, abs=0.01)
    m = re.search(r'<image[^>]*width="200" height="200" transform="matrix\(([\d.]+) 0 0 ([\d.]+) ', text)
    assert m is not None
    assert 200 * float(m.group(1)) * 25.4 / 72 == pytest.approx(100.0, abs=0.01)
    assert 200 * float(m.group(2)) * 25.4 / 72 == pytest.approx(100.0, abs=0.01)


def test_page_paths_and_bad_outputs(tmp_path):
    assert page_paths(tmp_path / "a.svg", 1) == [tmp_path / "a.svg"]
    assert page_paths(tmp_path / "a.svg", 2) == [tmp_path / "a-1.svg", tmp_path / "a-2.svg"]
    with pytest.raises(InputError, match="format"):
        write_sheets([1], tmp_path / "a.jpg")
    with pytest.raises(InputError, match="does not exist"):
        write_sheets([1], tmp_path / "nodir" / "a.pdf")
    with pytest.raises(InputError, match="outside"):
        write_sheets([100000], tmp_path / "a.pdf")


def test_cli_sticker(tmp_path, capsys):
    assert main(["sticker", "3", "5-6", "-o", str(tmp_path / "x.pdf")]) == 0
    assert (tmp_path / "x.pdf").stat().st_size > 1000
    assert main(["sticker", "3", "zz", "-o", str(tmp_path / "y.pdf")]) == 2
    err = capsys.readouterr().err.strip()
    assert "'zz'" in err and len(err.splitlines()) == 1
    assert not (tmp_path / "y.pdf").exists()
