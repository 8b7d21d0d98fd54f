"""The command line: a run builds only its own command's parser, with the same arguments as the full one;
a bad option is refused up front, in one line naming it."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from tagloc.cli import _command_modules, build_parser, main

DEMO_MAP = str(Path(__file__).resolve().parent.parent / "maps" / "demo.csv")


def test_each_command_parses_alone_as_in_the_full_parser(capsys):
    names = [m.NAME for m in _command_modules()]
    assert {"replay", "bench", "bench-identify", "live", "simulate"} <= set(names)
    full = build_parser()
    for name in names:
        assert [m.NAME for m in _command_modules(name)] == [name]
        with pytest.raises(SystemExit) as exc:
            main([name, "--help"])
        assert exc.value.code == 0
        assert f"usage: tagloc {name}" in capsys.readouterr().out
    argv = ["replay", "some/session", "--quiet", "--mode", "decoded-only"]
    alone, whole = vars(build_parser("replay").parse_args(argv)), vars(full.parse_args(argv))
    assert alone.keys() == whole.keys()
    assert {k: v for k, v in alone.items() if not k.startswith("_")} == {
        k: v for k, v in whole.items() if not k.startswith("_")
    }


def test_unknown_command_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice" in err and "replay" in err and "bench-identify" in err


@pytest.mark.parametrize(
    "argv, prog",
    [
        (["replay", "logs/walk2s", "--bogus"], "tagloc replay"),
        (["eval", "--bogus", "3"], "tagloc eval"),
        (["map", "grid", "-o", "x.csv", "--bogus"], "tagloc map"),
    ],
)
def test_an_unknown_option_is_refused_by_its_commands_own_parser(argv, prog, capsys):
    """The message names the command and shows its usage, not the top level's."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.splitlines()[-1].startswith(f"{prog}: error: unrecognized arguments: --bogus"), err
    assert f"usage: {prog}" in err and "usage: tagloc [-h]" not in err


