"""``tagloc eval --walks``: sessions one already has, scored as ``tagloc eval`` scores its presets.

Walks rendered by another simulator, or recorded on a site with a ground truth (a motion-capture
or total-station trajectory written as the session's ``groundtruth.tum``: the vest point on the
floor, see the README's body frame), go through the same localiser modes and the same figures as
the presets: RMSE, heading, the share of all frames within 10 cm, NEES against its
effective-sample bounds, wrong-ID fixes, and a plot per walk. Nothing is rendered.

Wrong IDs: a session from tagloc's simulator carries its per-frame truth of which sticker is where
in the image (``groundtruth_frames.jsonl``), and is checked against it; any other session is checked
by pose (:func:`tagloc.eval.evaluate.wrong_id_fixes_by_pose`: a fix placed further from the ground
truth than half the map's sticker spacing named the wrong sticker). The table's conditions column
gives each session's ``session.json`` notes, with the field conditions a simulated walk was
rendered with (:func:`session_conditions`).
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from tagloc.core.errors import InputError
from tagloc.io.session import FRAMES_CSV, GROUNDTRUTH_FILE, SessionReader

#: How deep below a given directory sessions are looked for: ``tagloc eval -o out/eval --preset all``
#: leaves them at out/eval/<preset>/sessions/<walk>.
SEARCH_DEPTH = 3


def find_sessions(paths: list[Path]) -> list[Path]:
    """The session directories ``paths`` name: each path is a session (it holds ``frames.csv``), or a
    directory with sessions at most :data:`SEARCH_DEPTH` levels below it (sorted). Refuses, in one
    line naming the path, one that is missing or holds no session, and a session named twice."""
    found: list[Path] = []
    for path in paths:
        path = Path(path)
        if not path.is_dir():
            raise InputError(f"{path}: " + ("not a directory" if path.exists() else "no such directory"))
        if (path / FRAMES_CSV).is_file():
            found.append(path)
            continue
        below = sorted(
            p.parent for depth in range(1, SEARCH_DEPTH + 1) for p in path.glob("/".join(["*"] * depth + [FRAMES_CSV]))
        )
        if not below:
            raise InputError(f"{path}: neither a session (no {FRAMES_CSV}) nor a directory holding sessions")
        found += below
    seen: set[str] = set()
    for p in found:
        real = os.path.realpath(p)
        if real in seen:
            raise InputError(f"{p}: the same session is named twice")
        seen.add(real)
    return found


def _number(d: dict, key: str) -> float:
    """``d[key]`` as a finite number, else 0 (absent, or not a number: another simulator's file)."""
    v = d.get(key) if isinstance(d, dict) else None
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v) else 0.0


def session_conditions(notes: str, extra: dict) -> str:
    """A walk's conditions for the table: its ``session.json`` notes, and for a session from tagloc's
    simulator the conditions its notes leave out and the presets' rows name (``extra`` is
    ``session.json`` beyond its standard fields; its ``simulation.config`` is what the walk was
    rendered with): otherwise a field walk's row reads as a clear-weather one. Today's simulator
    names them in the notes already (:meth:`tagloc.sim.simulate.SimConfig.describe`); sessions
    rendered before it did get them here, each once."""
    sim = extra.get("simulation") if isinstance(extra, dict) else None
    cfg = sim.get("config") if isinstance(sim, dict) else None
    if not isinstance(cfg, dict):
        return notes
    timing, survey = cfg.get("timing") or {}, cfg.get("survey") or {}
    named = [
        ("rolling shutter", cfg.get("rolling_shutter") is True, "rolling shutter"),
        ("jitter", _number(timing, "jitter_s"), f"jitter +-{1e3 * _number(timing, 'jitter_s'):g} ms"),
        (
            "drops",
            _number(timing, "drop_fraction") or _number(timing, "bursts_per_min"),
            f"drops {100 * _number(timing, 'drop_fraction'):g}% + {_number(timing, 'bursts_per_min'):g} bursts/min",
        ),
        (
            "survey",
            _number(survey, "sigma_m") or _number(survey, "sigma_deg"),
            f"survey {100 * _number(survey, 'sigma_m'):g} cm {_number(survey, 'sigma_deg'):g} deg"
            + (" stated" if survey.get("stated") is True else ""),
        ),
        (
            "missing",
            _number(cfg, "missing_fraction") or _number(cfg, "unmapped"),
            f"{100 * _number(cfg, 'missing_fraction'):g}% missing, {_number(cfg, 'unmapped'):g} unmapped",
        ),
        ("sensor", cfg.get("sensor_preset") not in (None, "standard"), f"sensor {cfg.get('sensor_preset')}"),
        ("resolution", _number(cfg, "scale") not in (0.0, 1.0), f"resolution x{_number(cfg, 'scale'):g}"),
    ]
    parts = [notes] + [text for word, on, text in named if on and word not in notes]
    return ", ".join(str(p) for p in parts)


