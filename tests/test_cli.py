"""The command line: a run builds only its own command's parser, with the same arguments as the full one."""

from __future__ import annotations

import pytest

from tagloc.cli import _command_modules, build_parser, main


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
    assert {k: v for k, v in alone.items() if k != "_run"} == {k: v for k, v in whole.items() if k != "_run"}


def test_unknown_command_lists_every_command(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["no-such-command"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "invalid choice" in err and "replay" in err and "bench-identify" in err
