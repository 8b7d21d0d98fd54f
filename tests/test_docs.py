"""The README and the measurement history link to each other by heading anchors; a heading renamed or
a section moved must not leave a link pointing nowhere."""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent
README = REPO / "README.md"
HISTORY = REPO / "benchmarks" / "HISTORY.md"


def github_anchor(heading: str) -> str:
    """The anchor GitHub gives a Markdown heading: lower case, punctuation other than hyphens and
    underscores dropped, spaces to hyphens."""
    return re.sub(r"[^\w\- ]", "", heading.strip().lower()).replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Every heading's anchor in ``text`` (fenced code blocks skipped: their ``#`` lines are comments)."""
    out, fenced = set(), False
    for line in text.splitlines():
        if line.startswith("```"):
            fenced = not fenced
        elif not fenced and (m := re.match(r"^#+\s+(.*)$", line)):
            out.add(github_anchor(m.group(1)))
    return out


def links(text: str, target: str) -> list[str]:
    """The anchors of the links to ``target`` (a file name as written in the link, '' for the page itself)."""
    return re.findall(r"\]\(" + re.escape(target) + r"#([^)\s]+)\)", text)


def test_github_anchor_matches_githubs_rule():
    assert github_anchor("Field physics: `tagloc eval --preset all --modes full -o out/eval`") == (
        "field-physics-tagloc-eval---preset-all---modes-full--o-outeval"
    )
    assert github_anchor("The wearer's legs: `python benchmarks/legs.py`") == "the-wearers-legs-python-benchmarkslegspy"


def test_every_anchor_link_between_readme_and_history_resolves():
    readme, history = README.read_text(), HISTORY.read_text()
    in_readme, in_history = anchors(readme), anchors(history)
    checks = [
        ("README.md -> README.md", links(readme, ""), in_readme),
        ("README.md -> HISTORY.md", links(readme, "benchmarks/HISTORY.md"), in_history),
        ("HISTORY.md -> HISTORY.md", links(history, ""), in_history),
        ("HISTORY.md -> README.md", links(history, "../README.md"), in_readme),
    ]
    assert sum(len(found) for _, found, _ in checks) > 20  # the documents do link to each other
    broken = [(where, a) for where, found, known in checks for a in found if a not in known]
    assert not broken, broken


def test_the_set_up_says_how_the_bare_commands_below_it_run():
    """The first screen runs `.venv/bin/tagloc`, every later command is written `tagloc ...` (and
    `rerun ...`, `python benchmarks/...`), which a fresh shell does not find: the set-up must say to
    activate the environment (a review ran the README top to bottom on a fresh clone)."""
    readme = README.read_text()
    set_up, rest = readme.split("\n## Contents", 1)
    assert re.search(r"^tagloc \w", rest, re.M)  # bare commands in code blocks below the set-up
    assert ". .venv/bin/activate" in set_up


def test_what_the_readme_commands_write_at_the_top_is_ignored_by_git():
    """.gitignore lists "what the README's commands write into the working tree"; the Commands table's
    bench, sticker, calibrate, rig fit, map refine, monitor and live lines write these at the top, and
    they showed as untracked after a run of the README (a review ran it on a fresh clone)."""
    if shutil.which("git") is None or not (REPO / ".git").exists():
        pytest.skip("not a git work tree")
    written = [
        "est.tum", "frames.jsonl", "sim1.rrd", "logs/sim1/frames.csv", "bench.json", "sheet.pdf", "sheet-1.png",
        "sheet-2.svg", "board.pdf", "camera.yaml", "camera_coverage.png", "rig.json", "refined.csv", "refined.md",
        "fleet.rrd", "fleet.png", "rec/frames.csv", "sessions/rec/frames.csv", "live.rrd", "shot.png", "follow.rbl",
    ]  # fmt: skip
    run = subprocess.run(["git", "check-ignore", "--no-index", *written], cwd=REPO, capture_output=True, text=True)
    assert sorted(run.stdout.split()) == sorted(written)


def test_the_readme_gives_every_exit_code_an_error_can_have():
    """A missing backend (libdmtx, a Rerun viewer at --rerun-connect) exits 3 and an internal error 70,
    which the README never said (it named 1 and 2 only), though a supervisor acts on the code."""
    from tagloc.core import errors

    codes = {c.exit_code for c in vars(errors).values() if isinstance(c, type) and issubclass(c, errors.TaglocError)}
    intro = README.read_text().split("\n## Commands\n", 1)[1].split("\n|", 1)[0]
    for code in sorted(codes | {70, 130}):
        assert re.search(rf"\b{code} (for|when)\b", intro), code
