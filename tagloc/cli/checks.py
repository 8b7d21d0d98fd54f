"""Argument checks shared by the subcommands: refuse out-of-range numbers and unwritable outputs up
front, with one line naming the option or path, before any work is done.

(No ``NAME``: this module is not a subcommand.)
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from tagloc.core.errors import InputError


def number(value: float | int, option: str, lo: float, hi: float, lo_open: bool = False) -> None:
    """Refuse ``value`` unless finite and in [lo, hi] (``lo_open``: (lo, hi])."""
    ok = isinstance(value, (int, float)) and math.isfinite(value) and value <= hi
    ok = ok and (value > lo if lo_open else value >= lo)
    if not ok:
        bracket = "(" if lo_open else "["
        raise InputError(f"{option} must be in {bracket}{lo:g}, {hi:g}], not {value}")


def output_file(path: Path | None, option: str) -> None:
    """Refuse a file path tagloc cannot create or overwrite (a directory or a file in the way, no permission)."""
    if path is None:
        return
    path = Path(path)
    if path.is_dir():
        raise InputError(f"{path}: {option} names a directory, want a file")
    _creatable(path.parent, path, option)
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError(f"{path}: {option}: no permission to write")


def output_dir(path: Path | None, option: str) -> None:
    """Refuse a directory path tagloc cannot create or write into."""
    if path is None:
        return
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: {option}: a file is in the way (want a directory)")
    _creatable(path, path, option)


def _creatable(directory: Path, target: Path, option: str) -> None:
    """``directory`` exists and is writable, or its nearest existing ancestor is a writable directory."""
    d = Path(os.path.abspath(directory))
    while not d.exists():
        d = d.parent
    if not d.is_dir():
        raise InputError(f"{target}: {option}: {d} is a file, not a directory")
    if not os.access(d, os.W_OK | os.X_OK):
        raise InputError(f"{target}: {option}: no permission to write in {d}")


def outputs_apart(
    outputs: list[tuple[str, Path | None]], inputs: list[Path | None], input_dirs: list[Path] = ()
) -> None:
    """Refuse two options that write the same file, and an output that is one of the run's ``inputs``
    or lies in one of ``input_dirs`` (a session's frames): a run must not overwrite what it reads."""
    seen: dict[Path, str] = {}
    read = {Path(os.path.realpath(p)) for p in inputs if p is not None}
    dirs = [Path(os.path.realpath(d)) for d in input_dirs]
    for option, path in outputs:
        if path is None:
            continue
        real = Path(os.path.realpath(path))
        if real in seen:
            raise InputError(f"{path}: {seen[real]} and {option} name the same file")
        if real in read or any(d in real.parents or d == real for d in dirs):
            raise InputError(f"{path}: {option} names one of the inputs it would overwrite")
        seen[real] = option
