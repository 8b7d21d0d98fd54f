"""Print-ready sticker sheets at true scale (PDF, PNG or SVG).

Each page is one matplotlib figure exactly the paper's size, with axes in millimetres from the
page's top-left corner, so a sticker drawn over a 100 mm extent prints 100 mm at 100 % scale.
Every sticker is :func:`tagloc.core.sticker.render_sticker` on its exact 0.5 mm grid, embedded
unresampled in PDF/SVG (crisp at any zoom) and nearest-neighbour resampled in PNG.

A page carries: the stickers in a grid, cut marks off each sticker's corners, the ID in small text
under each sticker's canonical bottom edge (text upright = sticker in canonical orientation), a
header and a labelled 50 mm scale bar to check the print scale.
"""

from __future__ import annotations

import math
import re
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import matplotlib as mpl
import numpy as np
from matplotlib.figure import Figure

from tagloc.core.errors import InputError
from tagloc.core.sticker import MAX_ID, SIZE_M, check_id, render_sticker
from tagloc.core.stickermap import shown

#: Paper sizes (width, height) in mm, portrait.
PAPER_MM = {"a4": (210.0, 297.0), "a3": (297.0, 420.0), "letter": (215.9, 279.4)}
#: Output formats, chosen by file extension.
FORMATS = (".pdf", ".png", ".svg")
#: Refuse ID lists longer than this (a typo like 0-99999 would otherwise print 50,000 pages).
MAX_STICKERS = 5000

STICKER_MM = SIZE_M * 1000.0
_RENDER_PX = 200  # render_sticker's exact 0.5 mm grid: no resampling before the figure
_CUT_OFFSET_MM = 1.5  # cut marks start this far from the corner so they never touch the frame
_CUT_LENGTH_MM = 4.0
_HEADER_MM = 8.0
_FOOTER_MM = 18.0


@dataclass(frozen=True)
class SheetConfig:
    """How sheets are laid out.

    Attributes:
        paper: key of :data:`PAPER_MM`.
        margin_mm: blank border kept on every side (printers cannot print to the edge).
        gap_mm: space between neighbouring stickers (holds cut marks and the ID label).
        dpi: resolution of PNG output (PDF/SVG are vector, the stickers embedded unresampled).
        scale_bar_mm: length of the scale bar.
    """

    paper: str = "a4"
    margin_mm: float = 10.0
    gap_mm: float = 14.0
    dpi: int = 600
    scale_bar_mm: float = 50.0


@dataclass(frozen=True)
class SheetLayout:
    """Where stickers go on a page: ``cols`` x ``rows`` slots; ``origins`` (cols*rows, 2) are the
    top-left corners of the slots in mm from the page's top-left, row-major."""

    page_mm: tuple[float, float]
    cols: int
    rows: int
    origins: np.ndarray

    @property
    def per_page(self) -> int:
        return self.cols * self.rows


# ASCII digits only, as every number tagloc reads (\d also takes "\u0661", Arabic-Indic one, as 1),
# at most 6 each: an ID is at most 99999, and int() of thousands of digits is refused by Python.
_TOKEN = re.compile(r"([0-9]{1,6})(?:-([0-9]{1,6}))?")


def parse_ids(tokens: Iterable[str]) -> list[int]:
    """Parse sticker ID tokens such as ``["12", "13", "20-29"]`` (commas also separate).

    Returns the IDs in the order given, duplicates dropped. Raises :class:`InputError` naming the
    bad token (not a number or range, reversed range, ID outside 0-99999, nothing given, too many).
    """
    ids: dict[int, None] = {}
    for token in tokens:
        for part in str(token).replace(",", " ").split():
            m = _TOKEN.fullmatch(part)
            if not m:
                raise InputError(f"sticker ID {shown(part)} is not a number in 0-{MAX_ID} or a range like 20-29")
            lo = int(m.group(1))
            hi = int(m.group(2)) if m.group(2) is not None else lo
            if hi < lo:
                raise InputError(f"sticker ID range {part!r} is reversed (want low-high)")
            for value in (lo, hi):
                if value > MAX_ID:
                    raise InputError(f"sticker ID {value} in {shown(part)} is outside 0-{MAX_ID}")
            ids.update(dict.fromkeys(range(lo, hi + 1)))
    if not ids:
        raise InputError("no sticker IDs given")
    if len(ids) > MAX_STICKERS:
        raise InputError(f"{len(ids)} sticker IDs given, at most {MAX_STICKERS} per run")
    return list(ids)


