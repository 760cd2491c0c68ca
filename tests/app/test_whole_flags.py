"""The CLI takes each flag only as spelled whole: `envisat run --duration 5` is argparse's own error (it was read as
`--duration-s 5`), on every verb and sub-verb, while the whole flag parses."""

import argparse

import pytest

from envisat_pose.app.cli import build_parser, main


def _parsers(parser: argparse.ArgumentParser, name: str = "envisat"):
    """(name, parser) of the CLI and each of its verbs and sub-verbs."""
    yield name, parser
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for verb, sub in action.choices.items():
                yield from _parsers(sub, f"{name} {verb}")


def test_an_abbreviated_flag_is_refused_by_argparse(capsys):
    with pytest.raises(SystemExit) as stop:
        main(["run", "--duration", "5", "--out", "x"])
    assert stop.value.code == 2
    assert "unrecognized arguments: --duration 5" in capsys.readouterr().err
    assert build_parser().parse_args(["run", "--duration-s", "5", "--out", "x"]).duration_s == 5.0
    with pytest.raises(SystemExit):  # a sub-verb's flag too: `dataset inspect --mont` for --montage
        build_parser().parse_args(["dataset", "inspect", "d", "--mont", "m.png"])


def test_a_flag_a_verb_does_not_take_is_refused_in_that_verbs_usage(capsys):
    """`envisat demo --target X` (demo is ENVISAT's): refused with demo's own usage, not the top level's."""
    with pytest.raises(SystemExit) as stop:
        main(["demo", "--target", "models/cubesat_3u.xml"])
    err = capsys.readouterr().err
    assert stop.value.code == 2 and err.startswith("usage: envisat demo ")
    assert "envisat demo: error: unrecognized arguments: --target models/cubesat_3u.xml" in err


def test_every_verb_refuses_abbreviations():
    names = [name for name, p in _parsers(build_parser()) if p.allow_abbrev]
    assert names == []
