"""Sessions thinned to every k-th frame of each camera: the same walk as a slower camera (or a core
too slow for its camera) delivers it, for replays at a lower frame rate without rendering again.

Run (from the repository root)::

    python benchmarks/thin_sessions.py out/eval/standard/sessions/* -o out/eval-15fps/standard/sessions
    PYTHONPATH=$PWD python benchmarks/eval_variants.py out/eval-15fps --jobs 2

Each thinned session is a directory named as its source under ``-o``: its own ``frames.csv`` (every
``--every``-th frame of each camera, the first kept) and ``session.json`` (``fps`` divided by
``--every``), and links to everything else (the frames, map, rig, calibration and ground truth), so
it costs no copy of the images. The frames keep their indices and timestamps, so the ground truth
and the simulator's per-frame truth (by frame index) still score them. The exposure, blur and
rolling-shutter read-out stay those of the faster camera: this is the same walk seen less often,
not another camera. Sessions are checked (:class:`tagloc.io.session.SessionReader`) before anything
is written, and an existing destination is refused.
"""

from __future__ import annotations

import argparse
import json
import os
from pathlib import Path

from tagloc.core.errors import InputError
from tagloc.io.session import FRAMES_CSV, SESSION_JSON, SessionReader, frames_csv_header, frames_csv_line


def thin_session(src: Path, dest: Path, every: int) -> int:
    """Write ``dest`` as ``src`` with every ``every``-th frame of each camera (the first kept);
    the number of frames kept."""
    if every < 1:
        raise InputError(f"--every must be at least 1, not {every}")
    reader = SessionReader(src)  # refuses a malformed session before anything is written
    if dest.exists():
        raise InputError(f"{dest}: already exists (thinned sessions are not overwritten)")
    seen: dict[int, int] = {}
    kept = []
    for index, stamp, camera in zip(reader.index, reader.timestamps, reader.cameras):
        n = seen.get(int(camera), 0)
        seen[int(camera)] = n + 1
        if n % every == 0:
            kept.append((int(index), float(stamp), int(camera)))
    dest.mkdir(parents=True)
    for item in src.iterdir():
        if item.name not in (FRAMES_CSV, SESSION_JSON):
            os.symlink(item.resolve(), dest / item.name)
    # As SessionWriter writes it: the kept lines read back to the same microseconds.
    multi = len(reader.rig) > 1
    lines = [frames_csv_line(index, stamp, camera, multi) for index, stamp, camera in kept]
    (dest / FRAMES_CSV).write_text(frames_csv_header(multi) + "".join(lines), encoding="utf-8")
    info = json.loads((src / SESSION_JSON).read_text())
    if isinstance(info.get("fps"), (int, float)):
        info["fps"] = info["fps"] / every
    info["notes"] = f"{info.get('notes', '')} [thinned: 1 frame in {every} of {src.name}]".strip()
    (dest / SESSION_JSON).write_text(json.dumps(info, indent=1) + "\n")
    return len(kept)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("sessions", type=Path, nargs="+", help="session directories to thin")
    ap.add_argument("-o", "--out", type=Path, required=True, help="directory to write the thinned sessions in")
    ap.add_argument("--every", type=int, default=2, help="keep every k-th frame of each camera (default 2)")
    args = ap.parse_args(argv)
    names = [s.name for s in args.sessions]
    if len(set(names)) < len(names):
        raise InputError("two sessions share a directory name; thin them into separate -o directories")
    for src in args.sessions:
        n = thin_session(src, args.out / src.name, args.every)
        print(f"{args.out / src.name}: {n} frames (every {args.every})")
    return 0


if __name__ == "__main__":
    from tagloc.cli import run_guarded

    raise SystemExit(run_guarded("thin_sessions.py", main))