def sheet_layout(config: SheetConfig = SheetConfig()) -> SheetLayout:
    """The sticker slots of one page, the block of stickers centred between header and footer."""
    if config.paper not in PAPER_MM:
        raise InputError(f"unknown paper {config.paper!r} (choose from {', '.join(PAPER_MM)})")
    if config.margin_mm < 0 or config.gap_mm < 2 * (_CUT_OFFSET_MM + _CUT_LENGTH_MM):
        raise InputError(
            f"margin must be >= 0 and gap >= {2 * (_CUT_OFFSET_MM + _CUT_LENGTH_MM):.0f} mm (room for cut marks)"
        )
    w, h = PAPER_MM[config.paper]
    avail_w = w - 2 * config.margin_mm
    avail_h = h - 2 * config.margin_mm - _HEADER_MM - _FOOTER_MM
    pitch = STICKER_MM + config.gap_mm
    cols = int(math.floor((avail_w + config.gap_mm) / pitch + 1e-9))
    rows = int(math.floor((avail_h + config.gap_mm) / pitch + 1e-9))
    if cols < 1 or rows < 1:
        raise InputError(f"no 100 mm sticker fits on {config.paper} with {config.margin_mm} mm margins")
    x0 = (w - (cols * pitch - config.gap_mm)) / 2
    top = config.margin_mm + _HEADER_MM
    y0 = top + (avail_h - (rows * pitch - config.gap_mm)) / 2
    origins = np.array([(x0 + c * pitch, y0 + r * pitch) for r in range(rows) for c in range(cols)])
    return SheetLayout((w, h), cols, rows, origins)


def _cut_marks(x0: float, y0: float) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """Segments (mm) continuing each edge of the sticker at (x0, y0) outwards past its corners."""
    a, b = _CUT_OFFSET_MM, _CUT_OFFSET_MM + _CUT_LENGTH_MM
    s = STICKER_MM
    segs = []
    for cx, sx in ((x0, -1), (x0 + s, 1)):
        for cy, sy in ((y0, -1), (y0 + s, 1)):
            segs.append(((cx + sx * a, cx + sx * b), (cy, cy)))  # horizontal, on the edge's line
            segs.append(((cx, cx), (cy + sy * a, cy + sy * b)))  # vertical
    return segs


def _scale_bar(ax: object, x0: float, y0: float, length_mm: float) -> None:
    """A bar ``length_mm`` long with ticks every 5 mm, labelled every 10 mm, top edge at y0."""
    ax.plot([x0, x0 + length_mm], [y0, y0], color="black", lw=0.8, solid_capstyle="butt")
    for k in range(int(round(length_mm / 5)) + 1):
        x = x0 + 5.0 * k
        major = k % 2 == 0
        ax.plot([x, x], [y0, y0 + (3.0 if major else 1.8)], color="black", lw=0.5, solid_capstyle="butt")
        if major:
            ax.text(x, y0 + 3.6, f"{5 * k}", ha="center", va="top", fontsize=6)
    ax.text(x0 + length_mm + 3.0, y0 + 3.6, "mm", ha="left", va="top", fontsize=6)
    ax.text(
        x0 + length_mm + 12.0,
        y0 + 1.5,
        f"Print at 100 % (actual size, no fit-to-page): this bar is {length_mm:g} mm "
        f"and every black square {STICKER_MM:g} mm.",
        ha="left",
        va="center",
        fontsize=6,
    )


