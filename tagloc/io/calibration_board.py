"""A printable ChArUco calibration board at true scale (PDF, PNG or SVG), one landscape page.

As with the sticker sheets (:mod:`tagloc.io.printing`) the page is one matplotlib figure exactly
the paper's size with axes in millimetres, and the board raster (an exact whole number of pixels
per marker cell) is embedded unresampled, so a 20 mm square prints 20 mm at 100 % scale. The page
names the board (squares, sizes, dictionary: what ``tagloc calibrate camera`` must be told if it
is not the default) and carries a 50 mm scale bar to check the print.
"""

from __future__ import annotations

from pathlib import Path

import matplotlib as mpl
from matplotlib.figure import Figure

from tagloc.core.charuco import DEFAULT_BOARD, BoardSpec, board_image
from tagloc.core.errors import InputError
from tagloc.io.printing import FORMATS, PAPER_MM

_MARGIN_MM = 10.0  # printers cannot print to the edge
_TEXT_MM = 14.0  # room above and below the board for the header and the scale bar


def _cells_px_per_mm(spec: BoardSpec) -> float:
    """Raster resolution giving every marker cell a whole number of pixels (at least 10 px/mm)."""
    cell_mm = spec.marker_m * 1000.0 / (spec.marker_bits + 2)
    px = 1
    while px / cell_mm < 10.0:
        px += 1
    return px / cell_mm


def _scale_bar(ax: object, x0: float, y0: float, length_mm: float = 50.0) -> None:
    ax.plot([x0, x0 + length_mm], [y0, y0], color="black", lw=0.8, solid_capstyle="butt")
    for k in range(int(length_mm // 5) + 1):
        tall = k % 2 == 0
        ax.plot([x0 + 5 * k] * 2, [y0, y0 + (3.0 if tall else 1.8)], color="black", lw=0.5, solid_capstyle="butt")
        if tall:
            ax.text(x0 + 5 * k, y0 + 3.6, f"{5 * k}", ha="center", va="top", fontsize=6)
    ax.text(x0 + length_mm + 3.0, y0 + 3.6, "mm", ha="left", va="top", fontsize=6)


def board_figure(spec: BoardSpec = DEFAULT_BOARD, paper: str = "a4") -> Figure:
    """The page (landscape) with the board centred; raises InputError when it does not fit."""
    if paper not in PAPER_MM:
        raise InputError(f"unknown paper {paper!r} (choose from {', '.join(PAPER_MM)})")
    h, w = PAPER_MM[paper]  # landscape
    bw, bh = (v * 1000.0 for v in spec.size_m)
    if bw > w - 2 * _MARGIN_MM or bh > h - 2 * (_MARGIN_MM + _TEXT_MM):
        raise InputError(f"a {bw:g} x {bh:g} mm board does not fit on landscape {paper} with margins and labels")
    fig = Figure(figsize=(w / 25.4, h / 25.4))
    ax = fig.add_axes((0.0, 0.0, 1.0, 1.0))
    x0, y0 = (w - bw) / 2, (h - bh) / 2
    ax.imshow(
        board_image(spec, _cells_px_per_mm(spec)),
        cmap="gray",
        vmin=0,
        vmax=255,
        interpolation="none",
        extent=(x0, x0 + bw, y0 + bh, y0),
        origin="upper",
    )
    ax.text(x0, y0 - 6.0, f"tagloc calibration board: {spec.describe()}", ha="left", va="bottom", fontsize=8)
    ax.text(
        x0,
        y0 - 2.0,
        "Glue flat to a rigid board. Measure one square: if it is not "
        f"{spec.square_m * 1000:g} mm, give the measured size to tagloc calibrate camera --square-mm.",
        ha="left",
        va="bottom",
        fontsize=6,
    )
    _scale_bar(ax, x0, y0 + bh + 5.0)
    ax.text(
        x0 + 65.0,
        y0 + bh + 6.5,
        "Print at 100 % (actual size, no fit-to-page): this bar is 50 mm.",
        ha="left",
        va="center",
        fontsize=6,
    )
    ax.set_xlim(0.0, w)
    ax.set_ylim(h, 0.0)
    ax.set_aspect("auto")
    ax.set_axis_off()
    return fig


def write_board(path: str | Path, spec: BoardSpec = DEFAULT_BOARD, paper: str = "a4", dpi: int = 600) -> Path:
    """Write the board page to ``path`` (.pdf, .png or .svg) and return it."""
    path = Path(path)
    fmt = path.suffix.lower()
    if fmt not in FORMATS:
        raise InputError(f"{path}: unknown format {path.suffix!r} (use {', '.join(FORMATS)})")
    if not path.parent.exists():
        raise InputError(f"{path}: directory {path.parent} does not exist")
    if fmt == ".png" and not 72 <= dpi <= 2400:
        raise InputError(f"PNG resolution {dpi} dpi is outside 72-2400")
    fig = board_figure(spec, paper)
    with mpl.rc_context({"image.composite_image": False, "svg.fonttype": "path", "pdf.fonttype": 42}):
        if fmt == ".pdf":
            fig.savefig(path, metadata={"Creator": "tagloc", "Title": "tagloc calibration board", "CreationDate": None})
        elif fmt == ".png":
            fig.savefig(path, dpi=dpi, metadata={"Software": "tagloc"})
        else:
            fig.savefig(path, metadata={"Creator": "tagloc", "Date": None})
    return path
