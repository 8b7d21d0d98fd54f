"""Argument checks shared by the subcommands: refuse out-of-range numbers and unwritable outputs up
front, with one line naming the option or path, before any work is done.

(No ``NAME``: this module is not a subcommand.)
"""

from __future__ import annotations

import math
import os
from pathlib import Path

from tagloc.core.errors import InputError


def number(
    value: float | int, option: str, lo: float, hi: float = math.inf, lo_open: bool = False, hi_open: bool = False
) -> None:
    """Refuse ``value`` unless finite and in [lo, hi] (``lo_open``, ``hi_open``: that end excluded;
    the default ``hi``: no upper bound)."""
    # An int is never NaN or infinite, and math.isfinite cannot take one beyond a float's range.
    ok = isinstance(value, int) or (isinstance(value, float) and math.isfinite(value))
    ok = ok and (value > lo if lo_open else value >= lo) and (value < hi if hi_open else value <= hi)
    if not ok:
        if math.isinf(hi):
            want = f"a number {'>' if lo_open else '>='} {lo:g}"
        else:
            want = f"in {'(' if lo_open else '['}{lo:g}, {hi:g}{')' if hi_open else ']'}"
        raise InputError(f"{option} must be {want}, not {value}")


def numbers(text: str, option: str, lo: float, hi: float, lo_open: bool = False) -> tuple[float, ...]:
    """The numbers of a comma-separated list such as ``0,2,4``, at least one, each as :func:`number` takes it."""
    items = [t.strip() for t in text.split(",") if t.strip()]
    if not items:
        raise InputError(f"{option}: no numbers in {text!r} (want a comma-separated list such as 0,2,4)")
    values = []
    for item in items:
        try:
            values.append(float(item))
        except ValueError:
            raise InputError(f"{option}: {item!r} is not a number") from None
        number(values[-1], option, lo, hi, lo_open)
    return tuple(values)


def names(text: str, option: str, allowed: tuple[str, ...]) -> tuple[str, ...]:
    """The names of a comma-separated list such as ``full,orb-all``, at least one, each one of ``allowed``
    and none twice (a name given twice would run twice and be pooled as two independent runs)."""
    given = tuple(t.strip() for t in text.split(",") if t.strip())
    unknown = [n for n in given if n not in allowed]
    if unknown or not given:
        what = f"unknown {', '.join(unknown)}" if unknown else "none given"
        raise InputError(f"{option}: {what} (want some of {', '.join(allowed)})")
    twice = [n for n in dict.fromkeys(given) if given.count(n) > 1]
    if twice:
        raise InputError(f"{option}: {', '.join(twice)} given twice")
    return given


#: Ranges (lo, hi] of the options the simulator's commands share (simulate, advise, demo): one
#: table, so that what one of them refuses the others refuse too.
SIM_RANGES = {
    "--seconds": (0, 3600),
    "--lux": (0, 200_000),  # twice full sunlight
    "--speed": (0, 5),  # m/s: a run beyond
    "--pitch": (0, 90),  # below horizontal: the camera must see the floor
    "--height": (0, 5),  # m
    "--scale": (0, 4),
}


def sim_option(value: float, option: str, lo_open: bool = True) -> None:
    """Refuse ``value`` outside ``option``'s range in :data:`SIM_RANGES` (``lo_open=False``: the low end taken)."""
    number(value, option, *SIM_RANGES[option], lo_open=lo_open)


def seed(value: int, option: str = "--seed") -> None:
    """Refuse a seed numpy's generators cannot take (a negative one)."""
    number(value, option, 0)


def output_file(path: Path | None, option: str, suffixes: tuple[str, ...] = ()) -> None:
    """Refuse a file path tagloc cannot create or overwrite (a directory or a file in the way, no
    permission), or, given ``suffixes`` (such as ``(".png",)``), whose suffix is none of them."""
    if path is None:
        return
    path = Path(path)
    # The writers (matplotlib, OpenCV) pick the format from the suffix, in any case.
    if suffixes and path.suffix.lower() not in suffixes:
        got = f"not {path.suffix!r}" if path.suffix else "not a name without one"
        raise InputError(f"{path}: {option} wants a {' or '.join(suffixes)} file, {got}")
    if path.is_dir():
        raise InputError(f"{path}: {option} names a directory, want a file")
    _creatable(path.parent, path, option)
    if path.exists() and not os.access(path, os.W_OK):
        raise InputError(f"{path}: {option}: no permission to write")


def publish_files(targets: list[str] | None) -> list[tuple[str, Path]]:
    """The files ``--publish`` would write (a JSON-lines or TUM path; stdout and the network write
    none), each checked as :func:`output_file` checks one, as (option, path) for :func:`outputs_apart`:
    a sink opens its file for writing, so one naming an input would overwrite it."""
    from tagloc.io.sinks import sink_file

    files = [("--publish", p) for p in (sink_file(t) for t in targets or []) if p is not None]
    for option, path in files:
        output_file(path, option)
    return files


def output_dir(path: Path | None, option: str) -> None:
    """Refuse a directory path tagloc cannot create or write into."""
    if path is None:
        return
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise InputError(f"{path}: {option}: a file is in the way (want a directory)")
    _creatable(path, path, option)


def new_dir(path: Path | None, option: str, why: str = "") -> None:
    """Refuse a directory path that exists already (``why``: what writes a new one, for the message)
    or that tagloc cannot create: a rosbag2 bag is a new directory, and its writer failed only once
    the run was under way (after ``tagloc live`` had built its reference bank)."""
    if path is None:
        return
    path = Path(path)
    if path.exists() or path.is_symlink():
        raise InputError(f"{path}: {option}: already exists{f'; {why}' if why else ''}")
    _creatable(path.parent, path, option)


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
