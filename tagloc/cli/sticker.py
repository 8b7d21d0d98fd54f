"""tagloc sticker: print-ready sticker sheets."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "sticker"
HELP = "write true-scale printable sticker sheets (PDF, PNG or SVG)"
DESCRIPTION = """Write sheets (A4, A3 or letter: --paper) of 100 mm floor stickers with cut marks, the ID under each sticker and a
50 mm scale bar. The format follows the extension: a PDF holds all pages; PNG and SVG write one
file per page, suffixed -1, -2, ... when there is more than one. Print at 100 % (actual size).

example:
  tagloc sticker 12 13 20-29 -o sheet.pdf"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("ids", nargs="+", metavar="ID", help="sticker IDs 0-99999 or ranges like 20-29")
    p.add_argument("-o", "--out", type=Path, required=True, help="output file: .pdf, .png or .svg")
    p.add_argument("--paper", default="a4", choices=("a4", "a3", "letter"), help="paper size (default a4)")
    p.add_argument("--dpi", type=int, default=600, help="PNG resolution (default 600)")


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.io.printing import SheetConfig, parse_ids, write_sheets

    checks.number(args.dpi, "--dpi", 72, 2400)
    checks.output_file(args.out, "-o")

    files = write_sheets(parse_ids(args.ids), args.out, SheetConfig(paper=args.paper, dpi=args.dpi))
    for f in files:
        print(f)
    return 0