def _page_figure(ids: Sequence[int], layout: SheetLayout, config: SheetConfig, page: int, pages: int) -> Figure:
    w, h = layout.page_mm
    fig = Figure(figsize=(w / 25.4, h / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    for sid, (x0, y0) in zip(ids, layout.origins):
        ax.imshow(
            render_sticker(sid, _RENDER_PX),
            cmap="gray",
            vmin=0,
            vmax=255,
            interpolation="none",
            extent=(x0, x0 + STICKER_MM, y0 + STICKER_MM, y0),
            origin="upper",
        )
        for xs, ys in _cut_marks(x0, y0):
            ax.plot(xs, ys, color="black", lw=0.3, solid_capstyle="butt")
        ax.text(x0 + STICKER_MM / 2, y0 + STICKER_MM + _CUT_OFFSET_MM, f"ID {sid}", ha="center", va="top", fontsize=7)
    m = config.margin_mm
    first, last = ids[0], ids[-1]
    listed = ", ".join(map(str, ids)) if len(ids) <= 3 else f"{first}, ..., {last}"
    ax.text(
        m,
        m,
        f"tagloc floor stickers {listed}"
        + f"   page {page}/{pages}   (ID label under each sticker's canonical bottom edge)",
        ha="left",
        va="top",
        fontsize=7,
    )
    _scale_bar(ax, m, h - m - _FOOTER_MM + 6.0, config.scale_bar_mm)
    # imshow resets limits and aspect; the axes must stay exactly the page in mm.
    ax.set_xlim(0.0, w)
    ax.set_ylim(h, 0.0)
    ax.set_aspect("auto")
    ax.set_axis_off()
    return fig


def page_paths(path: Path, pages: int) -> list[Path]:
    """Output files for PNG/SVG: ``path`` itself for one page, else ``stem-1.ext``, ``stem-2.ext``, ..."""
    if pages == 1:
        return [path]
    return [path.with_name(f"{path.stem}-{k}{path.suffix}") for k in range(1, pages + 1)]


def write_sheets(ids: Sequence[int], path: str | Path, config: SheetConfig = SheetConfig()) -> list[Path]:
    """Write true-scale sticker sheets for ``ids`` to ``path`` (.pdf, .png or .svg) and return the files.

    A PDF holds every page; PNG and SVG write one file per page (see :func:`page_paths`).
    """
    path = Path(path)
    fmt = path.suffix.lower()
    if fmt not in FORMATS:
        raise InputError(f"{path}: unknown sheet format {path.suffix!r} (use {', '.join(FORMATS)})")
    ids = [check_id(i) for i in ids]
    if not ids:
        raise InputError("no sticker IDs given")
    if fmt == ".png" and not 72 <= config.dpi <= 2400:
        raise InputError(f"PNG resolution {config.dpi} dpi is outside 72-2400")
    layout = sheet_layout(config)
    chunks = [ids[k : k + layout.per_page] for k in range(0, len(ids), layout.per_page)]
    if not path.parent.exists():
        raise InputError(f"{path}: directory {path.parent} does not exist")
    meta = {"Creator": "tagloc", "Title": "tagloc floor stickers"}
    # Compositing would merge the stickers into one image resampled at the (low) vector dpi.
    with mpl.rc_context({"image.composite_image": False, "svg.fonttype": "path", "pdf.fonttype": 42}):
        if fmt == ".pdf":
            from matplotlib.backends.backend_pdf import PdfPages

            with PdfPages(path, metadata={**meta, "CreationDate": None}) as pdf:
                for k, chunk in enumerate(chunks, 1):
                    pdf.savefig(_page_figure(chunk, layout, config, k, len(chunks)))
            return [path]
        out = page_paths(path, len(chunks))
        for k, (chunk, p) in enumerate(zip(chunks, out), 1):
            fig = _page_figure(chunk, layout, config, k, len(chunks))
            if fmt == ".png":
                fig.savefig(p, dpi=config.dpi, metadata={"Software": "tagloc"})
            else:
                fig.savefig(p, metadata={"Creator": "tagloc", "Date": None})
        return out