def _refused(argv: list[str], option: str, tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """``argv`` ({tmp}: ``tmp_path``, {map}: the demo map) exits 2 with one line naming ``option``,
    having written nothing (outputs go under {tmp})."""
    before = sorted(tmp_path.rglob("*"))
    rc = main([a.format(tmp=tmp_path, map=DEMO_MAP) for a in argv])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert err.count("\n") == 1 and "internal error" not in err, err
    assert re.search(rf"(?<![\w-]){re.escape(option)}(?![\w-])", err), err  # the option, not '-o' in '-of'
    assert sorted(tmp_path.rglob("*")) == before


@pytest.mark.parametrize(
    "argv",
    [
        ["simulate", "--map", "{map}", "-o", "{tmp}/s", "--quiet"],
        ["map", "grid", "-o", "{tmp}/g.csv"],
        ["advise", "--no-progress"],
        ["demo", "--map", "{map}", "-o", "{tmp}/d", "--quiet", "--no-rerun"],
        ["eval", "-o", "{tmp}/e", "--quiet"],
        ["bench", "--quick", "--no-progress"],
        ["bench-identify", "--no-progress"],
    ],
    ids=lambda argv: " ".join(a for a in argv[:2] if not a.startswith("-")),
)
def test_negative_seed_is_refused(argv, tmp_path, capsys):
    _refused([*argv, "--seed", "-1"], "--seed", tmp_path, capsys)


@pytest.mark.parametrize(
    "option, value",
    [
        ("--jitter", "nan"),
        ("--jitter", "inf"),
        ("--jitter", "-0.1"),
        ("--margin", "nan"),
        ("--margin", "-1"),
        ("--sequential-ids", "-5"),
        ("--sequential-ids", "100000"),
    ],
)
def test_map_grid_refuses_a_bad_number(option, value, tmp_path, capsys):
    _refused(["map", "grid", "-o", "{tmp}/g.csv", option, value], option, tmp_path, capsys)


SIMULATE = ["simulate", "--map", "{map}", "-o", "{tmp}/s", "--quiet"]
ADVISE = ["advise", "--no-progress"]


@pytest.mark.parametrize(
    "option, value",
    [
        ("--pitch", "95"),
        ("--pitch", "0"),
        ("--height", "0"),
        ("--height", "6"),
        ("--lux", "nan"),
        ("--lux", "3e5"),
        ("--scale", "-1"),
        ("--scale", "5"),
        ("--speed", "-1"),
        ("--speed", "inf"),
    ],
)
@pytest.mark.parametrize("command", [SIMULATE, ADVISE], ids=["simulate", "advise"])
def test_simulate_and_advise_refuse_the_same_values(command, option, value, tmp_path, capsys):
    _refused([*command, option, value], option, tmp_path, capsys)


@pytest.mark.parametrize(
    "option, values",
    [("--frames", ["0"]), ("--exposures", ["0"]), ("--exposures", ["1", "nan"]), ("--exposures", ["1e6"])],
)
def test_advise_refuses_bad_frames_and_exposures(option, values, tmp_path, capsys):
    _refused([*ADVISE, option, *values], option, tmp_path, capsys)


def test_advise_takes_a_camera_standing_still(capsys):
    """Speed 0, which a simulated walk refuses, is a question advise answers: no blur."""
    argv = [*ADVISE, "--speed", "0", "--frames", "1", "--exposures", "2", "--scale", "0.5"]
    assert main(argv) == 0
    assert "recommended: --exposure-ms 2" in capsys.readouterr().out


@pytest.mark.parametrize(
    "option, value",
    [("--seconds", "nan"), ("--seconds", "1e9"), ("--lux", "-1"), ("--speed", "0"), ("--speed", "100")],
)
def test_demo_refuses_a_bad_number(option, value, tmp_path, capsys):
    _refused(
        ["demo", "--map", "{map}", "-o", "{tmp}/d", "--quiet", "--no-rerun", option, value], option, tmp_path, capsys
    )


def test_demo_refuses_an_output_that_is_a_file(tmp_path, capsys):
    (tmp_path / "f").write_text("")
    _refused(["demo", "--map", "{map}", "-o", "{tmp}/f", "--quiet", "--no-rerun"], "-o", tmp_path, capsys)


MONITOR = ["monitor", "--from-bag", "{tmp}/no.bag2", "--map", "{map}"]


@pytest.mark.parametrize("name", ["x.txt", "x", "x.png.gz"])
@pytest.mark.parametrize("command", [["replay", "{tmp}/no-session"], MONITOR], ids=["replay", "monitor"])
def test_png_output_must_be_named_png(command, name, tmp_path, capsys):
    _refused([*command, "--png", f"{{tmp}}/{name}"], "--png", tmp_path, capsys)


def test_calibrate_coverage_must_be_named_png(tmp_path, capsys):
    argv = ["calibrate", "camera", "{tmp}/no-images", "-o", "{tmp}/c.yaml", "--coverage", "{tmp}/c.txt"]
    _refused(argv, "--coverage", tmp_path, capsys)


def test_monitor_refuses_a_save_path_that_is_a_directory(tmp_path, capsys):
    (tmp_path / "d.rrd").mkdir()
    _refused([*MONITOR, "--save", "{tmp}/d.rrd"], "--save", tmp_path, capsys)


@pytest.mark.parametrize(
    "option, value",
    [
        ("--trials", "0"),
        ("--trials", "-3"),
        ("--blurs", "a,b"),
        ("--blurs", ","),
        ("--blurs", "0,nan"),
        ("--blurs", "-1"),
        ("--blurs", "1000"),
        ("--candidates", "-1"),
        ("--candidates", "0"),
        ("--candidates", "200"),
        ("--methods", "appearance,bogus"),
        ("--methods", ","),
        ("--methods", "appearance,appearance"),
    ],
)
def test_bench_identify_refuses_a_bad_option(option, value, tmp_path, capsys):
    _refused(["bench-identify", "--no-progress", option, value], option, tmp_path, capsys)


@pytest.mark.parametrize("value", ["bogus", ",", "full,,nope", "full,decoded-only, full"])
def test_eval_refuses_unknown_no_or_repeated_modes(value, tmp_path, capsys):
    _refused(["eval", "-o", "{tmp}/e", "--quiet", "--modes", value], "--modes", tmp_path, capsys)


CALIBRATE_CAMERA = ["calibrate", "camera", "{tmp}/no-images", "-o", "{tmp}/c.yaml", "--no-progress"]


@pytest.mark.parametrize(
    "option, value",
    [
        ("--step", "-1"),
        ("--step", "0"),
        ("--max-frames", "0"),
        ("--max-frames", "-1"),
        ("--max-views", "0"),
        ("--max-views", "4"),
        ("--square-mm", "nan"),
        ("--square-mm", "-20"),
        ("--square-mm", "1e300"),
        ("--marker-mm", "nan"),
        ("--marker-mm", "20"),
    ],
)
def test_calibrate_camera_refuses_a_bad_number(option, value, tmp_path, capsys):
    _refused([*CALIBRATE_CAMERA, option, value], option, tmp_path, capsys)


@pytest.mark.parametrize("option, value", [("--dpi", "0"), ("--square-mm", "inf"), ("--marker-mm", "0")])
def test_calibrate_board_refuses_a_bad_number(option, value, tmp_path, capsys):
    _refused(["calibrate", "board", "-o", "{tmp}/b.pdf", option, value], option, tmp_path, capsys)


@pytest.mark.parametrize("value", ["-3", "0"])
def test_rig_fit_refuses_a_step_below_1(value, tmp_path, capsys):
    _refused(["rig", "fit", "{tmp}/no-session", "-o", "{tmp}/rig.json", "--step", value], "--step", tmp_path, capsys)


def test_rig_fit_refuses_an_output_that_is_a_directory(tmp_path, capsys):
    (tmp_path / "taken").mkdir()
    _refused(["rig", "fit", "{tmp}/no-session", "-o", "{tmp}/taken"], "-o", tmp_path, capsys)


@pytest.mark.parametrize(
    "option, value",
    [
        ("--readout-ms", "nan"),
        ("--readout-ms", "1e9"),
        ("--jitter-ms", "-1"),
        ("--drop-fraction", "1"),
        ("--drop-fraction", "nan"),
        ("--drop-bursts-per-min", "inf"),
        ("--drop-bursts-per-min", "1e9"),
        ("--survey-sigma-cm", "inf"),
        ("--survey-sigma-cm", "-1"),
        ("--survey-sigma-deg", "1e9"),
        ("--missing-fraction", "nan"),
        ("--missing-fraction", "1.5"),
    ],
)
def test_simulate_refuses_a_bad_field_condition(option, value, tmp_path, capsys):
    _refused([*SIMULATE, option, value], option, tmp_path, capsys)


@pytest.mark.parametrize(
    "option, value",
    [
        ("--stale", "nan"),
        ("--stale", "0"),
        ("--max-age", "-1"),
        ("--max-2sigma", "inf"),
        ("--max-skew", "0"),
        ("--safety-radius", "-1"),
        ("--trail", "nan"),
        ("--refresh", "inf"),
        ("--max-seconds", "-1"),
        ("--print-every", "nan"),
    ],
)
def test_monitor_refuses_a_bad_number(option, value, tmp_path, capsys):
    _refused([*MONITOR, option, value], option, tmp_path, capsys)


@pytest.mark.parametrize("option, value", [("--frames", "0"), ("--jpeg", "0"), ("--jpeg", "101"), ("--json", "{tmp}")])
def test_bench_refuses_a_bad_option(option, value, tmp_path, capsys):
    _refused(["bench", "--quick", "--no-progress", option, value], option, tmp_path, capsys)


@pytest.mark.parametrize("extra", [["--json", "{tmp}/profile.json"], ["--frames", "3"], ["--quick"], ["--no-paper"]])
def test_bench_profile_refuses_the_benchmarks_own_options(extra, tmp_path, capsys):
    """``--profile`` replays a session: the benchmark's options would be ignored (``--json`` wrote no file)."""
    walk = Path(__file__).resolve().parent.parent / "logs" / "walk2s"
    _refused(["bench", "--profile", str(walk), *extra], extra[0], tmp_path, capsys)


@pytest.mark.parametrize("value", ["inf", "nan", "-1"])
def test_live_refuses_a_gain_that_is_not_a_finite_number_from_0(value, tmp_path, capsys):
    _refused(["live", "--camera", "{tmp}/no-camera", "--map", "{map}", "--gain", value], "--gain", tmp_path, capsys)


@pytest.mark.parametrize(
    "extra, option",
    [
        (["--config", "{s}", "--record", "{s}"], "--record"),
        (["--map", "{s}/map.csv", "--rig", "{s}/rig.json", "--record-bag", "{s}"], "--record-bag"),
        (["--config", "{s}", "--log", "{s}/map.csv"], "--log"),
        (["--config", "{s}", "--rerun-save", "{s}/rig.json"], "--rerun-save"),
        # A file sink truncates its file: over the ground truth, a later replay scored the estimate against itself.
        (["--config", "{s}", "--publish", "{s}/groundtruth.tum"], "--publish"),
        (["--config", "{s}", "--publish", "{s}/map.csv"], "--publish"),
    ],
)
def test_live_refuses_an_output_over_its_inputs(extra, option, tmp_path, capsys):
    """Before any work: a recording into the directory it reads its set-up from, or a log over the map."""
    import shutil

    s = tmp_path / "site"
    shutil.copytree(Path(__file__).resolve().parent.parent / "logs" / "walk2s", s)
    before = {p: p.read_bytes() for p in s.rglob("*") if p.is_file()}
    argv = ["live", "--camera", str(s), "--no-pace", "--max-frames", "2", *(a.format(s=s) for a in extra)]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and option in err and "internal error" not in err, err
    assert {p: p.read_bytes() for p in s.rglob("*") if p.is_file()} == before


def test_live_fails_when_its_source_gives_no_frame_at_all(tmp_path, capsys):
    """A file OpenCV opens but reads no frame from (here text named .jpg) is an error naming it, not a
    run that ends with 0 frames and exit code 0."""
    src = tmp_path / "notimage.jpg"
    src.write_text("not an image\n")
    rc = main(["live", "--camera", str(src), "--map", DEMO_MAP, "--no-pace"])
    err = capsys.readouterr().err
    assert rc == 2, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("tagloc live: error: ") and str(src) in last and "no frame" in last, err
    assert "Traceback" not in err and "internal error" not in err, err


def test_every_action_of_a_command_has_help_with_an_example(capsys):
    """The README: every subcommand has --help with an example; so does each action (map grid, rig fit, ...)."""
    for name in [m.NAME for m in _command_modules()]:
        parser = build_parser(name)
        command = next(a for a in parser._subparsers._group_actions).choices[name]
        actions = [a for a in command._actions if isinstance(a, type(parser._subparsers._group_actions[0]))]
        for action in (c for a in actions for c in a.choices):
            with pytest.raises(SystemExit):
                main([name, action, "--help"])
            out = capsys.readouterr().out
            assert re.search(rf"^examples?:\n  tagloc {name} {action}\b", out, re.M), (name, action, out)


def test_simulate_help_examples_keep_their_line_continuations(capsys):
    """A backslash at a line's end in the help's examples is printed (it had joined the lines)."""
    with pytest.raises(SystemExit):
        main(["simulate", "--help"])
    out = capsys.readouterr().out
    assert "--jitter-ms 2 \\\n      --drop-fraction" in out, out


def test_live_fails_when_its_camera_is_lost_mid_run(tmp_path, capsys, monkeypatch):
    """A camera unplugged mid-run (every read failing) ends the run with a line saying so and exit
    code 1, not 0 as if it had been stopped (a review: a supervisor restarting on failure never did)."""
    import numpy as np

    from tagloc.io import capture

    class Unplugged:
        """cv2.VideoCapture of a camera that gives 3 frames, then is gone."""

        def __init__(self, spec):
            self.n = 0

        def isOpened(self):  # noqa: N802 - OpenCV's name
            return True

        def get(self, prop):
            return {capture.cv2.CAP_PROP_FRAME_WIDTH: 1296, capture.cv2.CAP_PROP_FRAME_HEIGHT: 972}.get(prop, 0.0)

        def read(self):
            self.n += 1
            return (True, np.zeros((972, 1296), np.uint8)) if self.n <= 3 else (False, None)

        def release(self):
            pass

    monkeypatch.setattr(capture.cv2, "VideoCapture", Unplugged)
    rc = main(
        ["live", "--camera", "0", "--map", DEMO_MAP, "--mode", "decoded-only", "--publish", str(tmp_path / "p.jsonl")]
    )
    err = capsys.readouterr().err
    assert rc == 1, err
    last = err.strip().splitlines()[-1]
    assert last.startswith("tagloc live: error: ") and "reads failed in a row" in last, err
    assert (tmp_path / "p.jsonl").read_text().count("\n") >= 1  # the frames before were published


def test_live_refuses_a_video_file_it_opens_but_cannot_read_a_frame_of(tmp_path, capsys, monkeypatch):
    """A file OpenCV opens, its header counting frames, none of which decodes: 'no frame could be
    read' (exit 2), not a clean run (exit 0) nor a camera lost mid-run (exit 1). Failed reads are
    counted as grabbed (and skipped): the check is on the frames read."""
    from tagloc.io import capture

    class Unreadable:
        """cv2.VideoCapture of a file whose 100 frames all fail to decode."""

        def __init__(self, spec):
            pass

        def isOpened(self):  # noqa: N802 - OpenCV's name
            return True

        def get(self, prop):
            return {capture.cv2.CAP_PROP_FRAME_COUNT: 100.0, capture.cv2.CAP_PROP_FPS: 30.0}.get(prop, 0.0)

        def read(self):
            return False, None

        def release(self):
            pass

    video = tmp_path / "v.mp4"
    video.write_bytes(b"\0" * 64)
    monkeypatch.setattr(capture.cv2, "VideoCapture", Unreadable)
    rc = main(["live", "--camera", str(video), "--map", DEMO_MAP, "--mode", "decoded-only", "--no-pace"])
    err = capsys.readouterr().err
    assert rc == 2, err
    assert "no frame could be read" in err.strip().splitlines()[-1], err


def test_demo_replaces_its_own_session_but_deletes_nothing_else(tmp_path, capsys):
    """-o OUT: the demo replaces OUT/session, its earlier run's simulated walk; a session directory
    that holds anything else (or is no simulated session) is refused with nothing deleted."""
    args = ["demo", "--map", DEMO_MAP, "-o", str(tmp_path / "d"), "--quiet", "--no-rerun", "--seconds", "1"]
    assert main(args) == 0
    assert main(args) == 0  # the earlier run's session is replaced
    precious = tmp_path / "d" / "session" / "precious.txt"
    precious.write_text("keep")
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "nothing deleted" in err
    assert precious.read_text() == "keep"
    other = tmp_path / "e" / "session"
    other.mkdir(parents=True)
    (other / "notes.md").write_text("mine")
    assert main([*args[:4], str(tmp_path / "e"), *args[5:]]) == 2
    assert (other / "notes.md").exists()


def test_the_demo_names_a_rerun_viewer_that_starts_from_here():
    """The demo's hint ('open it with: rerun ...') named a bare 'rerun', which the README's set-up
    does not put on the shell's path: it names the virtual environment's when that is the one."""
    import shutil

    from tagloc.apps.demo import _rerun_command

    cmd = _rerun_command()
    assert (cmd == "rerun" and shutil.which("rerun")) or Path(cmd).exists()
