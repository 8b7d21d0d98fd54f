"""The ``tagloc`` command: one subcommand per module of this package.

Each command module defines ``NAME``, ``HELP``, ``add_arguments(parser)`` and ``run(args) -> int``;
``run`` only turns arguments into one library call. A :class:`TaglocError` becomes one line on
stderr and its exit code.
"""

from __future__ import annotations

import argparse
import importlib
import os
import pkgutil
import sys

from tagloc import __version__
from tagloc.core.errors import TaglocError


def _command_modules() -> list:
    mods = [importlib.import_module(f"{__name__}.{m.name}") for m in pkgutil.iter_modules(__path__)]
    return sorted((m for m in mods if hasattr(m, "NAME")), key=lambda m: m.NAME)


def build_parser() -> argparse.ArgumentParser:
    """The argument parser with every subcommand."""
    parser = argparse.ArgumentParser(prog="tagloc", description="Localise a person from warehouse floor stickers.")
    parser.add_argument("--version", action="version", version=f"tagloc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules():
        p = sub.add_parser(
            mod.NAME,
            help=mod.HELP,
            description=getattr(mod, "DESCRIPTION", mod.HELP),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tagloc`` console script."""
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    try:
        return int(args._run(args) or 0)
    except TaglocError as exc:
        print(f"tagloc {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"tagloc {args.command}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        # Trouble writing or reading that no check could foresee (a full disk, a vanished mount).
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"tagloc {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - a bug: one line for the user, the traceback on request
        if os.environ.get("TAGLOC_DEBUG"):
            raise
        msg = str(exc).splitlines()[0][:300] if str(exc) else ""
        print(
            f"tagloc {args.command}: internal error: {type(exc).__name__}: {msg} "
            "(please report it; TAGLOC_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return 70


if __name__ == "__main__":
    sys.exit(main())
