"""tagloc refs: build the reference bank used to identify undecodable stickers."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "refs"
HELP = "build the ORB/appearance reference bank of a sticker map"
DESCRIPTION = """Render every sticker of a map, compute its ORB references and store them next to the map
(<map>.refs.npz). The cache is keyed by the map file's content and the bank parameters, so
tagloc rebuilds it by itself when the map changes; this command only does it ahead of time.

example:
  tagloc refs build maps/demo.csv"""


def add_arguments(p: argparse.ArgumentParser) -> None:
    sub = p.add_subparsers(dest="action", metavar="ACTION", required=True)
    b = sub.add_parser(
        "build",
        help="build (or refresh) the bank of a map",
        description="build (or refresh) the bank of a map\n\nexample:\n  tagloc refs build maps/demo.csv",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    b.add_argument("map", type=Path, help="sticker map CSV (id,x_m,y_m,yaw_deg)")
    b.add_argument("-o", "--out", type=Path, default=None, help="bank file (default: <map>.refs.npz next to the map)")
    b.add_argument("--force", action="store_true", help="rebuild even if the cache is up to date")
    b.add_argument("--quiet", action="store_true", help="no progress bar")


def run(args: argparse.Namespace) -> int:
    from tagloc.cli import checks
    from tagloc.vision.refs import default_cache_path, load_or_build_refs

    checks.output_file(args.out or default_cache_path(args.map), "-o")

    bank = load_or_build_refs(args.map, progress=not args.quiet, cache_path=args.out, rebuild=args.force)
    out = args.out or default_cache_path(args.map)
    print(f"{out}: {len(bank)} stickers, {len(bank.des)} ORB features, key {bank.key[:12]}")
    return 0
