"""``tagloc bench --profile``: the cProfile summary of a replay."""

from __future__ import annotations

from pathlib import Path

from tagloc.cli import main
from tagloc.eval.profile import profile_replay

WALK = Path(__file__).resolve().parent.parent / "logs" / "walk2s"


def test_profile_counts_every_frame_and_stage():
    summary = profile_replay(WALK, top=10)
    n = len(list((WALK / "frames").iterdir()))
    assert summary.frames == n
    stages = {label: (calls, s) for label, calls, s in summary.stages}
    assert stages["detect"][0] == n and stages["odometry"][0] == n
    assert stages["read JPEG (replay only)"][0] >= n  # the generator is entered once more at its end
    # Stages nest inside the profiled total; refinement is part of detection.
    assert 0 < stages["  refine (edge profiles)"][1] <= stages["detect"][1] < summary.total_s
    assert len(summary.top) == 10
    text = summary.format()
    assert "detect" in text and "ms/frame" in text


def test_bench_profile_cli(capsys):
    assert main(["bench", "--profile", str(WALK)]) == 0
    assert "cProfile of a replay" in capsys.readouterr().out
