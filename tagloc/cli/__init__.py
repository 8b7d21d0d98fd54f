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
from collections.abc import Callable

from tagloc import __version__
from tagloc.core.errors import TaglocError


def _quiet_native_logs() -> None:
    """Keep OpenCV's and its FFmpeg's own log lines off stderr ("[ WARN:0@0.4] global
    cap_v4l.cpp:915 ... can't open camera by index", "[mov,mp4,... @ 0x...] moov atom not found"):
    what they report reaches the user as tagloc's one-line message (a camera or video that cannot be
    opened, a frame that cannot be read). Set before cv2 is imported (OpenCV reads
    OPENCV_LOG_LEVEL when it loads, OPENCV_FFMPEG_LOGLEVEL when FFmpeg is first used; -8 is
    FFmpeg's AV_LOG_QUIET). A user's own setting wins, and TAGLOC_DEBUG=1 leaves them all on."""
    if os.environ.get("TAGLOC_DEBUG"):
        return
    os.environ.setdefault("OPENCV_LOG_LEVEL", "ERROR")
    os.environ.setdefault("OPENCV_FFMPEG_LOGLEVEL", "-8")


_quiet_native_logs()


def _command_modules(only: str | None = None) -> list:
    """The command modules, by NAME; with ``only``, just the module of that command if there is one
    (a command's module is its name with '-' as '_')."""
    names = [m.name for m in pkgutil.iter_modules(__path__)]
    if only is not None:
        name = only.replace("-", "_")
        if name in names:
            mod = importlib.import_module(f"{__name__}.{name}")
            if getattr(mod, "NAME", None) == only:
                return [mod]
    mods = [importlib.import_module(f"{__name__}.{n}") for n in names]
    return sorted((m for m in mods if hasattr(m, "NAME")), key=lambda m: m.NAME)


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The argument parser with every subcommand, or only ``command``'s when it names one (what a
    run of that command needs: building all of them imports and sets up every command module)."""
    parser = argparse.ArgumentParser(prog="tagloc", description="Localise a person from warehouse floor stickers.")
    parser.add_argument("--version", action="version", version=f"tagloc {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for mod in _command_modules(command):
        p = sub.add_parser(
            mod.NAME,
            help=mod.HELP,
            description=getattr(mod, "DESCRIPTION", mod.HELP),
            formatter_class=argparse.RawDescriptionHelpFormatter,
        )
        mod.add_arguments(p)
        p.set_defaults(_run=mod.run, _parser=p)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``tagloc`` console script."""
    argv = sys.argv[1:] if argv is None else list(argv)
    # The command is the first argument when it does not start with '-' (the top level takes only
    # options of its own that end the run: --help, --version).
    parser = build_parser(argv[0] if argv and not argv[0].startswith("-") else None)
    args, extra = parser.parse_known_args(argv)
    if extra:
        # The command's own parser says it, with its usage: the top level's would name only "tagloc".
        command = getattr(args, "_parser", parser)
        command.error(f"unrecognized arguments: {' '.join(extra)}")
    if not getattr(args, "_run", None):
        parser.print_help()
        return 2
    return run_guarded(f"tagloc {args.command}", lambda: args._run(args))


def run_guarded(name: str, run: Callable[[], int | None]) -> int:
    """``run()``'s exit code, with every error it raises made one line on stderr prefixed ``name``
    (the console script's subcommands, and the benchmark scripts): a :class:`TaglocError` is the
    user's input, an ``OSError`` the system's, anything else a bug (``TAGLOC_DEBUG=1``: raised)."""
    try:
        return int(run() or 0)
    except TaglocError as exc:
        print(f"{name}: error: {exc}", file=sys.stderr)
        return exc.exit_code
    except KeyboardInterrupt:
        print(f"{name}: interrupted", file=sys.stderr)
        return 130
    except OSError as exc:
        # Trouble writing or reading that no check could foresee (a full disk, a vanished mount).
        where = f"{exc.filename}: " if exc.filename else ""
        print(f"{name}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # noqa: BLE001 - a bug: one line for the user, the traceback on request
        if os.environ.get("TAGLOC_DEBUG"):
            raise
        msg = str(exc).splitlines()[0][:300] if str(exc) else ""
        print(
            f"{name}: internal error: {type(exc).__name__}: {msg} "
            "(please report it; TAGLOC_DEBUG=1 shows the traceback)",
            file=sys.stderr,
        )
        return 70


if __name__ == "__main__":
    sys.exit(main())