def walk_names(sessions: list[Path]) -> list[str]:
    """A row name per session: its directory's name, or, where two share one, its path below their
    common parent ("/" joined)."""
    names = [p.name for p in sessions]
    if len(set(names)) == len(names):
        return names
    common = Path(os.path.commonpath([os.path.abspath(p) for p in sessions]))
    return [Path(os.path.abspath(p)).relative_to(common).as_posix() for p in sessions]


def check_walks(sessions: list[Path], out: Path) -> list[SessionReader]:
    """Open every session before any work: each must read and hold a ``groundtruth.tum`` that covers
    some of its frames' time (and a readable ``groundtruth_frames.jsonl`` if it has one), and ``out``
    must not lie inside one (its report and plots would be
    written among the session's files)."""
    readers = []
    real_out = Path(os.path.realpath(out))
    for path in sessions:
        real = Path(os.path.realpath(path))
        if real_out == real or real in real_out.parents:
            raise InputError(f"{out}: -o lies inside the session {path}; choose a directory outside it")
        reader = SessionReader(path)
        gt = reader.groundtruth()
        if gt is None:
            raise InputError(f"{path}: no {GROUNDTRUTH_FILE} to score against")
        frames = np.asarray(reader.timestamps, float)
        if len(gt[0]) == 0 or gt[0][-1] < frames[0] or gt[0][0] > frames[-1]:  # (frames.csv lists >= 1)
            span = f"{gt[0][0]:.3f}-{gt[0][-1]:.3f} s" if len(gt[0]) else "no poses"
            raise InputError(
                f"{path}: {GROUNDTRUTH_FILE} ({span}) does not cover any frame "
                f"({frames[0]:.3f}-{frames[-1]:.3f} s in frames.csv): it cannot score the walk"
            )
        # Scored after the walk's localisation: a malformed line must be refused before it.
        from tagloc.eval.evaluate import read_frame_truth

        read_frame_truth(path)
        readers.append(reader)
    return readers


def score_walks(paths: list[Path], out: Path, modes: tuple[str, ...], progress: bool = True) -> str:
    """Score the sessions ``paths`` name (see :func:`find_sessions`) with each of ``modes``; write
    ``report.md``, ``results.json`` and a PNG per walk into ``out``; return the text to print (the
    table, the notes and the summary, as a preset's)."""
    from tqdm import tqdm

    from tagloc.eval.evaluate import format_notes, format_summary, format_table, plot_run, score_session, write_results

    sessions = find_sessions(paths)
    readers = check_walks(sessions, out)
    out.mkdir(parents=True, exist_ok=True)
    rows, plots = [], []
    for path, name, reader in tqdm(
        list(zip(sessions, walk_names(sessions), readers)), desc="eval", unit="session", disable=not progress
    ):
        conditions = session_conditions(reader.info.notes or reader.info.source, reader.info.extra)
        for mode in modes:
            row, session, log, gt = score_session(path, mode, progress)
            rows.append({"session": name, "path": str(path), "conditions": conditions, **row})
            if mode == "full":
                png = out / (name.replace("/", "-") + ".png")
                plots.append(plot_run(session, log, gt, png, title=f"{name} ({conditions})"))
    res = write_results(rows, plots, out)
    checks = sorted({r["wrong_id_check"] for r in rows})
    how = {
        "frames": "the simulator's per-frame truth",
        "pose": "pose (a fix further from the truth than half the map's sticker spacing)",
    }
    parts = [
        format_table(res["rows"], res["summary"]),
        "",
        "Wrong IDs checked by " + " and by ".join(how[c] for c in checks) + ".",
        "",
        format_notes(res["summary"]),
        "",
        f"report: {res['report']}",
        "",
        "## Summary",
        "",
        format_summary(f"{len(sessions)} walk{'s' if len(sessions) != 1 else ''}", res["summary"]),
    ]
    return "\n".join(parts)
